"""Reading a run directory's JSON files and rebuilding the system it was made for, as data: what the checker needs
of a run, without the networks, the training or the verifier (:mod:`drlyap.runs.directory` loads the rest)."""

from __future__ import annotations

import json
import os
import shlex
from pathlib import Path

from drlyap.runs.publish import RunDirError, complete_run_dir
from drlyap.runs.validate import check_schema
from drlyap.systems import UncertainSystem, get_system, identity_mismatch, resolve_system


def read_run_kind(path: Path) -> dict:
    """The ``run.json`` of a complete run directory, or a clear error."""
    marker = complete_run_dir(path)
    try:
        info = json.loads(marker.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise RunDirError(f"{marker} is not valid JSON: {err}") from err
    check_schema(marker, info, "run")
    return info


def read_run_json(path: str | os.PathLike, kind: str, *names: str) -> list[dict]:
    """Check that ``path`` is a complete run directory of ``kind`` and parse its JSON files ``names``."""
    path = Path(path)
    info = read_run_kind(path)
    if info.get("kind") != kind:
        raise RunDirError(f"{path} holds a {info.get('kind')!r} run, not a {kind!r} run")
    out = []
    for name in names:
        try:
            out.append(json.loads((path / name).read_text()))
        except FileNotFoundError:
            raise RunDirError(f"{path / name} is missing: the run directory is incomplete") from None
        except (OSError, json.JSONDecodeError, UnicodeDecodeError) as err:
            raise RunDirError(f"{path / name} is damaged: {err}") from None
    return out


def run_system(path: str | os.PathLike, name: str, system: UncertainSystem | None,
               info: dict | None = None, trust: bool = False) -> UncertainSystem:
    """The system a run was made for, never one with other dynamics.

    ``name``: the system named by the run's config; ``info``: its ``run.json``. Without ``system``, a registered
    name is rebuilt from the registry; a system that came from a file or a module is rebuilt from it only with
    ``trust`` (importing it runs its code: otherwise an error names the code and how to pass it). The result must
    carry ``name`` and match the recorded description (dimensions, parameters, boxes, equilibrium, uncertain
    names); a mismatch (e.g. an edited system file) is refused.
    """
    info = info or {}
    recorded = info.get("system") or {}
    if recorded.get("name", name) != name:
        raise RunDirError(f"{path}: config.json names system {name!r} but run.json records {recorded['name']!r}; "
                          "the run directory is inconsistent")
    if system is None:
        source = info.get("system_source") or {}
        spec = source.get("reload")
        if spec and ":" in str(spec) and not trust:
            raise RunDirError(f"{path}: its system {name!r} comes from {spec}; loading the run would run that code. "
                              f"Name it yourself (--system {shlex.quote(spec)}, or system= in Python) or trust the run "
                              "(--trust-run, or trust=True)")
        try:
            system = resolve_system(spec) if spec else get_system(name)
        except ValueError as err:
            hint = f" (recorded source {source.get('spec')!r})" if spec else \
                " (run.json records no source: pass the system, or register it with drlyap.register_system)"
            raise RunDirError(f"cannot rebuild system {name!r} of {path}{hint}: {err}") from err
    if system.name != name:
        raise RunDirError(f"{path} was made for system {name!r}, not {system.name!r}")
    diff = identity_mismatch(recorded, system)
    if diff:
        raise RunDirError(f"{path} was trained on other dynamics than system {name!r} has now; refusing to load it "
                          f"({'; '.join(diff)})")
    return system
