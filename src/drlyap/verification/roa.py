"""Certified regions of attraction: sublevel sets of V on which V provably decreases all the way to x*.

:func:`certified_roa` looks for the largest level ``c`` such that ``S = {z in box : V(z) <= c}``

1. lies inside the state box (``V > c`` on the box boundary), and
2. satisfies the condition's decrease on ``S`` outside the delta-ball (branch and bound, as
   :func:`drlyap.verification.verify_condition`), and
3. inside the delta-ball, ``Vdot < 0`` on S except at x* (:func:`local_decrease`): a second-order proof on a
   cube around x* and a branch and bound on the rest of the ball's part in S.

With all three, ``Vdot < 0`` on ``S`` minus x*, so ``S`` is forward invariant and every trajectory that
starts in it converges to x* (Lyapunov / LaSalle): ``S`` is a **region of attraction** of the model the
condition is about (the true model at ``xi``, or the design model at each training sample).

Where 3 cannot be proved, only **practical stability** is claimed: if ``c`` exceeds an upper bound ``c0``
of V on the delta-ball, trajectories from ``S`` stay in ``S`` and end up in ``{V <= c0}``. Nothing is
called a region of attraction unless it converges to x*.

The local proof (:func:`local_decrease`). For one sample's model ``q(z) = grad V(z) . F(z, pi(z))``:
``q(0) = 0`` and ``grad q(0) = H_V(0) F(0) = 0`` (``grad V(0) = 0`` by the construction of V, and x* is an
equilibrium of the model: checked to 1e-9 of the dynamics' scale, as the system declares it at build),
so by Taylor's theorem ``q(z) = z^T H_q(s z) z / 2`` for some ``s`` in [0, 1]. On a cube ``C`` around x*
the verifier encloses ``H_q`` over the whole cube (nested dual numbers running the networks' and the
system's own code); if every symmetric matrix in that interval matrix is negative definite (centre's
largest eigenvalue plus the radius matrix's Frobenius norm < 0), then ``q < 0`` on ``C`` minus x*. The cube
is shrunk until this holds (the controller must be unsaturated there); the rest of the delta-ball is
proved with plain decrease plus a small decay ``gamma_in ||z||`` (strict decrease away from x*).

The linearisation proof (:func:`linearisation_local`), tried when the one above fails (the networks are
trained outside the delta-ball only, so V's local quadratic part need not be a Lyapunov function of the
closed loop, or its Hessian of Vdot is so badly conditioned that no enclosure shows it: the mountain-car
pairs' is ``(-0.1, -3e4)``). For each sample's model:

a. ``A_j = dF_j/dz(0)`` (every one Hurwitz, else no claim); ``W(z) = z^T P z`` and a cube ``|z_i| <= h_i``
   chosen together (:func:`quadratic_roa`): ``P`` minimises a robust bound of ``P A + A^T P`` over the
   enclosure of the Jacobians on the cube
   (:func:`~drlyap.verification.linearisation.robust_lyapunov_matrix`, starting from the Lyapunov matrix of the
   samples' mean). This only *chooses* W; nothing about it is assumed.
b. ``Wdot < 0`` on ``L = {W <= c_q}`` minus x*, and ``L`` inside the box. On the cube, by the mean-value form
   (:func:`_jacobian_negative`: ``F_j(z) = A z`` with ``A`` in the hull of the cube's Jacobian enclosure, so only
   first derivatives are enclosed; on the quadrotor its cube is 16x wider per side than the Hessian test's);
   ``c_cube = min_i h_i^2 / (P^-1)_ii`` puts ``{W <= c_cube}`` inside the cube; :func:`certified_roa` run on
   ``W`` may prove a larger level. ``L`` is forward invariant and every trajectory in it converges to x*:
   it is itself a region of attraction of the closed loop, which :func:`certified_roa` reports (``quadratic``)
   where no sublevel set of V is certified.
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

The band proof (:func:`band_roa`), tried when none of the above certifies a sublevel set of V but the closed
loop's own ellipsoid ``L = {W <= c_q}`` (step b) is certified: on 6 states the condition's proof outside the
delta-ball and V's proof near x* do not finish (the closed loop is stiff), while L is proved by its Jacobians alone.
It proves strict decrease ``Vdot + 1e-9 ||z|| <= 0`` (every sample's model) on ``S = {V <= c}`` minus L, over the
whole box, with ``c`` below V's lower bound on the box's faces. Then every trajectory from S converges to x*:
while outside L it keeps V <= c (V decreases there, and S does not reach the faces), so it stays in S; it cannot
stay in S minus L for ever: that set is bounded away from x* (L holds a neighbourhood of it), so there V falls
at least at the uniform rate ``1e-9 sqrt(c_q / lambda_max(P))`` while V is bounded below; once in L it stays in
L and converges. ``S`` together with L is forward invariant; S alone need not be (a
trajectory inside L may leave S). The search (:func:`_level_search` with the ellipsoid) drops boxes inside L,
bounds V on each box's part outside L (:func:`_outside_lower`), and asks the decrease only on the part with
``V <= c`` (:func:`~drlyap.verification.bounds.sublevel_upper`); levels are tried from just above V's sampled
minimum on L's boundary up, 1.3x apart. ``local`` then reads ``method: "band"``.
"""

from __future__ import annotations

import math
import time

import torch
from torch import Tensor

from drlyap.conditions import Condition, PlainDecrease, local_rates
from drlyap.enclosures import F64, REL1, Dual, Interval, _down, _up, _vertices
from drlyap.networks import Controller, Lyapunov, QuadraticLyapunov
from drlyap.regions import Region, box_grid, default_grid, near_dist, split
from drlyap.systems import UncertainSystem
from drlyap.verification.bounds import (
    box_bounds,
    check_enclosure,
    combine_lower,
    combine_upper,
    condition_and_value_objective,
    default_enclosure,
    sublevel_upper,
    value_objective,
)
from drlyap.verification.branch_and_bound import as_region, maximize, verify_condition
from drlyap.verification.falsifier import DEFAULT_STARTS, settle_unknown
from drlyap.verification.linearisation import (
    closed_loop_jacobians,
    common_lyapunov_matrix,
    is_hurwitz,
    jacobian_enclosures,
    robust_decrease_matrix,
    robust_lyapunov_matrix,
    scaled_jacobians,
)


def _faces(lo: Tensor, hi: Tensor, per_axis: list[int]) -> tuple[Tensor, Tensor]:
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


