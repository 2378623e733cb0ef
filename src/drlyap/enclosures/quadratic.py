"""Bounds of quadratic polynomials over the unit cube, ``max over e in [-1, 1]^K of g . e + e^T q e``: the
joint bound of an affine form's linear and quadratic parts."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from drlyap.enclosures.rounding import EPS, F64, TINY


def quadratic_max(g: Tensor, q: Tensor) -> Tensor:
    """An upper bound ``(...)`` of ``max over e in [-1, 1]^K of g . e + e^T q e`` for ``g (..., K)`` and a
    symmetric ``q (..., K, K)``, exact up to rounding when ``q``'s diagonal is non-negative, and where ``q`` is
    negative semidefinite and the search of :func:`_convex_min` finds the maximiser.

    The smallest of three bounds. Vertices: each concave diagonal term (``q_kk < 0``) is replaced by its tangent at
    ``t_k`` (``q_kk e^2 <= q_kk (2 t_k e - t_k^2)``, ``t_k`` the one-coordinate maximiser); what is left is convex
    in every coordinate separately, so its maximum over the cube is at one of the ``2^K`` vertices, all evaluated
    (two matrix products), padded outward for the rounding of the float64 sums. Dual: :func:`_dual_max`, for a
    ``q`` curved downward along mixed directions (measured on the cart-pole's default pair: its proof in 114,200
    boxes instead of 168,403). Convexity: :func:`_convex_min` of the negation, for a maximum on a face of the cube,
    where the dual bound takes the unconstrained maximum (a quadrotor pair's trained proof in 3,830,051 boxes
    instead of 5,242,650).
    """
    return quadratic_span(g, q, lower=False)[1]


def quadratic_span(g: Tensor, q: Tensor, lower: bool | Tensor = True) -> tuple[Tensor | None, Tensor]:
    """Lower and upper bounds ``(...)`` of ``g . e + e^T q e`` over ``e in [-1, 1]^K``: :func:`quadratic_max` of it
    and (``lower``; else None) of its negation, sharing the vertex values and the eigendecomposition.

    ``lower`` may be a bool mask over the last axis of ``...`` (the entries whose lower bound is read): the lower
    bound is then computed for those entries only, ``-inf`` elsewhere (a sound bound that says nothing)."""
    k = g.shape[-1]
    verts = vertices(k, g.device)  # (2^K, K)
    diag = torch.diagonal(q, dim1=-2, dim2=-1)
    eye = torch.eye(k, dtype=F64, device=g.device)
    outer = (verts.unsqueeze(-1) * verts.unsqueeze(-2)).flatten(1) - eye.flatten()  # e_k^2 = 1
    base = g @ verts.T + q.flatten(-2) @ outer.T  # (..., 2^K): the linear and off-diagonal parts at the vertices
    mag = g.abs().sum(-1) + 4.0 * q.abs().sum((-2, -1))
    pad = 4 * (k * k + k + 4) * EPS * mag + TINY
    finite = (torch.isfinite(g).all(-1) & torch.isfinite(q).flatten(-2).all(-1))[..., None, None]
    lam, u = torch.linalg.eigh(torch.where(finite, (q + q.mT) * 0.5, 0.0))  # eigh reads one triangle
    hi = torch.minimum(torch.minimum(_vertex_max(g, diag, base, verts) + pad, _dual_max(g, q, (lam, u))),
                       -_convex_min(-g, -q, -lam.flip(-1)))
    if isinstance(lower, Tensor):
        if not bool(lower.any()):
            return torch.full_like(hi, -torch.inf), hi
        if not bool(lower.all()):  # only the entries read: the rest of the work is half of this function's
            lo = torch.full_like(hi, -torch.inf)
            lo[..., lower] = _lower(g[..., lower, :], q[..., lower, :, :], diag[..., lower, :], base[..., lower, :],
                                    verts, pad[..., lower], lam[..., lower, :], u[..., lower, :, :])
            return lo, hi
    elif not lower:
        return None, hi
    return _lower(g, q, diag, base, verts, pad, lam, u), hi


def _lower(g: Tensor, q: Tensor, diag: Tensor, base: Tensor, verts: Tensor, pad: Tensor, lam: Tensor,
           u: Tensor) -> Tensor:
    """The lower side of :func:`quadratic_span`: the best of the vertex bound and the dual bound of the negation, and
    :func:`_convex_min`."""
    lo = -torch.minimum(_vertex_max(-g, -diag, -base, verts) + pad, _dual_max(-g, -q, (-lam.flip(-1), u.flip(-1))))
    return torch.maximum(lo, _convex_min(g, q, lam))


def _finite_symmetric(g: Tensor, q: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Where ``g`` and ``q`` are finite ``(...)``, both with zeros elsewhere, ``q``'s symmetric part and the rounding
    of its entries summed (``eps |q|_1``: ``e'qe = e'q_sym e`` in real arithmetic): what the dual and convexity bounds
    start from."""
    finite = torch.isfinite(g).all(-1) & torch.isfinite(q).flatten(-2).all(-1)
    g = torch.where(finite[..., None], g, 0.0)
    q = torch.where(finite[..., None, None], q, 0.0)
    return finite, g, (q + q.mT) * 0.5, EPS * q.abs().sum((-2, -1))


