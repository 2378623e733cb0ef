"""Loading a run directory of any kind (Lyapunov, LQR, RL, imported) as a :class:`~drlyap.runs.PolicyRun`."""

from __future__ import annotations

import os
from pathlib import Path

from drlyap.rl.agents import load_rl_run
from drlyap.runs import PolicyRun, RunDirError, load_imported_run, load_lqr_run, load_lyapunov_policy_run, read_run_kind
from drlyap.systems import UncertainSystem

LOADERS = {"lyapunov": load_lyapunov_policy_run, "lqr": load_lqr_run, "rl": load_rl_run, "imported": load_imported_run}
"""Run kind -> loader ``(path, system or None) -> PolicyRun``."""


def load_policy_run(path: str | os.PathLike, system: UncertainSystem | None = None, trust: bool = False) -> PolicyRun:
    """Load a run directory of any kind (``lyapunov``, ``lqr``, ``rl``, ``imported``) as a :class:`~drlyap.runs.PolicyRun`
    (``system``, ``trust``: as :func:`drlyap.runs.load_run`)."""
    path = Path(path)
    kind = read_run_kind(path).get("kind")
    if kind not in LOADERS:
        raise RunDirError(f"{path} holds a run of unknown kind {kind!r}; valid: {', '.join(sorted(LOADERS))}")
    return LOADERS[kind](path, system, trust)
