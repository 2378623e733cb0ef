"""Finding a system by name or spec: the registry of named systems, user systems from a module or a file, and
what a run directory records about where its system came from (so that it can be rebuilt and compared)."""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import math
import sys
import traceback
from collections.abc import Callable
from pathlib import Path

from drlyap.specs import is_file_spec, split_spec, system_file, unknown_name
from drlyap.systems.library import cartpole, mountain_car, pendulum, quadrotor2d
from drlyap.systems.model import UncertainSystem
from drlyap.systems.probe import probe_system

_REGISTRY: dict[str, Callable[[], UncertainSystem]] = {
    "pendulum": pendulum,
    "pendulum-u9": lambda: pendulum(9.0),
    "mountain-car": mountain_car,
    "cartpole": cartpole,
    "quadrotor2d": quadrotor2d,
}  # the names of drlyap.specs.BUILT_IN


def register_system(name: str, factory: Callable[[], UncertainSystem]) -> None:
    """Make a user-defined system available by name to the CLI and :func:`get_system`."""
    _REGISTRY[name] = factory


def system_names() -> list[str]:
    """The registered names, sorted."""
    return sorted(_REGISTRY)


def get_system(name: str) -> UncertainSystem:
    """A registered system by name; the error lists the valid names."""
    try:
        return _REGISTRY[name]()
    except KeyError:
        raise ValueError(f"unknown system {name!r}; valid: {', '.join(system_names())}") from None


# --------------------------------------------------------------------------- user systems
# Fields of describe() that fix the dynamics a run was trained on (compared when a run is reloaded).
IDENTITY_KEYS = ("name", "n", "m", "k", "states", "inputs", "parameters", "uncertain", "state_box", "input_box",
                 "equilibrium", "equilibrium_input", "angle_dims")


def _import_file(path: Path):
    """Import a Python file under a module name unique to its absolute path (no clash between files)."""
    path = system_file(str(path))
    name = "drlyap_user_" + hashlib.sha1(str(path).encode()).hexdigest()[:12]
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ValueError(f"cannot import {path} as a Python file")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except SyntaxError as err:
        sys.modules.pop(name, None)
        raise ValueError(f"{err.filename or path}:{err.lineno}: {err.msg} (system file)") from None
    except Exception as err:
        sys.modules.pop(name, None)
        frames = [f for f in traceback.extract_tb(err.__traceback__) if Path(f.filename).resolve() == path]
        where = f"{path}:{frames[-1].lineno}" if frames else str(path)
        raise ValueError(f"{where}: importing the system file failed: {type(err).__name__}: {err}") from None
    return module


def resolve_system(spec: str, verifier: bool | None = None) -> UncertainSystem:
    """A system from a command-line spec: a registered name (``pendulum``), ``package.module:factory``
    or ``path/to/file.py:factory``.

    ``factory`` names an :class:`UncertainSystem` object or a zero-argument callable returning one.
    A file is imported by path (under a module name unique to its absolute path), so it need not be
    on ``sys.path``. Errors name the spec and the valid forms. A system from a file or a module has its dynamics
    run once through what training, the verifier and the checker will run them on
    (:func:`~drlyap.systems.probe.probe_system`; the verifier's enclosures only where this process has loaded them):
    an operation they cannot take is a ValueError naming the file, the line and the operation. ``verifier``: True
    or False to probe the verifier's enclosures or not, whatever this process has loaded.
    """
    spec = str(spec).strip()
    if ":" not in spec:
        if spec in _REGISTRY:
            return get_system(spec)
        raise unknown_name(spec, system_names())
    target, attr = split_spec(spec)
    if is_file_spec(target):
        module = _import_file(Path(target))
    else:
        try:
            module = importlib.import_module(target)
        except ImportError as err:
            raise ValueError(f"cannot import module {target!r} of system spec {spec!r}: {err}") from err
    if not hasattr(module, attr):
        raise ValueError(f"{target} has no attribute {attr!r} (system spec {spec!r})")
    obj = getattr(module, attr)
    if callable(obj) and not isinstance(obj, UncertainSystem):
        try:
            obj = obj()
        except TypeError as err:
            raise ValueError(f"{spec}: the factory must take no arguments, or it failed ({err})") from None
        except ValueError:
            raise
        except Exception as err:
            raise ValueError(f"{spec}: the factory failed: {type(err).__name__}: {err}") from None
    if not isinstance(obj, UncertainSystem):
        raise ValueError(f"{spec} gives a {type(obj).__name__}, not an UncertainSystem")
    probe_system(obj, verifier=verifier)  # None: the verifier's enclosures where this process has loaded them
    return obj


def system_source(spec: str, system: UncertainSystem) -> dict:
    """What a run directory records about where its system came from, so that it can be reloaded.

    ``spec``: as given; ``reload``: the spec to reload with (file paths made absolute); ``path``: the
    absolute file path, if any. The run's ``run.json`` also holds ``system.describe()``, compared on reload.
    """
    spec = str(spec).strip()
    target, _, attr = spec.rpartition(":")
    path = str(Path(target).resolve()) if target and is_file_spec(target) else None
    return {"spec": spec, "reload": f"{path}:{attr}" if path else spec, "path": path}


def default_source(system: UncertainSystem) -> dict:
    """The source of a system handed in as an object: its registered name when the registry builds the
    same system, else nothing to reload from (loading such a run needs ``system=``)."""
    if system.name in _REGISTRY and not identity_mismatch(get_system(system.name).describe(), system):
        return system_source(system.name, system)
    return {"spec": None, "reload": None, "path": None}


def _same(a, b) -> bool:
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return math.isclose(a, b, rel_tol=1e-12, abs_tol=1e-300)
    return a == b


def identity_mismatch(recorded: dict, system: UncertainSystem) -> list[str]:
    """The :data:`IDENTITY_KEYS` on which ``system.describe()`` differs from a ``recorded`` description
    (keys absent from ``recorded``, e.g. in older runs, are not compared)."""
    now = system.describe()
    return [f"{key}: recorded {recorded[key]!r}, now {now[key]!r}" for key in IDENTITY_KEYS
            if key in recorded and not _same(recorded[key], now[key])]