def boundary_minimum(lyapunov: Lyapunov, region: Region, time_limit: float = 5.0, min_width: float = 1e-4,
                     enclosure: str = "mean-value", rel_tol: float = 1e-3) -> tuple[float, float]:
    """``(lower, upper)``: a sound lower bound of the minimum of V over the boundary of the state box, and a value
    of V taken at a point of the boundary (so ``lower <= min <= upper``); boxes are refined until ``lower`` is
    within ``rel_tol`` of ``upper`` (or time runs out: ``lower`` is then ``-inf``)."""
    if isinstance(lyapunov, QuadraticLyapunov):  # min of z'Pz on the hyperplane z_i = b is b^2 / (P^-1)_ii
        p = lyapunov.P.to(F64)
        inv_diag = torch.linalg.inv(p).diagonal()
        sides = torch.stack([region.lo, region.hi], -1)  # (n, 2)
        minima = sides.square() / inv_diag[:, None]  # on each face's hyperplane
        low = float(_down(minima.min(), 1e-9))
        i, j = divmod(int(minima.argmin()), 2)
        point = torch.clamp(torch.linalg.solve(p, torch.eye(region.n, dtype=F64)[i]) * (sides[i, j] / inv_diag[i]),
                            region.lo, region.hi)
        point[i] = sides[i, j]
        return low, float(lyapunov(point[None])[0])
    vobj = value_objective(lyapunov)
    flo, fhi = _faces(region.lo, region.hi, default_grid(region.n))
    best, neg_up, _ = maximize(lambda z: -vobj(z), flo, fhi, region.scale, time_limit=time_limit, min_width=min_width,
                               enclosure=enclosure, rel_tol=rel_tol)
    return float(-neg_up[0]), float(-best[0])


def verify_sublevel(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, condition: Condition,
                    delta: float | Region, level: float, time_limit: float = 30.0, min_width: float = 1e-4,
                    enclosure: str = "mean-value", **kwargs) -> dict:
    """Prove what region-of-attraction training asks (``TrainConfig.roa_level``): the condition on
    ``{V <= level}`` minus the delta-ball (:func:`verify_condition` with ``level``) and ``V > level`` on the
    boundary of the box (:func:`boundary_minimum`), so that the sublevel set lies inside the box.

    Returns :meth:`VerificationResult.to_dict` plus ``boundary_min_lower`` / ``boundary_min_upper``; ``status``
    is ``verified`` only when both hold, ``violated`` when a boundary point has ``V <= level`` or a state of the
    set violates the condition.
    """
    region = as_region(system, delta)
    start = time.perf_counter()
    low, high = boundary_minimum(lyapunov, region, time_limit / 4, min_width, enclosure, rel_tol=0.02)
    left = max(1.0, time_limit - (time.perf_counter() - start))
    out = verify_condition(system, lyapunov, controller, condition, region, time_limit=left, min_width=min_width,
                           enclosure=enclosure, level=level, **kwargs).to_dict()
    out.update(boundary_min_lower=low, boundary_min_upper=high, time_s=time.perf_counter() - start)
    if high <= level:
        out["status"], out["stopped"] = "violated", f"V = {high:.6g} <= {level:g} at a point of the box's boundary"
    elif low <= level and out["status"] == "verified":
        out["status"], out["stopped"] = "unknown", f"V > {level:g} on the box's boundary not proved (bound {low:.6g})"
    return out


def prove_trained(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, condition: Condition,
                  delta: float | Region, level: float | None = None, falsify_starts: int = DEFAULT_STARTS,
                  **kwargs) -> dict:
    """The proof of a trained condition as a dict: :func:`verify_condition` on X_delta (``level`` None) or
    :func:`verify_sublevel` on ``{V <= level}`` (region-of-attraction training). Where the proof comes back
    ``unknown``, a falsifier from ``falsify_starts`` states looks for a certain violation
    (:func:`~drlyap.verification.falsifier.settle_unknown`; 0: none)."""
    region = as_region(system, delta)
    if level is None:
        out = verify_condition(system, lyapunov, controller, condition, region, **kwargs).to_dict()
    else:
        out = verify_sublevel(system, lyapunov, controller, condition, region, level, **kwargs)
    return settle_unknown(out, system, lyapunov, controller, condition, region, level, starts=falsify_starts)


def _hessian_negative(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, plain: PlainDecrease,
                      half_width: Tensor) -> tuple[bool, float, str]:
    """Is ``z^T H_q z < 0`` for every Hessian of every sample's ``q = Vdot`` over the cube ``|z_i| <= half_width_i``?

    Returns (proved, the bound ``lambda`` with ``q(z) <= lambda ||z||^2 / 2`` on the cube, reason)."""
    n = system.n
    lo, hi = (-half_width)[None], half_width[None]
    eye = torch.eye(n, dtype=F64)[None]
    first = Dual(Interval(lo, hi), Interval(eye, eye))
    z = Dual(first, Dual(Interval(eye, eye), None))
    try:
        terms = plain.terms(system, lyapunov, controller, z)
    except TypeError as err:  # e.g. the controller saturates on the cube (clamp has no second derivative)
        return False, math.nan, str(err)
    vdot = terms.vdot  # (1, N) nested duals; decay is not part of q
    hess = vdot.d.d  # (1, N, n, n) interval
    worst = -math.inf
    for j in range(hess.shape[1]):
        hlo, hhi = hess.lo[0, j], hess.hi[0, j]
        centre, radius = (hlo + hhi) / 2, (hhi - hlo) / 2
        centre, radius = (centre + centre.T) / 2, (radius + radius.T) / 2
        if not bool(torch.isfinite(centre).all() and torch.isfinite(radius).all()):
            return False, math.nan, "non-finite Hessian enclosure"
        top = float(torch.linalg.eigvalsh(centre).max())
        spread = float(torch.linalg.matrix_norm(radius))
        pad = 1e-12 * (float(torch.linalg.matrix_norm(centre)) + spread) + 1e-300
        worst = max(worst, top + spread + pad)
    return worst < 0, worst, "" if worst < 0 else "Hessian not provably negative definite"


def _below(level: float) -> float:
    """A level rounded one float64 step down (a sound level stays sound below), infinities as they are."""
    return float(_down(torch.tensor(level, dtype=F64), REL1)) if math.isfinite(level) else level


def _jacobian_negative(system: UncertainSystem, controller: Controller, plain: PlainDecrease, p: Tensor,
                       half: Tensor, half_widths: Tensor, log_t: Tensor | None = None,
                       scaled: tuple[Tensor, Tensor] | None = None) -> tuple[bool, float, str]:
    """Is ``Wdot = 2 z^T P F_j(z) < 0`` for every sample's model on the cube ``|z_i| <= half_i`` minus x*
    (``W = z^T P z``)?

    The mean-value form: ``F_j(0) = 0``, so ``F_j(z) = A z`` for some ``A`` in the hull of the enclosure of
    ``dF_j/dz`` over the cube (:func:`~drlyap.verification.linearisation.jacobian_enclosures`; the cube holds the
    segment from x* to z), and ``Wdot = z^T (P A + A^T P) z``. In the coordinates scaled by ``half_widths`` this
    is at most ``z_s^T M z_s`` with ``M`` of
    :func:`~drlyap.verification.linearisation.robust_decrease_matrix` (its ``t`` fitted here, any ``t`` is
    sound); ``M``'s largest eigenvalue plus a rounding pad of 1e-9 of the terms' norms below 0 proves it.
    Only first derivatives are enclosed (the Hessian test of :func:`_hessian_negative` needs second ones).

    ``scaled``: that cube's :func:`~drlyap.verification.linearisation.scaled_jacobians` when the caller has them.

    Returns (proved, the bound ``lambda`` with ``Wdot <= lambda ||z||^2 / 2`` on the cube, reason)."""
    s = half_widths.to(F64)
    centre, radius = scaled or scaled_jacobians(jacobian_enclosures(system, controller, plain, half), s)
    if not bool(torch.isfinite(centre).all() and torch.isfinite(radius).all()):
        return False, math.nan, "non-finite Jacobian enclosure"
    p_s = p.to(F64) * s[:, None] * s[None, :]
    unit = float(torch.linalg.eigvalsh(p_s).min())  # P / unit has lambda_min 1, as robust_lyapunov_matrix's
    if not unit > 0:
        return False, math.nan, "P is not positive definite"
    p_n = p_s / unit

    def proved_rate(log_t: Tensor) -> float:
        m = robust_decrease_matrix(p_n, centre, radius, log_t)
        t = log_t.exp()
        norms = (2 * torch.linalg.matrix_norm(p_n) * torch.linalg.matrix_norm(centre)
                 + torch.linalg.matrix_norm(p_n) ** 2 * (radius * t).sum(-1).amax(-1)
                 + (radius / t).sum(-2).amax(-1) + torch.linalg.matrix_norm(m))
        top = torch.linalg.eigvalsh(m).amax(-1) + 1e-9 * norms + 1e-300
        return float(top.max())

    worst = proved_rate(log_t) if log_t is not None else math.nan
    for stop in (0.0, None):  # fit t: first until the rate is negative, then (if the pads undo it) all the way
        if worst < 0:
            break
        _, log_t, _ = robust_lyapunov_matrix(centre, radius, p_n, log_t, steps=300, fit_p=False, stop_below=stop)
        worst = proved_rate(log_t)
    if not worst < 0:  # NaN included
        return False, math.nan, "P A + A^T P not provably negative definite over the Jacobian enclosure"
    return True, 2 * unit * worst / float(s.max()) ** 2, ""


