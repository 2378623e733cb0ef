"""Run directories: writing them atomically, loading them, and one interface for runs of every kind.

* :mod:`~drlyap.runs.directory` -- Lyapunov runs: :func:`save_run`, :func:`load_run`, :class:`Run`;
* :mod:`~drlyap.runs.policies` -- :class:`PolicyRun`, the interface of runs of every kind;
* :mod:`~drlyap.runs.lqr` -- LQR runs (:func:`train_lqr`);
* :mod:`~drlyap.runs.imported` -- pairs brought as ONNX files (:func:`import_run`, :func:`load_onnx_pair`);
* :mod:`~drlyap.runs.publish` -- where a run directory may be written, and whether one is complete (no torch).

The names below load their module on first use, so that :mod:`~drlyap.runs.publish` can check a command's paths
before the numerical code is imported.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the same names, for type checkers and the import-graph test; at run time __getattr__ loads them
    from drlyap.runs.directory import FORMAT_VERSION, Run, atomic_dir, ensure_new, load_run, read_run_kind, save_run
    from drlyap.runs.imported import import_run, load_imported_run, load_onnx_pair
    from drlyap.runs.lqr import load_lqr_run, save_lqr_run, train_lqr
    from drlyap.runs.policies import PolicyRun, load_lyapunov_policy_run
    from drlyap.runs.publish import DirectoryLock, RunDirError, check_writable, proof_checkpoints

_NAMES = {
    "drlyap.runs.directory": ("FORMAT_VERSION", "Run", "atomic_dir", "ensure_new", "load_run", "read_run_kind",
                              "save_run"),
    "drlyap.runs.imported": ("import_run", "load_imported_run", "load_onnx_pair"),
    "drlyap.runs.lqr": ("load_lqr_run", "save_lqr_run", "train_lqr"),
    "drlyap.runs.policies": ("PolicyRun", "load_lyapunov_policy_run"),
    "drlyap.runs.publish": ("DirectoryLock", "RunDirError", "check_writable", "proof_checkpoints"),
}
_MODULE = {name: module for module, names in _NAMES.items() for name in names}

__all__ = ["FORMAT_VERSION", "DirectoryLock", "PolicyRun", "Run", "RunDirError", "atomic_dir", "check_writable",
           "ensure_new", "import_run", "load_imported_run", "load_lqr_run", "load_lyapunov_policy_run", "load_onnx_pair",
           "load_run", "proof_checkpoints", "read_run_kind", "save_lqr_run", "save_run", "train_lqr"]


def __getattr__(name: str):
    if name not in _MODULE:
        raise AttributeError(f"module 'drlyap.runs' has no attribute {name!r}")
    value = getattr(importlib.import_module(_MODULE[name]), name)
    globals()[name] = value
    return value
