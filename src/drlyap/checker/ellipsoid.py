"""The checker's proof of the closed loop's own quadratic region of attraction ``L = {z^T P z <= c}`` (an
``ellipsoid`` certificate), reported where no sublevel set of V is certified.

``W = z^T P z`` decreases near x* by the mean-value form: for each sample's model ``F_j(0) = 0`` (x* an equilibrium:
the checker asks that its enclosure of ``F_j`` there holds 0, the rest is the claim's premise), so ``F_j(z) = A z``
with ``A`` in the hull of an enclosure ``[C - R, C + R]`` of ``dF_j/dz`` over the claim's box ``|z_i| <= h_i`` (it
holds the segment from x* to z), and ``Wdot = z^T (P A + A^T P) z``. With the claim's weights ``tau > 0``,
``2 (Pz)^T E z <= sum_ij R_ij (tau_ij (Pz)_i^2 + z_j^2 / tau_ij)`` for ``|E| <= R``, so
``Wdot <= z^T M z`` with ``M = P C + C^T P + P D1 P + D2``, ``D1 = diag(sum_j R_ij tau_ij)``,
``D2 = diag(sum_i R_ij / tau_ij)``: ``M`` negative definite proves ``Wdot < 0`` on the box minus x*. The checker
encloses ``dF_j/dz`` with its own dual numbers (the controller's clamp by its Clarke derivative), computes ``M`` in
interval arithmetic, scales it by the box's half-widths (a congruence) and asks every symmetric matrix of the
enclosure to be negative definite (:func:`~drlyap.checker.ball.surely_negative_definite`).

``L`` (convex: ``P`` positive semidefinite) is then a region of attraction where W decreases on all of it: either
``L`` lies in the box (``P >= (c / h_i^2) e_i e_i^T`` for each i, by a Cholesky factorisation: then
``z_i^2 <= c / (c / h_i^2)``), or the certificate's partition proves a strict decrease of W on ``L`` outside the ball
of radius ``delta <= min_i h_i`` (with ``W > c`` on the state box's faces, checked as for V's sets: ``L`` convex and
off the faces lies in the state box) and the box covers that ball.

A region of attraction of V that rests on ``L`` (a ``roa-ball`` or ``roa`` certificate with a ``core``: the
linearisation route and the band proof) has leaves inside ``L`` (``INSIDE_CORE``): every vertex of such a leaf has
``z^T P z <= c`` by the checker's interval arithmetic (:func:`inside_core`), so the leaf lies in the convex ``L``. The
rest of the claim follows from V's strict decrease on the set outside ``L`` (its other leaves, and outside the ball
the certificate it names), V above the level on the faces, and ``L`` a region of attraction (the ``ellipsoid``
certificate the core names, checked on its own and compared here by :func:`~drlyap.checker.agreement.core_missing`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from drlyap.checker.arith import EPS, F64, TINY, Du, Iv, _up
from drlyap.checker.ball import not_equilibrium, surely_negative_definite
from drlyap.checker.model import Residual
from drlyap.checker.quadratic import _corners, surely_semidefinite


class QuadraticPair:
    """``W(z) = z^T P z`` with a pair's controller: what an ``ellipsoid`` certificate's claims are about."""

    def __init__(self, base, p: Tensor) -> None:
        self.base, self.p, self.n = base, p.to(F64), base.n

    def to(self, device: torch.device | str) -> QuadraticPair:
        return QuadraticPair(self.base.to(device), self.p.to(device))

    def value(self, z):
        return quadratic_form(z, self.p)

    def value_and_grad(self, z) -> tuple[object, object]:
        pz = z.linear(self.p)  # P symmetric: z P^T = (P z)^T
        return (z * pz).sum(-1), pz * 2.0

    def controller(self, z):
        return self.base.controller(z)


def quadratic_form(z, p: Tensor):
    """``z^T P z`` for ``z (B, n)`` in the checker's arithmetic (``P`` symmetric)."""
    return (z * z.linear(p)).sum(-1)


def _read_matrix(value, n: int, what: str) -> Tensor:
    """``P (n, n)`` from a claim, or a ValueError where it is not a finite symmetric ``n x n`` matrix (``what``: whose)."""
    p = torch.as_tensor(value, dtype=F64)
    if p.shape != (n, n) or not bool(torch.isfinite(p).all()) or not torch.equal(p, p.T):
        raise ValueError(f"the {what}'s P is not a finite symmetric {n} x {n} matrix")
    return p