def _proved_cube(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, plain: PlainDecrease,
                 half: Tensor, smallest: float, half_widths: Tensor) -> tuple[Tensor | None, float, str]:
    """The first cube ``|z_i| <= half_i`` (halving ``half`` until its largest side is below ``smallest``) on which
    ``Vdot < 0`` except at x* is proved: by :func:`_jacobian_negative` for a quadratic V, else by
    :func:`_hessian_negative`. Returns ``(half, bound, "")`` (``Vdot <= bound ||z||^2 / 2`` there), or
    ``(None, nan, reason)``."""
    bound, reason = math.nan, ""
    for _ in range(60):
        if isinstance(lyapunov, QuadraticLyapunov):
            ok, bound, reason = _jacobian_negative(system, controller, plain, lyapunov.P, half, half_widths)
        else:
            ok, bound, reason = _hessian_negative(system, lyapunov, controller, plain, half)
        if ok:
            return half, bound, ""
        half = half / 2
        if float(half.max()) < smallest:
            break
    what = "mean-value (Jacobian)" if isinstance(lyapunov, QuadraticLyapunov) else "second-order"
    return None, math.nan, f"{what} proof failed on every cube down to {float(half.max()):.3g} ({reason})"


def _resolving(min_width: float, r_in: float, region: Region) -> float:
    """A minimum box width (relative to the box) small enough for boxes to resolve a ball of radius ``r_in``
    (the second-order cube around x* that a branch and bound has to close around)."""
    return min(min_width, 0.05 * r_in / float(region.scale.max()))


def _not_equilibrium(system: UncertainSystem, controller: Controller, plain: PlainDecrease, region: Region) -> str:
    """Why x* is not an equilibrium of some sample's model (``F(x*, pi(x*)) = 0`` up to 1e-9 of the box's
    scale, with the verifier's enclosures), or "" when it is of every one: the local proofs rest on it."""
    zero = torch.zeros(system.n, system.n, dtype=F64)  # n copies of x*, one per unit covector below
    x_star = system.to_user(Interval(zero, zero))
    u_star = controller(Interval(zero, zero))
    unit = Interval(torch.eye(system.n, dtype=F64), torch.eye(system.n, dtype=F64))
    scale = float(region.scale.abs().max())
    for xi in plain.xi:
        if plain.model == "true":
            f = system.true_dynamics(x_star, u_star, xi)
        else:  # e_i . (f + W xi) for each unit covector e_i: the design model's field at x*
            gf, gw = system.weighted_design(x_star, u_star, unit)
            f = gf + (gw * Interval.const(xi)).sum(-1)
        size = float(torch.maximum(f.lo.abs(), f.hi.abs()).max())
        if size > 1e-9 * max(scale, 1.0):
            return f"x* is not an equilibrium of the model at xi = {xi.tolist()} (|F(x*)| up to {size:.3g})"
    return ""


def local_decrease(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, condition: Condition,
                   region: Region, time_limit: float = 10.0, min_width: float = 1e-4,
                   enclosure: str = "mean-value", level: float | None = None) -> dict:
    """Prove ``Vdot < 0`` on the delta-ball minus x* (with ``level``: on its part in ``{V <= level}``) for every
    sample of ``condition``'s model (see the module docstring). Returns ``proved``, the cube half-width ``cube``
    of the second-order proof, its bound ``hessian_bound``, the ring verification's status and ``reason`` when
    it fails."""
    start = time.perf_counter()
    method = "mean-value Jacobian" if isinstance(lyapunov, QuadraticLyapunov) else "second order"
    out: dict = {"method": method, "proved": False, "cube": None, "hessian_bound": None, "ring": None, "reason": ""}
    plain = condition.per_sample()
    if plain is None:
        out["reason"] = "the condition implies no per-sample decrease (a CVaR over several samples)"
        return out
    delta = region.delta
    if delta <= 0:
        out.update(proved=True, reason="no ball to cover (delta = 0)")
        return out
    reason = _not_equilibrium(system, controller, plain, region)
    if reason:
        out["reason"] = reason
        return out
    out["equilibrium"] = True  # the preconditions hold: a failure below is one of the second-order proof
    half = torch.minimum(torch.minimum(-region.lo, region.hi), torch.full_like(region.lo, delta))
    half, bound, reason = _proved_cube(system, lyapunov, controller, plain, half, 1e-7 * delta,
                                       region.scale / 2)
    if half is None:
        out["reason"] = reason
        if not isinstance(lyapunov, QuadraticLyapunov):  # why: is V a Lyapunov function of the linearisation at all?
            with torch.enable_grad():
                rate = float(local_rates(plain, system, lyapunov, controller).detach().max())
            out["local_rate"] = rate
            out["reason"] += f"; V's second-order rate at x*: Vdot <= {rate:+.3g} V" + (
                " (V rises along some direction arbitrarily close to x*: no cube can prove its decrease)"
                if rate > 0 else "")
        return out
    out["cube"] = half.tolist()
    out["hessian_bound"] = bound
    r_in = float(half.min())
    if bool((half >= delta).all()):  # the cube covers the ball
        out.update(proved=True, time_s=time.perf_counter() - start)
        return out
    # the rest of the ball: strict decrease Vdot + gamma_in ||z|| <= 0 on (ball-box) minus the r_in-ball
    gamma_in = 0.25 * abs(bound) / 2 * r_in
    ring_plain = PlainDecrease(plain.xi, gamma_in, 0.0, plain.model)
    ring = Region(torch.maximum(region.lo, torch.full_like(region.lo, -delta)),
                  torch.minimum(region.hi, torch.full_like(region.hi, delta)), r_in)
    left = max(0.5, time_limit - (time.perf_counter() - start))
    res = verify_condition(system, lyapunov, controller, ring_plain, ring, time_limit=left,
                           min_width=_resolving(min_width, r_in, region),
                           stop_at_counterexample=True, enclosure=enclosure, level=level)
    out["ring"] = {"status": res.status, "decay_rate": gamma_in, "inner_radius": r_in, "boxes": res.boxes_processed,
                   "verified_fraction": res.verified_fraction}
    out["proved"] = res.status == "verified"
    if not out["proved"]:
        out["reason"] = f"decrease between the cube and the delta-ball: {res.status}"
    out["time_s"] = time.perf_counter() - start
    return out


