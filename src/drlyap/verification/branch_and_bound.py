"""Branch and bound over boxes of X_delta: prove a decrease condition, or find where it fails; suprema.

:func:`verify_condition` proves ``residual(z) <= 0`` for every local state ``z`` of a region X_delta (the
state box minus the open delta-ball) for a per-state condition of :mod:`drlyap.conditions`, or finds a
state where it fails (re-checked by the ordinary torch code path). :func:`maximize` bounds suprema of
functions over a union of boxes; :func:`uniform_margin` uses it for the uniform DR condition.

The networks are the stored weights read as float64 numbers and evaluated in exact real arithmetic;
every bound is computed in float64 with outward rounding (:mod:`drlyap.enclosures`), so it encloses the
real value. Boxes whose upper bound is ``<= 0`` are verified, a box whose centre violates the condition
is a counterexample, the rest are bisected (on the side that adds most to the bound, among the sides at
least 1/16 of the widest normalised one) until a time limit, box budget or minimum box size is reached.

Limits: the claim is about the float64 reading of the weights in real arithmetic (training and simulation
run float32; counterexamples report the residual both ways). A box straddling the sphere ``||z|| = delta``
is bounded as a whole, so a violation just inside the ball keeps it unverified down to the minimum box
size (the verdict is then ``unknown``, never wrong). Costs grow exponentially with the state dimension.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition, DRUniform
from drlyap.config import Budget
from drlyap.enclosures import EPS, F64, round_down, round_up
from drlyap.regions import Region, box_grid, default_grid, inside_ball, split
from drlyap.verification.bounds import (
    box_bounds,
    combine_lower,
    combine_upper,
    condition_and_value_objective,
    condition_objective,
    sublevel_upper,
)
from drlyap.verification.partition import PartitionRecorder
from drlyap.verification.results import ConditionProof, UniformMargin


def verify_condition(loop: ClosedLoop, condition: Condition, region: Region, budget: Budget = Budget(), *,
                     level: float | None = None, grid: Sequence[int] | None = None, keep_boxes: int = 50,
                     stop_at_counterexample: bool = False, violation_width: float = 1e-2) -> ConditionProof:
    """Prove ``residual(z) <= 0`` for the closed loop on the region X_delta by branch and bound, or find where it
    fails, within ``budget`` (boxes, seconds, minimum box width, enclosure).

    ``level``: prove it only on the sublevel set ``{V <= level}`` of X_delta (a box on which V provably exceeds
    the level needs nothing more; a counterexample must have ``V <= level``); the verified fraction is then
    the share of X_delta where the condition or ``V > level`` is proved.

    ``budget.min_width``: boxes whose widest side (relative to the state box) is below it are not split further.
    ``violation_width``: a box whose centre is a confirmed counterexample is still split (to sharpen the
    verified fraction) until its widest relative side is below this. ``budget.boxes``: processed boxes at most.
    ``grid``: boxes per axis at the start. ``keep_boxes``: how many unverified boxes to list.
    ``stop_at_counterexample``: return at the first confirmed one (the fraction then counts every box not
    yet verified as unverified). ``budget.enclosure``: how boxes are bounded
    (:func:`~drlyap.verification.bounds.box_bounds`: ``mean-value`` or ``affine``; None: by the dimension).
    """
    if not condition.per_state:
        raise ValueError("use uniform_margin for the uniform condition")
    system = loop.system
    enclosure = budget.enclosure_for(system.n)
    time_limit, max_boxes, min_width, batch = budget.seconds, budget.boxes, budget.min_width, budget.batch
    delta = region.delta
    start = time.perf_counter()
    objective = (condition_objective if level is None else condition_and_value_objective)(loop, condition)
    scale = region.scale
    per_axis = list(grid or default_grid(system.n))
    lo, hi = box_grid(region.lo, region.hi, per_axis)
    tree = PartitionRecorder(per_axis, lo.shape[0], enclosure)
    keep = region.meets(lo, hi)
    tree.inside_ball(tree.roots[~keep])
    lo, hi, ids = lo[keep], hi[keep], tree.roots[keep]
    volume = region.volume()
    processed = verified_count = 0
    unverified_vol = 0.0
    leaves_lo: list[Tensor] = []
    leaves_hi: list[Tensor] = []
    sup_lo, sup_hi = -math.inf, -math.inf
    cex: tuple[float, Tensor] | None = None
    n_cex_boxes = 0
    stopped = "finished"
    while lo.shape[0]:
        if time.perf_counter() - start > time_limit:
            stopped = "time limit"
            break
        if processed >= max_boxes:
            stopped = "box budget"
            break
        clo, chi, lo, hi = lo[:batch], hi[:batch], lo[batch:], hi[batch:]
        cids, ids = ids[:batch], ids[batch:]
        lb_c, ub_c, at, sens, form = box_bounds(objective, clo, chi, enclosure, sensitivity=True, keep_form=True)
        processed += clo.shape[0]
        centre = (clo + chi) / 2
        in_region = region.in_region(centre)
        at_lo = at.lo
        outside = torch.zeros(clo.shape[0], dtype=torch.bool)
        if level is not None:  # the last component is V: boxes above the level are done, centres must lie in the set
            outside, in_region = lb_c[:, -1] > level, in_region & (at.hi[:, -1] <= level)
            ub_c, at_lo = ub_c[:, :-1], at_lo[:, :-1]
        ub = combine_upper(condition, ub_c)
        if level is not None and form is not None:
            ub = torch.minimum(ub, sublevel_upper(condition, form, level))
        centre_lb = combine_lower(condition, at_lo)
        if in_region.any():
            sup_lo = max(sup_lo, float(centre_lb[in_region].max()))
        ub = torch.where(outside, -torch.inf, ub)
        ok = ub <= 0
        tree.proved(cids[ok & ~outside], ub[ok & ~outside])
        tree.above_level(cids[ok & outside], lb_c[ok & outside, -1])  # none without a level: outside is all False
        verified_count += int(ok.sum())
        if (ok & ~outside).any():
            sup_hi = max(sup_hi, float(ub[ok & ~outside].max()))
        bad = ~ok & in_region & (centre_lb > 0)
        if bad.any():
            values = loop.exact(condition, centre[bad])
            confirmed = values > 0
            if confirmed.any():
                best = int(values.argmax())
                if cex is None or float(values[best]) > cex[0]:
                    cex = (float(values[best]), centre[bad][best])
                n_cex_boxes += int(confirmed.sum())
                idx = bad.nonzero().squeeze(-1)[confirmed]
                bad = torch.zeros_like(bad)
                bad[idx] = True
            else:
                bad = torch.zeros_like(bad)
        if bad.any() and stop_at_counterexample:
            stopped = "counterexample"
            unverified_vol += float((chi[~ok] - clo[~ok]).prod(-1).sum())
            leaves_lo.append(clo[~ok])
            leaves_hi.append(chi[~ok])
            sup_hi = math.inf
            break
        rel_width = ((chi - clo) / scale).amax(-1)
        bad = bad & (rel_width < violation_width)  # violating boxes still wide enough are split like the rest
        if bad.any():
            unverified_vol += float((chi[bad] - clo[bad]).prod(-1).sum())
            sup_hi = max(sup_hi, float(ub[bad].max()))
            leaves_lo.append(clo[bad])
            leaves_hi.append(chi[bad])
        rest = ~ok & ~bad
        small = rest & (rel_width < min_width)
        if small.any():
            unverified_vol += float((chi[small] - clo[small]).prod(-1).sum())
            sup_hi = max(sup_hi, float(ub[small].max()))
            leaves_lo.append(clo[small])
            leaves_hi.append(chi[small])
        divide = rest & ~small
        if divide.any():
            nlo, nhi = split(clo[divide], chi[divide], scale, sens[divide])
            children = tree.split(cids[divide], chi[divide], nhi)
            keep = region.meets(nlo, nhi)
            tree.inside_ball(children[~keep])
            lo, hi, ids = torch.cat([lo, nlo[keep]]), torch.cat([hi, nhi[keep]]), torch.cat([ids, children[keep]])
    if lo.shape[0]:
        unverified_vol += float((hi - lo).prod(-1).sum())
        leaves_lo.append(lo)
        leaves_hi.append(hi)
        sup_hi = math.inf
    left_lo = torch.cat(leaves_lo) if leaves_lo else torch.empty(0, system.n, dtype=F64)
    left_hi = torch.cat(leaves_hi) if leaves_hi else torch.empty(0, system.n, dtype=F64)
    if cex is not None:
        status = "violated"
    elif left_lo.shape[0] == 0:
        status = "verified"
    else:
        status = "unknown"
    fraction = max(0.0, min(1.0, 1.0 - unverified_vol / volume)) if volume > 0 else 1.0
    if status == "verified":
        fraction = 1.0
    boxes = [{"lo": system.to_user(a[None])[0].tolist(), "hi": system.to_user(b[None])[0].tolist()}
             for a, b in zip(left_lo[:keep_boxes], left_hi[:keep_boxes])]
    result = ConditionProof(
        condition=condition.label, status=status, verified_fraction=fraction, delta=float(delta),
        boxes_processed=processed, boxes_verified=verified_count, time_s=time.perf_counter() - start,
        n_unverified=int(left_lo.shape[0]), unverified_boxes=boxes, n_counterexample_boxes=n_cex_boxes,
        sup_bounds=[sup_lo, sup_hi], stopped=stopped, level=level)
    if status == "verified":
        result.partition = tree.finish()
    if cex is not None:
        result.counterexample_value = cex[0]
        result.counterexample_value_float32 = float(loop.exact(condition, cex[1][None], torch.float32)[0])
        result.counterexample_local = cex[1].tolist()
        result.counterexample = system.to_user(cex[1][None])[0].tolist()
    return result


# =========================================================================== suprema
def maximize(objective: Callable, lo: Tensor, hi: Tensor, scale: Tensor, budget: Budget, *,
             centre_ok: Callable | None = None, box_ok: Callable | None = None, rel_tol: float = 1e-3,
             abs_tol: float = 1e-9) -> tuple[Tensor, Tensor, dict]:
    """Bounds ``lower <= sup <= upper`` (each ``(Q,)``) of every component of ``objective`` over a union of boxes
    ``[lo, hi] (B, n)`` (``scale (n,)``: the widths that box sides are measured against).

    The upper bound is sound over the boxes (kept by ``box_ok``); the lower bound comes from box centres
    accepted by ``centre_ok`` (points of the set). Boxes that may still raise some component's supremum
    by more than the tolerance are split, widest side first, until the budget's time or boxes or minimum size.
    ``budget.enclosure``: as for :func:`verify_condition` (None: by the boxes' dimension).
    """
    enclosure = budget.enclosure_for(lo.shape[-1])
    time_limit, max_boxes, min_width, batch = budget.seconds, budget.boxes, budget.min_width, budget.batch
    start = time.perf_counter()
    closed: Tensor | None = None
    best: Tensor | None = None
    processed = 0
    stopped = "finished"
    if box_ok is not None:
        keep = box_ok(lo, hi)
        lo, hi = lo[keep], hi[keep]
    known: Tensor | None = None  # (B, Q): an upper bound on each queued box (its parent's), once one is split
    while lo.shape[0]:
        if time.perf_counter() - start > time_limit or processed >= max_boxes:
            stopped = "time limit" if processed < max_boxes else "box budget"
            break
        clo, chi, lo, hi = lo[:batch], hi[:batch], lo[batch:], hi[batch:]
        if known is not None:
            known = known[clo.shape[0]:]
        _, ub, at = box_bounds(objective, clo, chi, enclosure)
        processed += clo.shape[0]
        centre = (clo + chi) / 2
        good = centre_ok(centre) if centre_ok is not None else torch.ones(clo.shape[0], dtype=torch.bool)
        if good.any():
            cand = at.lo[good].amax(0)
            best = cand if best is None else torch.maximum(best, cand)
        ref = best if best is not None else torch.full_like(ub[0], -torch.inf)
        tol = torch.clamp(rel_tol * ref.abs(), min=abs_tol)
        refine = (ub > ref + tol).any(-1) & (((chi - clo) / scale).amax(-1) >= min_width)
        done = ~refine
        if done.any():
            cand = ub[done].amax(0)
            closed = cand if closed is None else torch.maximum(closed, cand)
        if refine.any():
            nlo, nhi = split(clo[refine], chi[refine], scale)
            inherited = ub[refine].repeat(2, 1)  # split() returns the lower halves, then the upper halves
            if box_ok is not None:
                keep = box_ok(nlo, nhi)
                nlo, nhi, inherited = nlo[keep], nhi[keep], inherited[keep]
            if known is None:
                known = torch.full((lo.shape[0], ub.shape[1]), torch.inf, dtype=ub.dtype, device=ub.device)
            lo, hi, known = torch.cat([lo, nlo]), torch.cat([hi, nhi]), torch.cat([known, inherited])
    if lo.shape[0]:
        if lo.shape[0] <= 4 * batch:
            rest = box_bounds(objective, lo, hi, enclosure)[1].amax(0)
        elif known is not None:  # too many to bound again in time: their parents' bounds hold for them
            rest = known.amax(0)
        else:
            rest = torch.full_like(closed if closed is not None else best, torch.inf)
        closed = rest if closed is None else torch.maximum(closed, rest)
    if closed is None:
        raise ValueError("the set to maximise over is empty")
    if best is None:
        best = torch.full_like(closed, -torch.inf)
    return best, closed, {"boxes_processed": processed, "time_s": time.perf_counter() - start, "stopped": stopped}


def uniform_margin(loop: ClosedLoop, condition: DRUniform, region: Region, budget: Budget = Budget(seconds=3.0), *,
                   rel_tol: float = 1e-3) -> UniformMargin:
    """Bounds of the uniform DR condition's left side over X_delta (``eq: dr_clf_constraint_relaxed``), see
    :class:`~drlyap.verification.results.UniformMargin`."""
    delta = region.delta
    lo, hi = region.boxes()
    lower, upper, info = maximize(
        condition_objective(loop, condition), lo, hi, region.scale, budget,
        centre_ok=region.in_region, box_ok=lambda a, b: ~inside_ball(a, b, delta), rel_tol=rel_tol)
    coef = condition.r / condition.eps
    m_up = float(round_up(condition.margin(upper), 64 * EPS, upper.abs().amax() * (1 + coef)))
    m_lo = float(round_down(condition.margin(lower), 64 * EPS, lower.abs().amax() * (1 + coef)))
    status = "verified" if m_up <= 0 else ("violated" if m_lo > 0 else "unknown")
    return UniformMargin(condition="DR uniform", status=status, margin_upper=m_up, margin_lower=m_lo,
                         lipschitz_sup=[float(lower[0]), float(upper[0])],
                         h_sup=[[float(a), float(b)] for a, b in zip(lower[1:], upper[1:])],
                         lipschitz_term=[coef * float(lower[0]), coef * float(upper[0])], delta=float(delta), **info)


