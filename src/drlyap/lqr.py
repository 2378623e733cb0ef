"""The classical baseline: LQR on the true model's linearisation at the equilibrium.

:func:`lqr_design` linearises the TRUE model ``F(x, u, p0 + E xi)`` at ``x*, u*`` (autograd Jacobians,
:func:`drlyap.closed_loop.jacobian`), ``A = dF/dx``, ``B = dF/du``, at the nominal parameters (``xi = 0``) unless
a shift is given, and solves the continuous algebraic Riccati equation ``A^T P + P A - P B R^-1 B^T P + Q = 0``
with :func:`scipy.linalg.solve_continuous_are`; ``K = R^-1 B^T P``.

Default weights (Bryson's rule on the boxes): ``Q = diag(1 / h_x^2)`` with ``h_x`` the half-widths of the state
box, ``R = diag(1 / h_u^2)`` with ``h_u`` the half-widths of the input box. For the pendulum that is
``Q = diag(1/pi^2, 1/64)``, ``R = 1/225`` (``1/81`` for ``pendulum-u9``).

Controller: ``u = clamp(u* - K z, U)`` with ``z = x - x*`` and angles wrapped into ``[-pi, pi)``
(:meth:`UncertainSystem.to_local`), so the feedback is discontinuous on the circle exactly like the learned
controllers. Certificate: the quadratic Lyapunov function ``V(x) = z^T P z`` of the unsaturated linearisation (a
certificate only near ``x*``; along large-angle trajectories it may rise). LQR run directories:
:mod:`drlyap.runs.lqr`; the warm start of region-of-attraction training: :mod:`drlyap.training.trainer`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from drlyap.closed_loop import jacobian
from drlyap.systems import UncertainSystem


def linearize(system: UncertainSystem, xi: Sequence[float] | Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``A (n, n)``, ``B (n, m)``: Jacobians of the true model at ``x*, u*`` (float64, autograd)."""
    point = torch.tensor([[*system.equilibrium, *system.equilibrium_input]], dtype=torch.float64)
    shift = None if xi is None else system.check_xi(xi)
    n = system.n
    _, jac = jacobian(lambda xu: system.true_dynamics(xu[:, :n], xu[:, n:], shift), point)
    return jac[0, :, :n], jac[0, :, n:]


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