def quadratic_roa(system: UncertainSystem, controller: Controller, condition: Condition, region: Region,
                  time_limit: float = 10.0, min_width: float = 1e-4, batch: int = 4096,
                  enclosure: str = "affine") -> dict:
    """A certified region of attraction ``{z^T P z <= c_q}`` of the closed loop of every sample's model of
    ``condition`` (the controller's, whatever V is), from its linearisation (module docstring, steps a and b).

    Two candidates ``(P, cube)``, each with ``Wdot < 0`` proved on its cube minus x* by
    :func:`_jacobian_negative`: the samples' Lyapunov-equation ``P`` (:func:`common_lyapunov_matrix`) on the
    widest cube (halving) where it is proved, and a ``P`` fitted to the cube (:func:`_fitted_cube`: wider cubes,
    rounder ellipsoids). For each, ``c_cube = min_i h_i^2 / (P^-1)_ii`` (rounded down) puts ``{W <= c_cube}``
    inside the cube, and :func:`certified_roa` on ``W`` may prove a larger level (:func:`_quadratic_level`; the
    candidates share the time left). The result is the candidate with the larger volume: ``proved``, ``P``,
    ``P_choice``, ``q_level`` (``c_q``), ``cube``, ``cube_level``, ``q_roa`` (the search beyond the cube),
    ``share_of_box`` (the ellipsoid's exact volume over the box's), ``candidates`` (both, each with its ``P``),
    the Jacobians and their eigenvalues, and ``reason`` when it fails."""
    start = time.perf_counter()
    deadline = start + time_limit
    out: dict = {"method": "linearisation", "proved": False, "q_level": None, "share_of_box": 0.0, "reason": ""}
    plain = condition.per_sample()
    if plain is None:
        out["reason"] = "the condition implies no per-sample decrease (a CVaR over several samples)"
        return out
    out["reason"] = _not_equilibrium(system, controller, plain, region)
    if out["reason"]:
        return out
    # 1. the linearisation (this only chooses W = z^T P z; everything after is proved)
    jacobians = closed_loop_jacobians(system, controller, plain)
    out["jacobians"] = [a.tolist() for a in jacobians]
    eigenvalues = []
    for a in jacobians:
        ok, ev = is_hurwitz(a)
        eigenvalues.append([[e.real, e.imag] for e in ev])
        if not ok:
            out["eigenvalues"] = eigenvalues
            out["reason"] = f"the closed-loop linearisation at x* is not Hurwitz (eigenvalues {[str(e) for e in ev]})"
            return out
    out["eigenvalues"] = eigenvalues
    s = region.scale / 2
    half_box = torch.minimum(-region.lo, region.hi)
    p_mean = common_lyapunov_matrix(jacobians, s)
    if not bool(torch.isfinite(p_mean).all()) or float(torch.linalg.eigvalsh(p_mean).min()) <= 0:
        out["reason"] = "the Lyapunov matrix P is not positive definite"
        return out
    # 2. two candidates for W and its cube: the samples' Lyapunov-equation P on the widest cube where it is
    # proved, and a P fitted to the widest cube it can be proved on; each W's region then searched beyond it
    cube_deadline = start + 0.5 * time_limit
    candidates = []
    half, bound, reason = _proved_cube(system, QuadraticLyapunov(p_mean), controller, plain, half_box,
                                       1e-9 * float(half_box.max()), s)
    if half is not None:
        candidates.append(("Lyapunov equation", p_mean, half, bound))
    fitted = _fitted_cube(system, controller, plain, p_mean, half_box, s, cube_deadline)
    if fitted is not None:
        candidates.append(("fitted", *fitted))
    if not candidates:
        out["reason"] = f"W = z'Pz: Wdot < 0 not proved on any cube around x* ({reason})"
        return out
    results = []
    for i, (name, p, half, bound) in enumerate(candidates):
        left = (deadline - time.perf_counter()) / (len(candidates) - i)
        results.append(_quadratic_level(system, controller, plain, region, p, half, bound, left, min_width, batch,
                                        enclosure) | {"P_choice": name})
    best = max(results, key=lambda r: r["share_of_box"])
    out.update(best)
    out["candidates"] = results  # each with its P: linearisation_local tries every one
    out.update(proved=True, time_s=time.perf_counter() - start)
    return out


def _fitted_cube(system: UncertainSystem, controller: Controller, plain: PlainDecrease, p_mean: Tensor,
                 half_box: Tensor, s: Tensor, deadline: float) -> tuple[Tensor, Tensor, float] | None:
    """``(P, half, bound)``: the widest cube ``half_box * f`` (f halving, then two bisection steps) on which a
    ``P`` fitted by :func:`robust_lyapunov_matrix` (from ``p_mean``, warm-started cube to cube) is proved by
    :func:`_jacobian_negative`, that ``P`` refitted for the largest ellipsoid inside the cube; None if none."""

    def attempt(frac: float, p_from: Tensor, t_from: Tensor | None, steps: int):
        h = half_box * frac
        centre, radius = scaled_jacobians(jacobian_enclosures(system, controller, plain, h), s)
        if not bool(torch.isfinite(centre).all() and torch.isfinite(radius).all()):
            return None, p_from, t_from
        p_s, log_t, rate = robust_lyapunov_matrix(centre, radius, p_from, t_from, steps=steps, stop_below=0.0)
        if not rate < 0:
            return None, p_s, log_t
        p = p_s / s[:, None] / s[None, :]
        p = (p + p.T) / 2
        ok, bound, _ = _jacobian_negative(system, controller, plain, p, h, s, log_t, (centre, radius))
        return ((p, h, bound, log_t) if ok else None), p_s, log_t

    found, frac, failed, log_t = None, 1.0, None, None
    p_start = p_mean * s[:, None] * s[None, :]
    while found is None and frac > 1e-9 and time.perf_counter() < deadline:
        found, p_start, log_t = attempt(frac, p_start, log_t, 300)
        if found is None:
            failed, frac = frac, frac / 2
    if found is None:
        return None
    for _ in range(2):
        if failed is None or time.perf_counter() > deadline:
            break
        mid = (frac + failed) / 2
        better, _, _ = attempt(mid, found[0] * s[:, None] * s[None, :], found[3], 1000)
        if better is not None:
            found, frac = better, mid
        else:
            failed = mid
    p, half, bound, log_t = found
    centre, radius = scaled_jacobians(jacobian_enclosures(system, controller, plain, half), s)
    p_s, log_t, rate = robust_lyapunov_matrix(centre, radius, p * s[:, None] * s[None, :], log_t, steps=1000,
                                              volume=True)
    if rate < 0:
        rounder = (p_s + p_s.T) / 2 / s[:, None] / s[None, :]
        ok, rounder_bound, _ = _jacobian_negative(system, controller, plain, rounder, half, s, log_t,
                                                  (centre, radius))
        if ok:
            p, bound = (rounder + rounder.T) / 2, rounder_bound
    return p, half, bound


