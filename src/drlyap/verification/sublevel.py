"""Proofs on a sublevel set ``{V <= level}``: V's minimum on the box's faces (the set lies inside the box when it is
above the level), V's minimum where a model's flow may leave the box through them (:func:`exit_minimum`: below it the
flow enters the box wherever the set meets a face), and the condition of region-of-attraction training proved there
(:func:`verify_sublevel`); :func:`prove_trained` proves a run's trained condition either way and settles an unknown
verdict with the falsifier."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition
from drlyap.enclosures import F64, round_down
from drlyap.kinds import Model, Status
from drlyap.networks import QuadraticLyapunov
from drlyap.proof_settings import DEFAULT_SETTLE_STARTS, Budget
from drlyap.regions import Domain, Region, box_grid, default_grid
from drlyap.verification.bounds import box_bounds, value_objective
from drlyap.verification.branch_and_bound import maximize, verify_condition
from drlyap.verification.falsifier import settle_unknown
from drlyap.verification.results import ConditionProof


def box_faces(lo: Tensor, hi: Tensor, per_axis: list[int]) -> tuple[Tensor, Tensor]:
    """Boxes covering the boundary of the box ``[lo, hi]`` (one coordinate pinned per face)."""
    out_lo, out_hi = [], []
    for i in range(lo.shape[0]):
        per = list(per_axis)
        per[i] = 1
        for side in (lo[i], hi[i]):
            flo, fhi = box_grid(lo, hi, per)
            flo[:, i] = side
            fhi[:, i] = side
            out_lo.append(flo)
            out_hi.append(fhi)
    return torch.cat(out_lo), torch.cat(out_hi)


@dataclass
class FaceMinimum:
    """V's least value over (a part of) the state box's faces: ``lower`` a sound lower bound, ``upper`` V at a point
    there (``lower <= min <= upper``); the branch and bound's ``boxes_processed`` and ``stopped`` (``finished``,
    ``box budget`` or ``time limit``)."""

    lower: float
    upper: float
    boxes_processed: int = 0
    stopped: str = "finished"


def boundary_minimum(lyapunov, region: Region, budget: Budget = Budget(seconds=5.0, boxes=1_000_000),
                     rel_tol: float = 1e-3) -> FaceMinimum:
    """A sound lower bound of the minimum of V over the boundary of the state box, and a value of V taken at a point
    of the boundary (so ``lower <= min <= upper``); boxes are refined until ``lower`` is within ``rel_tol`` of
    ``upper`` (or the budget runs out: ``lower`` is then ``-inf``). ``lyapunov``: V (a network, or a quadratic form,
    whose minimum on the faces is computed exactly)."""
    if isinstance(lyapunov, QuadraticLyapunov):  # min of z'Pz on the hyperplane z_i = b is b^2 / (P^-1)_ii
        p = lyapunov.P.to(F64)
        inv_diag = torch.linalg.inv(p).diagonal()
        sides = torch.stack([region.lo, region.hi], -1)  # (n, 2)
        minima = sides.square() / inv_diag[:, None]  # on each face's hyperplane
        low = float(round_down(minima.min(), 1e-9))
        i, j = divmod(int(minima.argmin()), 2)
        point = torch.clamp(torch.linalg.solve(p, torch.eye(region.n, dtype=F64)[i]) * (sides[i, j] / inv_diag[i]),
                            region.lo, region.hi)
        point[i] = sides[i, j]
        return FaceMinimum(low, float(lyapunov(point[None])[0]))
    vobj = value_objective(lyapunov)
    flo, fhi = box_faces(region.lo, region.hi, default_grid(region.n))
    best, neg_up, found = maximize(lambda z: -vobj(z), Domain(flo, fhi, region.scale), budget, rel_tol=rel_tol,
                                   label="V's least value on the box's faces")
    return FaceMinimum(float(-neg_up[0]), float(-best[0]), found.boxes_processed, found.stopped)


def face_sides(lo: Tensor, hi: Tensor, region: Region) -> tuple[Tensor, Tensor]:
    """The face each face box ``[lo, hi] (B, n)`` of :func:`box_faces` lies on: its axis ``(B,)`` and the outward
    sign ``(B,)`` (+1 on the upper face, -1 on the lower)."""
    upper = (lo == region.hi) & (hi == region.hi)
    lower = (lo == region.lo) & (hi == region.lo)
    if not bool((upper | lower).any(-1).all()):
        raise ValueError("a face box lies on no face of the state box")
    axis = (upper | lower).to(torch.int8).argmax(-1)
    return axis, torch.where(upper.gather(-1, axis[:, None])[:, 0], 1.0, -1.0).to(lo.dtype)


def outward_bounds(loop: ClosedLoop, condition: Condition, region: Region, lo: Tensor, hi: Tensor,
                   enclosure: str) -> tuple[Tensor, Tensor]:
    """Lower and upper bounds ``(B, N)`` of the outward component ``s zdot_i`` of the flow of each of the condition's
    ``N`` models (the true model at its shifts, or every shift of its box) over the face boxes ``[lo, hi] (B, n)``
    (face ``i``, outward sign ``s``: :func:`face_sides`)."""
    if condition.model != Model.TRUE:
        raise ValueError("the flow through the box's faces is taken on the true model only")
    axis, sign = face_sides(lo, hi, region)
    xi = condition.xi

    def flows(z):
        return torch.cat([loop.rhs(z, shift) for shift in xi], -1)

    low, up, _ = box_bounds(flows, lo, hi, enclosure)
    n = region.n
    rows = torch.arange(lo.shape[0], device=lo.device)
    cols = torch.arange(low.shape[1] // n, device=lo.device) * n
    at = cols[None, :] + axis.long()[:, None]  # (B, N): the face's component of each model's flow
    lo_i, up_i = low[rows[:, None], at], up[rows[:, None], at]
    out_lo = torch.where(sign[:, None] > 0, lo_i, -up_i)
    out_up = torch.where(sign[:, None] > 0, up_i, -lo_i)
    return torch.nan_to_num(out_lo, nan=-torch.inf), torch.nan_to_num(out_up, nan=torch.inf)


def exit_minimum(loop: ClosedLoop, condition: Condition, region: Region,
                 budget: Budget = Budget(seconds=5.0, boxes=1_000_000), rel_tol: float = 1e-3) -> FaceMinimum:
    """A sound lower bound of V's minimum over the points of the box's faces where the flow of a
    model of ``condition`` (the true model, :func:`outward_bounds`) is not proved to point strictly into the box,
    and V at a face point where some model's flow points out of it or along the face (``inf`` where none was
    found). Below ``lower``, wherever ``{V <= c}`` meets a face every model's flow enters the box there, so no
    trajectory leaves ``{z in box : V(z) <= c}`` through a face. Face boxes whose flow is proved inward are dropped;
    the rest are refined as in :func:`boundary_minimum` (``lower`` is ``-inf`` where the budget runs out first,
    ``inf`` where every face box is dropped)."""
    enclosure = budget.enclosure_for(region.n)
    vobj = value_objective(loop.lyapunov)
    flo, fhi = box_faces(region.lo, region.hi, default_grid(region.n))

    def may_leave(a: Tensor, b: Tensor) -> Tensor:
        return (outward_bounds(loop, condition, region, a, b, enclosure)[1] >= 0).any(-1)

    def leaves(centre: Tensor) -> Tensor:
        return (outward_bounds(loop, condition, region, centre, centre, enclosure)[0] >= 0).any(-1)

    if not bool(may_leave(flo, fhi).any()):
        return FaceMinimum(float("inf"), float("inf"))
    best, neg_up, found = maximize(lambda z: -vobj(z), Domain(flo, fhi, region.scale, may_leave, leaves), budget,
                                   rel_tol=rel_tol, label="V's least value where the flow may leave the box")
    return FaceMinimum(float(-neg_up[0]), float(-best[0]), found.boxes_processed, found.stopped)


FACES_SHARE = 0.25
"""The share of a proof's seconds that a bound of V on the box's faces gets before the condition is proved (with at
most a million boxes): :func:`verify_sublevel`, and the band claim's faces."""


