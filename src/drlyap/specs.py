"""System specs read without building a system (a leaf module: it imports neither torch nor the rest of drlyap), so
that a command refuses a SYSTEM that cannot be one before it loads the numerical code: the built-in names, the forms
a spec takes and the checks that import nothing. :mod:`drlyap.systems.registry` builds systems from them."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

BUILT_IN = ("cartpole", "mountain-car", "pendulum", "pendulum-u9", "quadrotor2d")
"""The names the registry (:mod:`drlyap.systems.registry`) holds before anything registers more."""

SPEC_FORMS = "a registered name, 'package.module:factory' or 'path/to/file.py:factory'"


def is_file_spec(target: str) -> bool:
    """Whether the part before ``:factory`` names a file (rather than a module)."""
    return target.endswith(".py") or "/" in target or "\\" in target


def unknown_name(spec: str, names: Iterable[str]) -> ValueError:
    """The error of a spec without ``:factory`` that is no registered name (``names``)."""
    import difflib

    hint = " (add ':factory', the name of the system or of a function returning it)" if is_file_spec(spec) else ""
    close = difflib.get_close_matches(spec, list(names), n=1, cutoff=0.6)
    guess = f" (did you mean {close[0]!r}?)" if close and not hint else ""
    return ValueError(f"unknown system {spec!r}{hint}{guess}; valid: {', '.join(sorted(names))}, or {SPEC_FORMS}")


def split_spec(spec: str) -> tuple[str, str]:
    """``(target, factory)`` of a spec ``target:factory``; a ValueError naming the valid forms otherwise."""
    target, _, attr = spec.rpartition(":")
    if not target or not attr.isidentifier():
        raise ValueError(f"system spec {spec!r} must be {SPEC_FORMS}")
    return target, attr


def system_file(target: str) -> Path:
    """The absolute path of a system file that exists, or a ValueError naming it."""
    path = Path(target).resolve()
    if not path.is_file():
        raise ValueError(f"system file {path} does not exist")
    return path


def check_spec(spec: str, names: Iterable[str] = BUILT_IN) -> None:
    """Refuse a spec that cannot name a system, importing nothing: a name that is not among ``names``, a malformed
    ``target:factory``, a system file that does not exist. The module, the factory and what it returns are checked
    when the system is built (:func:`drlyap.systems.resolve_system`)."""
    spec = str(spec).strip()
    if ":" not in spec:
        if spec not in set(names):
            raise unknown_name(spec, names)
        return
    target, _ = split_spec(spec)
    if is_file_spec(target):
        system_file(target)
