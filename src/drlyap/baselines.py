"""Classical baseline (LQR) and one loader for every kind of run (Lyapunov, LQR, RL).

LQR design (:func:`lqr_design`): the TRUE model ``F(x, u, p0 + E xi)`` is linearised at ``x*, u*``
with autograd Jacobians, ``A = dF/dx``, ``B = dF/du``, at the nominal parameters (``xi = 0``) unless
a shift is given. The continuous algebraic Riccati equation ``A^T P + P A - P B R^-1 B^T P + Q = 0``
is solved with :func:`scipy.linalg.solve_continuous_are` and ``K = R^-1 B^T P``.

Default weights (Bryson's rule on the boxes): ``Q = diag(1 / h_x^2)`` with ``h_x`` the half-widths of
the state box, ``R = diag(1 / h_u^2)`` with ``h_u`` the half-widths of the input box. For the
pendulum that is ``Q = diag(1/pi^2, 1/64)``, ``R = 1/225`` (``1/81`` for ``pendulum-u9``).

Controller: ``u = clamp(u* - K z, U)`` with ``z = x - x*`` and angles wrapped into ``[-pi, pi)``
(:meth:`UncertainSystem.to_local`), so the feedback is discontinuous on the circle exactly like the
learned controllers. Certificate: the quadratic Lyapunov function ``V(x) = z^T P z`` of the
unsaturated linearisation (a certificate only near ``x*``; along large-angle trajectories it may rise).

Comparison of runs of any kind lives in :mod:`drlyap.comparison` (``drlyap compare``).

Run directory of kind ``lqr`` (written atomically)::

    RUN_DIR/
      run.json       {"kind": "lqr", "format": 1, "system": system.describe()}
      config.json    system, Q, R, xi used for the design
      lqr.json       K, P, A, B, closed-loop eigenvalues of A - B K
      metrics.json   samples (0), train_time_s, closed-loop eigenvalues, optional evaluations
      figures/

:func:`drlyap.rundir.load_policy_run` loads any run directory (``lyapunov``, ``lqr``, ``rl``) into a
:class:`drlyap.rundir.PolicyRun` with a common interface; this module registers the ``lqr`` loader.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from drlyap.rundir import (  # noqa: F401  (PolicyRun, load_policy_run: re-exported for existing callers)
    PolicyRun,
    RunDirError,
    atomic_dir,
    ensure_new,
    load_policy_run,
    read_run_json,
    register_loader,
    run_record,
    run_system,
    write_json,
)
from drlyap.systems import UncertainSystem, resolve_system, system_source


# --------------------------------------------------------------------------- linearisation and LQR
def linearize(system: UncertainSystem, xi: Sequence[float] | Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``A (n, n)``, ``B (n, m)``: Jacobians of the true model at ``x*, u*`` (float64, autograd)."""
    x_star = torch.tensor([system.equilibrium], dtype=torch.float64)
    u_star = torch.tensor([system.equilibrium_input], dtype=torch.float64)
    shift = None if xi is None else system.check_xi(xi)
    a, b = torch.autograd.functional.jacobian(lambda x, u: system.true_dynamics(x, u, shift)[0], (x_star, u_star))
    return a[:, 0, :].detach(), b[:, 0, :].detach()


def default_weights(system: UncertainSystem) -> tuple[Tensor, Tensor]:
    """Bryson's rule: ``Q = diag(1 / half-width(X)^2)``, ``R = diag(1 / half-width(U)^2)``."""
    slo, shi = (torch.tensor(b, dtype=torch.float64) for b in system.state_box)
    ulo, uhi = (torch.tensor(b, dtype=torch.float64) for b in system.input_box)
    return torch.diag(4.0 / (shi - slo) ** 2), torch.diag(4.0 / (uhi - ulo) ** 2)


@dataclass
class LQRDesign:
    """An LQR design: weights, linearisation, gain and Riccati solution (all float64 tensors)."""

    system: UncertainSystem
    Q: Tensor
    R: Tensor
    A: Tensor
    B: Tensor
    K: Tensor  # (m, n)
    P: Tensor  # (n, n)
    xi: list[float] | None = None

    @property
    def closed_loop_eigenvalues(self) -> list[complex]:
        return [complex(v) for v in np.linalg.eigvals((self.A - self.B @ self.K).numpy())]

    def controller(self, x: Tensor) -> Tensor:
        """``u = clamp(u* - K z, U)`` for user-coordinate states ``x (B, n)`` -> ``(B, m)`` float64."""
        z = self.system.to_local(_check_states(self.system, x))
        u_star = torch.tensor(self.system.equilibrium_input, dtype=torch.float64)
        lo, hi = (torch.tensor(b, dtype=torch.float64) for b in self.system.input_box)
        return torch.clamp(u_star - z @ self.K.T, lo, hi)

    def certificate(self, x: Tensor) -> Tensor:
        """``V = z^T P z`` ``(B,)``."""
        z = self.system.to_local(_check_states(self.system, x))
        return torch.einsum("bi,ij,bj->b", z, self.P, z)


def _check_states(system: UncertainSystem, x: Tensor) -> Tensor:
    x = torch.as_tensor(x)
    if x.ndim != 2 or x.shape[1] != system.n:
        raise ValueError(f"{system.name} states must have shape (B, {system.n}), got {tuple(x.shape)}")
    return x.to(torch.float64)


def _diag_weights(values: Sequence[float] | Tensor | None, size: int, default: Tensor, what: str) -> Tensor:
    if values is None:
        return default
    t = torch.as_tensor(values, dtype=torch.float64)
    if t.ndim == 1:
        t = torch.diag(t)
    if t.shape != (size, size) or not torch.isfinite(t).all():
        raise ValueError(f"{what} must be {size} diagonal entries or a {size}x{size} matrix, got shape {tuple(t.shape)}")
    return t


