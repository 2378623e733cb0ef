"""The checker's proof of V's decrease near x*, the part of a region of attraction inside the delta-ball that no box
proves: ``Vdot < 0`` on a cube around x* except at x* (a ``roa-ball`` certificate's ``cube``).

For one sample's model ``q(z) = grad V(z) . F(z, pi(z))``: ``q(0) = 0`` and ``grad q(0) = H_V(0) F(0) = 0`` where
x* is an equilibrium (``F(x*, pi(x*)) = 0``; the checker asks that its enclosure of ``F`` there holds 0, the rest is
the claim's premise: an equilibrium cannot be confirmed in floating point), so ``q(z) = z^T H_q(s z) z / 2`` for
some ``s`` in [0, 1] and ``q < 0`` on the cube minus x* when every symmetric matrix in an enclosure of ``H_q`` over the
cube is negative definite. The checker encloses ``H_q`` with its own nested dual numbers (second derivatives in the
state of its own residual; the controller must lie strictly inside its bounds or strictly outside on the cube) and
establishes ``C + t I`` negative definite, ``C`` the enclosure's centre and ``t`` an upper bound of the Frobenius norm
of its radius, by a Cholesky factorisation with its backward error (:func:`~drlyap.checker.affine.surely_semidefinite`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from drlyap.checker.arith import EPS, F64, TINY, Du, Iv, _up
from drlyap.checker.model import Residual
from drlyap.checker.quadratic import surely_semidefinite


def not_equilibrium(residual: Residual) -> str:
    """Why x* is not an equilibrium of some sample's model by the checker's enclosures (``F(x*, pi(x*))``, or on the
    design model ``f + W xi``, does not hold 0 in some coordinate), or ""."""
    zero = Iv.point(torch.zeros(1, residual.pair.n, dtype=F64, device=residual.x_star.device))
    for j, f in enumerate(residual.fields(zero)):
        if not bool(((f.lo <= 0) & (f.hi >= 0)).all()):
            return f"x* is not an equilibrium of sample {j}'s model (F(x*) encloses [{f.lo.tolist()}, {f.hi.tolist()}])"
    return ""


def hessian_negative(residual: Residual, half: Tensor) -> tuple[bool, float, str]:
    """Whether ``z^T H_q z < 0`` for every sample's ``q`` (``residual``'s components without decay) at every point of
    the cube ``|z_i| <= half_i`` and every ``z != 0``. Returns (proved, the largest ``lambda_max(C) + t`` bound found,
    where ``-(C + t I)`` was not proved positive definite: ``inf``; the reason where not proved)."""
    n = half.shape[0]
    cube = Iv((-half)[None].to(F64), half[None].to(F64))
    z = Du.seed(Du.seed(cube, n, list(range(n))), n, list(range(n)))
    try:
        comps = residual.components(z)  # (1, Q), duals of level 2
    except TypeError as err:  # e.g. the controller touches a bound on the cube
        return False, math.inf, str(err)
    count = comps.shape[-1]
    lo = torch.stack([torch.stack([comps.d[j].d[i].lo[0] for i in range(n)], -1) for j in range(n)], -2)  # (Q, n, n)
    hi = torch.stack([torch.stack([comps.d[j].d[i].hi[0] for i in range(n)], -1) for j in range(n)], -2)
    if not bool(torch.isfinite(lo).all() and torch.isfinite(hi).all()):
        return False, math.inf, "the Hessian's enclosure is not finite on the cube"
    negative, worst = surely_negative_definite(lo, hi)
    if not count:
        worst = -math.inf
    if bool(negative.all()):
        return True, worst, ""
    return False, worst, f"the Hessian of Vdot is not proved negative definite on the cube (lambda_max + spread " \
                         f"about {worst:.3g})"


def surely_negative_definite(lo: Tensor, hi: Tensor) -> tuple[Tensor, float]:
    """``(Q,)``: where every symmetric matrix whose entries lie in the finite interval matrices ``[lo, hi] (Q, n, n)``
    is negative definite (``C + t I``, ``C`` the centre of the symmetrised enclosure and ``t`` an upper bound of the
    Frobenius norm of its radius, by a Cholesky factorisation with its backward error); and the largest
    ``lambda_max(C) + t`` (about: float eigenvalues), a measure of how far from proved."""
    n = lo.shape[-1]
    lo = torch.minimum(lo, lo.transpose(-1, -2))  # H_ij and H_ji both lie in [lo_s, hi_s]: so does the symmetric part
    hi = torch.maximum(hi, hi.transpose(-1, -2))
    centre = (lo + hi) / 2
    radius = _up(torch.maximum(_up(hi - centre), _up(centre - lo)))
    frobenius = radius.square().sum((-1, -2)).sqrt()
    t = _up(frobenius * (1 + (n * n + 4) * EPS) + TINY)
    eye = torch.eye(n, dtype=F64, device=lo.device)
    m = -centre - t[:, None, None] * eye
    # m's diagonal is rounded once: move it down by that error before asking for semidefiniteness
    m = m - (2 * EPS * torch.diagonal(m, dim1=-2, dim2=-1).abs().amax(-1) + TINY)[:, None, None] * eye
    worst = float((torch.linalg.eigvalsh(centre).amax(-1) + t).amax()) if lo.shape[0] else -math.inf
    return surely_semidefinite(m), worst


def ball_failures(claim: dict, pair, system, lo: Tensor, hi: Tensor, ring_delta: float,
                  ring: bool) -> tuple[list[str], float | None]:
    """What keeps a ``roa-ball`` certificate's claim from following: its ``cube`` (``claim["cube"]["half"]``) must hold
    the ring's inner ball (radius ``ring_delta``; without a ``ring`` partition, the whole ball's box ``[lo, hi]``), the
    ring's decrease must be strict (a decay > 0), x* an equilibrium and ``Vdot < 0`` on the cube minus x* (above).
    Returns (the failures, the Hessian test's bound ``lambda_max(C) + t``, or None where it did not run)."""
    try:
        half = torch.as_tensor(claim["cube"]["half"], dtype=F64).reshape(-1)
    except (KeyError, TypeError, ValueError):
        return ["the claim's cube has no half-widths"], None
    if half.shape[0] != lo.shape[0] or not bool(torch.isfinite(half).all() and (half > 0).all()):
        return [f"the claim's cube {half.tolist()} is not {lo.shape[0]} finite positive half-widths"], None
    failures = []
    if ring:
        if not ring_delta <= float(half.min()):
            failures.append(f"the ring's inner ball (radius {ring_delta:g}) is not inside the cube")
        if not float(claim["condition"].get("decay_rate") or 0.0) > 0:
            failures.append("the ring's decrease is not strict (its decay rate is not > 0)")
    elif not bool((half >= torch.maximum(-lo, hi)).all()):
        failures.append("without a ring, the cube does not cover the ball's box")
    local = Residual(dict(claim["condition"], decay_rate=0.0, exp_rate=0.0), pair, system)
    why, bound = not_equilibrium(local), None
    if not why:
        _, bound, why = hessian_negative(local, half)
    return failures + ([why] if why else []), bound
