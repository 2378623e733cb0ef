"""One interface for runs of every kind (Lyapunov pairs, LQR, RL): :class:`PolicyRun`.

Each kind has its loader: :func:`load_lyapunov_policy_run` here, :func:`drlyap.runs.lqr.load_lqr_run`,
:func:`drlyap.rl.agents.load_rl_run`; :func:`drlyap.workflows.policies.load_policy_run` picks by the run's kind.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from torch import Tensor

from drlyap.kinds import Method
from drlyap.runs.directory import load_run
from drlyap.systems import UncertainSystem


@dataclass
class PolicyRun:
    """Any run directory, loaded: ``controller(x)`` ``(B, n) -> (B, m)`` and ``certificate(x)`` ``(B,)``
    (or None) in user coordinates, float64.

    ``certificate``: V for Lyapunov runs, ``z^T P z`` for LQR, the negated critic value for RL (so that
    *decreasing* is the good direction for all of them).

    ``samples``: what training consumed. Lyapunov: model evaluations at training states,
    ``n_states * iterations`` when states are redrawn every iteration (the default), else ``n_states``
    (the paper's count); ``distinct_states`` in ``info`` always holds ``n_states``. RL: environment
    steps. LQR: 0 (one linearisation).
    """

    path: Path
    kind: str
    system: UncertainSystem
    controller: Callable[[Tensor], Tensor]
    certificate: Callable[[Tensor], Tensor] | None
    samples: int | None
    train_time_s: float | None
    label: str
    config: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)


def load_lyapunov_policy_run(path: Path, system: UncertainSystem | None = None, trust: bool = False) -> PolicyRun:
    """A Lyapunov run directory as a :class:`PolicyRun` (V as its certificate; samples counted over every round)."""
    run = load_run(path, system, trust)
    cfg = run.config
    cegis = run.metrics.get("cegis") or {}  # counterexample-guided runs: count every round
    iters = int(cegis.get("total_iterations") or run.metrics.get("iterations") or 0)
    samples = int(cfg.n_states) * (iters if cfg.resample else 1)
    label = f"lyapunov-{cfg.method}" + (f"-{cfg.loss}" if cfg.method == Method.DR else "")
    return PolicyRun(path, "lyapunov", run.system, run.controller, run.lyapunov, samples,
                     cegis.get("total_time_s", run.metrics.get("train_time_s")), label, cfg.to_dict(), run.metrics,
                     {"run": run, "distinct_states": int(cfg.n_states), "iterations": iters})