def _convex_min(g: Tensor, q: Tensor, lam: Tensor, steps: int = 2) -> Tensor:
    """A lower bound ``(...)`` of ``min over e in [-1, 1]^K of g . e + e^T q e``, exact (up to rounding) where ``q``
    is positive semidefinite and the search below finds the minimiser: the minimum of a convex quadratic over the
    cube, which sits on a face where the box straddles a sublevel set's boundary (the vertex bound and the dual bound
    are loose there).

    With ``s >= -lambda_min(q)`` (``lam``: the eigenvalues of ``(q + q^T) / 2``, ascending) ``M = q_sym + s I`` is
    positive semidefinite, and for any ``e0`` in the cube, by convexity and ``|e_k| <= 1``,
    ``g . e + e^T M e >= -e0^T M e0 - |g + 2 M e0|_1``, with equality at the minimiser (its optimality conditions).
    So the minimum is at least that less ``s K``, for every ``e0``: the best of the points of an active-set search
    (the unconstrained minimiser clamped to the cube, then ``steps`` times: the coordinates at a bound whose gradient
    points out of the cube held there, the others solved for) is taken. M's semidefiniteness is checked by a Cholesky
    factorisation (:func:`surely_semidefinite`) and the sums are padded for rounding. ``-inf`` where the check fails
    or an input is not finite."""
    k = g.shape[-1]
    finite, g, q, asym = _finite_symmetric(g, q)
    finite = finite & torch.isfinite(lam).all(-1)
    eye = torch.eye(k, dtype=F64, device=g.device)
    shift = (torch.where(finite, (-lam[..., 0]).clamp_min(0.0), 0.0) * (1 + 1e-9) + 1e-12 * q.abs().sum((-2, -1))
             + 1e-300)
    m = q + shift[..., None, None] * eye
    gd, md = g.detach(), m.detach()  # the points searched: any point gives a bound, none needs a gradient
    mdiag = torch.diagonal(md, dim1=-2, dim2=-1)
    fixed = torch.zeros_like(gd, dtype=torch.bool)
    e0 = torch.zeros_like(gd)
    best = torch.full_like(shift, -torch.inf)
    for _ in range(steps + 1):
        free = ~fixed
        both = free.unsqueeze(-1) & free.unsqueeze(-2)
        rhs = torch.where(free, -0.5 * gd - ((md * fixed.unsqueeze(-2)) @ e0.unsqueeze(-1)).squeeze(-1), e0)
        step = torch.linalg.solve_ex(torch.where(both, md, 0.0) + torch.diag_embed(fixed.to(F64)), rhs.unsqueeze(-1))
        e0 = step[0].squeeze(-1).clamp(-1.0, 1.0)
        e0 = torch.where(torch.isfinite(e0), e0, 0.0)
        for i in range(k):  # one round of exact minimisation along each coordinate: what the clamping left
            rest = gd[..., i] + 2 * (md[..., i, :] * e0).sum(-1) - 2 * mdiag[..., i] * e0[..., i]
            e0[..., i] = torch.where(mdiag[..., i] > 0, -rest / (2 * mdiag[..., i]), e0[..., i]).clamp(-1.0, 1.0)
        me = (m @ e0.unsqueeze(-1)).squeeze(-1)
        grad = g + 2 * me
        value = -(e0 * me).sum(-1) - grad.abs().sum(-1) - shift * k
        m_e = (m.abs() @ e0.abs().unsqueeze(-1)).squeeze(-1)
        pad = (8 * (k + 2) * EPS * ((e0.abs() * m_e).sum(-1) + g.abs().sum(-1) + 2 * m_e.sum(-1) + shift * k)
               + asym + 2 * EPS * m.abs().sum((-2, -1)) + TINY)
        best = torch.maximum(best, torch.where(torch.isfinite(value), value - pad, -torch.inf))
        fixed = ((e0 >= 1.0) & (grad.detach() <= 0)) | ((e0 <= -1.0) & (grad.detach() >= 0))
    return torch.where(finite & surely_semidefinite(m), best, -torch.inf)


def _vertex_max(g: Tensor, diag: Tensor, base: Tensor, verts: Tensor) -> Tensor:
    """The vertex bound of :func:`quadratic_max` before its pad, from ``base``: ``g . e`` plus the off-diagonal part
    at the vertices."""
    neg = torch.clamp(diag, max=0.0)
    t = torch.where(neg < 0, torch.clamp(g / (-2.0 * torch.where(neg < 0, neg, -1.0)), -1.0, 1.0), 0.0)
    values = base + (2.0 * neg * t) @ verts.T
    return values.amax(-1) - (neg * t * t).sum(-1) + torch.clamp(diag, min=0.0).sum(-1)