def read_ellipsoid(claim: dict, n: int) -> tuple[Tensor, float, Tensor, Tensor]:
    """``(P (n, n), c, h (n,), tau (J, n, n))`` from a claim's ``ellipsoid``, or a ValueError saying what is wrong."""
    e = claim["ellipsoid"]
    p = _read_matrix(e["P"], n, "ellipsoid")
    h = torch.as_tensor(e["box"], dtype=F64).reshape(-1)
    tau = torch.as_tensor(e["tau"], dtype=F64)
    c = float(e["level"])
    if h.shape != (n,) or not bool(torch.isfinite(h).all() and (h > 0).all()):
        raise ValueError(f"the ellipsoid's box is not {n} finite positive half-widths")
    if tau.ndim != 3 or tau.shape[1:] != (n, n) or not bool(torch.isfinite(tau).all() and (tau > 0).all()):
        raise ValueError("the ellipsoid's weights tau are not (J, n, n) finite positive numbers")
    if not c > 0:
        raise ValueError("the ellipsoid's level is not > 0")
    return p, c, h, tau


def jacobian_decrease(residual: Residual, p: Tensor, h: Tensor, tau: Tensor) -> tuple[bool, float, str]:
    """Whether ``Wdot < 0`` on the box ``|z_i| <= h_i`` minus x* for every sample's model of ``residual`` (module
    docstring). Returns (proved, the largest ``lambda_max + spread`` of the scaled ``M``'s, the reason where not)."""
    n = h.shape[0]
    cube = Iv((-h)[None], h[None])
    try:
        fields = residual.fields(Du.seed(cube, n, list(range(n))))
    except TypeError as err:
        return False, float("inf"), str(err)
    if len(fields) != tau.shape[0]:
        return False, float("inf"), f"the claim has {tau.shape[0]} weight matrices for {len(fields)} samples"
    scale = Iv.point(h[:, None] * h[None, :])  # exact up to one rounding each, which the interval carries
    scale = Iv(torch.nextafter(scale.lo, torch.tensor(-torch.inf, dtype=F64)),
               torch.nextafter(scale.hi, torch.tensor(torch.inf, dtype=F64)))
    lows, highs = [], []
    pp = Iv.point(p)
    for f, t in zip(fields, tau):
        lo = torch.stack([f.d[i].lo[0] for i in range(n)], -1)  # (n, n): row r, column i is dF_r/dz_i
        hi = torch.stack([f.d[i].hi[0] for i in range(n)], -1)
        if not bool(torch.isfinite(lo).all() and torch.isfinite(hi).all()):
            return False, float("inf"), "the Jacobian's enclosure is not finite on the box"
        centre = (lo + hi) / 2
        radius = Iv.point(_up(torch.maximum(_up(hi - centre), _up(centre - lo))))
        pc = pp.linear(centre.T)  # (P C)_rj = sum_k P_rk C_kj
        d1 = (radius * Iv.point(t)).sum(-1).hi
        d2 = (radius / Iv.point(t)).sum(-2).hi
        pdp = (pp * Iv.point(d1)[None, :]).linear(p)  # sum_k P_rk d1_k P_jk
        m = pc + Iv(pc.lo.T, pc.hi.T) + pdp + Iv.point(torch.diag(d2))
        m = m * scale
        lows.append(m.lo)
        highs.append(m.hi)
    negative, worst = surely_negative_definite(torch.stack(lows), torch.stack(highs))
    if bool(negative.all()):
        return True, worst, ""
    return False, worst, f"P A + A^T P is not proved negative definite over the Jacobian's enclosure (lambda_max + " \
                         f"spread about {worst:.3g})"


def inside_box(p: Tensor, c: float, h: Tensor) -> bool:
    """Whether ``{z^T P z <= c}`` lies in the box ``|z_i| <= h_i``: ``P - (c / h_i^2) e_i e_i^T`` positive
    semidefinite for each i (``c / h_i^2`` rounded up)."""
    n = h.shape[0]
    a = (Iv.point(torch.full_like(h, c)) / (Iv.point(h) * Iv.point(h))).hi
    a = _up(a * (1 + 4 * EPS) + TINY)
    m = p.expand(n, n, n).clone()
    idx = torch.arange(n)
    m[idx, idx, idx] = _down_exact(p.diagonal() - a)
    return bool(surely_semidefinite(m).all())


