"""V's own decrease near x*: inside the delta-ball, ``Vdot < 0`` except at x* (:func:`local_decrease`).

For one sample's model ``q(z) = grad V(z) . F(z, pi(z))``: ``q(0) = 0`` and ``grad q(0) = H_V(0) F(0) = 0``
(``grad V(0) = 0`` by the construction of V, and x* is an equilibrium of the model: its enclosure of ``F(x*)``
holds 0, :func:`not_equilibrium`), so by Taylor's theorem ``q(z) = z^T H_q(s z) z / 2`` for some ``s`` in
[0, 1]. On a cube ``C`` around x* the verifier encloses ``H_q`` over the whole cube (nested dual numbers running
the networks' and the system's own code); if every symmetric matrix in that interval matrix is negative definite
(centre's largest eigenvalue plus the radius matrix's Frobenius norm < 0), then ``q < 0`` on ``C`` minus x*. The
cube is shrunk until this holds (:func:`proved_cube`; the controller must be unsaturated there); the rest of the
delta-ball is proved with plain decrease plus a small decay ``gamma_in ||z||`` (strict decrease away from x*).
For a quadratic V the cube test is the Jacobians' mean-value form instead
(:func:`~drlyap.verification.linearisation.jacobian_negative`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition, PlainDecrease, local_rates
from drlyap.enclosures import F64, Dual, Interval
from drlyap.kinds import Enclosure, Model, Status
from drlyap.networks import QuadraticLyapunov
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.verification.branch_and_bound import ProofRules, verify_condition
from drlyap.verification.linearisation import jacobian_negative
from drlyap.verification.results import BallProof
from drlyap.verification.roa.levels import time_capped
from drlyap.verification.roa_steps import LocalProof, RingProof


def _hessian_negative(loop: ClosedLoop, plain: PlainDecrease, half_width: Tensor) -> tuple[bool, float, str]:
    """Is ``z^T H_q z < 0`` for every Hessian of every sample's ``q = Vdot`` over the cube ``|z_i| <= half_width_i``?

    Returns (proved, the bound ``lambda`` with ``q(z) <= lambda ||z||^2 / 2`` on the cube, reason)."""
    n = loop.n
    lo, hi = (-half_width)[None], half_width[None]
    eye = torch.eye(n, dtype=F64)[None]
    first = Dual(Interval(lo, hi), Interval(eye, eye))
    z = Dual(first, Dual(Interval(eye, eye), None))
    try:
        terms = plain.terms(loop, z)
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


def proved_cube(loop: ClosedLoop, plain: PlainDecrease, half: Tensor, smallest: float,
                half_widths: Tensor) -> tuple[Tensor | None, float, str]:
    """The first cube ``|z_i| <= half_i`` (halving ``half`` until its largest side is below ``smallest``) on which
    ``Vdot < 0`` except at x* is proved: by :func:`~drlyap.verification.linearisation.jacobian_negative` for a
    quadratic V, else by
    :func:`_hessian_negative`. Returns ``(half, bound, "")`` (``Vdot <= bound ||z||^2 / 2`` there), or
    ``(None, nan, reason)``."""
    bound, reason = math.nan, ""
    for _ in range(60):
        if isinstance(loop.lyapunov, QuadraticLyapunov):
            ok, bound, reason = jacobian_negative(loop, plain, loop.lyapunov.P, half, half_widths)
        else:
            ok, bound, reason = _hessian_negative(loop, plain, half)
        if ok:
            return half, bound, ""
        half = half / 2
        if float(half.max()) < smallest:
            break
    what = "mean-value (Jacobian)" if isinstance(loop.lyapunov, QuadraticLyapunov) else "second-order"
    return None, math.nan, f"{what} proof failed on every cube down to {float(half.max()):.3g} ({reason})"


def resolving(min_width: float, r_in: float, region: Region) -> float:
    """A minimum box width (relative to the box) small enough for boxes to resolve a ball of radius ``r_in``
    (the second-order cube around x* that a branch and bound has to close around)."""
    return min(min_width, 0.05 * r_in / float(region.scale.max()))


def resolving_ellipsoid(min_width: float, p: Tensor, level: float, region: Region) -> float:
    """A minimum box width (relative to the box) small enough for boxes to resolve the ellipsoid ``{z^T P z <= level}``
    (1e-4 of its smallest extent ``sqrt(level (P^-1)_ii)`` relative to the box's side)."""
    extent = (level * torch.linalg.inv(p).diagonal()).sqrt()
    return min(min_width, 1e-4 * float((extent / region.scale).min()))


def not_equilibrium(loop: ClosedLoop, plain: PlainDecrease, region: Region) -> str:
    """Why x* is not an equilibrium of some sample's model, or "" when it may be of every one: the local proofs
    rest on it. The verifier's enclosure of ``F(x*, pi(x*))`` must hold 0 in every coordinate (one that does not
    proves x* is no equilibrium, e.g. for a controller with ``pi(x*) = u* + 1e-12``) and lie within 1e-9 of the
    box's scale; that the real value is 0 is the premise floating point cannot confirm."""
    system, controller = loop.system, loop.controller
    zero = torch.zeros(system.n, system.n, dtype=F64)  # n copies of x*, one per unit covector below
    x_star = system.to_user(Interval(zero, zero))
    u_star = controller(Interval(zero, zero))
    unit = Interval(torch.eye(system.n, dtype=F64), torch.eye(system.n, dtype=F64))
    scale = float(region.scale.abs().max())
    for xi in plain.xi:
        if plain.model == Model.TRUE:
            f = system.true_dynamics(x_star, u_star, xi)
        else:  # e_i . (f + W xi) for each unit covector e_i: the design model's field at x*
            gf, gw = system.weighted_design(x_star, u_star, unit)
            f = gf + (gw * Interval.const(xi)).sum(-1)
        size = float(torch.maximum(f.lo.abs(), f.hi.abs()).max())
        if not bool(((f.lo <= 0) & (f.hi >= 0)).all()):
            return (f"x* is not an equilibrium of the model at xi = {xi.tolist()} (F(x*) proved nonzero, "
                    f"|F(x*)| up to {size:.3g})")
        if size > 1e-9 * max(scale, 1.0):
            return f"x* is not an equilibrium of the model at xi = {xi.tolist()} (|F(x*)| up to {size:.3g})"
    return ""


def local_decrease(loop: ClosedLoop, condition: Condition, region: Region,
                   budget: Budget = Budget(seconds=10.0, enclosure=Enclosure.MEAN_VALUE), level: float | None = None,
                   keep: BallKeeper | None = None) -> LocalProof:
    """Prove ``Vdot < 0`` on the delta-ball minus x* (with ``level``: on its part in ``{V <= level}``) for every
    sample of ``condition``'s model (see the module docstring). Returns ``proved``, the cube half-width ``cube``
    of the second-order proof, its bound ``hessian_bound``, the ring verification's status and ``reason`` when
    it fails, and ``boxes``: the ring's boxes (its proof: ``budget``, boxes and seconds; ``capped`` names it where
    it stopped at its time cap). ``keep``: where a proof that holds is put, as ``keep.ball`` (a
    :class:`~drlyap.verification.results.BallProof`, the ring's partition kept), for a certificate to write down."""
    start = time.perf_counter()
    time_limit, min_width = budget.seconds, budget.min_width
    method = "mean-value Jacobian" if isinstance(loop.lyapunov, QuadraticLyapunov) else "second order"
    out = LocalProof(method)
    plain = condition.per_sample()
    if plain is None:
        out.reason = "the condition implies no per-sample decrease (a CVaR over several samples)"
        return out
    delta = region.delta
    if delta <= 0:
        out.proved, out.reason = True, "no ball to cover (delta = 0)"
        return out
    reason = not_equilibrium(loop, plain, region)
    if reason:
        out.reason = reason
        return out
    out.equilibrium = True  # the preconditions hold: a failure below is one of the second-order proof
    half = torch.minimum(torch.minimum(-region.lo, region.hi), torch.full_like(region.lo, delta))
    half, bound, reason = proved_cube(loop, plain, half, 1e-7 * delta, region.scale / 2)
    if half is None:
        out.reason = reason
        if not isinstance(loop.lyapunov, QuadraticLyapunov):  # why: is V a Lyapunov function of the linearisation?
            with torch.enable_grad():
                rate = float(local_rates(plain, loop).detach().max())
            out.local_rate = rate
            out.reason += f"; V's second-order rate at x*: Vdot <= {rate:+.3g} V" + (
                " (V rises along some direction arbitrarily close to x*: no cube can prove its decrease)"
                if rate > 0 else "")
        return out
    out.cube = half.tolist()
    out.hessian_bound = bound
    r_in = float(half.min())
    if bool((half >= delta).all()):  # the cube covers the ball
        out.proved, out.time_s = True, time.perf_counter() - start
        if keep is not None:
            keep.ball = BallProof(cube=half.tolist())
        return out
    # the rest of the ball: strict decrease Vdot + gamma_in ||z|| <= 0 on (ball-box) minus the r_in-ball
    gamma_in = 0.25 * abs(bound) / 2 * r_in
    ring_plain = PlainDecrease(plain.xi, gamma_in, 0.0, plain.model)
    ring = region.ball_box(r_in)
    left = max(0.5, time_limit - (time.perf_counter() - start))
    res = verify_condition(loop, ring_plain, ring, replace(budget, seconds=left,
                                                           min_width=resolving(min_width, r_in, region)),
                           level=level, rules=ProofRules(stop_at_counterexample=True, keep_partition=keep is not None))
    out.ring = RingProof(res.status, gamma_in, r_in, res.boxes_processed, res.verified_fraction, res.stopped)
    out.boxes = res.boxes_processed
    if time_capped(res.stopped):
        out.capped = ["the proof between the cube and the delta-ball"]
    out.proved = res.status == Status.VERIFIED
    if out.proved and keep is not None:
        keep.ball = BallProof(cube=half.tolist(), condition=ring_plain, region=ring, ring=res)
    if not out.proved:
        out.reason = f"decrease between the cube and the delta-ball: {res.status} ({res.stopped})"
    out.time_s = time.perf_counter() - start
    return out


@dataclass
class BallKeeper:
    """Where :func:`local_decrease` puts a proof that holds (``ball``), for a certificate to write down."""

    ball: BallProof | None = None