def _quadratic_level(system: UncertainSystem, controller: Controller, plain: PlainDecrease, region: Region,
                     p: Tensor, half: Tensor, bound: float, time_limit: float, min_width: float, batch: int,
                     enclosure: str) -> dict:
    """The certified level ``q_level`` of ``W = z^T P z`` whose decrease is proved on the cube ``half``: the
    largest ellipsoid inside the cube (``cube_level``), grown while :func:`_jacobian_negative` proves the decrease
    on the ellipsoid's bounding box (``box_level``; up to 30% of the time), or more where :func:`certified_roa`
    on W proves it; with
    ``P``, the cube, ``share_of_box`` (the ellipsoid's exact volume over the box's), ``extent`` (the largest
    ``|z_i|`` in it, per state) and the search's details."""
    start = time.perf_counter()
    inv_diag = torch.linalg.inv(p).diagonal()
    c_cube = float(_down((half.square() / inv_diag).min(), 1e-6))
    # grow the level while W decreases on the ellipsoid's bounding box |z_i| <= sqrt(c (P^-1)_ii) (it holds the
    # ellipsoid and the segments to x*): doubling, then four geometric bisection steps
    half_box = torch.minimum(-region.lo, region.hi)

    def bounding_box(c: float) -> Tensor:
        return _up((c * inv_diag).sqrt(), 1e-6)

    def decreases(c: float) -> bool:
        box = bounding_box(c)
        return bool((box <= half_box).all()) and _jacobian_negative(
            system, controller, plain, p, box, region.scale / 2)[0]

    c_box, failed = c_cube, None
    while failed is None and time.perf_counter() - start < 0.3 * time_limit:
        if decreases(2 * c_box):
            c_box *= 2
        else:
            failed = 2 * c_box
    for _ in range(4):
        if failed is None or time.perf_counter() - start > 0.3 * time_limit:
            break
        mid = math.sqrt(c_box * failed)
        c_box, failed = (mid, failed) if decreases(mid) else (c_box, mid)
    proved_on = bounding_box(c_box) if c_box > c_cube else half
    w = QuadraticLyapunov(p)
    r_in = float(proved_on.min())
    ring = PlainDecrease(plain.xi, 0.25 * abs(bound) / 2 * r_in, 0.0, plain.model)
    w_roa = certified_roa(system, w, controller, ring, Region(region.lo, region.hi, r_in),
                          time_limit=max(1.0, time_limit - (time.perf_counter() - start)),
                          min_width=_resolving(min_width, r_in, region),
                          samples_per_axis=50, batch=batch, linearisation=False, enclosure=enclosure)
    c_q = c_box
    if w_roa["kind"] == "region of attraction" and w_roa["level"] > c_q:
        c_q = w_roa["level"]
    n = system.n
    volume = math.pi ** (n / 2) / math.gamma(n / 2 + 1) * c_q ** (n / 2) / math.sqrt(float(torch.linalg.det(p)))
    return {"P": p.tolist(), "q_level": c_q, "share_of_box": volume / float(region.scale.prod()),
            "extent": (c_q * inv_diag).sqrt().tolist(),  # the largest |z_i| in the ellipsoid, per state
            "cube": half.tolist(), "cube_fraction": float((half / torch.minimum(-region.lo, region.hi)).max()),
            "hessian_bound": bound, "cube_level": c_cube, "box_level": c_box, "box": proved_on.tolist(),
            "q_roa": {k: w_roa[k] for k in ("level", "kind", "limited_by", "boxes_processed", "time_s")} | {
                "decay_rate": ring.decay_rate, "inner_radius": r_in}}


def linearisation_local(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, condition: Condition,
                        region: Region, level: float, time_limit: float = 10.0, min_width: float = 1e-4,
                        batch: int = 4096, enclosure: str = "mean-value") -> dict:
    """The local proof from the closed-loop linearisation, for when V's own second-order proof fails (module
    docstring, "The linearisation proof"). ``level``: the level ``c`` up to which ``condition`` is proved on
    ``{V <= c}`` outside the delta-ball. Returns ``proved``, ``level`` (the largest ``c' <= c`` for which the
    whole chain holds: ``{V <= c'}`` is then a region of attraction), ``P``, ``q_level`` (``c_q``), ``inner_level``
    (``c_1``), ``quadratic`` (:func:`quadratic_roa`'s result), the proofs' details and ``reason`` when it fails."""
    start = time.perf_counter()
    deadline = start + time_limit
    out: dict = {"method": "linearisation", "proved": False, "level": None, "reason": ""}
    quad = quadratic_roa(system, controller, condition, region, time_limit=0.4 * time_limit, min_width=min_width,
                         batch=batch, enclosure=enclosure)
    out["quadratic"] = {k: v for k, v in quad.items() if k not in ("jacobians", "eigenvalues")}
    out.update({k: quad[k] for k in ("jacobians", "eigenvalues", "P", "q_level", "cube") if k in quad})
    if not quad["proved"]:
        out["reason"] = quad["reason"]
        return out
    plain = condition.per_sample()
    # 3. c_1 <= min of V over {W >= c_q} in the box, so that {V <= c_1} lies inside {W <= c_q}; of the candidate
    # W's (quadratic_roa), the one that holds the largest sublevel set of V
    vobj = value_objective(lyapunov)
    blo, bhi = box_grid(region.lo, region.hi, default_grid(system.n))
    c_1, chosen = -math.inf, None
    candidates = quad["candidates"]
    for i, cand in enumerate(candidates):
        p_i, c_qi = torch.tensor(cand["P"], dtype=F64), cand["q_level"]
        w_i = QuadraticLyapunov(p_i)
        wobj = value_objective(w_i)

        def outside(a, b, wobj=wobj, c_qi=c_qi):
            return box_bounds(wobj, a, b, enclosure)[1][:, 0] >= c_qi

        _, neg_up, _ = maximize(lambda z: -vobj(z), blo, bhi, region.scale, box_ok=outside,
                                centre_ok=lambda z, w_i=w_i, c_qi=c_qi: w_i(z) >= c_qi, min_width=min_width,
                                time_limit=max(1.0, 0.3 * (deadline - time.perf_counter()) / (len(candidates) - i)),
                                enclosure=enclosure)
        c_1i = float(_down(_down(-neg_up[0], REL1), 1e-9))
        cand["inner_level"] = c_1i
        if c_1i > c_1:
            c_1, chosen = c_1i, cand
    out["inner_level"] = c_1
    if chosen is not None:  # the W the chain below rests on, with its level and cube
        out.update({k: chosen[k] for k in ("P", "q_level", "cube")})
    if not c_1 > 0:
        out["reason"] = "no sublevel set of V provably inside {W <= c_q}"
        return out
    p, c_q = torch.tensor(chosen["P"], dtype=F64), chosen["q_level"]
    # any smaller c_1 will do ({V <= c_1} only shrinks): keep it below the outer level, so that the annulus
    # {c_1 <= V <= c} is not empty and {V <= c} is forward invariant
    c_1 = min(c_1, level / 2)
    out["inner_level"] = c_1
    # 4. V decreases strictly on {c_1 <= V <= c} inside the ball (outside it the condition's decay already does);
    # with no decay in the condition, on the whole box
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
    extent = (c_q * torch.linalg.inv(p).diagonal()).sqrt()
    fine = min(min_width, 1e-4 * float((extent / region.scale).min()))
    c_2, limited_by, cex, boxes = _level_search(
        system, lyapunov, controller, inner, alo, ahi, region.scale, level, "outer proof",
        max(deadline, time.perf_counter() + 1.0), meets=meets,
        in_region=lambda centre, v: centre.norm(dim=-1) < delta, floor=c_1, min_width=fine, batch=batch,
        enclosure=enclosure)
    c_2 = _below(c_2)
    out["annulus"] = {"level": c_2, "limited_by": limited_by, "boxes": boxes, "decay_rate": inner.decay_rate,
                      "exp_rate": inner.exp_rate, "region": "delta-ball" if strict else "box", "min_width": fine,
                      "counterexample": None if cex is None else system.to_user(cex[None])[0].tolist()}
    out["time_s"] = time.perf_counter() - start
    if not c_2 > c_1:
        out["reason"] = (f"decrease of V on {{{c_1:.4g} <= V <= c}} inside the ball fails below the inner level "
                         f"({limited_by})")
        return out
    out.update(proved=True, level=c_2)
    return out