def _down_exact(x: Tensor) -> Tensor:
    """``x`` moved one ulp down (a subtraction rounded to nearest is within half an ulp)."""
    return torch.nextafter(x, torch.tensor(-torch.inf, dtype=F64))


def ellipsoid_failures(claim: dict, residual: Residual, lo: Tensor, hi: Tensor, delta: float,
                       ring: bool) -> tuple[list[str], float | None]:
    """What keeps an ``ellipsoid`` certificate's claim from following (module docstring): its ellipsoid readable, its
    box inside the state box ``[lo, hi]``, x* an equilibrium and W decreasing on the box; with a ``ring`` partition, the
    ring's inner ball (radius ``delta``) inside the box and its decrease strict, else the ellipsoid inside the box.
    ``residual``: the claim's condition on W (its decay is not used here). Returns (the failures, the Jacobian test's
    bound, or None where it did not run)."""
    try:
        p, c, h, tau = read_ellipsoid(claim, lo.shape[0])
    except (KeyError, TypeError, ValueError) as err:
        return [str(err) if isinstance(err, ValueError) else f"the claim's ellipsoid lacks {err}"], None
    failures = []
    if not bool(surely_semidefinite(p)):  # then {W <= c} is convex: away from the faces, it lies in the box
        failures.append("the ellipsoid's P is not positive semidefinite")
    if not bool((h <= torch.minimum(-lo, hi)).all()):
        failures.append("the ellipsoid's box does not lie in the state box")
    if ring:
        if not delta <= float(h.min()):
            failures.append(f"the ring's inner ball (radius {delta:g}) is not inside the ellipsoid's box")
        if not float(claim["condition"].get("decay_rate") or 0.0) > 0:
            failures.append("the ring's decrease is not strict (its decay rate is not > 0)")
    elif not inside_box(p, c, h):
        failures.append(f"{{z'Pz <= {c:g}}} is not proved to lie in the ellipsoid's box")
    if float(claim["region"].get("level") or 0.0) != c:
        failures.append("the region's level is not the ellipsoid's")
    why, bound = not_equilibrium(residual), None
    if not why:
        _, bound, why = jacobian_decrease(residual, p, h, tau)
    return failures + ([why] if why else []), bound


def read_core(claim: dict, n: int) -> tuple[Tensor, float]:
    """``(P (n, n), c)`` of a claim's ``core``, or a ValueError saying what is wrong (P finite, symmetric and positive
    semidefinite: the ellipsoid is then convex and a box whose vertices lie in it lies in it)."""
    core = claim["core"]
    p = _read_matrix(core["P"], n, "core")
    c = float(core["level"])
    if not bool(surely_semidefinite(p)):
        raise ValueError("the core's P is not positive semidefinite")
    if not (c > 0 and c < float("inf")):
        raise ValueError("the core's level is not a finite number > 0")
    if float(claim["region"].get("delta") or 0.0) != 0.0:
        raise ValueError("a claim with a core has no inner ball (its delta must be 0)")
    if not float(claim["condition"].get("decay_rate") or 0.0) > 0:
        raise ValueError("the decrease outside the core is not strict (its decay rate is not > 0)")
    return p, c


def inside_core(p: Tensor, c: float, lo: Tensor, hi: Tensor) -> Tensor:
    """``(B,)``: whether every vertex of each box ``[lo, hi] (B, n)`` has ``z^T P z <= c`` (interval arithmetic)."""
    n = lo.shape[-1]
    if not lo.shape[0]:
        return torch.ones(0, dtype=torch.bool)
    upper = _corners(n, lo.device)[0] > 0  # (2^n, n): which coordinates of each vertex are the box's upper ends
    vertices = torch.where(upper[None], hi[:, None, :], lo[:, None, :]).reshape(-1, n)
    values = quadratic_form(Iv.point(vertices), p.to(vertices))
    return (values.hi <= c).reshape(-1, 2 ** n).all(-1)
