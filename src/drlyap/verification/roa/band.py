"""The band proof: a certified sublevel set of V from the closed loop's own certified ellipsoid.

Tried when no sublevel set of V is certified by V's own proofs but the closed loop's ellipsoid ``L = {W <= c_q}``
(:func:`~drlyap.verification.roa.quadratic.quadratic_roa`) is: on 6 states the condition's proof outside the
delta-ball and V's proof near x* do not finish (the closed loop is stiff), while L is proved by its Jacobians alone.
:func:`band_roa` proves strict decrease ``Vdot + 1e-9 ||z|| <= 0`` (every sample's model) on ``S = {V <= c}``
minus L, over the whole box, with ``c`` below V's lower bound on the box's faces. Then every trajectory from S
converges to x*: while outside L it keeps V <= c (V decreases there, and S does not reach the faces), so it stays
in S; it cannot stay in S minus L for ever: that set is bounded away from x* (L holds a neighbourhood of it), so
there V falls at least at the uniform rate ``1e-9 sqrt(c_q / lambda_max(P))`` while V is bounded below; once in L
it stays in L and converges. ``S`` together with L is forward invariant; S alone need not be (a trajectory inside
L may leave S). The search (:func:`~drlyap.verification.roa.levels.level_search` with the ellipsoid) drops boxes
inside L, bounds V on each box's part outside L (:func:`~drlyap.verification.roa.levels.outside_lower`), and asks
the decrease only on the part with ``V <= c`` (:func:`~drlyap.verification.bounds.sublevel_upper`); levels are
tried from just above V's sampled minimum on L's boundary up, 1.3x apart. ``local`` then reads ``method: "band"``.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition, PlainDecrease
from drlyap.enclosures import F64
from drlyap.kinds import Enclosure
from drlyap.proof_settings import Budget
from drlyap.regions import Domain, Region, box_grid, default_grid
from drlyap.verification.branch_and_bound import Exempt, ProofRules, verify_condition
from drlyap.verification.roa.levels import BOX_BUDGET, TIME_LIMIT, below, level_search, time_capped
from drlyap.verification.roa.local import resolving_ellipsoid
from drlyap.verification.roa.quadratic import CoredProof
from drlyap.verification.roa_steps import BandRegion, LevelTry, QuadraticRegion


def band_roa(loop: ClosedLoop, condition: Condition, region: Region, quadratic: QuadraticRegion | None, top: float,
             limited_by: str = "box boundary", budget: Budget = Budget(seconds=10.0)) -> BandRegion:
    """The band proof (module docstring): the largest level ``c <= top`` (up to the search's resolution) such that
    V decreases strictly (``Vdot + 1e-9 ||z|| <= 0``, every sample's model of ``condition``) on ``{V <= c}``
    outside ``L = {z^T P z <= c_q}``, the closed loop's certified ellipsoid of
    :func:`~drlyap.verification.roa.quadratic.quadratic_roa` (``quadratic``: its result, with ``P`` and ``q_level``).
    ``top`` must be a lower bound of V on the box's faces (or lower). Runs
    :func:`~drlyap.verification.roa.levels.level_search` with the ellipsoid (affine enclosure) over the whole box,
    one level after the other, until ``budget.boxes`` boxes are spent between them (``limited_by``
    :data:`~drlyap.verification.roa.levels.BOX_BUDGET`), or ``budget.seconds``, a time cap (``TIME_LIMIT``, and
    ``capped`` names the band proof).

    Returns ``proved`` (``c > 0``), ``level``, ``limited_by``, ``boxes``, ``time_s``, ``counterexample`` (user
    coordinates, or None), ``P``, ``q_level``, ``v_on_ellipsoid``: V's smallest and largest value at 20,000
    sampled points of L's boundary, and ``beyond_ellipsoid``: ``c`` above that smallest value, so that
    ``{V <= c}`` reaches outside L and the decrease proved there is what carries it (from samples, not a proof;
    otherwise the set may lie inside L)."""
    start = time.perf_counter()
    system, time_limit, min_width = loop.system, budget.seconds, budget.min_width
    out = BandRegion()
    plain = condition.per_sample()
    if plain is None:
        out.reason = "the condition implies no per-sample decrease (a CVaR over several samples)"
        return out
    if quadratic is None or not quadratic.proved:
        out.reason = "no certified ellipsoid of the closed loop to start from"
        return out
    if not (top > 0 and math.isfinite(top)):
        out.reason = f"V's lower bound on the box's faces is {top:.3g}: no positive level fits in the box"
        return out
    p, c_q = torch.tensor(quadratic.P, dtype=F64), float(quadratic.q_level)
    if not c_q > 0:
        out.reason = f"the ellipsoid's level is {c_q:.3g}: no ellipsoid to start from"
        return out
    out.P, out.q_level, out.v_on_ellipsoid = p.tolist(), c_q, _on_ellipsoid(loop.f64.lyapunov, p, c_q)
    if not out.v_on_ellipsoid[0] > 0:
        out.reason = "V is not positive on the ellipsoid's boundary"
        return out
    strict = PlainDecrease(plain.xi, 1e-9, 0.0, plain.model)
    lo, hi = box_grid(region.lo, region.hi, default_grid(system.n))
    # boxes must resolve a set as small as L (the box holding x* has to fit inside it)
    fine = resolving_ellipsoid(min_width, p, c_q, region)

    # levels from just above V's sampled minimum on L's boundary up, 1.3x apart: a search with a fixed level drops
    # the boxes above it at once and bounds the rest on {V <= level} only; one with the top level would spend the
    # time on the sets far above the level it reaches
    target = min(top, 1.1 * out.v_on_ellipsoid[0])
    reached, boxes, cex, targets = -math.inf, 0, None, []
    while True:
        level, why, cex, count = level_search(
            loop, strict, Domain(lo, hi, region.scale), target,
            limited_by if target >= top else "next level not reached",
            replace(budget, seconds=start + time_limit - time.perf_counter(), boxes=max(1, budget.boxes - boxes),
                    min_width=fine, enclosure=Enclosure.AFFINE), ellipsoid=(p, c_q))
        boxes += count
        targets.append(LevelTry(target, level >= target, count, time.perf_counter() - start))
        if level >= target and target < top:
            reached = target
            if boxes >= budget.boxes:
                limited_by = BOX_BUDGET
            elif time.perf_counter() < start + time_limit:
                target = min(top, 1.3 * target)
                continue
            else:
                limited_by = TIME_LIMIT
        elif level > reached:  # the last search's own level (a lower bound of V on what it left), if higher
            reached, limited_by = level, why
        else:
            limited_by, cex = f"{why} at the next level ({target:.4g})", None
        break
    c = below(reached)
    if time_capped(limited_by):
        out.capped = ["the band proof"]
    out = replace(out, proved=c > 0, level=c, limited_by=limited_by, boxes=boxes, decay_rate=strict.decay_rate,
                  levels=targets, beyond_ellipsoid=c > out.v_on_ellipsoid[0],
                  counterexample=None if cex is None else system.to_user(cex[None])[0].tolist(),
                  time_s=time.perf_counter() - start)
    if not c > 0:
        out.reason = f"V's decrease outside the ellipsoid not proved on any sublevel set ({limited_by})"
    return out


def _on_ellipsoid(lyapunov, p: Tensor, c_q: float, count: int = 20_000) -> list[float]:
    """V's smallest and largest value (V in float64) at ``count`` points of ``{z^T P z = c_q}`` (a fixed seed; not a
    bound)."""
    g = torch.Generator().manual_seed(0)
    e = torch.randn(count, p.shape[0], generator=g, dtype=F64)
    e = e / e.norm(dim=-1, keepdim=True)
    chol = torch.linalg.cholesky(p)
    z = torch.linalg.solve_triangular(chol.T, e.T, upper=True).T * math.sqrt(c_q)
    with torch.no_grad():
        values = lyapunov(z)
    return [float(values.min()), float(values.max())]



def band_proof(loop: ClosedLoop, condition: Condition, region: Region, band: BandRegion,
               budget: Budget) -> CoredProof | None:
    """The proof behind a sublevel set ``{V <= c}`` that :func:`band_roa` certified (``band``, its result), as a
    certificate states it: V's strict decrease (the band's decay) on ``{V <= c}`` over the whole box except where a box
    lies in the ellipsoid ``L = {z^T P z <= c_q}`` (``verify_condition``'s ``core``; no delta-ball), with the affine
    enclosure, a minimum width that resolves L, and its partition kept. A box that straddles L's boundary is split
    until it lies in L, above the level by V's own bound, or is proved (the search bounded V on its part outside L
    instead, so this proof may need more boxes, or not finish: None then)."""
    plain = condition.per_sample()
    if plain is None or not band.proved:
        return None
    p, c_q = torch.tensor(band.P, dtype=F64), float(band.q_level)
    strict = PlainDecrease(plain.xi, float(band.decay_rate), 0.0, plain.model)
    fine = resolving_ellipsoid(budget.min_width, p, c_q, region)
    whole = region.with_delta(0.0)
    proof = verify_condition(loop, strict, whole, replace(budget, min_width=fine, enclosure=Enclosure.AFFINE),
                             level=float(band.level), exempt=Exempt(core=(p, c_q)), rules=ProofRules(keep_partition=True))
    return CoredProof(strict, whole, proof, p, c_q) if proof.verified else None
