"""The V step of a V-pi iteration: a quadratic V's set grown by convex programs, the controller held fixed.

For ``V(z) = z^T P z`` and a fixed controller, everything a per-state condition is made of is affine in ``P`` at a
fixed state ``z``: ``V``, ``Vdot_j = grad V . zdot_j = 2 z^T P zdot_j``, the decay ``gamma ||z|| + alpha V``, and the
vector ``W^T grad V`` whose norm is the DR conditions' ``lip``. Where the condition combines its components by the
maximum over the samples (plain decrease, the baseline's one sample, DR pointwise with ``eps N <= 1``), the
condition at ``z`` is then a second-order cone constraint on ``P``, and so is the whole trained condition at a finite
set of states. :func:`grow_quadratic` takes ``steps`` steps of majorise-minimise on ``log det P`` (the set's volume is
``det P^-1/2`` up to a constant; ``tr(P_k^-1 P)`` majorises ``log det P`` at ``P_k``), each a semidefinite program::

    minimise tr(P_k^-1 P)  subject to
        the condition, with the training's margin ``margin_rate V``, at states drawn in {z^T P_k z <= (1 + trust) c}
        P >= P_k / (1 + trust)                    (the new set inside the one the states were drawn in)
        min over each face of z^T P z >= c_faces  (``[[P, e_i], [e_i^T, h_i^2 / c_faces]] >= 0``)
        s P s >= alpha_hat I                      (a P the network ``||A z/s||^2 + alpha_hat ||z/s||^2`` can hold)
        A_j^T P + P A_j + local_rate P <= 0       (V's local rate at x*, every sample's closed-loop Jacobian)

It is the sampled form of the classical expansion of a region of attraction by alternating V and the controller
(the V-s iteration of sum-of-squares programming; Jarvis-Wloszek et al. 2003, Topcu et al. 2008): the controller
is trained with V (:mod:`drlyap.training.trainer`), then this step enlarges V's set as far as that controller's
condition allows at the states drawn. The states are samples, so the result is a proposal: the acceptance check and
the proofs that follow judge it, exactly as they judge a trained pair. The condition's own code supplies every
quantity (its ``components`` read on unit terms give how each enters), so no formula is written twice.
"""

from __future__ import annotations

import copy
import warnings
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition, DecreaseTerms
from drlyap.kinds import Model
from drlyap.regions import Region, ball_volume

TRUST = 0.3
"""How far one step may grow the set: the states are drawn in ``{V <= (1 + TRUST) c}`` and the new set lies inside it."""


def quadratic_form(lyapunov) -> Tensor | None:
    """``P (n, n)`` float64 on the CPU with ``V(z) = z^T P z`` for a V without hidden layers (None for any other V)."""
    phi = lyapunov.phi
    if phi.skip is not None or len(phi.layers) != 1:
        return None
    s = phi.input_scale.double().cpu()
    a = phi.layers[0].weight.detach().double().cpu() / s
    return a.T @ a + torch.diag(lyapunov.alpha_hat / s.square())


