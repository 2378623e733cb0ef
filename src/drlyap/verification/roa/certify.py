"""Certified regions of attraction: sublevel sets of V on which V provably decreases all the way to x*.

:func:`certified_roa` tries, in this order, and reports the first that certifies a sublevel set of V (each is a
module of this package, with its argument in its docstring):

1. V's own proofs (:mod:`~drlyap.verification.roa.sublevel`): the condition on ``{V <= c}`` outside the
   delta-ball, strict there (a decay ``gamma ||z||``, or ``alpha V`` with V > 0 there), V above ``c`` on the
   faces, and inside the ball V's second-order decrease (:mod:`~drlyap.verification.roa.local`);
2. where the proof inside the ball fails, or the decrease outside it is not strict, the closed loop's
   linearisation (:mod:`~drlyap.verification.roa.quadratic`): ``{V <= c_1}`` inside the closed loop's certified
   ellipsoid ``{z^T P z <= c_q}``, V strictly decreasing on the rest;
3. where no sublevel set of V is certified but the ellipsoid is, the band proof (:mod:`~drlyap.verification.roa.band`):
   V strictly decreasing on ``{V <= c}`` outside the ellipsoid.

Nothing is called a region of attraction unless every trajectory from it converges to x*; a set whose decrease is
proved only outside the delta-ball is practical stability (trajectories end up in ``{V <= c0}``), and where V's sets
are not certified the closed loop's own ellipsoid is reported beside them (``quadratic``: a region of attraction of
the same closed loop, not a sublevel set of V).
"""

from __future__ import annotations

import math
from dataclasses import replace

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.verification.results import ConditionProof, RegionOfAttraction
from drlyap.verification.roa.band import band_roa
from drlyap.verification.roa.local import BallKeeper, local_decrease
from drlyap.verification.roa.quadratic import linearisation_local, quadratic_roa
from drlyap.verification.roa.sublevel import (
    finish,
    near_budget,
    outer_search,
    outer_strictness,
    proof_fits,
    proved_outer,
)
from drlyap.verification.roa_steps import LinearisationProof, LocalProof, RouteSteps

REGION_RATE = 0.01
"""The decay ``alpha`` of ``Vdot + alpha V <= 0`` that a region of attraction at a shift asks of the true model by
default: any ``alpha > 0`` makes the decrease strict where V > 0, all a region of attraction needs, and a small one
asks the least of the pair (the run's own alpha where that is smaller, :func:`region_rate`)."""


def region_rate(decay_rate: float, exp_rate: float) -> float | None:
    """The decay ``alpha`` a region of attraction asks of the true model at a shift by default, where it is not the
    pair's own (None: the pair's ``gamma ||z||`` already makes its decrease strict, or its ``alpha`` is at most
    :data:`REGION_RATE`); else :data:`REGION_RATE`."""
    if decay_rate > 0 or 0 < exp_rate <= REGION_RATE:
        return None
    return REGION_RATE


def certified_roa(loop: ClosedLoop, condition: Condition, region: Region, budget: Budget = Budget(seconds=10.0), *,
                  samples_per_axis: int = 400, max_level: float = math.inf,
                  band_time: float | None = None, proved: ConditionProof | None = None) -> RegionOfAttraction:
    """The largest level ``c`` (up to the search's resolution) with ``S = {V <= c}`` certified for the closed loop
    on the model of ``condition`` (module docstring), within ``budget`` (its ``enclosure`` bounds V and the
    conditions in every branch and bound here, inside the ball too; None: by the dimension; the Hessian enclosure
    on the cube around x* is interval arithmetic on nested dual numbers).

    ``budget.boxes`` is the search's work: the level search gets 60% of it (all of it with ``delta = 0``), each bound
    of V (on the faces, where the flow may leave them, on the ball) up to a quarter, and the proofs near x* what the
    level search leaves (:func:`~drlyap.verification.roa.sublevel.near_budget`: half of it to V's own proof in the
    ball, then the rest to the linearisation or the closed loop's ellipsoid), so that the result does not depend on
    the machine's speed. ``budget.seconds`` is a cap on the wall time, split in the same proportions; a step that
    reaches it is named in ``limited_by`` (:data:`~drlyap.verification.roa.levels.TIME_LIMIT`).

    ``max_level`` caps the search (e.g. at the level a region of attraction was trained for: ``limited_by`` then
    is ``TRAINED_LEVEL`` when the cap is proved). ``band_time``: the time cap of the band proof, where it runs (None:
    ``budget.seconds`` again; 0: not run); it gets ``budget.boxes`` boxes again. ``samples_per_axis``: the grid that
    estimates the share of the box in S (n <= 2). ``proved``: a verified proof of ``condition`` on ``{V <= level}`` (a
    region-of-attraction run's, :func:`~drlyap.verification.sublevel.verify_sublevel`, ``level <= max_level``), taken
    for the search outside the ball (:func:`~drlyap.verification.roa.sublevel.proved_outer`); the search runs where it
    does not fit (:func:`~drlyap.verification.roa.sublevel.proof_fits`).
    """
    budget = replace(budget, enclosure=budget.enclosure_for(loop.n))
    if proof_fits(proved, region, max_level):
        outer = proved_outer(loop, proved, region, budget)
    else:
        outer = outer_search(loop, condition, region, budget, max_level)
    c = outer.level
    strict = outer_strictness(loop, condition, region, budget) if c > 0 else None
    keep = BallKeeper()
    local: LocalProof | LinearisationProof = local_decrease(
        loop, condition, region, near_budget(budget, outer, fraction=0.5), level=c if c > 0 else None, keep=keep)
    spent = local.boxes  # by the proofs near x*
    own_failed = not local.proved or not (strict is None or strict.strict)
    if own_failed and local.equilibrium and c > 0:  # the linearisation's chain needs no strictness outside
        second = local
        local = linearisation_local(loop, condition, region, c, near_budget(budget, outer, spent, least_seconds=3.0))
        spent += local.boxes
        local.second_order = second
        local.capped = [*(second.capped or ()), *(local.capped or ())] or None
    quadratic = None  # the closed loop's own quadratic Lyapunov function, reported where V's sublevel sets are not certified
    if not (c > 0 and local.proved and (not own_failed or isinstance(local, LinearisationProof))):
        quadratic = (local.quadratic if isinstance(local, LinearisationProof) else None) or quadratic_roa(
            loop, condition, region, near_budget(budget, outer, spent, least_seconds=3.0))
        quadratic = quadratic.reported()
    band = None
    if quadratic is not None and quadratic.proved and (band_time is None or band_time > 0):
        band = band_roa(loop, condition, region, quadratic, *outer.inside,
                        replace(budget, seconds=budget.seconds if band_time is None else band_time))
    found = finish(loop, condition, region, outer, RouteSteps(local, quadratic, band, strict), samples_per_axis)
    if found.certified and found.local is local and found.level == c:  # V's own proofs, the level not lowered
        found.ball = keep.ball
    return found
