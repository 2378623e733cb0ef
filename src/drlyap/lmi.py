"""The largest invariant ellipsoid of the linearisations: a quadratic V and a linear gain from one convex program.

For the true model's linearisations ``(A_j, B_j)`` at ``x*, u*`` (:func:`drlyap.lqr.linearize`, one per shift
``xi_j``), :func:`invariant_ellipsoid` solves, in ``Q = P^-1 (n, n)`` and ``Y = -K Q (m, n)``,

    maximise log det Q  subject to
        A_j Q + Q A_j^T + B_j Y + Y^T B_j^T + rate Q  <=  0      (every j: V = z^T P z decays at ``rate`` under u* - K z)
        Q_ii                                          <=  h_i^2  (the ellipsoid {z^T P z <= 1} inside the state box)
        [[room_k^2, Y_k], [Y_k^T, Q]]                 >=  0      (|K_k z| <= room_k on it: no input saturates)

with ``h`` the state box's half-widths about x* (the nearer face) and ``room`` the input box's room about u* (the
nearer bound). It is the classical design of a saturation-free invariant ellipsoid (Boyd et al., *Linear Matrix
Inequalities in System and Control Theory*, 1994, ch. 7), solved by cvxpy with the Clarabel solver. The LQR's
Riccati solution instead weighs states and inputs: its sublevel set that fits the box is usually far smaller
(measured on the quadrotor: docs/tuning.md, planar quadrotor). The result is a design for the
linearisation only; the warm start (:mod:`drlyap.training.warm_start`) hands it to training, which learns the
condition on the nonlinear model and the proofs check it.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from drlyap.lqr import LQRDesign, linearize
from drlyap.regions import ball_volume
from drlyap.systems import UncertainSystem


def invariant_ellipsoid(system: UncertainSystem, xi: Sequence[Sequence[float]] | Tensor | None = None,
                        rate: float = 0.0) -> LQRDesign:
    """The largest ellipsoid ``{z^T P z <= 1}`` in the state box that ``u = u* - K z`` keeps invariant, with ``V``
    decaying at ``rate`` (1/time unit, >= 0) and no input saturating, for the linearisations at the nominal
    parameters and at every row of ``xi (N, k)`` (module docstring). Returns the design as an
    :class:`~drlyap.lqr.LQRDesign` (``P``, ``K``, the nominal ``A``, ``B``; ``Q``, ``R`` empty). Raises
    ``ValueError`` when the program has no solution (no gain stabilises every linearisation at that rate)."""
    import cvxpy as cp

    if not (math.isfinite(rate) and rate >= 0):
        raise ValueError(f"the ellipsoid's decay rate must be a finite number >= 0, got {rate}")
    shifts = [None] + ([] if xi is None else [system.check_xi(row) for row in torch.as_tensor(xi, dtype=torch.float64)])
    models = [linearize(system, shift) for shift in shifts]
    lo, hi = system.local_box()
    half = torch.minimum(-lo, hi).numpy()
    ulo, uhi = (torch.tensor(b, dtype=torch.float64) for b in system.input_box)
    u_star = torch.tensor(system.equilibrium_input, dtype=torch.float64)
    room = torch.minimum(u_star - ulo, uhi - u_star).numpy()
    if not (half > 0).all() or not (room > 0).all():
        raise ValueError(f"{system.name}: x* and u* must lie inside the state and input boxes for an invariant ellipsoid")
    n, m = system.n, system.m
    q, y = cp.Variable((n, n), symmetric=True), cp.Variable((m, n))
    constraints = [q >> 0]
    for a, b in models:
        a, b = a.numpy(), b.numpy()
        lhs = a @ q + q @ a.T + b @ y + y.T @ b.T + rate * q
        constraints.append((lhs + lhs.T) / 2 << 0)
    constraints += [q[i, i] <= half[i] ** 2 for i in range(n)]
    constraints += [cp.bmat([[np.array([[room[k] ** 2]]), y[k:k + 1, :]], [y[k:k + 1, :].T, q]]) >> 0 for k in range(m)]
    problem = cp.Problem(cp.Maximize(cp.log_det(q)), constraints)
    try:
        with warnings.catch_warnings():  # an inaccurate optimum is still a valid start: training and the proofs judge it
            warnings.simplefilter("ignore", UserWarning)
            problem.solve(solver=cp.CLARABEL)
        status = problem.status
    except cp.error.SolverError:
        status = "not solved: the solver failed"
    if status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or q.value is None:
        raise ValueError(f"{system.name}: no linear gain keeps an ellipsoid in the box invariant at decay rate {rate} "
                         f"for every linearisation (the program is {status})")
    q_t = torch.as_tensor((q.value + q.value.T) / 2, dtype=torch.float64)
    p = torch.linalg.inv(q_t)
    k = -torch.as_tensor(y.value, dtype=torch.float64) @ p
    a0, b0 = models[0]
    empty = torch.zeros(0, 0, dtype=torch.float64)
    return LQRDesign(system, empty, empty, a0, b0, k, (p + p.T) / 2)


def ellipsoid_share(system: UncertainSystem, p: Tensor) -> float:
    """The share of the state box's volume held by ``{z^T P z <= 1}`` (``p (n, n)``, positive definite)."""
    lo, hi = (torch.tensor(b, dtype=torch.float64) for b in system.state_box)
    return float(ball_volume(1.0, system.n) / torch.linalg.det(p).sqrt() / (hi - lo).prod())