def _affine_structure(condition: Condition, count: int) -> tuple[Tensor, Tensor] | None:
    """``(decay coefficient (N,), lip coefficient (N,))`` with ``components = vdot + decay c_d + lip c_l`` and a
    combine that is the maximum over the samples, read from the condition's own code; None where it is not so."""
    zero, one = torch.zeros(1, count, dtype=torch.float64), torch.ones(1, dtype=torch.float64)
    probe = torch.randn(3, count, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    nil = torch.zeros(3, dtype=torch.float64)
    try:
        plain = condition.components(DecreaseTerms(vdot=probe, lip=nil, decay=nil, value=nil))
        c_d = condition.components(DecreaseTerms(vdot=zero, lip=one * 0, decay=one, value=one))[0]
        c_l = condition.components(DecreaseTerms(vdot=zero, lip=one, decay=one * 0, value=one))[0]
        combined = condition.combine(probe)
    except (NotImplementedError, TypeError, AttributeError):
        return None
    if plain.shape != probe.shape or not torch.allclose(plain, probe) \
            or not torch.allclose(combined, probe.max(-1).values):
        return None
    return c_d, c_l


@dataclass(frozen=True)
class GrowthTarget:
    """What the programs of :func:`grow_quadratic` grow and keep: the set ``{V <= level}``, V at least
    ``faces_level`` on every face of the box, the condition with the training's margin ``margin_rate V`` and V's local
    rate at x* at least ``local_rate`` (0: not asked)."""

    level: float
    faces_level: float
    margin_rate: float = 0.0
    local_rate: float = 0.0


def grow_quadratic(loop: ClosedLoop, condition: Condition, region: Region, target: GrowthTarget, steps: int,
                   generator: torch.Generator, n_states: int = 12000, bar=None) -> dict | None:
    """Grow the set ``{V <= target.level}`` of ``loop``'s quadratic V with its controller fixed (module docstring), in
    place (V is set to the last P found), by ``steps`` programs on ``n_states`` states each. Returns a record (the
    shares of the box before and after, the steps taken and why it stopped), or None where V is not quadratic or the
    condition does not combine by the maximum. ``bar``: a progress reporter (:func:`drlyap.progress.progress`) told
    of each program solved."""
    import cvxpy as cp

    level, faces_level = target.level, target.faces_level
    margin_rate, local_rate = target.margin_rate, target.local_rate

    p = quadratic_form(loop.lyapunov)
    count = condition.xi.shape[0] if condition.xi is not None else 0
    structure = _affine_structure(condition, count) if count else None
    if p is None or structure is None:
        return None
    c_d, c_l = (c.numpy() for c in structure)
    n = loop.system.n
    f64 = ClosedLoop(loop.system, copy.deepcopy(loop.lyapunov).double().cpu(),
                     copy.deepcopy(loop.controller).double().cpu())
    region = Region(region.lo.double().cpu(), region.hi.double().cpu(), region.delta)
    half = torch.minimum(-region.lo, region.hi).double()
    scale = f64.lyapunov.phi.input_scale.double()
    z0 = torch.zeros(1, n, dtype=torch.float64)
    xi = condition.xi.double().cpu()
    jacobians = [f64.jacobian(z0, row, condition.model)[1][0] for row in xi]
    d = torch.diag(half).numpy()
    # in units of the half-widths (P~ = D P D), where the program is well scaled
    local = [(torch.diag(1 / half) @ a @ torch.diag(half)).numpy() for a in jacobians]
    before, stopped, taken = share(p / level, region), "the steps ran out", 0
    for _ in range(steps):
        z = _states_in(p, level * (1 + TRUST), region, n_states, generator)
        rows, lips = _condition_rows(f64, condition, xi, z, half)
        value = _outer(z / half, z / half)
        big = cp.Variable((n, n), symmetric=True)
        vec = cp.vec(big, order="C")
        p_k = (d @ p.numpy() @ d)
        cons = []
        norm = cp.norm(cp.vstack([g @ vec for g in lips]), 2, axis=0) if lips else 0
        for j, row in enumerate(rows):
            affine = row + (c_d[j] * condition.exp_rate + margin_rate) * value
            size = np.abs(affine).max(1) + 1e-12
            decay = c_d[j] * condition.decay_rate * np.linalg.norm(z.numpy(), axis=1)
            lhs = (affine / size[:, None]) @ vec + decay / size
            cons.append((lhs + cp.multiply(c_l[j] / size, norm) if lips else lhs) <= 0)
        for i in range(n):
            e = np.zeros((n, 1))
            e[i] = 1
            cons.append(cp.bmat([[big, e], [e.T, np.array([[1 / faces_level]])]]) >> 0)
        s = (scale / half).numpy()
        cons.append(np.diag(s) @ big @ np.diag(s) >> loop.lyapunov.alpha_hat * np.eye(n))
        cons.append(big >> p_k / (1 + TRUST))
        cons += [a.T @ big + big @ a + local_rate * big << 0 for a in local] if local_rate else []
        problem = cp.Problem(cp.Minimize(cp.trace(np.linalg.inv(p_k) @ big)), cons)
        try:
            with warnings.catch_warnings():  # an inaccurate optimum is still a proposal: the checks judge it
                warnings.simplefilter("ignore", UserWarning)
                problem.solve(solver=cp.CLARABEL)
        except cp.error.SolverError:
            stopped = "the solver failed"
            break
        if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or big.value is None:
            stopped = f"the program is {problem.status}"
            break
        inv = torch.diag(1 / half)
        p = inv @ torch.as_tensor((big.value + big.value.T) / 2, dtype=torch.float64) @ inv
        taken += 1
        if bar is not None:
            bar.set_postfix(share=f"{share(p / level, region):.3g}")
            bar.update(1)
    if taken:
        loop.lyapunov.set_quadratic(p)
    return {"steps": taken, "stopped": stopped, "share_before": before, "share_after": share(p / level, region),
            "states_per_step": n_states}


def share(p: Tensor, region: Region) -> float:
    """The share of the region's box held by ``{z^T P z <= 1}`` (the ellipsoid may leave the box: then above it)."""
    return float(ball_volume(1.0, p.shape[0]) / torch.linalg.det(p).sqrt() / (region.hi - region.lo).double().prod())


def _states_in(p: Tensor, level: float, region: Region, count: int, generator: torch.Generator) -> Tensor:
    """States ``(<= count, n)`` of X_delta in ``{z^T P z <= level}``: half uniform in it, half in its outer shell
    (``V`` in ``[0.64, 1] level``, where the condition binds)."""
    n = p.shape[0]
    chol = torch.linalg.cholesky(p / level)
    d = torch.randn(count, n, generator=generator, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    radius = torch.rand(count, 1, generator=generator, dtype=torch.float64)
    radius = torch.where(torch.arange(count)[:, None] < count // 2, 0.8 + 0.2 * radius, radius ** (1 / n))
    z = torch.linalg.solve_triangular(chol.T, (d * radius).T, upper=True).T
    return z[region.contains(z)]


def _outer(a: Tensor, b: Tensor) -> np.ndarray:
    """Rows ``vec(a_i b_i^T)`` ``(B, n n)``: ``a_i^T P b_i = vec(a_i b_i^T) . vec(P)``."""
    return (a[:, :, None] * b[:, None, :]).reshape(a.shape[0], -1).numpy()


def _condition_rows(loop: ClosedLoop, condition: Condition, xi: Tensor, z: Tensor, half: Tensor) -> tuple[list, list]:
    """For ``P~ = D P D`` (``D = diag(half)``): ``Vdot_j`` at ``z`` as rows ``(B, n n)`` with ``Vdot_j = row . vec(P~)``,
    one per sample, and ``W^T grad V`` as ``k`` such row blocks (empty on the true model)."""
    x = loop.system.to_user(z)
    with torch.no_grad():
        u = loop.controller(z)
        zs = z / half
        if condition.model == Model.TRUE:
            rates = [loop.system.true_dynamics(x, u, row) for row in xi]
            return [2 * _outer(zs, r / half) for r in rates], []
        f, w = loop.system.design_model(x, u)
        rates = [f + (w * row.reshape(1, 1, -1)).sum(-1) for row in xi]
        lips = [2 * _outer((w[:, :, col] / half), zs) for col in range(w.shape[-1])]
        return [2 * _outer(zs, r / half) for r in rates], lips
