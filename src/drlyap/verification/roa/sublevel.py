"""The first route to a region of attraction: V's sublevel sets, V's own proofs.

For a closed loop and a condition (:mod:`drlyap.conditions`) :func:`outer_search` finds the largest level ``c``
such that ``S = {z in box : V(z) <= c}``

1. lies inside the state box (``V > c`` on the box boundary: :func:`~drlyap.verification.sublevel.boundary_minimum`),
   or, for a condition on the true model, is not left through the box's faces: wherever ``V <= c`` on a face, the
   flow of each of its models points strictly into the box
   (:func:`~drlyap.verification.sublevel.exit_minimum`; ``faces`` ``"inward"``, the set then cut by the box: a
   trajectory that reached a face with ``V <= c`` would enter the box again at once, and one that reached ``V = c``
   inside it would go on decreasing, so none leaves S),
2. satisfies the condition's decrease on ``S`` outside the delta-ball (:func:`~drlyap.verification.roa.levels.level_search`),

and bounds V on the delta-ball. The decrease of 2 is strict (``Vdot < 0``) by a decay ``gamma ||z||``, or by
``alpha V`` where V > 0 outside the ball: by V's form (drlyap's V, ``alpha_hat > 0``; a positive definite
``z^T P z``) or, for any other V (an imported graph), proved by a branch and bound on V's lower bound
(:func:`outer_strictness`); ``{V <= 0}`` lies in ``S``, so V > 0 on X_delta is what ``S`` needs. With, 3.,
``Vdot < 0`` on S inside the ball except at x* (:func:`~drlyap.verification.roa.local.local_decrease`),
``Vdot < 0`` on ``S`` minus x*, so ``S`` is forward invariant and every trajectory that starts in it converges to x*
(Lyapunov / LaSalle): ``S`` is a **region of attraction** of the model the condition is about. Where the decrease
is not strict neither claim is made (a rest point with ``V <= 0`` outside the ball satisfies it). Where 3 cannot be
proved, only **practical stability** is claimed: if ``c`` exceeds an upper bound ``c0`` of V on the delta-ball,
trajectories from ``S`` stay in ``S`` and end up in ``{V <= c0}`` (:func:`finish` decides which).
:func:`sublevel_roa` is this route alone (the one :func:`~drlyap.verification.roa.quadratic.quadratic_roa` runs on
``W = z^T P z``); :func:`~drlyap.verification.roa.certify.certified_roa` adds the other proofs where it fails.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition
from drlyap.enclosures import F64
from drlyap.enclosures.quadratic import surely_semidefinite
from drlyap.kinds import Model
from drlyap.networks import Lyapunov, QuadraticLyapunov
from drlyap.proof_settings import Budget
from drlyap.regions import Domain, Region, box_grid, default_grid, near_dist
from drlyap.verification.bounds import value_objective
from drlyap.verification.branch_and_bound import SearchInfo, maximize
from drlyap.verification.results import ConditionProof, RegionOfAttraction
from drlyap.verification.roa.levels import BOX_BUDGET, TIME_LIMIT, below, level_search, time_capped
from drlyap.verification.roa.levels import share as box_share
from drlyap.verification.roa.local import local_decrease
from drlyap.verification.roa_steps import LinearisationProof, RouteSteps, Strictness
from drlyap.verification.sublevel import boundary_minimum, exit_minimum

EXIT_ROOM = 0.01
"""A set cut by the box is claimed up to ``(1 - EXIT_ROOM)`` times V's lower bound where the flow may leave the box:
room for the checker's own bisection of the faces, which must separate the set from those points (on the planar
quadrotor it needed 204,166 face boxes at 1% below, and did not finish within 200,000 one float step below)."""

TRAINED_LEVEL = "the level the run was trained for (--roa-at-level keeps the search there)"
"""``limited_by`` of a search capped at the level the run was trained for."""


def exit_top(exit_min_lower: float | None, boundary_min_lower: float) -> float | None:
    """The level a set cut by the box may reach, ``(1 - EXIT_ROOM)`` times V's lower bound where the flow may leave
    the box, where that is above V's lower bound on the faces (else None: the faces' rule stands)."""
    if exit_min_lower is None or not (1 - EXIT_ROOM) * exit_min_lower > boundary_min_lower:
        return None
    return (1 - EXIT_ROOM) * exit_min_lower


@dataclass
class OuterSearch:
    """Steps 1 and 2 of the route (module docstring) and V's bound on the delta-ball: ``level`` (rounded down) the
    largest proved, ``top`` the level the search started from (V's lower bound on the faces, or the cap asked for)
    with ``why`` it, ``counterexample`` (local) one that limited it, ``boxes`` the level search's boxes (or the
    proof's that stood for it), ``spent`` those this search's level search bounded, ``deadline`` the end of the whole
    budget's time cap, ``capped`` the bounds of V that stopped at their time cap (their names)."""

    boundary_min_lower: float
    ball_max_upper: float
    level: float
    limited_by: str
    counterexample: Tensor | None
    boxes: int
    top: float
    why: str
    start: float
    deadline: float
    exit_min_lower: float | None = None
    capped: tuple[str, ...] = ()
    spent: int = 0

    @property
    def faces(self) -> str:
        """How S stays off the box's faces: ``"above"`` (V above the level there) or ``"inward"`` (the flow enters
        the box wherever V is at most the level there: step 1 of the module docstring)."""
        widened = exit_top(self.exit_min_lower, self.boundary_min_lower) is not None
        return "inward" if widened and self.level >= self.boundary_min_lower else "above"

    @property
    def inside(self) -> tuple[float, str]:
        """The level the search started from and why, capped at V's lower bound on the faces (for the proofs that
        need ``V > c`` there)."""
        return (self.top, self.why) if self.top < self.boundary_min_lower else (self.boundary_min_lower, "box boundary")


def bound_budget(budget: Budget) -> Budget:
    """The budget of each bound of V in a search with ``budget`` (V's minimum on the faces, where the flow may leave
    them, outside the ball; its maximum on the ball): a quarter of its boxes and of its seconds."""
    return replace(budget, seconds=budget.seconds / 4, boxes=box_share(budget.boxes, 0.25))


def outer_search(loop: ClosedLoop, condition: Condition, region: Region, budget: Budget,
                 max_level: float = math.inf, cut_by_box: bool = True) -> OuterSearch:
    """The faces' minimum of V, for a condition on the true model V's minimum where its flow may leave the box
    (:func:`~drlyap.verification.sublevel.exit_minimum`), V's maximum on the delta-ball (each a quarter of the budget's
    boxes and seconds at most: :func:`bound_budget`), and the level search outside the ball (60% of the boxes, all of
    them when ``delta = 0``; its time cap ends when 60% of the budget's seconds are spent, all of them when
    ``delta = 0``), capped at ``max_level``. ``cut_by_box`` False: V above the level on the faces only (no set cut
    by the box)."""
    start = time.perf_counter()
    system, lyapunov = loop.system, loop.lyapunov
    enclosure = budget.enclosure_for(system.n)
    time_limit, min_width = budget.seconds, budget.min_width
    delta = region.delta
    scale = region.scale
    grid = default_grid(system.n)
    quarter = replace(bound_budget(budget), enclosure=enclosure)
    capped = []
    # 1. min of V on the boundary of the box
    on_faces = boundary_minimum(lyapunov, region, quarter)
    boundary_min_lower = on_faces.lower
    faces, face_why = boundary_min_lower, "box boundary"
    if not math.isfinite(boundary_min_lower) and on_faces.stopped != "finished":  # no level fits: say why
        face_why = TIME_LIMIT if time_capped(on_faces.stopped) else BOX_BUDGET
    capped += ["V's minimum on the faces"] if time_capped(on_faces.stopped) else []
    # 2. max of V on the delta-ball
    ball_max_upper, stopped = _ball_max(lyapunov, region, quarter)
    capped += ["V's maximum on the ball"] if time_capped(stopped) else []
    # 3. the decrease condition on the sublevel set outside the ball
    lo, hi = region.boxes(grid)
    exit_min_lower = None
    if cut_by_box and condition.model == Model.TRUE and boundary_min_lower < max_level:
        exits = exit_minimum(loop, condition, region, quarter)
        found = exits.lower
        capped += ["V's minimum where the flow may leave"] if time_capped(exits.stopped) else []
        exit_min_lower = found if math.isfinite(found) else None  # inf: no face box may leave; -inf: out of budget
        widened = exit_top(exit_min_lower, boundary_min_lower)
        if widened is not None:
            faces, face_why = widened, "the box's faces where the flow leaves the box"
    top, why = (faces, face_why) if faces <= max_level else (max_level, TRAINED_LEVEL)
    whole = 0.6 if delta > 0 else 1.0  # 40% kept for the ball
    level, limited_by, cex, processed = level_search(
        loop, condition, Domain(lo, hi, scale, region.meets, region.in_region), top, why,
        replace(budget, seconds=start + whole * time_limit - time.perf_counter(), boxes=box_share(budget.boxes, whole),
                min_width=min_width, enclosure=enclosure))
    return OuterSearch(boundary_min_lower, ball_max_upper, below(level), limited_by, cex, processed, top, why, start,
                       start + time_limit, exit_min_lower, tuple(capped), processed)


def _ball_max(lyapunov, region: Region, budget: Budget) -> tuple[float, str]:
    """An upper bound of V on the delta-ball (0 without a ball), and how its branch and bound stopped."""
    delta = region.delta
    if delta <= 0:
        return 0.0, "finished"
    ball = region.ball_box(delta)
    glo, ghi = box_grid(ball.lo, ball.hi, default_grid(region.lo.shape[0]))
    _, up, info = maximize(value_objective(lyapunov), Domain(glo, ghi, region.scale, lambda a, b: near_dist(a, b) < delta),
                           budget, label="V's largest value on the delta-ball")
    return float(up[0]), info.stopped


def near_budget(budget: Budget, outer: OuterSearch, spent: int = 0, fraction: float = 1.0,
                least_seconds: float = 1.0) -> Budget:
    """The budget of a proof near x* after the level search ``outer`` of a search with ``budget``: ``fraction`` of the
    boxes the level search left (``budget.boxes`` less its boxes and ``spent`` by the proofs near x* before it; at
    least a tenth of the budget's), and ``fraction`` of the seconds left before the budget's time cap (at least
    ``least_seconds``)."""
    boxes = box_share(max(budget.boxes - outer.spent - spent, budget.boxes // 10), fraction)
    return replace(budget, boxes=boxes,
                   seconds=max(least_seconds, fraction * (outer.deadline - time.perf_counter())))


def outer_strictness(loop: ClosedLoop, condition: Condition, region: Region, budget: Budget) -> Strictness:
    """Whether ``condition``'s decrease outside the delta-ball is strict, ``Vdot < 0`` (module docstring): ``strict``
    and ``by`` (``"decay"``: gamma > 0; ``"form"``: alpha > 0 and drlyap's V; ``"proof"``: alpha > 0 and V > 0 on
    X_delta proved, ``lower`` its bound; None), with the proof's ``boxes``, ``time_s``, ``stopped`` and a ``reason`` where
    it is not. The proof runs on a quarter of the budget's boxes and seconds (:func:`bound_budget`)."""
    if condition.decay_rate > 0:
        return Strictness(True, "decay")
    if not condition.exp_rate > 0:
        return Strictness(False, None, reason="the decrease has no decay (gamma = alpha = 0): it is not strict")
    if positive_by_form(loop.lyapunov):
        return Strictness(True, "form")
    lower, info = positive_lower(loop.lyapunov, region, replace(bound_budget(budget),
                                                                enclosure=budget.enclosure_for(loop.n)))
    out = Strictness(lower > 0, "proof" if lower > 0 else None, lower=lower, boxes=info.boxes_processed,
                     time_s=info.time_s, stopped=info.stopped)
    if not lower > 0:
        out.reason = (f"V > 0 outside the ball not proved (V's lower bound there {lower:.3g}, "
                      f"{info.boxes_processed} boxes, {info.stopped}): with no decay gamma ||z||, alpha V "
                      "makes the decrease strict only where V > 0")
    return out


def positive_by_form(lyapunov) -> bool:
    """Whether V > 0 away from x* follows from V's form: drlyap's V (``alpha_hat > 0``), or ``z^T P z`` with a
    symmetric P that a Cholesky factorisation of ``P - p I`` shows positive definite (``p`` above its backward error,
    ``2 (n + 1)^2 eps max_i P_ii``)."""
    if isinstance(lyapunov, Lyapunov):
        return True
    if not isinstance(lyapunov, QuadraticLyapunov):
        return False
    p = lyapunov.P.to(F64)
    return bool(torch.equal(p, p.T)) and bool(surely_semidefinite(p))


def positive_lower(lyapunov, region: Region, budget: Budget) -> tuple[float, SearchInfo]:
    """A sound lower bound of V on X_delta (the box minus the open delta-ball), refined until it is at least half of
    V's least value at the boxes' centres, or the budget is spent (``maximize``'s info as the second result)."""
    vobj = value_objective(lyapunov)
    lo, hi = region.boxes(default_grid(region.n))
    _, neg_up, info = maximize(lambda z: -vobj(z), Domain(lo, hi, region.scale, region.meets, region.in_region), budget,
                               rel_tol=0.5, label="V's least value outside the delta-ball")
    return float(-neg_up[0]), info


def proof_fits(proof: ConditionProof | None, region: Region, max_level: float = math.inf) -> bool:
    """Whether ``proof`` can stand for steps 1 and 2 on ``region``: verified on a sublevel set ``{V <= level}``
    (``level <= max_level``) of the same X_delta, with V proved above the level on the faces."""
    return (proof is not None and proof.verified and proof.level is not None and proof.level <= max_level
            and proof.boundary_min_lower is not None and proof.boundary_min_lower > proof.level
            and proof.delta == region.delta)


def proved_outer(loop: ClosedLoop, proof: ConditionProof, region: Region, budget: Budget) -> OuterSearch:
    """Steps 1 and 2 of the route from a verified proof of the same condition on ``{V <= level}``
    (:func:`~drlyap.verification.sublevel.verify_sublevel`: the condition there outside the delta-ball and V above
    the level on the faces), instead of a level search; V's bound on the ball as :func:`outer_search` takes it."""
    if not proof_fits(proof, region):
        raise ValueError("a verified proof on a sublevel set {V <= level} of this X_delta, with V above the level "
                         "on the faces, is needed")
    start = time.perf_counter()
    quarter = replace(bound_budget(budget), enclosure=budget.enclosure_for(loop.n))
    ball_max_upper, stopped = _ball_max(loop.lyapunov, region, quarter)
    return OuterSearch(proof.boundary_min_lower, ball_max_upper, below(proof.level), TRAINED_LEVEL, None,
                       proof.boxes_processed, proof.level, TRAINED_LEVEL, start, start + budget.seconds,
                       capped=("V's maximum on the ball",) if time_capped(stopped) else ())


def finish(loop: ClosedLoop, condition: Condition, region: Region, outer: OuterSearch, steps: RouteSteps,
           samples_per_axis: int = 400) -> RegionOfAttraction:
    """The region the proofs add up to (``steps``): a region of attraction where the band proof certified a level
    (``band``), or where the outer level is positive, its decrease strict (``strict``: :func:`outer_strictness`; the
    linearisation proof needs no more than its own annulus, where V >= c_1 > 0) and the proof near x* (``local``) holds
    (the annulus inside the ball may lower the level); practical stability where the outer level only exceeds V's bound
    on the ball and its decrease is strict; else none. Where a step of the search stopped at its time cap (its
    ``capped``), ``limited_by`` says so (:data:`~drlyap.verification.roa.levels.TIME_LIMIT`)."""
    system = loop.system
    local, quadratic, band, strict = steps.local, steps.quadratic, steps.band, steps.strict
    c, limited_by = outer.level, outer.limited_by
    is_strict = strict is None or strict.strict
    counterexample = None if outer.counterexample is None else system.to_user(outer.counterexample[None])[0].tolist()
    if band is not None and band.proved:  # V's sublevel set from the band proof (the outer search's stays)
        kind, c, limited_by, local = "region of attraction", band.level, band.limited_by, band
        counterexample = band.counterexample
    elif c > 0 and local.proved and (is_strict or isinstance(local, LinearisationProof)):
        kind = "region of attraction"
        if isinstance(local, LinearisationProof) and local.level is not None and local.level < c:
            c = local.level  # the annulus inside the ball may lower it
            if local.annulus.limited_by != "outer proof":
                limited_by = f"inside the ball: {local.annulus.limited_by}"
    elif c > 0 and c > outer.ball_max_upper and is_strict:
        kind = "practical stability"
    else:
        kind = None
        if c > 0 and not is_strict:
            limited_by = strict.reason
    capped = [*outer.capped, *(["V > 0 outside the ball"] if strict is not None and time_capped(strict.stopped) else []),
              *(name for step in (local, quadratic, band) if step is not None for name in step.capped or ())]
    if capped and not time_capped(limited_by):
        limited_by = f"{limited_by}; {TIME_LIMIT} (reached by {', '.join(dict.fromkeys(capped))})"
    share = share_of_box(loop.f64.lyapunov, region, c, samples_per_axis) if c > 0 else 0.0
    by_band = band is not None and band.proved
    faces = "inward" if outer.faces == "inward" and kind and not by_band and c >= outer.boundary_min_lower else "above"
    return RegionOfAttraction(
        level=c, kind=kind, certified=kind == "region of attraction",
        practical_level=outer.ball_max_upper if kind == "practical stability" else None, outer_level=outer.level,
        contains_ball=c > outer.ball_max_upper, limited_by=limited_by, local=local,
        boundary_min_lower=outer.boundary_min_lower, ball_max_upper=outer.ball_max_upper, share_of_box=share,
        counterexample=counterexample, boxes_processed=outer.boxes, time_s=time.perf_counter() - outer.start,
        delta=float(region.delta), condition=condition.label, quadratic=quadratic, band=band, strict=strict,
        faces=faces, exit_min_lower=outer.exit_min_lower)


def sublevel_roa(loop: ClosedLoop, condition: Condition, region: Region, budget: Budget = Budget(seconds=10.0), *,
                 samples_per_axis: int = 400, max_level: float = math.inf, cut_by_box: bool = True
                 ) -> RegionOfAttraction:
    """The largest certified ``{V <= c}`` by V's own proofs (module docstring), within ``budget`` (the level search
    as in :func:`outer_search`, the proof near x* what it leaves: :func:`near_budget`; ``cut_by_box``: as for
    :func:`outer_search`)."""
    outer = outer_search(loop, condition, region, budget, max_level, cut_by_box)
    c = outer.level
    strict = outer_strictness(loop, condition, region, budget) if c > 0 else None
    local = local_decrease(loop, condition, region, replace(near_budget(budget, outer),
                                                            enclosure=budget.enclosure_for(loop.n)),
                           level=c if c > 0 else None)
    return finish(loop, condition, region, outer, RouteSteps(local, strict=strict), samples_per_axis)


def share_of_box(lyapunov, region: Region, level: float, samples_per_axis: int) -> float:
    """Share of the box volume in ``{V <= level}``: on a grid for n <= 3, else from 100,000 uniform samples; where
    fewer than 1,000 of those fall in the set (a share below 1%), stratified over the nested boxes
    ``B_k = 2^-k X`` around x*: 20,000 uniform samples in each ``B_k`` estimate the set's share of the shell
    ``B_k \\ B_{k+1}``, down to the first ``B_k`` the set fills at least half of (its samples then estimate all of
    it), or until the shells left are below 1e-6 of the estimate. ``lyapunov``: V in float64 (``loop.f64.lyapunov``)."""
    n = region.n

    def values_at(z: Tensor) -> Tensor:
        with torch.no_grad():
            return torch.cat([lyapunov(z[i:i + 50_000]) for i in range(0, z.shape[0], 50_000)])

    if n <= 3:
        per = samples_per_axis if n <= 2 else 60
        axes = [region.lo[i] + region.scale[i] * (torch.arange(per, dtype=F64) + 0.5) / per for i in range(n)]
        return float((values_at(torch.cartesian_prod(*axes).reshape(-1, n)) <= level).double().mean())
    g = torch.Generator().manual_seed(0)
    z = region.lo + region.scale * torch.rand(100_000, n, generator=g, dtype=F64)
    hits = values_at(z) <= level
    if int(hits.sum()) >= 1000:
        return float(hits.double().mean())
    share = 0.0
    for k in range(64):
        lo, hi = region.lo * 2.0 ** -k, region.hi * 2.0 ** -k  # x* = 0 (local coordinates) lies in every B_k
        if k:
            z = lo + (hi - lo) * torch.rand(20_000, n, generator=g, dtype=F64)
            hits = values_at(z) <= level
        inner = ((z >= lo / 2) & (z <= hi / 2)).all(-1)
        weight = 2.0 ** (-n * k)  # B_k's share of the box
        if float(hits.double().mean()) >= 0.5:
            return share + weight * float(hits.double().mean())
        share += weight * float((hits & ~inner).double().mean())
        if weight * 2.0 ** -n < 1e-6 * share:
            break
    return share