def lqr_design(system: UncertainSystem, Q: Sequence[float] | Tensor | None = None, R: Sequence[float] | Tensor | None = None,
               xi: Sequence[float] | Tensor | None = None) -> LQRDesign:
    """LQR for ``system`` linearised at ``x*, u*`` (nominal parameters unless ``xi`` is given).

    ``Q``/``R``: diagonals or full matrices (default :func:`default_weights`). Raises ``ValueError``
    when the Riccati equation has no stabilising solution (e.g. an uncontrollable linearisation).
    """
    from scipy.linalg import solve_continuous_are

    q0, r0 = default_weights(system)
    q = _diag_weights(Q, system.n, q0, "Q")
    r = _diag_weights(R, system.m, r0, "R")
    if np.linalg.eigvalsh(q.numpy()).min() < 0:
        raise ValueError("Q must be positive semidefinite")
    if np.linalg.eigvalsh(r.numpy()).min() <= 0:
        raise ValueError("R must be positive definite")
    a, b = linearize(system, xi)
    try:
        p = solve_continuous_are(a.numpy(), b.numpy(), q.numpy(), r.numpy())
    except (np.linalg.LinAlgError, ValueError) as err:
        raise ValueError(f"no stabilising LQR solution for {system.name}: {err}") from err
    p_t = torch.as_tensor(p, dtype=torch.float64)
    p_t = (p_t + p_t.T) / 2
    k = torch.linalg.solve(r, b.T @ p_t)
    design = LQRDesign(system, q, r, a, b, k, p_t, None if xi is None else system.check_xi(xi).tolist())
    if max(v.real for v in design.closed_loop_eigenvalues) >= 0:
        raise ValueError(f"LQR for {system.name} does not stabilise the linearisation: "
                         f"eigenvalues {design.closed_loop_eigenvalues}")
    return design


def save_lqr_run(out: str | os.PathLike, design: LQRDesign, metrics: dict | None = None, overwrite: bool = False,
                 design_time_s: float = 0.0, source: dict | None = None) -> Path:
    """Write an LQR design as a run directory of kind ``lqr`` (atomically); ``source``: see
    :func:`drlyap.rundir.run_record`."""
    system = design.system
    eigs = design.closed_loop_eigenvalues

    def fill(tmp: Path) -> None:
        write_json(tmp / "config.json", {"system": system.name, "Q": design.Q.tolist(), "R": design.R.tolist(),
                                          "xi": design.xi, "weights": "Bryson: 1/half-width^2 (default) or user-given"})
        write_json(tmp / "lqr.json", {"K": design.K.tolist(), "P": design.P.tolist(), "A": design.A.tolist(),
                                       "B": design.B.tolist(),
                                       "closed_loop_eigenvalues": [[v.real, v.imag] for v in eigs]})
        write_json(tmp / "metrics.json", {"samples": 0, "train_time_s": design_time_s,
                                           "closed_loop_eigenvalues": [[v.real, v.imag] for v in eigs]}
                    | (metrics or {}))
        (tmp / "figures").mkdir()
        write_json(tmp / "run.json", run_record("lqr", system, source))

    return atomic_dir(Path(out), fill, overwrite)


def train_lqr(system: str | UncertainSystem, out: str | os.PathLike, Q: Sequence[float] | None = None,
              R: Sequence[float] | None = None, evaluate_test: bool = True, n_init: int = 200, seed: int = 0) -> dict:
    """Design LQR for a system (an object, or a spec for :func:`drlyap.systems.resolve_system`), optionally
    evaluate it at the system's test shift, save a run dir.

    Returns the metrics dict written to ``metrics.json``.
    """
    from drlyap.simulation import evaluate, initial_states

    source = None
    if isinstance(system, str):
        spec, system = system, resolve_system(system)
        source = system_source(spec, system)
    ensure_new(out)
    tic = time.perf_counter()
    design = lqr_design(system, Q, R)
    elapsed = time.perf_counter() - tic
    metrics: dict = {"samples": 0, "train_time_s": elapsed}
    if evaluate_test and system.test_xi is not None:
        x0 = initial_states(system, n_init, torch.Generator().manual_seed(seed))
        xi = torch.tensor(system.test_xi, dtype=torch.float64)
        metrics["evaluations"] = {"test_xi": evaluate(system, design.controller, x0, xi, lyapunov=design.certificate)}
    save_lqr_run(out, design, metrics, design_time_s=elapsed, source=source)
    return json.loads((Path(out) / "metrics.json").read_text())


# --------------------------------------------------------------------------- loader
def load_lqr_run(path: str | os.PathLike, system: UncertainSystem | None = None) -> PolicyRun:
    path = Path(path)
    info, config, gains, metrics = read_run_json(path, "lqr", "run.json", "config.json", "lqr.json", "metrics.json")
    system = run_system(path, config["system"], system, info)
    t = {k: torch.tensor(gains[k], dtype=torch.float64) for k in ("K", "P", "A", "B")}
    if t["K"].shape != (system.m, system.n) or t["P"].shape != (system.n, system.n):
        raise RunDirError(f"{path}: K/P shapes {tuple(t['K'].shape)}/{tuple(t['P'].shape)} do not fit {system.name}")
    design = LQRDesign(system, torch.tensor(config["Q"], dtype=torch.float64), torch.tensor(config["R"], dtype=torch.float64),
                       t["A"], t["B"], t["K"], t["P"], config.get("xi"))
    return PolicyRun(path, "lqr", system, design.controller, design.certificate, 0, metrics.get("train_time_s"), "lqr",
                     config, metrics, {"design": design})


register_loader("lqr", load_lqr_run)
