"""The level search behind every region of attraction: the largest level ``c`` such that a condition holds on
``{V <= c}`` (over given boxes, optionally outside an ellipsoid ``{z^T P z <= c_q}``), by branch and bound with
the boxes of lowest V first (:func:`level_search`); and how a region-of-attraction search is budgeted.

**Work, not seconds.** Every step of a region-of-attraction search stops after a number of boxes (its share of the
budget's ``boxes``, ``--roa-boxes``), so that what it certifies does not depend on how busy the machine is. The
budget's ``seconds`` (``--roa-time``) stay as a cap on the wall time, split between the steps as the boxes are; a
step that reaches it says so (:data:`TIME_LIMIT`, :func:`time_capped`): its result may differ on a faster machine."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition
from drlyap.enclosures import F64, REL1, round_down
from drlyap.kinds import Enclosure
from drlyap.networks import QuadraticLyapunov
from drlyap.progress import progress as show_progress
from drlyap.proof_settings import Budget
from drlyap.regions import Domain, split
from drlyap.verification.bounds import (
    box_bounds,
    combine_lower,
    combine_upper,
    condition_and_value_objective,
    sublevel_upper,
    value_objective,
    vertex_max,
)
from drlyap.verification.search import BOX_BUDGET as BOX_BUDGET_STOP
from drlyap.verification.search import TIME_LIMIT as TIME_LIMIT_STOP
from drlyap.verification.search import Boxes, DomainQueue, Stopping, Taking, branch_and_bound, in_process

BOX_BUDGET = "box budget (--roa-boxes)"
"""``limited_by`` of a level search that spent its box budget (the level is V's least lower bound on the boxes it left
open)."""

TIME_LIMIT = "time limit (--roa-time): the result may differ on a faster machine"
"""``limited_by`` of a level search stopped by its time cap (as for :data:`BOX_BUDGET`), and what a search whose step
reached its time cap adds to its ``limited_by`` (:func:`time_capped`)."""


def share(boxes: int, fraction: float) -> int:
    """``fraction`` of a box budget ``boxes``, at least 1."""
    return max(1, int(boxes * fraction))


def time_capped(stopped: str | None) -> bool:
    """Whether a step's ``stopped`` (a branch and bound's) or ``limited_by`` (a level search's) is its time cap."""
    return stopped is not None and (stopped == TIME_LIMIT_STOP or TIME_LIMIT in stopped)


def below(level: float) -> float:
    """A level rounded one float64 step down (a sound level stays sound below), infinities as they are."""
    return float(round_down(torch.tensor(level, dtype=F64), REL1)) if math.isfinite(level) else level


class LevelFound(NamedTuple):
    """What :func:`level_search` found: the level, what limited it, the counterexample that did (local coordinates,
    or None) and the boxes it bounded."""

    level: float
    limited_by: str
    counterexample: Tensor | None
    boxes: int


def level_search(loop: ClosedLoop, condition: Condition, domain: Domain, level: float, limited_by: str,
                 budget: Budget, *, floor: float = -math.inf,
                 ellipsoid: tuple[Tensor, float] | None = None) -> LevelFound:
    """The largest level (at most ``level``) such that ``condition`` holds on every state of ``domain`` (its starting
    boxes, and their parts it ``meets``) with ``floor <= V <= level`` (with ``ellipsoid = (P, c_q)``: and
    ``z^T P z >= c_q``, outside the ellipsoid ``L``).

    Boxes with V's lower bound above the level, or V's upper bound below ``floor``, need no proof; the rest are
    proved or split, those with the lowest bound on V first (a box's parts inherit its bound), so that the
    sets ``{V <= c}`` are settled from small ``c`` up and a budget that runs out costs the least level. A box that
    cannot be proved lowers the level to (a lower bound of) V on it: to V at its centre when that centre is a
    confirmed violation the domain ``contains``, else to V's lower bound on it once it reaches ``budget.min_width``,
    or once ``budget.boxes`` boxes are processed (``limited_by`` :data:`BOX_BUDGET`) or ``budget.seconds`` have
    passed (:data:`TIME_LIMIT`, a cap), whichever comes first. Boxes are bounded ``budget.batch`` at a time with
    ``budget.enclosure``.

    With ``ellipsoid`` (the affine enclosure only): boxes inside ``L`` (every vertex; ``L`` is convex) need no proof,
    V's lower bound is taken on each box's part outside ``L`` (:func:`outside_lower`), and boxes are split on the side
    that adds most to the bounds (``split``'s sensitivity): the search behind
    :func:`~drlyap.verification.roa.band.band_roa`. ``budget.compute.progress``: a line on stderr of the boxes
    processed, the level so far and the boxes queued."""
    enclosure = budget.enclosure_for(domain.lo.shape[-1])
    if ellipsoid is not None and enclosure != Enclosure.AFFINE:
        raise ValueError("the search outside an ellipsoid needs the affine enclosure")
    rule = _LevelRule(loop, condition, domain, level, limited_by, floor, ellipsoid, budget.min_width)
    bar = show_progress(budget.boxes, "region of attraction: level search, boxes", budget.compute.progress)
    rule.bar = bar
    try:
        outcome = branch_and_bound(
            rule.queue, in_process(lambda b: box_bounds(rule.objective, b.lo, b.hi, enclosure,
                                                        sensitivity=ellipsoid is not None, keep_form=True)),
            rule.sort, Stopping(int(budget.boxes), budget.seconds),
            Taking(int(budget.batch), lowest_first=True, prune=None if ellipsoid is None else rule.outside_ellipsoid),
            bar=bar)
    finally:
        bar.close()
    level, limited_by = rule.level, rule.limited_by
    if outcome.stopped in (BOX_BUDGET_STOP, TIME_LIMIT_STOP):
        level, limited_by = _settle_open(rule.queue.queued, _value_lower(loop, enclosure), level, limited_by,
                                         BOX_BUDGET if outcome.stopped == BOX_BUDGET_STOP else TIME_LIMIT, budget.batch)
    return LevelFound(level, limited_by, rule.cex, outcome.taken)


class _LevelRule:
    """The rule of :func:`level_search` for a batch's bounds: the level lowered to V where the condition fails (a
    confirmed violation, or an open box at the minimum size), the boxes still open under the level split (their parts
    inheriting V's lower bound, ``known``), and queued boxes the lowered level no longer asks about dropped."""

    def __init__(self, loop: ClosedLoop, condition: Condition, domain: Domain, level: float, limited_by: str,
                 floor: float, ellipsoid: tuple[Tensor, float] | None, min_width: float) -> None:
        self.loop, self.condition, self.domain, self.floor, self.min_width = loop, condition, domain, floor, min_width
        self.level, self.limited_by = level, limited_by
        self.cex: Tensor | None = None
        self.bar = None
        base = condition_and_value_objective(loop, condition)
        self.ellipsoid = ellipsoid
        self.objective = base
        if ellipsoid is not None:
            self.w, self.c_q = QuadraticLyapunov(ellipsoid[0]), float(ellipsoid[1])

            def objective(z):  # the condition's components, W, then V (W's form shares the box's symbols)
                out = base(z)
                return torch.cat([out[..., :-1], self.w(z).unsqueeze(-1), out[..., -1:]], -1)
            self.objective = objective
        self.queue = DomainQueue(Boxes(domain.lo, domain.hi, torch.zeros(domain.lo.shape[0], dtype=torch.int64),
                                       torch.full((domain.lo.shape[0],), -math.inf, dtype=domain.lo.dtype)))

    def outside_ellipsoid(self, boxes: Boxes) -> Boxes:
        """The boxes not inside L (every vertex; L is convex): those inside need no proof."""
        return boxes.select(~(vertex_max(self.w.P, boxes.lo, boxes.hi) <= self.c_q))

    def sort(self, boxes: Boxes, bounds: tuple) -> None:
        condition, floor, clo, chi = self.condition, self.floor, boxes.lo, boxes.hi
        lb, ub, at, form = bounds[0], bounds[1], bounds[2], bounds[-1]
        sens = bounds[3] if self.ellipsoid is not None else None
        v_lb = lb[:, -1]
        if self.ellipsoid is not None:
            v_lb = torch.maximum(v_lb, outside_lower(form[:, -1], form[:, -2], at.mid[:, -1], at.mid[:, -2], self.c_q,
                                                     self.level))
            keep = [*range(lb.shape[1] - 2), lb.shape[1] - 1]
            lb, ub, at, form = lb[:, keep], ub[:, keep], at[:, keep], form[:, keep]
        active = (v_lb <= self.level) & (ub[:, -1] >= floor)
        res_ub = combine_upper(condition, ub[:, :-1])
        if form is not None:  # a box proved on {V <= level} is proved on every smaller sublevel set
            res_ub = torch.minimum(res_ub, sublevel_upper(condition, form, self.level))
        centre = (clo + chi) / 2
        open_ = active & (res_ub > 0)
        bad = (open_ & self.domain.points_in(centre) & (at.hi[:, -1] >= floor)
               & (combine_lower(condition, at.lo[:, :-1]) > 0))
        if self.ellipsoid is not None:  # a violation inside L does not count against the band
            bad = bad & (self.w(centre) > self.c_q)
        if bad.any():
            values = self.loop.exact(condition, centre[bad])
            if (values > 0).any():
                v_at = at.hi[:, -1][bad][values > 0]
                j = int(v_at.argmin())
                if float(v_at[j]) < self.level:
                    self.level, self.limited_by = float(v_at[j]), "counterexample"
                    self.cex = centre[bad][values > 0][j]
        small = open_ & (((chi - clo) / self.domain.scale).amax(-1) < self.min_width)
        if small.any() and float(v_lb[small].min()) < self.level:
            self.level, self.limited_by = float(v_lb[small].min()), "unverified box at minimum size"
        divide = open_ & ~small & (v_lb <= self.level)
        if divide.any():
            nlo, nhi = split(clo[divide], chi[divide], self.domain.scale, None if sens is None else sens[divide])
            fits = self.domain.boxes_meeting(nlo, nhi)
            children = Boxes(nlo, nhi, torch.zeros(nlo.shape[0], dtype=torch.int64), v_lb[divide].repeat(2))
            self.queue.push(children.select(fits))
        self.queue.keep(~(self.queue.queued.known > self.level))  # queued boxes the lowered level no longer asks about
        if self.bar is not None:
            self.bar.set_postfix(level=f"{self.level:.6g}", queued=len(self.queue))
        return None


def _value_lower(loop: ClosedLoop, enclosure: str):
    """V's lower bounds ``(B,)`` over boxes ``lo, hi (B, n)`` with ``enclosure``."""
    vobj = value_objective(loop.lyapunov)
    return lambda lo, hi: box_bounds(vobj, lo, hi, enclosure)[0][:, 0]


def _settle_open(left: Boxes, value_lower, level: float, limited_by: str, why: str, batch: int) -> tuple[float, str]:
    """The level a search that stopped with boxes ``left`` queued may claim: at most V's least lower bound on them
    (the lowest inherited bounds tightened, ``16 * batch`` boxes of them, the rest standing as they are)."""
    order = left.known.argsort()
    first = order[:16 * batch]
    v_min = float(left.known[order[16 * batch:]].min()) if order.shape[0] > first.shape[0] else math.inf
    for i in range(0, first.shape[0], batch):
        rows = first[i:i + batch]
        fresh = value_lower(left.lo[rows], left.hi[rows])
        v_min = min(v_min, float(torch.maximum(fresh, left.known[rows]).min()))  # both are lower bounds
    if v_min < level:
        return v_min, why
    return level, limited_by


def outside_lower(v_form, w_form, v_centre: Tensor, w_centre: Tensor, c_q: float, level: float) -> Tensor:
    """A lower bound ``(B,)`` of V on the part of each box where ``W >= c_q`` (``-inf`` where none is found).

    For any ``mu >= 0`` and ``W(z) >= c_q``: ``V(z) >= V(z) - mu (W(z) - c_q) >= min_box (V - mu W) + mu c_q``.
    ``V - mu W`` is bounded on the affine forms of V and W over the box (the same noise symbols, so the parts of
    V's variation that follow W's cancel); ``mu`` is tried at 1/2 and 1 times ``V / W`` at the box centre (where
    V and W vary alike) and at 1/2, 1 and 2 times ``level / c_q`` (V at the level where W is at ``c_q``). Near a
    boundary of ``L = {W <= c_q}`` on which V is above the level, this shows V above the level on the box's part
    outside L, which V's own bound on the whole box (down to V's values inside L) cannot."""
    ratio = torch.where(w_centre > 0, v_centre / w_centre, 0.0).clamp(min=0.0)
    best = torch.full_like(v_centre, -math.inf)
    ref = max(level, 0.0) / c_q if math.isfinite(level) else 0.0
    for mu in (0.5 * ratio, ratio, torch.full_like(ratio, 0.5 * ref), torch.full_like(ratio, ref),
               torch.full_like(ratio, 2 * ref)):
        low = (v_form - w_form * mu).tight_interval().lo
        shift = mu * c_q
        bound = round_down(low + shift, 4 * REL1, low.abs() + shift.abs())  # the product's and the sum's rounding
        best = torch.maximum(best, torch.where(torch.isnan(bound), -math.inf, bound))
    return best
