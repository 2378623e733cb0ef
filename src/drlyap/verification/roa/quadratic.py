"""The closed loop's own quadratic Lyapunov function, and V's sublevel sets from it where V's Hessian test fails.

The linearisation proof (:func:`linearisation_local`), tried when V's own second-order proof
(:mod:`~drlyap.verification.roa.local`) fails (the networks are trained outside the delta-ball only, so V's local
quadratic part need not be a Lyapunov function of the closed loop, or its Hessian of Vdot is so badly conditioned
that no enclosure shows it: the mountain-car pairs' is ``(-0.1, -3e4)``). For each sample's model:

a. ``A_j = dF_j/dz(0)`` (every one Hurwitz, else no claim); ``W(z) = z^T P z`` and a cube ``|z_i| <= h_i``
   chosen together (:func:`quadratic_roa`): ``P`` minimises a robust bound of ``P A + A^T P`` over the
   enclosure of the Jacobians on the cube
   (:func:`~drlyap.verification.linearisation.robust_lyapunov_matrix`, starting from the Lyapunov matrix of the
   samples' mean). This only *chooses* W; nothing about it is assumed.
b. ``Wdot < 0`` on ``L = {W <= c_q}`` minus x*, and ``L`` inside the box. On the cube, by the mean-value form
   (:func:`~drlyap.verification.linearisation.jacobian_negative`: ``F_j(z) = A z`` with ``A`` in the hull of the
   cube's Jacobian enclosure, so only first derivatives are enclosed; on the quadrotor its cube is 16x wider per
   side than the Hessian test's); ``c_cube = min_i h_i^2 / (P^-1)_ii`` puts ``{W <= c_cube}`` inside the cube;
   :func:`~drlyap.verification.roa.sublevel.sublevel_roa` run on ``W`` may prove a larger level. ``L`` is forward
   invariant and every trajectory in it converges to x*: it is itself a region of attraction of the closed loop,
   which :func:`~drlyap.verification.roa.certify.certified_roa` reports (``quadratic``) where no sublevel set of V
   is certified.
c. ``c_1 <=`` a lower bound of V on ``{W >= c_q}`` in the box (branch and bound), and ``c_1 < c``: then
   ``{V <= c_1}`` lies inside ``L``.
d. Strict decrease of V (plain, decay ``1e-3`` of the condition's) on ``{c_1 <= V <= c}`` inside the delta-ball
   (outside it the condition already gives it; with no decay in the condition, on the whole box),
   possibly lowering ``c``.

Then V decreases strictly on ``S`` minus ``{V < c_1}``: a trajectory from ``S`` stays in ``S`` (V never rises
above ``max(V(0), c_1) <= c``), reaches ``{V <= c_1}`` in finite time (a compact set away from x*, a
uniform rate), and from there lies in ``L`` for ever, where W, hence the state, tends to x*: ``S`` is a
region of attraction. The result's ``local`` then reads ``method: "linearisation"`` with ``P``, ``q_level``
``c_q``, ``inner_level`` ``c_1``, the Jacobians' eigenvalues, and the failed attempt as ``second_order``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition, PlainDecrease
from drlyap.enclosures import F64, REL1, round_down, round_up
from drlyap.kinds import Enclosure
from drlyap.networks import QuadraticLyapunov
from drlyap.proof_settings import Budget
from drlyap.regions import Domain, Region, box_grid, default_grid, near_dist
from drlyap.verification.bounds import box_bounds, value_objective
from drlyap.verification.branch_and_bound import Exempt, ProofRules, maximize, verify_condition
from drlyap.verification.linearisation import (
    closed_loop_jacobians,
    common_lyapunov_matrix,
    decrease_weights,
    is_hurwitz,
    jacobian_enclosures,
    jacobian_negative,
    robust_lyapunov_matrix,
    scaled_jacobians,
)
from drlyap.verification.results import ConditionProof
from drlyap.verification.roa.levels import below, level_search, share, time_capped
from drlyap.verification.roa.local import not_equilibrium, proved_cube, resolving, resolving_ellipsoid
from drlyap.verification.roa.sublevel import sublevel_roa
from drlyap.verification.roa_steps import (
    Annulus,
    EllipsoidCandidate,
    EllipsoidSearch,
    LinearisationProof,
    QuadraticRegion,
)


def quadratic_roa(loop: ClosedLoop, condition: Condition, region: Region,
                  budget: Budget = Budget(seconds=10.0, enclosure=Enclosure.AFFINE)) -> QuadraticRegion:
    """A certified region of attraction ``{z^T P z <= c_q}`` of the closed loop of every sample's model of
    ``condition`` (the controller's, whatever V is), from its linearisation (module docstring, steps a and b).

    Two candidates ``(P, cube)``, each with ``Wdot < 0`` proved on its cube minus x* by
    :func:`~drlyap.verification.linearisation.jacobian_negative`: the samples' Lyapunov-equation ``P``
    (:func:`common_lyapunov_matrix`) on the widest cube (halving) where it is proved, and a ``P`` fitted to the cube
    (:func:`_fitted_cube`: wider cubes, rounder ellipsoids). For each, ``c_cube = min_i h_i^2 / (P^-1)_ii`` (rounded
    down) puts ``{W <= c_cube}`` inside the cube, and :func:`~drlyap.verification.roa.sublevel.sublevel_roa` on ``W``
    may prove a larger level (:func:`_quadratic_level`; the candidates share the budget's boxes, and its seconds
    left). The choice of the cubes is not a branch and bound: a bounded number of tries (halving, then bisection
    steps), each capped by half the budget's seconds (``capped`` names a step that stopped at its time cap). The result
    is the candidate with the larger volume: ``proved``, ``P``, ``P_choice``, ``q_level`` (``c_q``), ``cube``,
    ``cube_level``, ``q_roa`` (the search beyond the cube), ``share_of_box`` (the ellipsoid's exact volume over the
    box's), ``candidates`` (both, each with its ``P``), ``boxes`` (all the searches'), the Jacobians and their
    eigenvalues, and ``reason`` when it fails."""
    start = time.perf_counter()
    time_limit = budget.seconds
    deadline = start + time_limit
    out = QuadraticRegion()
    plain = condition.per_sample()
    if plain is None:
        out.reason = "the condition implies no per-sample decrease (a CVaR over several samples)"
        return out
    out.reason = not_equilibrium(loop, plain, region)
    if out.reason:
        return out
    # 1. the linearisation (this only chooses W = z^T P z; everything after is proved)
    jacobians = closed_loop_jacobians(loop, plain)
    out.jacobians = [a.tolist() for a in jacobians]
    eigenvalues = []
    for a in jacobians:
        ok, ev = is_hurwitz(a)
        eigenvalues.append([[e.real, e.imag] for e in ev])
        if not ok:
            out.eigenvalues = eigenvalues
            out.reason = f"the closed-loop linearisation at x* is not Hurwitz (eigenvalues {[str(e) for e in ev]})"
            return out
    out.eigenvalues = eigenvalues
    s = region.scale / 2
    half_box = torch.minimum(-region.lo, region.hi)
    p_mean = common_lyapunov_matrix(jacobians, s)
    if not bool(torch.isfinite(p_mean).all()) or float(torch.linalg.eigvalsh(p_mean).min()) <= 0:
        out.reason = "the Lyapunov matrix P is not positive definite"
        return out
    # 2. two candidates for W and its cube: the samples' Lyapunov-equation P on the widest cube where it is
    # proved, and a P fitted to the widest cube it can be proved on; each W's region then searched beyond it
    cube_deadline = start + 0.5 * time_limit
    candidates = []
    half, bound, reason = proved_cube(loop.with_lyapunov(QuadraticLyapunov(p_mean)), plain, half_box,
                                      1e-9 * float(half_box.max()), s)
    if half is not None:
        candidates.append(("Lyapunov equation", p_mean, half, bound))
    capped = []
    fitted = _fitted_cube(loop, plain, p_mean, half_box, s, cube_deadline, capped)
    if fitted is not None:
        candidates.append(("fitted", *fitted))
    if not candidates:
        out.reason = f"W = z'Pz: Wdot < 0 not proved on any cube around x* ({reason})"
        out.capped = capped or None
        return out
    results, spent = [], 0
    for i, (name, p, half, bound) in enumerate(candidates):
        left = (deadline - time.perf_counter()) / (len(candidates) - i)
        boxes = share(max(budget.boxes - spent, budget.boxes // 10), 1 / (len(candidates) - i))
        found, found_capped = _quadratic_level(loop, plain, region, p, half, bound,
                                               replace(budget, seconds=left, boxes=boxes))
        found.P_choice = name
        spent += found.boxes
        capped += found_capped
        results.append(found)
    best = max(results, key=lambda r: r.share_of_box)
    # candidates: each with its P, linearisation_local tries every one
    return replace(out.choose(best), candidates=results, time_s=time.perf_counter() - start, boxes=spent,
                   capped=capped or None)


def _fitted_cube(loop: ClosedLoop, plain: PlainDecrease, p_mean: Tensor, half_box: Tensor, s: Tensor,
                 deadline: float, capped: list | None = None) -> tuple[Tensor, Tensor, float] | None:
    """``(P, half, bound)``: the widest cube ``half_box * f`` (f halving down to 1e-9, then two bisection steps) on
    which a ``P`` fitted by :func:`robust_lyapunov_matrix` (from ``p_mean``, warm-started cube to cube) is proved by
    :func:`~drlyap.verification.linearisation.jacobian_negative`, that ``P`` refitted for the largest ellipsoid inside
    the cube; None if none. Past ``deadline`` (a time cap) no further cube is tried, and ``capped`` (a list) gets
    the step's name."""

    def attempt(frac: float, p_from: Tensor, t_from: Tensor | None, steps: int):
        h = half_box * frac
        centre, radius = scaled_jacobians(jacobian_enclosures(loop, plain, h), s)
        if not bool(torch.isfinite(centre).all() and torch.isfinite(radius).all()):
            return None, p_from, t_from
        p_s, log_t, rate = robust_lyapunov_matrix(centre, radius, p_from, t_from, steps=steps, stop_below=0.0)
        if not rate < 0:
            return None, p_s, log_t
        p = p_s / s[:, None] / s[None, :]
        p = (p + p.T) / 2
        ok, bound, _ = jacobian_negative(loop, plain, p, h, s, log_t, (centre, radius))
        return ((p, h, bound, log_t) if ok else None), p_s, log_t

    def out_of_time() -> bool:
        late = time.perf_counter() > deadline
        if late and capped is not None:
            capped.append("the fitted cube of the closed loop's quadratic W")
        return late

    found, frac, failed, log_t = None, 1.0, None, None
    p_start = p_mean * s[:, None] * s[None, :]
    while found is None and frac > 1e-9 and not out_of_time():
        found, p_start, log_t = attempt(frac, p_start, log_t, 300)
        if found is None:
            failed, frac = frac, frac / 2
    if found is None:
        return None
    for _ in range(2):
        if failed is None or out_of_time():
            break
        mid = (frac + failed) / 2
        better, _, _ = attempt(mid, found[0] * s[:, None] * s[None, :], found[3], 1000)
        if better is not None:
            found, frac = better, mid
        else:
            failed = mid
    p, half, bound, log_t = found
    centre, radius = scaled_jacobians(jacobian_enclosures(loop, plain, half), s)
    p_s, log_t, rate = robust_lyapunov_matrix(centre, radius, p * s[:, None] * s[None, :], log_t, steps=1000,
                                              volume=True)
    if rate < 0:
        rounder = (p_s + p_s.T) / 2 / s[:, None] / s[None, :]
        ok, rounder_bound, _ = jacobian_negative(loop, plain, rounder, half, s, log_t, (centre, radius))
        if ok:
            p, bound = (rounder + rounder.T) / 2, rounder_bound
    return p, half, bound


def _quadratic_level(loop: ClosedLoop, plain: PlainDecrease, region: Region, p: Tensor, half: Tensor, bound: float,
                     budget: Budget) -> tuple[EllipsoidCandidate, list[str]]:
    """The certified level ``q_level`` of ``W = z^T P z`` whose decrease is proved on the cube ``half``: the
    largest ellipsoid inside the cube (``cube_level``), grown while
    :func:`~drlyap.verification.linearisation.jacobian_negative` proves the decrease on the ellipsoid's bounding box
    (``box_level``; up to 30% of the time), or more where :func:`~drlyap.verification.roa.sublevel.sublevel_roa` on
    W proves it (the budget's boxes; the doubling and bisection are a bounded number of tests, up to 30% of the
    seconds as a cap, named in ``capped`` where reached); with ``P``, the cube, ``share_of_box`` (the ellipsoid's
    exact volume over the box's), ``extent`` (the largest ``|z_i|`` in it, per state), ``boxes`` and the search's
    details; and the steps that stopped at their time cap."""
    start = time.perf_counter()
    time_limit = budget.seconds
    inv_diag = torch.linalg.inv(p).diagonal()
    c_cube = float(round_down((half.square() / inv_diag).min(), 1e-6))
    # grow the level while W decreases on the ellipsoid's bounding box |z_i| <= sqrt(c (P^-1)_ii) (it holds the
    # ellipsoid and the segments to x*): doubling, then four geometric bisection steps
    half_box = torch.minimum(-region.lo, region.hi)

    def bounding_box(c: float) -> Tensor:
        return round_up((c * inv_diag).sqrt(), 1e-6)

    def decreases(c: float) -> bool:
        box = bounding_box(c)
        return bool((box <= half_box).all()) and jacobian_negative(loop, plain, p, box, region.scale / 2)[0]

    capped = []

    def out_of_time() -> bool:
        late = time.perf_counter() - start > 0.3 * time_limit
        if late:
            capped.append("the growth of the closed loop's ellipsoid W")
        return late

    c_box, failed = c_cube, None  # doubling ends where the bounding box leaves the state box, if not before
    while failed is None and not out_of_time():
        if decreases(2 * c_box):
            c_box *= 2
        else:
            failed = 2 * c_box
    for _ in range(4):
        if failed is None or out_of_time():
            break
        mid = math.sqrt(c_box * failed)
        c_box, failed = (mid, failed) if decreases(mid) else (c_box, mid)
    proved_on = bounding_box(c_box) if c_box > c_cube else half
    w = QuadraticLyapunov(p)
    r_in = float(proved_on.min())
    ring = PlainDecrease(plain.xi, 0.25 * abs(bound) / 2 * r_in, 0.0, plain.model)
    w_roa = sublevel_roa(loop.with_lyapunov(w), ring, Region(region.lo, region.hi, r_in),
                         replace(budget, seconds=max(1.0, time_limit - (time.perf_counter() - start)),
                                 min_width=resolving(budget.min_width, r_in, region)), samples_per_axis=50,
                         cut_by_box=False)  # L must lie inside the box: its certificate is W above c_q on the faces
    c_q = c_box
    if w_roa.kind == "region of attraction" and w_roa.level > c_q:
        c_q = w_roa.level
    if time_capped(w_roa.limited_by):
        capped.append("the search of the closed loop's ellipsoid W")
    n = loop.n
    volume = math.pi ** (n / 2) / math.gamma(n / 2 + 1) * c_q ** (n / 2) / math.sqrt(float(torch.linalg.det(p)))
    search = EllipsoidSearch(w_roa.level, w_roa.kind, w_roa.limited_by, w_roa.boxes_processed, w_roa.time_s,
                             ring.decay_rate, r_in, budget.enclosure)
    found = EllipsoidCandidate(
        P=p.tolist(), q_level=c_q, share_of_box=volume / float(region.scale.prod()),
        extent=(c_q * inv_diag).sqrt().tolist(),  # the largest |z_i| in the ellipsoid, per state
        cube=half.tolist(), cube_fraction=float((half / torch.minimum(-region.lo, region.hi)).max()),
        hessian_bound=bound, cube_level=c_cube, box_level=c_box, box=proved_on.tolist(), q_roa=search,
        boxes=w_roa.boxes_processed + (w_roa.local.boxes if w_roa.local is not None else 0))
    return found, capped


def linearisation_local(loop: ClosedLoop, condition: Condition, region: Region, level: float,
                        budget: Budget = Budget(seconds=10.0, enclosure=Enclosure.MEAN_VALUE)) -> LinearisationProof:
    """The local proof from the closed-loop linearisation, for when V's own second-order proof fails (module
    docstring, "The linearisation proof"). ``level``: the level ``c`` up to which ``condition`` is proved on
    ``{V <= c}`` outside the delta-ball. Returns ``proved``, ``level`` (the largest ``c' <= c`` for which the
    whole chain holds: ``{V <= c'}`` is then a region of attraction), ``P``, ``q_level`` (``c_q``), ``inner_level``
    (``c_1``), ``quadratic`` (:func:`quadratic_roa`'s result), ``boxes``, the proofs' details and ``reason`` when it
    fails. ``budget``: :func:`quadratic_roa` gets 40% of its boxes and seconds, V's bound outside each candidate
    ellipsoid 30% (shared between them), the annulus the rest; ``capped`` names a step that stopped at its time cap."""
    start = time.perf_counter()
    time_limit, enclosure = budget.seconds, budget.enclosure_for(loop.n)
    deadline = start + time_limit
    quad = quadratic_roa(loop, condition, region, replace(budget, seconds=0.4 * time_limit,
                                                          boxes=share(budget.boxes, 0.4), enclosure=enclosure))
    out = LinearisationProof(quadratic=quad.reported(), jacobians=quad.jacobians, eigenvalues=quad.eigenvalues,
                             P=quad.P, q_level=quad.q_level, cube=quad.cube)
    capped, spent = list(quad.capped or ()), quad.boxes

    def done() -> LinearisationProof:
        out.boxes, out.capped = spent, capped or None
        return out

    if not quad.proved:
        out.reason = quad.reason
        return done()
    c_1, chosen, inner_capped = _inner_level(loop, quad.candidates, region, replace(budget, enclosure=enclosure),
                                             deadline)
    capped += inner_capped
    out.inner_level = c_1
    if chosen is not None:  # the W the chain below rests on, with its level and cube
        out.P, out.q_level, out.cube = chosen.P, chosen.q_level, chosen.cube
    if not c_1 > 0:
        out.reason = "no sublevel set of V provably inside {W <= c_q}"
        return done()
    # any smaller c_1 will do ({V <= c_1} only shrinks): keep it below the outer level, so that the annulus
    # {c_1 <= V <= c} is not empty and {V <= c} is forward invariant
    c_1 = min(c_1, level / 2)
    out.inner_level = c_1
    annulus = _annulus(loop, condition, region, level, c_1, chosen, deadline,
                       replace(budget, enclosure=enclosure, boxes=share(max(budget.boxes - spent, budget.boxes // 10), 1.0)))
    spent += annulus.boxes
    capped += ["the annulus inside the ball"] if time_capped(annulus.limited_by) else []
    out.annulus = annulus
    out.time_s = time.perf_counter() - start
    if not annulus.level > c_1:
        out.reason = (f"decrease of V on {{{c_1:.4g} <= V <= c}} inside the ball fails below the inner level "
                      f"({annulus.limited_by})")
        return done()
    out.proved, out.level = True, annulus.level
    return done()


def _inner_level(loop: ClosedLoop, candidates: list[EllipsoidCandidate], region: Region, budget: Budget,
                 deadline: float) -> tuple[float, EllipsoidCandidate | None, list[str]]:
    """Step c: ``c_1 <=`` the least V over ``{W >= c_q}`` in the box, so that ``{V <= c_1}`` lies inside
    ``{W <= c_q}``; of the candidate W's (:func:`quadratic_roa`), the one that holds the largest sublevel set of V.
    Each candidate's ``inner_level`` is set; returns ``(c_1, that candidate or None, the steps that stopped at their
    time cap)``. ``budget``: its enclosure, and 30% of its boxes shared between the candidates, by ``deadline``."""
    vobj = value_objective(loop.lyapunov)
    blo, bhi = box_grid(region.lo, region.hi, default_grid(loop.system.n))
    c_1, chosen, capped = -math.inf, None, []
    for i, cand in enumerate(candidates):
        p_i, c_qi = torch.tensor(cand.P, dtype=F64), cand.q_level
        w_i = QuadraticLyapunov(p_i)
        wobj = value_objective(w_i)

        def outside(a, b, wobj=wobj, c_qi=c_qi):
            return box_bounds(wobj, a, b, budget.enclosure)[1][:, 0] >= c_qi

        seconds = max(1.0, 0.3 * (deadline - time.perf_counter()) / (len(candidates) - i))
        outside_ellipsoid = Domain(blo, bhi, region.scale, outside, lambda z, w_i=w_i, c_qi=c_qi: w_i(z) >= c_qi)
        _, neg_up, info = maximize(lambda z: -vobj(z), outside_ellipsoid,
                                   replace(budget, seconds=seconds, boxes=share(budget.boxes, 0.3 / len(candidates))),
                                   label="V's least value outside the closed loop's ellipsoid")
        capped += ["V's minimum outside the closed loop's ellipsoid"] if time_capped(info.stopped) else []
        c_1i = float(round_down(round_down(-neg_up[0], REL1), 1e-9))
        cand.inner_level = c_1i
        if c_1i > c_1:
            c_1, chosen = c_1i, cand
    return c_1, chosen, capped


def _annulus(loop: ClosedLoop, condition: Condition, region: Region, level: float, c_1: float,
             chosen: EllipsoidCandidate, deadline: float, budget: Budget) -> Annulus:
    """Step d: V's strict decrease (plain, decay ``1e-3`` of the condition's) on ``{c_1 <= V <= c}`` inside the
    delta-ball (outside it the condition's decay already gives it; with no decay in the condition, on the whole box),
    with boxes near ``{V = c_1}`` fine enough to resolve the ellipsoid ``{W <= c_q}`` of ``chosen``. ``budget``: its
    enclosure and boxes, by ``deadline``. The :class:`Annulus` holds the level it reached (rounded below)."""
    system, plain = loop.system, condition.per_sample()
    strict = condition.decay_rate > 0 or condition.exp_rate > 0
    inner = PlainDecrease(plain.xi, 1e-3 * condition.decay_rate if strict else 1e-9,
                          1e-3 * condition.exp_rate if strict else 0.0, plain.model)
    delta = region.delta if strict else math.inf
    alo, ahi = box_grid(torch.maximum(region.lo, torch.full_like(region.lo, -delta)),
                        torch.minimum(region.hi, torch.full_like(region.hi, delta)), default_grid(system.n))

    def meets(a, b):
        return near_dist(a, b) < delta

    fits = meets(alo, ahi)
    alo, ahi = alo[fits], ahi[fits]
    # boxes near {V = c_1} must resolve a set as small as {W <= c_q}: a minimum width relative to it
    fine = resolving_ellipsoid(budget.min_width, torch.tensor(chosen.P, dtype=F64), chosen.q_level, region)
    c_2, limited_by, cex, boxes = level_search(
        loop, inner, Domain(alo, ahi, region.scale, meets, lambda centre: centre.norm(dim=-1) < delta), level,
        "outer proof", replace(budget, seconds=max(deadline - time.perf_counter(), 1.0), min_width=fine),
        floor=c_1)
    return Annulus(below(c_2), limited_by, boxes, inner.decay_rate, inner.exp_rate,
                   "delta-ball" if strict else "box", fine,
                   None if cex is None else system.to_user(cex[None])[0].tolist())


@dataclass
class EllipsoidProof:
    """What an ``ellipsoid`` certificate writes down (:func:`ellipsoid_proof`): ``W = z^T P z`` decreasing on the box
    ``|z_i| <= box_i`` by the Jacobian's enclosure with the weights ``tau (J, n, n)``, and, where the ellipsoid
    ``{W <= level}`` reaches beyond that box, ``ring``: W's strict decrease (``condition``) on it outside the ball of
    ``region`` (the state box, ``delta`` the box's smallest half-width), with W above the level on the box's faces."""

    p: Tensor
    level: float
    box: Tensor
    tau: Tensor
    condition: PlainDecrease
    region: Region
    ring: ConditionProof | None


def ellipsoid_proof(loop: ClosedLoop, condition: Condition, region: Region, ellipsoid: EllipsoidCandidate,
                    budget: Budget) -> EllipsoidProof | None:
    """The proofs behind a certified ``{z^T P z <= q_level}`` of :func:`quadratic_roa` (``ellipsoid``: the one it
    chose, :meth:`QuadraticRegion.ellipsoid`, or another of its candidates) as a certificate states them: the Jacobian
    test's weights on the box it proved (:func:`decrease_weights`), and beyond that box W's decrease proved again on
    ``{W <= q_level}`` outside the inner ball with its partition kept (``budget``, with the enclosure and minimum
    width of the search that found the level). None where either is not proved again."""
    plain = condition.per_sample()
    if plain is None:
        return None
    p, level, box = (torch.as_tensor(v, dtype=F64) for v in (ellipsoid.P, ellipsoid.q_level, ellipsoid.box))
    tau = decrease_weights(loop, plain, p, box, region.scale / 2)
    if tau is None:
        return None
    level = float(level)
    r_in = float(box.min())
    ring_region = Region(region.lo, region.hi, r_in)
    if level <= float(ellipsoid.box_level):
        return EllipsoidProof(p, level, box, tau, PlainDecrease(plain.xi, 0.0, 0.0, plain.model), ring_region, None)
    ring_condition = PlainDecrease(plain.xi, float(ellipsoid.q_roa.decay_rate), 0.0, plain.model)
    ring = verify_condition(loop.with_lyapunov(QuadraticLyapunov(p)), ring_condition, ring_region,
                            replace(budget, min_width=resolving(budget.min_width, r_in, region),
                                    enclosure=ellipsoid.q_roa.enclosure or budget.enclosure),
                            level=level, rules=ProofRules(keep_partition=True))
    if not ring.verified:
        return None
    return EllipsoidProof(p, level, box, tau, ring_condition, ring_region, ring)



@dataclass
class CoredProof:
    """V's strict decrease (``condition``) on ``{V <= level}`` over ``region`` (no inner ball) except where a box lies
    in the ellipsoid core ``{z^T P z <= c_q}`` of ``ellipsoid`` (``proof``: a verified proof with its partition), the
    part of a region of attraction that rests on the closed loop's own certified ellipsoid."""

    condition: PlainDecrease
    region: Region
    proof: ConditionProof
    p: Tensor
    q_level: float


def linearisation_proofs(loop: ClosedLoop, condition: Condition, region: Region, local: LinearisationProof,
                         budget: Budget) -> tuple[EllipsoidProof, CoredProof] | None:
    """The proofs behind a region of attraction ``{V <= c}`` that :func:`linearisation_local` certified (``local``,
    its result; ``c`` its ``level``) as certificates state them: the ellipsoid ``L = {z^T P z <= c_q}`` it rests on
    (:func:`ellipsoid_proof`), and V's strict decrease (the annulus's decay) on ``{V <= c}`` inside the delta-ball's
    box except where a box lies in ``L`` (its partition kept; ``verify_condition``'s ``core``). Outside the ball the
    condition's own proof on ``{V <= c}`` covers the rest; with V above ``c`` on the faces, a trajectory from the set
    stays in it while outside ``L`` (V decreases there) and reaches ``L`` (the band argument of
    :mod:`~drlyap.verification.roa.band`): this needs no inner level. None where the annulus's decay is not > 0 (its
    proof then ran over the whole box) or either proof does not hold again."""
    plain = condition.per_sample()
    annulus = local.annulus
    if (plain is None or not local.proved or annulus is None or annulus.region != "delta-ball" or region.delta <= 0
            or not annulus.decay_rate > 0):
        return None
    chosen = next((cand for cand in local.quadratic.candidates or ()
                   if cand.P == local.P and cand.q_level == local.q_level), None)
    if chosen is None:
        return None
    ellipsoid = ellipsoid_proof(loop, condition, region, chosen, budget)
    if ellipsoid is None:
        return None
    strict = PlainDecrease(plain.xi, float(annulus.decay_rate), 0.0, plain.model)
    ball = region.ball_box(0.0)
    fine = float(annulus.min_width) * float((region.scale / ball.scale).min())
    ring = verify_condition(loop, strict, ball, replace(budget, min_width=min(budget.min_width, fine)),
                            level=float(local.level), exempt=Exempt(core=(ellipsoid.p, ellipsoid.level)),
                            rules=ProofRules(keep_partition=True))
    if not ring.verified:
        return None
    return ellipsoid, CoredProof(strict, ball, ring, ellipsoid.p, ellipsoid.level)