def band_roa(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, condition: Condition,
             region: Region, quadratic: dict, top: float, limited_by: str = "box boundary", time_limit: float = 10.0,
             min_width: float = 1e-4, batch: int = 4096) -> dict:
    """The band proof (module docstring): the largest level ``c <= top`` (up to the search's resolution) such that
    V decreases strictly (``Vdot + 1e-9 ||z|| <= 0``, every sample's model of ``condition``) on ``{V <= c}``
    outside ``L = {z^T P z <= c_q}``, the closed loop's certified ellipsoid of :func:`quadratic_roa`
    (``quadratic``: its result, with ``P`` and ``q_level``). ``top`` must be a lower bound of V on the box's
    faces (or lower). Runs :func:`_level_search` with the ellipsoid (affine enclosure) over the whole box.

    Returns ``proved`` (``c > 0``), ``level``, ``limited_by``, ``boxes``, ``time_s``, ``counterexample`` (user
    coordinates, or None), ``P``, ``q_level``, ``v_on_ellipsoid``: V's smallest and largest value at 20,000
    sampled points of L's boundary, and ``beyond_ellipsoid``: ``c`` above that smallest value, so that
    ``{V <= c}`` reaches outside L and the decrease proved there is what carries it (from samples, not a proof;
    otherwise the set may lie inside L)."""
    start = time.perf_counter()
    out: dict = {"method": "band", "proved": False, "level": None, "limited_by": None, "reason": ""}
    plain = condition.per_sample()
    if plain is None:
        out["reason"] = "the condition implies no per-sample decrease (a CVaR over several samples)"
        return out
    if not quadratic or not quadratic.get("proved"):
        out["reason"] = "no certified ellipsoid of the closed loop to start from"
        return out
    if not (top > 0 and math.isfinite(top)):
        out["reason"] = f"V's lower bound on the box's faces is {top:.3g}: no positive level fits in the box"
        return out
    p, c_q = torch.tensor(quadratic["P"], dtype=F64), float(quadratic["q_level"])
    if not c_q > 0:
        out["reason"] = f"the ellipsoid's level is {c_q:.3g}: no ellipsoid to start from"
        return out
    out.update(P=p.tolist(), q_level=c_q, v_on_ellipsoid=_on_ellipsoid(lyapunov, p, c_q))
    if not out["v_on_ellipsoid"][0] > 0:
        out["reason"] = "V is not positive on the ellipsoid's boundary"
        return out
    strict = PlainDecrease(plain.xi, 1e-9, 0.0, plain.model)
    lo, hi = box_grid(region.lo, region.hi, default_grid(system.n))
    # boxes must resolve a set as small as L (the box holding x* has to fit inside it)
    extent = (c_q * torch.linalg.inv(p).diagonal()).sqrt()
    fine = min(min_width, 1e-4 * float((extent / region.scale).min()))

    def everywhere(a, b):
        return torch.ones(a.shape[0], dtype=torch.bool, device=a.device)

    # levels from just above V's sampled minimum on L's boundary up, 1.3x apart: a search with a fixed level drops
    # the boxes above it at once and bounds the rest on {V <= level} only; one with the top level would spend the
    # time on the sets far above the level it reaches
    target = min(top, 1.1 * out["v_on_ellipsoid"][0])
    reached, boxes, cex, targets = -math.inf, 0, None, []
    while True:
        level, why, cex, count = _level_search(
            system, lyapunov, controller, strict, lo, hi, region.scale, target,
            limited_by if target >= top else "next level not reached", start + time_limit, meets=everywhere,
            in_region=lambda centre, v: everywhere(centre, centre), min_width=fine, batch=batch,
            enclosure="affine", ellipsoid=(p, c_q))
        boxes += count
        targets.append({"level": target, "reached": level >= target, "boxes": count,
                        "time_s": time.perf_counter() - start})
        if level >= target and target < top:
            reached = target
            if time.perf_counter() < start + time_limit:
                target = min(top, 1.3 * target)
                continue
            limited_by = "time limit"
        elif level > reached:  # the last search's own level (a lower bound of V on what it left), if higher
            reached, limited_by = level, why
        else:
            limited_by, cex = f"{why} at the next level ({target:.4g})", None
        break
    c = _below(reached)
    out.update(proved=c > 0, level=c, limited_by=limited_by, boxes=boxes, decay_rate=strict.decay_rate, levels=targets,
               beyond_ellipsoid=c > out["v_on_ellipsoid"][0],
               counterexample=None if cex is None else system.to_user(cex[None])[0].tolist(),
               time_s=time.perf_counter() - start)
    if not c > 0:
        out["reason"] = f"V's decrease outside the ellipsoid not proved on any sublevel set ({limited_by})"
    return out


def _on_ellipsoid(lyapunov: Lyapunov, p: Tensor, c_q: float, count: int = 20_000) -> list[float]:
    """V's smallest and largest value at ``count`` points of ``{z^T P z = c_q}`` (a fixed seed; not a bound)."""
    import copy

    g = torch.Generator().manual_seed(0)
    e = torch.randn(count, p.shape[0], generator=g, dtype=F64)
    e = e / e.norm(dim=-1, keepdim=True)
    chol = torch.linalg.cholesky(p)
    z = torch.linalg.solve_triangular(chol.T, e.T, upper=True).T * math.sqrt(c_q)
    with torch.no_grad():
        values = copy.deepcopy(lyapunov).to(F64)(z)
    return [float(values.min()), float(values.max())]


