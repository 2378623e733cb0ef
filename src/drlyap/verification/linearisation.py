"""The closed-loop linearisation at x* and its quadratic Lyapunov function, for the local proof of
:mod:`drlyap.verification.roa` when the neural V's own second-order proof fails.

:func:`closed_loop_jacobians` computes ``A_j = dF_j/dz (0)`` of every sample's closed loop
``F_j(z) = f(x* + z, pi(z), xi_j)`` by running the system's and the controller's own code on dual numbers
(the same code path the verifier bounds; the result is the midpoint of a float64 interval enclosure).
:func:`lyapunov_matrix` solves ``A_s^T P_s + P_s A_s = -I`` in the coordinates scaled by the box's half-widths
``s`` (``z = S z_s``) and returns ``P = S^-1 P_s S^-1``, so ``W(z) = z^T P z`` has the Hessian of ``Wdot`` at
x* equal to ``-2 S^-2`` for that ``A``: negative definite and conditioned like the box, whatever V looks like.
:func:`common_lyapunov_matrix` picks one ``P`` for all samples' ``A_j`` (their mean's, improved numerically
where it fails for some ``A_j``).

Nothing here is a proof: ``A`` and ``P`` only *choose* the certificate ``W``; what is claimed about ``W`` is
proved afterwards by the verifier's enclosures and branch and bound (:func:`drlyap.verification.roa.linearisation_local`).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import torch
from torch import Tensor

from drlyap.conditions import PlainDecrease
from drlyap.enclosures import F64, Dual, Interval
from drlyap.networks import Controller
from drlyap.systems import UncertainSystem


def closed_loop_jacobians(system: UncertainSystem, controller: Controller, plain: PlainDecrease) -> list[Tensor]:
    """``A_j (n, n)`` for every sample ``xi_j`` of ``plain`` on its model (``true``: ``F(x, u, p0 + xi)``;
    ``design``: ``f + W xi``), at the local origin ``z = 0``."""
    n = system.n
    eye = torch.eye(n, dtype=F64)
    out = []
    if plain.model == "true":
        zero = torch.zeros(1, n, dtype=F64)
        z = Dual(Interval(zero, zero), Interval(eye[None], eye[None]))
        x, u = system.to_user(z), controller(z)
        for xi in plain.xi:
            f = system.true_dynamics(x, u, xi)
            out.append(f.d.mid[0].clone())
        return out
    # design model: row i of F is e_i . (f + W xi), evaluated on n copies of x* with unit covectors e_i
    zero = torch.zeros(n, n, dtype=F64)
    tangent = eye[None].expand(n, n, n).clone()
    z = Dual(Interval(zero, zero), Interval(tangent, tangent))
    x, u = system.to_user(z), controller(z)
    gf, gw = system.weighted_design(x, u, Interval(eye, eye))
    for xi in plain.xi:
        f = gf + (gw * Interval.const(xi)).sum(-1)
        out.append(f.d.mid.clone())
    return out


def is_hurwitz(a: Tensor) -> tuple[bool, list[complex]]:
    """Whether every eigenvalue of ``a`` has a negative real part (numerically), and the eigenvalues."""
    ev = np.linalg.eigvals(a.numpy())
    return bool(np.all(ev.real < 0)), [complex(e) for e in ev]


def lyapunov_matrix(a: Tensor, half_widths: Tensor) -> Tensor:
    """``P`` with ``A^T P + P A = -S^-2`` (``S = diag(half_widths)``): the solution of the Lyapunov equation
    with ``Q = I`` in box-scaled coordinates, mapped back to local ones; symmetric, positive definite when
    ``A`` is Hurwitz."""
    s = half_widths.to(F64)
    a_s = (a * s[None, :] / s[:, None]).numpy()  # S^-1 A S
    p_s = scipy.linalg.solve_continuous_lyapunov(a_s.T, -np.eye(a.shape[0]))
    p = torch.as_tensor(p_s, dtype=F64) / s[:, None] / s[None, :]
    return (p + p.T) / 2


def decrease_rates(jacobians: Tensor | list[Tensor], p: Tensor, half_widths: Tensor) -> Tensor:
    """``(J,)``: for each ``A_j``, the largest eigenvalue of ``A_j^T P + P A_j`` over the smallest of ``P``, both
    in box-scaled coordinates: negative exactly when ``z^T P z`` decreases along ``A_j``'s linear flow."""
    s = torch.diag(half_widths.to(F64))
    a = torch.stack(list(jacobians)) if isinstance(jacobians, list) else jacobians
    low = torch.linalg.eigvalsh(s @ p @ s).min()
    return torch.linalg.eigvalsh(s @ (a.transpose(-1, -2) @ p + p @ a) @ s).amax(-1) / low


def common_lyapunov_matrix(jacobians: list[Tensor], half_widths: Tensor, steps: int = 2000) -> Tensor:
    """A ``P`` with ``A_j^T P + P A_j`` negative definite for every sample's ``A_j`` where one is found: the
    :func:`lyapunov_matrix` of their mean if it already is one (the usual case when the samples differ
    little), else that ``P`` improved by Adam on a Cholesky factor in box-scaled coordinates, minimising a
    soft maximum of :func:`decrease_rates` (the quadrotor's samples move its fast attitude mode from -106 to
    -129, and the mean's ``P`` fails for three of five). Returns the best ``P`` seen."""
    s = half_widths.to(F64)
    stack = torch.stack(jacobians).to(F64)
    p = lyapunov_matrix(stack.mean(0), s)
    if not bool(torch.isfinite(p).all()):
        return p
    best_rate = float(decrease_rates(stack, p, s).max())
    if best_rate < 0:
        return p
    a_s = stack * s[None, None, :] / s[None, :, None]  # S^-1 A_j S
    p_s = p * s[:, None] * s[None, :]
    factor, info = torch.linalg.cholesky_ex(p_s / torch.trace(p_s))
    if int(info) != 0:  # the mean's A is not Hurwitz: no starting point
        return p
    best, unit = p, torch.ones_like(s)
    with torch.enable_grad():
        factor = factor.clone().requires_grad_(True)
        opt = torch.optim.Adam([factor], lr=1e-3)
        for _ in range(steps):
            q = factor @ factor.T
            q = q / torch.trace(q)
            rates = decrease_rates(a_s, q, unit)  # already in box-scaled coordinates
            worst = float(rates.detach().max())
            if worst < best_rate:
                best_rate, best = worst, (q.detach() / s[:, None] / s[None, :])
            loss = torch.logsumexp(20 * rates / rates.detach().abs().max(), 0)
            opt.zero_grad()
            loss.backward()
            opt.step()
    return (best + best.T) / 2
