"""What every command shares: the thread policy, parsing of number lists, one-line errors, defaults read from the
settings dataclasses. Imports neither torch nor the numerical code, so ``--help`` is fast."""

from __future__ import annotations

import dataclasses
import enum
import json
import math
import os
import shlex
import sys
from collections.abc import Iterable
from pathlib import Path

import click


def setup_threads() -> None:
    """One torch thread unless ``DRLYAP_THREADS`` says otherwise (the two shared cores of a laptop-class machine),
    and freed memory kept for reuse (:mod:`drlyap.memory`)."""
    from drlyap.memory import keep_freed_memory

    keep_freed_memory()
    value = os.environ.get("DRLYAP_THREADS", "1")
    if not value.isdigit() or int(value) < 1:
        raise click.ClickException(f"DRLYAP_THREADS must be a positive integer, got {value!r}")
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(int(value))
    else:  # torch takes its thread count from here when a command first imports it (a --help never does)
        os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = value


def default(cls, name: str):
    """The default of dataclass ``cls``'s field ``name`` (the one place that default lives); a word of
    :mod:`drlyap.kinds` as its plain string, as the command line takes it."""
    for f in dataclasses.fields(cls):
        if f.name == name:
            return f.default.value if isinstance(f.default, enum.Enum) else f.default
    raise KeyError(f"{cls.__name__} has no field {name!r}")


def floats(text: str | None, what: str) -> list[float] | None:
    """Comma-separated finite numbers, or a usage error naming ``what``."""
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise click.BadParameter(f"{what} must be comma-separated numbers, got {text!r}") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise click.BadParameter(f"{what} must be finite numbers, got {text!r}")
    return values


def fail(err: Exception) -> None:
    """A one-line error (exit status 1); a path to write to that cannot be used is named as the ``--out`` it came
    from."""
    from drlyap.runs.publish import DestinationError

    raise click.ClickException(err.for_option("--out") if isinstance(err, DestinationError) else str(err))


def refuse_early(runs: Iterable[Path | None] = (), systems: Iterable[str | None] = ()) -> None:
    """Refuse, before the numerical code loads, a SYSTEM spec that cannot name a system
    (:func:`drlyap.specs.check_spec`, against the names registered in this process) and a RUN_DIR that is no complete
    run directory (:func:`drlyap.runs.publish.complete_run_dir`); None entries are skipped. A one-line error."""
    from drlyap.runs.publish import complete_run_dir
    from drlyap.specs import BUILT_IN, check_spec

    registry = sys.modules.get("drlyap.systems.registry")  # loaded where something may have registered more names
    names = registry.system_names() if registry is not None else BUILT_IN
    try:
        for spec in systems:
            if spec is not None:
                check_spec(spec, names)
        for path in runs:
            if path is not None:
                complete_run_dir(path)
    except ValueError as err:
        fail(err)


def run_source_options(command):
    """``--system`` and ``--trust-run``: how a run whose system came from a file or a module is loaded (the
    run's recorded code is never run unless the user names it or trusts the run)."""
    command = click.option("--trust-run", is_flag=True,
                           help="Trust the run directory: rebuild its system from the file or module it records (that "
                                "runs that code), and read an older RL run's pickled model.zip.")(command)
    return click.option("--system", "system_spec", default=None,
                        help="The run's system, when it came from a file or a module: path/to/file.py:factory or "
                             "package.module:factory (run as you name it; default: refuse to run recorded code).")(command)


def run_system_of(spec: str | None, verifier: bool | None = None):
    """The system object ``--system`` names, or None. Its dynamics are probed as :func:`drlyap.systems.resolve_system`
    says (``verifier=False``: not on the verifier's enclosures, for a command that runs only the checker); a dynamics
    that cannot run there is a ValueError naming the file, the line and the operation (one ``Error:`` line)."""
    if spec is None:
        return None
    from drlyap.systems import resolve_system

    return resolve_system(spec, verifier=verifier)


def compute_options(with_device: bool = True):
    """``--workers``, ``--backend``, ``--address`` (and ``--device``): where a command's proofs bound their boxes
    (:class:`~drlyap.compute.Compute`; how fast, never what is proved)."""

    def decorate(command):
        if with_device:
            command = click.option("--device", default="cpu", show_default=True,
                                   help="Where this process bounds the boxes of the proofs (or the checker's "
                                        "leaves): cpu, or cuda (float64 on the GPU, outward rounded there too; one "
                                        "worker).")(command)
        command = click.option("--address", default=None,
                               help="The Ray cluster of --backend ray (ray://host:10001 or host:6379) [RAY_ADDRESS, "
                                    "else a local Ray with --workers CPUs].")(command)
        command = click.option("--backend", type=click.Choice(["local", "ray"]), default="local", show_default=True,
                               help="Where the proof workers run: processes on this machine, or actors of a Ray "
                                    "cluster.")(command)
        return click.option("--workers", type=click.IntRange(min=1), default=1, show_default=True,
                            help="Processes that bound each proof's boxes, one torch thread each (the verdict and the "
                                 "certificate are the same for any number).")(command)

    return decorate


def compute_settings(workers: int, backend: str, address: str | None, device: str = "cpu"):
    """The :class:`~drlyap.compute.Compute` of ``--workers``, ``--backend``, ``--address``, ``--device`` (checked: a usage
    error names what is wrong), with progress on stderr."""
    from drlyap.compute import compute_problems

    problems = compute_problems(workers, backend, address, device)
    if problems:
        raise click.UsageError("; ".join(problems))
    if device != "cpu":
        from drlyap.parallel import check_device

        try:
            check_device(device)
        except ValueError as err:
            raise click.UsageError(str(err)) from None
    if workers > 1 and backend == "local":  # its fork server imports torch now, beside this process, not at the proof
        from drlyap.lifeline import start_fork_server

        start_fork_server()
    from drlyap.compute import Compute

    return Compute(workers=workers, backend=backend, address=address, device=device, progress=True)


def recorded_source(run_dir: Path, system_spec: str | None = None) -> dict | None:
    """Where a run's system came from, as its ``run.json`` records it (``system_source``), read as plain JSON: nothing
    is imported. Where it records none (a run saved from Python with a system object), the ``--system`` the command
    was given (``system_spec``), so that a hint printed for the next command runs as printed. None where neither."""
    try:
        source = json.loads((Path(run_dir) / "run.json").read_text()).get("system_source")
    except (OSError, ValueError, AttributeError):
        source = None
    if isinstance(source, dict) and source.get("reload"):
        return source
    return {"reload": system_spec} if system_spec else (source if isinstance(source, dict) else None)


def command_hint(*words: object, source: dict | None = None) -> str:
    """A ``drlyap`` command to print for the user to run next, quoted for a POSIX shell, with ``--system SPEC`` where
    the run's system came from a file or a module (``source``: :func:`drlyap.systems.system_source`, as ``run.json``
    records it), so that it runs as printed."""
    spec = (source or {}).get("reload")
    needs = ["--system", str(spec)] if spec and ":" in str(spec) else []
    return shlex.join(["drlyap", *(str(w) for w in words), *needs])
