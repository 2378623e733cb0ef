"""Run directories: writing them atomically, loading them, and one interface for runs of every kind.

* :mod:`~drlyap.runs.directory` -- Lyapunov runs: :func:`save_run`, :func:`load_run`, :class:`Run`;
* :mod:`~drlyap.runs.policies` -- :class:`PolicyRun`, the interface of runs of every kind;
* :mod:`~drlyap.runs.lqr` -- LQR runs (:func:`train_lqr`);
* :mod:`~drlyap.runs.imported` -- pairs brought as ONNX files (:func:`import_run`, :func:`load_onnx_pair`).
"""

from drlyap.runs.directory import FORMAT_VERSION, Run, RunDirError, atomic_dir, ensure_new, load_run, read_run_kind, save_run
from drlyap.runs.imported import import_run, load_imported_run, load_onnx_pair
from drlyap.runs.lqr import load_lqr_run, save_lqr_run, train_lqr
from drlyap.runs.policies import PolicyRun, load_lyapunov_policy_run
from drlyap.runs.publish import DirectoryLock, check_writable, proof_checkpoints

__all__ = ["FORMAT_VERSION", "DirectoryLock", "PolicyRun", "Run", "RunDirError", "atomic_dir", "check_writable",
           "ensure_new", "import_run", "load_imported_run", "load_lqr_run", "load_lyapunov_policy_run", "load_onnx_pair",
           "load_run", "proof_checkpoints", "read_run_kind", "save_lqr_run", "save_run", "train_lqr"]