def certified_roa(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, condition: Condition,
                  delta: float | Region, time_limit: float = 10.0, min_width: float = 1e-4,
                  samples_per_axis: int = 400, batch: int = 4096, linearisation: bool = True,
                  enclosure: str | None = None, max_level: float = math.inf, band_time: float | None = None) -> dict:
    """The largest level ``c`` (up to the search's resolution) with ``S = {V <= c}`` certified (module docstring).

    Returns a JSON-friendly dict: ``level`` c; ``kind``: ``"region of attraction"`` (every trajectory of the
    condition's model from S converges to x*), ``"practical stability"`` (trajectories from S end up in
    ``{V <= practical_level}``) or None; ``certified`` (True only for a region of attraction); ``local`` (the
    proof inside the ball: :func:`local_decrease`'s, or with ``linearisation`` where that fails,
    :func:`linearisation_local`'s, ``method`` says which); ``outer_level`` (the level proved outside the ball);
    ``boundary_min_lower``, ``ball_max_upper``, ``share_of_box`` (share of the box
    volume in S), ``limited_by``, a ``counterexample`` that limited the level, times and boxes. ``enclosure``
    bounds V and the conditions in every branch and bound here, inside the ball too (None:
    :func:`~drlyap.verification.bounds.default_enclosure`); the Hessian enclosure on the cube around x* is
    interval arithmetic on nested dual numbers. ``max_level`` caps the search (e.g. at the level a region of
    attraction was trained for: ``limited_by`` then reads ``"level asked for"`` when the cap is proved).
    ``quadratic``: where no sublevel set of V is certified (and ``linearisation``), :func:`quadratic_roa`'s
    result: a region of attraction ``{z^T P z <= q_level}`` of the same closed loop, not of V; else None.
    ``band``: where that ellipsoid is certified and no sublevel set of V is, :func:`band_roa`'s result (V's decrease
    on ``{V <= c}`` outside the ellipsoid), run for ``band_time`` seconds more (None: ``time_limit``; 0: not run);
    where it proves a level, that level is the result's (``local["method"]`` reads ``"band"``); else None.
    """
    start = time.perf_counter()
    enclosure = check_enclosure(enclosure or default_enclosure(system.n))
    region = as_region(system, delta)
    delta = region.delta
    box_lo, box_hi, scale = region.lo, region.hi, region.scale
    grid = default_grid(system.n)
    vobj = value_objective(lyapunov)

    # 1. min of V on the boundary of the box
    boundary_min_lower = boundary_minimum(lyapunov, region, time_limit / 4, min_width, enclosure)[0]
    # 2. max of V on the delta-ball
    ball_max_upper = 0.0
    if delta > 0:
        blo = torch.maximum(box_lo, torch.full_like(box_lo, -delta))
        bhi = torch.minimum(box_hi, torch.full_like(box_hi, delta))
        glo, ghi = box_grid(blo, bhi, grid)
        _, up, _ = maximize(vobj, glo, ghi, scale, time_limit=time_limit / 4, enclosure=enclosure,
                            box_ok=lambda a, b: near_dist(a, b) < delta, min_width=min_width)
        ball_max_upper = float(up[0])
    # 3. the decrease condition on the sublevel set outside the ball
    lo, hi = region.boxes(grid)
    top, why = (boundary_min_lower, "box boundary") if boundary_min_lower <= max_level else (max_level,
                                                                                             "level asked for")
    level, limited_by, cex, processed = _level_search(
        system, lyapunov, controller, condition, lo, hi, scale, top, why,
        start + (0.6 if delta > 0 else 1.0) * time_limit, meets=region.meets,  # 40% kept for the ball
        in_region=lambda centre, v: region.in_region(centre),
        min_width=min_width, batch=batch, enclosure=enclosure)
    deadline = start + time_limit
    c = _below(level)
    # 4. inside the ball
    left = max(1.0, (deadline - time.perf_counter()) / (2 if linearisation else 1))
    local = local_decrease(system, lyapunov, controller, condition, region, time_limit=left, min_width=min_width,
                           enclosure=enclosure, level=c if c > 0 else None)
    if linearisation and not local["proved"] and local.get("equilibrium") and c > 0:
        left = max(3.0, deadline - time.perf_counter())
        local = linearisation_local(system, lyapunov, controller, condition, region, c, time_limit=left,
                                    min_width=min_width, batch=batch, enclosure=enclosure) | {"second_order": local}
    outer_level = c
    quadratic = None  # the closed loop's own certificate, reported where V's sublevel sets are not certified
    if linearisation and not (c > 0 and local["proved"]):
        quadratic = local.get("quadratic") or quadratic_roa(
            system, controller, condition, region, time_limit=max(3.0, deadline - time.perf_counter()),
            min_width=min_width, batch=batch, enclosure=enclosure)
        quadratic = {k: v for k, v in quadratic.items() if k not in ("jacobians", "eigenvalues")}
    band = None
    counterexample = None if cex is None else system.to_user(cex[None])[0].tolist()
    if quadratic is not None and quadratic.get("proved") and (band_time is None or band_time > 0):
        band = band_roa(system, lyapunov, controller, condition, region, quadratic, top, why,
                        time_limit=time_limit if band_time is None else band_time, min_width=min_width, batch=batch)
    if band is not None and band["proved"]:  # V's sublevel set from the band proof (the outer search's stays)
        kind, c, limited_by, local = "region of attraction", band["level"], band["limited_by"], band
        counterexample = band["counterexample"]
    elif c > 0 and local["proved"]:
        kind = "region of attraction"
        if local.get("level") is not None and local["level"] < c:  # the annulus inside the ball may lower it
            c = local["level"]
            if local["annulus"]["limited_by"] != "outer proof":
                limited_by = f"inside the ball: {local['annulus']['limited_by']}"
    elif c > 0 and c > ball_max_upper:
        kind = "practical stability"
    else:
        kind = None
    share = _share_of_box(lyapunov, region, c, samples_per_axis) if c > 0 else 0.0
    return {"level": c, "kind": kind, "certified": kind == "region of attraction",
            "practical_level": ball_max_upper if kind == "practical stability" else None,
            "outer_level": outer_level,
            "contains_ball": c > ball_max_upper, "limited_by": limited_by, "local": local,
            "boundary_min_lower": boundary_min_lower, "ball_max_upper": ball_max_upper, "share_of_box": share,
            "counterexample": counterexample,
            "boxes_processed": processed, "time_s": time.perf_counter() - start, "delta": float(delta),
            "condition": condition.label, "quadratic": quadratic, "band": band}