def _dual_max(g: Tensor, q: Tensor, eig: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """A second upper bound of ``max over e in [-1, 1]^K of g . e + e^T q e``, tight where the vertex bound is
    not: ``q`` strongly curved downward along directions that mix the coordinates (a stiff closed loop's
    ``Vdot`` near x*, where the linear part's growth along the stiff direction is cancelled by the quadratic's
    curvature, which a bound term by term cannot see).

    For ``t >= lambda_max(q)``, ``M = t I - q`` is positive semidefinite and, for any vector ``y``,
    ``g . e + e^T q e = t |e|^2 - (e - y)^T M (e - y) + (g - 2 M y) . e + y^T M y
    <= max(t, 0) K + sum_k |g - 2 M y|_k + y^T M y``. ``t`` is the best of a geometric grid for the
    eigendecomposition's estimate (``eig``: that of ``(q + q^T) / 2`` where the caller has it), ``y = M^-1 g / 2``;
    the bound holds for any ``y``, so only ``M``'s semidefiniteness is checked: a Cholesky factorisation of
    ``M - p I`` succeeds, ``p`` above its backward error (``2 (K + 1)^2 eps max_k M_kk``, after Rump's test), and the
    few sums are padded for rounding. ``inf`` where the check fails or an input is not finite.
    """
    k = g.shape[-1]
    finite, g, q, asym = _finite_symmetric(g, q)
    if eig is None:
        lam, u = torch.linalg.eigh(q)
    else:
        lam, u = (torch.where(finite[..., None], eig[0], 0.0),
                  torch.where(finite[..., None, None], eig[1], torch.eye(k, dtype=F64, device=g.device)))
    gu = (u.mT @ g.unsqueeze(-1)).squeeze(-1)
    size = q.flatten(-2).norm(dim=-1)
    steps = torch.pow(2.0, torch.arange(-14, 15, dtype=F64, device=g.device))
    t = (lam[..., -1:] + (g.norm(dim=-1, keepdim=True) / (2 * math.sqrt(k))).clamp_min(1e-300) * steps
         + 2e-11 * size[..., None] + 1e-300)  # (..., J): t - lambda_max > 0 up to the eigensolver's error
    estimate = t.clamp_min(0) * k + 0.25 * (gu.unsqueeze(-2).square() / (t[..., None] - lam.unsqueeze(-2))).sum(-1)
    t = t.gather(-1, estimate.argmin(-1, keepdim=True))[..., 0]
    y = 0.5 * (u @ (gu / (t[..., None] - lam)).unsqueeze(-1)).squeeze(-1)
    eye = torch.eye(k, dtype=F64, device=g.device)
    m = t[..., None, None] * eye - q
    my = (m @ y.unsqueeze(-1)).squeeze(-1)
    m_y = (m.abs() @ y.abs().unsqueeze(-1)).squeeze(-1)
    value = t.clamp_min(0) * k + (g - 2 * my).abs().sum(-1) + (y * my).sum(-1)
    pad = 8 * (k + 2) * EPS * (g.abs().sum(-1) + 2 * m_y.sum(-1) + (y.abs() * m_y).sum(-1) + t.abs() * k) + TINY
    semidefinite = surely_semidefinite(m)
    value = value + pad + asym + 2 * EPS * m.abs().sum((-2, -1))
    return torch.where(finite & semidefinite & torch.isfinite(value), value, torch.inf)


def surely_semidefinite(m: Tensor) -> Tensor:
    """``(...)``: where the symmetric float64 matrices ``m (..., k, k)`` are surely positive semidefinite: a Cholesky
    factorisation of ``m - p I`` succeeds, ``p`` above its backward error (``2 (k + 1)^2 eps max_i m_ii``)."""
    k = m.shape[-1]
    eye = torch.eye(k, dtype=F64, device=m.device)
    backward = 2 * (k + 1) ** 2 * EPS * torch.diagonal(m, dim1=-2, dim2=-1).abs().amax(-1) + 1e-300
    return torch.linalg.cholesky_ex(m - backward[..., None, None] * eye).info == 0


_VERTICES: dict = {}


def vertices(k: int, device) -> Tensor:
    key = (k, str(device))
    if key not in _VERTICES:
        _VERTICES[key] = torch.cartesian_prod(*[torch.tensor([-1.0, 1.0], dtype=F64)] * k).reshape(-1, k).to(device)
    return _VERTICES[key]


def max_lin_quad(g: Tensor, d: Tensor) -> Tensor:
    """``max over e in [-1, 1] of g e + d e^2`` for each symbol, ``(..., K)`` (the vertex ``-g / 2d`` where it
    lies inside and ``d < 0``, else an end); float64, not yet padded for rounding."""
    a = g.abs()
    inner = (d < 0) & (a < -2.0 * d)
    return torch.where(inner, a * a / (-4.0 * torch.where(inner, d, -1.0)), a + d)


def sym_outer(a: Tensor, b: Tensor) -> Tensor:
    """``(a b^T + b a^T) / 2`` over the last axis, ``(..., K) -> (..., K, K)``: the symmetric coefficients of
    ``(a . e)(b . e)`` (quadratic parts are kept symmetric, so their range needs no symmetrising)."""
    if a is b:
        return a.unsqueeze(-1) * a.unsqueeze(-2)
    ab = a.unsqueeze(-1) * b.unsqueeze(-2)
    return (ab + ab.transpose(-1, -2)) * 0.5