def faces_budget(budget: Budget, n: int) -> Budget:
    """The budget of a bound of V on the faces of an ``n``-state box before a proof within ``budget``:
    :data:`FACES_SHARE` of its seconds, a million boxes, its enclosure resolved for ``n`` states."""
    return replace(budget, seconds=budget.seconds * FACES_SHARE, boxes=1_000_000, enclosure=budget.enclosure_for(n))


def budget_left(budget: Budget, n: int, start: float) -> Budget:
    """What ``budget`` leaves to the condition's proof after the faces' (begun at ``time.perf_counter()`` = ``start``):
    the rest of its seconds (at least one), its enclosure resolved for ``n`` states."""
    left = max(1.0, budget.seconds - (time.perf_counter() - start))
    return replace(budget, seconds=left, enclosure=budget.enclosure_for(n))


def verify_sublevel(loop: ClosedLoop, condition: Condition, region: Region, level: float, budget: Budget = Budget(),
                    **kwargs) -> ConditionProof:
    """Prove what region-of-attraction training asks (``TrainConfig.roa_level``): the condition on
    ``{V <= level}`` minus the delta-ball (:func:`verify_condition` with ``level``) and ``V > level`` on the
    boundary of the box (:func:`boundary_minimum`), so that the sublevel set lies inside the box.

    The result's ``boundary_min_lower`` / ``boundary_min_upper`` bracket V's minimum on the faces; ``status`` is
    ``verified`` only when both hold, ``violated`` when a boundary point has ``V <= level`` or a state of the set
    violates the condition. A quarter of the budget goes to the faces (with boxes up to a million), the rest to
    the condition.
    """
    start = time.perf_counter()
    faces = boundary_minimum(loop.lyapunov, region, faces_budget(budget, loop.n), rel_tol=0.02)
    low, high = faces.lower, faces.upper
    out = verify_condition(loop, condition, region, budget_left(budget, loop.n, start), level=level, **kwargs)
    out.boundary_min_lower, out.boundary_min_upper, out.time_s = low, high, time.perf_counter() - start
    if high <= level:
        out.status, out.stopped = Status.VIOLATED, f"V = {high:.6g} <= {level:g} at a point of the box's boundary"
    elif low <= level and out.status == Status.VERIFIED:
        out.status, out.stopped = Status.UNKNOWN, f"V > {level:g} on the box's boundary not proved (bound {low:.6g})"
    return out


def prove_trained(loop: ClosedLoop, condition: Condition, region: Region, budget: Budget = Budget(),
                  level: float | None = None, falsify_starts: int = DEFAULT_SETTLE_STARTS, **kwargs) -> ConditionProof:
    """The proof of a trained condition: :func:`verify_condition` on X_delta (``level`` None) or
    :func:`verify_sublevel` on ``{V <= level}`` (region-of-attraction training). Where the proof comes back
    ``unknown``, a falsifier from ``falsify_starts`` states looks for a certain violation
    (:func:`~drlyap.verification.falsifier.settle_unknown`; 0: none)."""
    if level is None:
        out = verify_condition(loop, condition, region, budget, **kwargs)
    else:
        out = verify_sublevel(loop, condition, region, level, budget, **kwargs)
    return settle_unknown(out, loop, condition, region, level, starts=falsify_starts)