def _level_search(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, condition: Condition,
                  lo: Tensor, hi: Tensor, scale: Tensor, level: float, limited_by: str, deadline: float, *,
                  meets, in_region, floor: float = -math.inf, min_width: float = 1e-4,
                  batch: int = 4096, enclosure: str = "mean-value",
                  ellipsoid: tuple[Tensor, float] | None = None) -> tuple[float, str, Tensor | None, int]:
    """The largest level (at most ``level``) such that ``condition`` holds on every state of the boxes
    ``[lo, hi]`` (and of their parts where ``meets(lo, hi)``, a ``(B,)`` mask) with ``floor <= V <= level``
    (with ``ellipsoid = (P, c_q)``: and ``z^T P z >= c_q``, outside the ellipsoid ``L``).

    Boxes with V's lower bound above the level, or V's upper bound below ``floor``, need no proof; the rest are
    proved or split, those with the lowest bound on V first (a box's parts inherit its bound), so that the
    sets ``{V <= c}`` are settled from small ``c`` up and a time limit costs the least level. A box that cannot
    be proved lowers the level to (a lower bound of) V on it: to V at its centre when that centre is a
    confirmed violation in the region (``in_region(centre, V enclosure)``), else to V's lower bound on it once
    it reaches the minimum size or the time runs out.

    With ``ellipsoid`` (the affine enclosure only): boxes inside ``L`` (every vertex; ``L`` is convex) need no
    proof, V's lower bound is taken on each box's part outside ``L`` (:func:`_outside_lower`), and boxes are
    split on the side that adds most to the bounds (``split``'s sensitivity): the search behind
    :func:`band_roa`. Returns the level, what limited it, the counterexample (local, or None) and the number of
    boxes processed."""
    base = condition_and_value_objective(condition, system, lyapunov, controller)
    if ellipsoid is None:
        objective = base
    else:
        if enclosure != "affine":
            raise ValueError("the search outside an ellipsoid needs the affine enclosure")
        w = QuadraticLyapunov(ellipsoid[0])
        c_q = float(ellipsoid[1])

        def objective(z):  # the condition's components, W, then V (W's form shares the box's symbols)
            out = base(z)
            return torch.cat([out[..., :-1], w(z).unsqueeze(-1), out[..., -1:]], -1)
    vobj = value_objective(lyapunov)
    processed = 0
    cex = None
    known = torch.full((lo.shape[0],), -math.inf, dtype=lo.dtype)  # a lower bound of V on each queued box
    while lo.shape[0]:
        if time.perf_counter() > deadline:
            order = known.argsort()
            first = order[:16 * batch]  # tighten the lowest inherited bounds, the rest stand as they are
            v_min = float(known[order[16 * batch:]].min()) if order.shape[0] > first.shape[0] else math.inf
            for i in range(0, first.shape[0], batch):
                rows = first[i:i + batch]
                fresh = box_bounds(vobj, lo[rows], hi[rows], enclosure)[0][:, 0]
                v_min = min(v_min, float(torch.maximum(fresh, known[rows]).min()))  # both are lower bounds
            if v_min < level:
                level, limited_by = v_min, "time limit"
            break
        if lo.shape[0] > batch:
            take = torch.zeros(lo.shape[0], dtype=torch.bool)
            take[torch.topk(known, batch, largest=False).indices] = True
        else:
            take = torch.ones(lo.shape[0], dtype=torch.bool)
        clo, chi = lo[take], hi[take]
        lo, hi, known = lo[~take], hi[~take], known[~take]
        if ellipsoid is not None:
            inside = _vertex_max(w.P, clo, chi) <= c_q
            clo, chi = clo[~inside], chi[~inside]
            if not clo.shape[0]:
                continue
        bounds = box_bounds(objective, clo, chi, enclosure, sensitivity=ellipsoid is not None, keep_form=True)
        lb, ub, at, form = bounds[0], bounds[1], bounds[2], bounds[-1]
        sens = bounds[3] if ellipsoid is not None else None
        processed += clo.shape[0]
        v_lb = lb[:, -1]
        if ellipsoid is not None:
            v_lb = torch.maximum(v_lb, _outside_lower(form[:, -1], form[:, -2], at.mid[:, -1], at.mid[:, -2], c_q, level))
            keep = [*range(lb.shape[1] - 2), lb.shape[1] - 1]
            lb, ub, at, form = lb[:, keep], ub[:, keep], at[:, keep], form[:, keep]
        active = (v_lb <= level) & (ub[:, -1] >= floor)
        res_ub = combine_upper(condition, ub[:, :-1])
        if form is not None:  # a box proved on {V <= level} is proved on every smaller sublevel set
            res_ub = torch.minimum(res_ub, sublevel_upper(condition, form, level))
        centre = (clo + chi) / 2
        open_ = active & (res_ub > 0)
        bad = (open_ & in_region(centre, at[:, -1]) & (at.hi[:, -1] >= floor)
               & (combine_lower(condition, at.lo[:, :-1]) > 0))
        if ellipsoid is not None:  # a violation inside L does not count against the band
            bad = bad & (w(centre) > c_q)
        if bad.any():
            values = condition.exact(system, lyapunov, controller, centre[bad])
            if (values > 0).any():
                v_at = at.hi[:, -1][bad][values > 0]
                j = int(v_at.argmin())
                if float(v_at[j]) < level:
                    level, limited_by = float(v_at[j]), "counterexample"
                    cex = centre[bad][values > 0][j]
        small = open_ & (((chi - clo) / scale).amax(-1) < min_width)
        if small.any() and float(v_lb[small].min()) < level:
            level, limited_by = float(v_lb[small].min()), "unverified box at minimum size"
        divide = open_ & ~small & (v_lb <= level)
        if divide.any():
            nlo, nhi = split(clo[divide], chi[divide], scale, None if sens is None else sens[divide])
            nknown = v_lb[divide].repeat(2)
            fits = meets(nlo, nhi)
            lo, hi, known = torch.cat([lo, nlo[fits]]), torch.cat([hi, nhi[fits]]), torch.cat([known, nknown[fits]])
        above = known > level  # queued boxes the lowered level no longer asks about
        if above.any():
            lo, hi, known = lo[~above], hi[~above], known[~above]
    return level, limited_by, cex, processed


def _vertex_max(p: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """``max z^T P z`` over each box ``[lo, hi] (B, n)`` (at a vertex: the form is convex), rounded up."""
    n = lo.shape[-1]
    p = p.to(lo)
    if n > 8:  # 2^n vertices per box: beyond that, the interval bound
        return QuadraticLyapunov(p)(Interval(lo, hi)).hi
    vertices = torch.where(_vertices(n, lo.device)[None] > 0, hi[:, None, :], lo[:, None, :])  # (B, 2^n, n)
    values = (vertices @ p * vertices).sum(-1)
    mag = (vertices.abs() @ p.abs() * vertices.abs()).sum(-1)
    return _up(values, 4 * (n + 2) * REL1, mag).amax(-1)


def _outside_lower(v_form, w_form, v_centre: Tensor, w_centre: Tensor, c_q: float, level: float) -> Tensor:
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
        bound = _down(low + shift, 4 * REL1, low.abs() + shift.abs())  # the product's and the sum's rounding
        best = torch.maximum(best, torch.where(torch.isnan(bound), -math.inf, bound))
    return best


def _share_of_box(lyapunov: Lyapunov, region: Region, level: float, samples_per_axis: int) -> float:
    """Share of the box volume in ``{V <= level}``: on a grid for n <= 3, else from 100,000 uniform samples; where
    fewer than 1,000 of those fall in the set (a share below 1%), stratified over the nested boxes
    ``B_k = 2^-k X`` around x*: 20,000 uniform samples in each ``B_k`` estimate the set's share of the shell
    ``B_k \\ B_{k+1}``, down to the first ``B_k`` the set fills at least half of (its samples then estimate all of
    it), or until the shells left are below 1e-6 of the estimate."""
    import copy

    n = region.n
    lyap = copy.deepcopy(lyapunov).to(F64)

    def values_at(z: Tensor) -> Tensor:
        with torch.no_grad():
            return torch.cat([lyap(z[i:i + 50_000]) for i in range(0, z.shape[0], 50_000)])

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
