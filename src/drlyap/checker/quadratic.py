"""The range of a second-order form's variable part, ``l . e + e^T q e`` over ``e in [-1, 1]^k``, for the checker's
forms (:mod:`.affine`): every corner of the cube after replacing the concave diagonal terms by tangents
(:func:`quad_max`, :func:`quad_span`), a dual bound through a semidefinite ``t I - q`` (:func:`_dual_max`), and a
cheap bound for products (:func:`_quick_spans`); all padded for rounding on the checker's own rules (:mod:`.arith`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from drlyap.checker.arith import EPS, F64, INF, TINY, Iv, _down, _up

_MAX_VERTICES_K = 10
_CORNERS: dict[tuple[int, str], tuple[Tensor, Tensor, Tensor]] = {}


def _corners(k: int, device: torch.device | str = "cpu") -> tuple[Tensor, Tensor, Tensor]:
    """The ``2^k`` corners of ``[-1, 1]^k`` as rows ``(2^k, k)``, the products ``e_i e_j`` (``i < j``) at the corners
    ``(2^k, P)``, and the ``(k * k, P)`` matrix of zeros and ones that sums ``q_ij + q_ji`` from a flattened ``q``, on
    ``device``."""
    key = (k, str(device))
    if key not in _CORNERS:
        corners = torch.cartesian_prod(*[torch.tensor([-1.0, 1.0], dtype=F64, device=device)] * k).reshape(-1, k)
        pairs = torch.triu_indices(k, k, 1, device=device)
        select = torch.zeros(k * k, pairs.shape[1], dtype=F64, device=device)
        columns = torch.arange(pairs.shape[1], device=device)
        select[pairs[0] * k + pairs[1], columns] = 1.0
        select[pairs[1] * k + pairs[0], columns] = 1.0
        _CORNERS[key] = corners, corners[:, pairs[0]] * corners[:, pairs[1]], select
    return _CORNERS[key]


def _parts(q: Tensor) -> tuple[Tensor, Tensor]:
    """The diagonal ``(..., k)`` of ``q (..., k, k)`` and the sums ``q_ij + q_ji`` over ``i < j`` ``(..., P)`` (a
    product with zeros and ones: each sum is one rounded addition, as written; a non-finite entry makes its row
    NaN, which no bound reads as finite)."""
    k = q.shape[-1]
    return torch.diagonal(q, dim1=-2, dim2=-1), q.flatten(-2) @ _corners(k, q.device)[2]


def _corner_max(lin: Tensor, diag: Tensor, off: Tensor, base: Tensor, mag: Tensor) -> Tensor:
    """An upper bound of ``max over e in [-1, 1]^k of lin . e + sum_i diag_i e_i^2 + sum_{i<j} off_ij e_i e_j``
    (see :func:`quad_max`). ``base (..., 2^k)``: ``lin . e + off . (e_i e_j)`` at the corners as computed (shared by a
    form's upper and lower bounds); ``mag``: an upper bound of ``|lin|_1 + |diag|_1 + |off|_1``, for the pad."""
    k = lin.shape[-1]
    corners = _corners(k, lin.device)[0]
    concave = diag.clamp(max=0.0)
    t = torch.where(concave < 0, (lin / (-2.0 * torch.where(concave < 0, concave, -1.0))).clamp(-1.0, 1.0), 0.0)
    values = base + (2.0 * concave * t) @ corners.T
    top = values.amax(-1) - (concave * t * t).sum(-1) + diag.clamp(min=0.0).sum(-1)
    return _up(top + 4 * (k * k + k + 8) * EPS * 4.0 * mag + TINY)


def quad_max(lin: Tensor, q: Tensor, dual: bool = False) -> Tensor:
    """An upper bound ``(...)`` of ``max over e in [-1, 1]^k of lin . e + e^T q e`` (``lin (..., k)``, ``q (..., k,
    k)``). A concave diagonal term ``q_ii e_i^2`` (``q_ii < 0``) lies below its tangent at ``t_i`` (the coordinate's
    own maximiser ``-lin_i / (2 q_ii)`` clipped to ``[-1, 1]``): ``q_ii (2 t_i e_i - t_i^2)``; what remains is convex
    in each coordinate alone, so its maximum over the cube is at a corner (where ``e_i^2 = 1``), and every corner is
    evaluated. Above ``k = 10`` coordinates, :func:`_quick_span`. Padded for the rounding of the float64 sums.
    ``dual``: also :func:`_dual_max`, and the smaller of the two (an eigendecomposition and a factorisation per entry:
    used for final bounds, not inside every product)."""
    k = lin.shape[-1]
    if k > _MAX_VERTICES_K:
        return _quick_span(lin, q).hi
    corner = _corner_max(lin, *_corner_inputs(lin, q))
    return torch.minimum(torch.minimum(corner, _dual_max(lin, q)), _face_max(lin, q)) if dual else corner


def quad_max_minus(lin: Tensor, q: Tensor, lin2: Tensor, q2: Tensor, lam: Tensor, dual: bool = False,
                   mags: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """:func:`quad_max` ``(B, Q, L)`` of ``lin - lam lin2`` and ``q - lam q2`` for ``lin (B, Q, k)``, ``q (B, Q, k, k)``,
    ``lin2 (B, k)``, ``q2 (B, k, k)`` and multipliers ``lam (B, Q, L)``, without forming the ``L`` quadratic parts
    for the corner bound: the corner values of both forms are computed once and combined (their rounding is in the
    pad, which is taken on ``|lin|_1 + |q|_1 + lam (|lin2|_1 + |q2|_1)``; ``mags``: those two sums where the caller
    has them). ``dual``: the dual bound too, which forms them."""
    k = lin.shape[-1]
    if k > _MAX_VERTICES_K:
        return quad_max(lin[:, :, None] - lam[..., None] * lin2[:, None, None],
                        q[:, :, None] - lam[..., None, None] * q2[:, None, None], dual)
    corners, products, _ = _corners(k, lin.device)
    (d1, o1), (d2, o2) = _parts(q), _parts(q2)
    scaled = lam[..., None]
    combined = lin[:, :, None] - scaled * lin2[:, None, None]
    base = ((lin @ corners.T + o1 @ products.T)[:, :, None]
            - scaled * (lin2 @ corners.T + o2 @ products.T)[:, None, None])
    if mags is None:
        mags = lin.abs().sum(-1) + q.abs().flatten(-2).sum(-1), lin2.abs().sum(-1) + q2.abs().flatten(-2).sum(-1)
    mag = (mags[0][..., None] + lam * mags[1][:, None, None]) * (1 + 8 * EPS)
    corner = _corner_max(combined, d1[:, :, None] - scaled * d2[:, None, None],
                         o1[:, :, None] - scaled * o2[:, None, None], base, mag)
    if not dual:
        return corner
    joint = q[:, :, None] - lam[..., None, None] * q2[:, None, None]
    return torch.minimum(torch.minimum(corner, _dual_max(combined, joint)), _face_max(combined, joint))


def quad_span(lin: Tensor, q: Tensor, qabs: Tensor | None = None) -> Iv:
    """Bounds of ``lin . e + e^T q e`` over the cube by :func:`quad_max` of it and of its negation (the corner values
    computed once). ``qabs``: ``|q|_1`` where known."""
    k = lin.shape[-1]
    if k > _MAX_VERTICES_K:
        return _quick_span(lin, q)
    diag, off, base, mag = _corner_inputs(lin, q, qabs)
    top = _corner_max(lin, diag, off, base, mag)
    bottom = -_corner_max(-lin, -diag, -off, -base, mag)
    return Iv(torch.where(torch.isnan(bottom), -INF, bottom), top)


def _corner_inputs(lin: Tensor, q: Tensor, qabs: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """What :func:`_corner_max` takes besides ``lin``: ``q``'s diagonal and pair sums (:func:`_parts`), the corner
    values ``lin . e + off . (e_i e_j)`` and ``|lin|_1 + |q|_1`` (``qabs``: ``|q|_1`` where known)."""
    corners, products, _ = _corners(lin.shape[-1], lin.device)
    diag, off = _parts(q)
    mag = lin.abs().sum(-1) + (q.abs().flatten(-2).sum(-1) if qabs is None else qabs)
    return diag, off, lin @ corners.T + off @ products.T, mag


def _quick_span(lin: Tensor, q: Tensor) -> Iv:
    """Bounds of ``lin . e + e^T q e`` over the cube, cheaply: each coordinate's ``q_ii e_i^2 + lin_i e_i`` exactly
    (its ends and vertex), the cross terms ``(q_ij + q_ji) e_i e_j`` by their magnitudes; padded for rounding."""
    return _quick_spans(lin, q)[1]


def _quick_spans(lin: Tensor, q: Tensor, qabs: Tensor | None = None,
                 with_lin: bool = True) -> tuple[Iv, Iv | None]:
    """:func:`_quick_span` of ``e^T q e`` alone and (``with_lin``) of ``lin . e + e^T q e``, sharing the work on ``q``
    (``qabs``: ``|q|_1`` where known)."""
    k = q.shape[-1]
    diag, off = _parts(q)
    cross = off.abs().sum(-1)
    qabs = q.abs().flatten(-2).sum(-1) if qabs is None else qabs
    pad_q = 4 * (k * k + k + 8) * EPS * 2.0 * qabs + TINY
    q_only = Iv(_down(diag.clamp(max=0.0).sum(-1) - cross - pad_q), _up(diag.clamp(min=0.0).sum(-1) + cross + pad_q))
    if not with_lin:
        return q_only, None
    a = lin.abs()
    pad = pad_q + 4 * (k * k + k + 8) * EPS * a.sum(-1)
    vertex = -(lin * lin) / (4 * torch.where(diag != 0, diag, 1.0))
    top = torch.where((diag < 0) & (a < -2 * diag), vertex, diag + a).sum(-1)
    bottom = torch.where((diag > 0) & (a < 2 * diag), vertex, diag - a).sum(-1)
    return q_only, Iv(_down(bottom - cross - pad), _up(top + cross + pad))


def _finite_symmetric(lin: Tensor, q: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Where ``lin`` and ``q`` are finite ``(...)``, both with zeros elsewhere, ``q``'s symmetric part ``q_s`` and the
    rounding of its entries summed (``eps |q|_1``): what the dual and face bounds start from."""
    finite = torch.isfinite(lin).all(-1) & torch.isfinite(q).flatten(-2).all(-1)
    lin = torch.where(finite[..., None], lin, 0.0)
    q = torch.where(finite[..., None, None], q, 0.0)
    return finite, lin, (q + q.transpose(-1, -2)) / 2, EPS * q.abs().flatten(-2).sum(-1)


def _dual_max(lin: Tensor, q: Tensor) -> Tensor:
    """A second upper bound of ``max over e in [-1, 1]^k of lin . e + e^T q e``, for ``q`` curved downward along
    directions that mix the coordinates (which the corner bound cannot see). For ``M = t I - q_s`` positive
    semidefinite (``q_s`` the symmetric part) and any ``y``: ``-e^T M e <= -2 y^T M e + y^T M y``, so the function is
    at most ``max(t, 0) k + sum |lin - 2 M y| + y^T M y``. ``t`` is chosen on a geometric grid above the largest
    eigenvalue (estimated), ``y = M^-1 lin / 2``; the bound needs ``M`` semidefinite only, established by a Cholesky
    factorisation of ``M - p I`` with ``p`` above its backward error (``2 (k + 1)^2 eps max_i M_ii``).
    ``inf`` where that fails or an input is not finite."""
    k = lin.shape[-1]
    finite, lin, qs, sym_pad = _finite_symmetric(lin, q)
    lam, vec = torch.linalg.eigh(qs)
    lv = (vec.transpose(-1, -2) @ lin[..., None])[..., 0]
    scale = (lin.norm(dim=-1, keepdim=True) / (2 * math.sqrt(k))).clamp(min=TINY)
    steps = 2.0 ** torch.arange(-14, 15, dtype=F64, device=lin.device)
    grid = lam[..., -1:] + scale * steps + 1e-10 * qs.flatten(-2).norm(dim=-1)[..., None]
    guess = grid.clamp(min=0.0) * k + 0.25 * (lv[..., None, :] ** 2 / (grid[..., None] - lam[..., None, :])).sum(-1)
    t = grid.gather(-1, guess.argmin(-1, keepdim=True))[..., 0]
    y = 0.5 * (vec @ (lv / (t[..., None] - lam))[..., None])[..., 0]
    eye = torch.eye(k, dtype=F64, device=lin.device)
    m = t[..., None, None] * eye - qs
    semidefinite = surely_semidefinite(m)
    my = (m @ y[..., None])[..., 0]
    mag_my = (m.abs() @ y.abs()[..., None])[..., 0]
    value = t.clamp(min=0.0) * k + (lin - 2 * my).abs().sum(-1) + (y * my).sum(-1)
    pad = 8 * (k + 2) * EPS * (lin.abs().sum(-1) + 2 * mag_my.sum(-1) + (y.abs() * mag_my).sum(-1) + t.abs() * k)
    value = _up(value + pad + 4 * k * k * sym_pad + 2 * EPS * m.abs().flatten(-2).sum(-1) + TINY)
    return torch.where(finite & semidefinite & torch.isfinite(value), value, INF)


def _face_max(lin: Tensor, q: Tensor, rounds: int = 4) -> Tensor:
    """A third upper bound of ``max over e in [-1, 1]^k of lin . e + e^T q e``, for a maximum on a face of the cube
    (a concave form whose unconstrained maximiser lies outside it, which the dual bound takes for the maximum). With
    ``s`` at least ``q_s``'s largest eigenvalue, ``M = s I - q_s`` is positive semidefinite and
    ``h(e) = lin . e - e^T M e`` concave, so for any ``p`` in the cube ``h(e) <= h(p) + grad h(p) . (e - p)
    <= p^T M p + |lin - 2 M p|_1``, and the form is ``h(e) + s |e|^2 <= h(e) + s k``. Any ``p`` gives a bound; the
    least over a few rounds is taken, each round: ``h``'s maximiser over the coordinates not held at an end of the
    cube (an end where ``h`` rises outward holds its coordinate), clipped, then one pass of exact maximisation along
    each coordinate in turn. ``M`` checked semidefinite by a Cholesky factorisation (:func:`surely_semidefinite`),
    the sums padded. ``inf`` where that fails or an input is not finite."""
    k = lin.shape[-1]
    finite, lin, qs, sym_pad = _finite_symmetric(lin, q)
    top = torch.linalg.eigvalsh(qs)[..., -1]
    s = top.clamp(min=0.0) * (1 + 1e-9) + 1e-12 * qs.abs().flatten(-2).sum(-1) + TINY
    eye = torch.eye(k, dtype=F64, device=lin.device)
    m = s[..., None, None] * eye - qs
    mii = torch.diagonal(m, dim1=-2, dim2=-1)
    p = torch.zeros_like(lin)
    held = torch.zeros_like(lin, dtype=torch.bool)
    best = torch.full_like(s, INF)

    def bound(p: Tensor) -> Tensor:
        mp = (m @ p[..., None])[..., 0]
        mag_mp = (m.abs() @ p.abs()[..., None])[..., 0]
        value = (p * mp).sum(-1) + (lin - 2 * mp).abs().sum(-1) + s * k
        pad = 8 * (k + 2) * EPS * ((p.abs() * mag_mp).sum(-1) + lin.abs().sum(-1) + 2 * mag_mp.sum(-1) + s * k)
        value = _up(value + pad + 4 * k * k * sym_pad + 2 * EPS * m.abs().flatten(-2).sum(-1) + TINY)
        return torch.where(torch.isfinite(value), value, INF)

    for _ in range(rounds):
        free = ~held
        system = torch.where(free[..., None] & free[..., None, :], m, 0.0) + torch.diag_embed(held.to(F64))
        right = torch.where(free, 0.5 * lin - ((m * held[..., None, :]) @ p[..., None])[..., 0], p)
        p = torch.linalg.solve_ex(system, right[..., None])[0][..., 0]
        p = torch.where(torch.isfinite(p), p, 0.0).clamp(-1.0, 1.0)
        for i in range(k):  # h's maximiser along coordinate i, the others held
            others = lin[..., i] - 2 * ((m[..., i, :] * p).sum(-1) - mii[..., i] * p[..., i])
            p[..., i] = torch.where(mii[..., i] > 0, others / (2 * mii[..., i]), p[..., i]).clamp(-1.0, 1.0)
        best = torch.minimum(best, bound(p))
        rise = lin - 2 * (m @ p[..., None])[..., 0]
        held = ((p >= 1.0) & (rise >= 0)) | ((p <= -1.0) & (rise <= 0))
    return torch.where(finite & surely_semidefinite(m), best, INF)


def surely_semidefinite(m: Tensor) -> Tensor:
    """``(...)``: where the symmetric float matrices ``m (..., k, k)`` are surely positive semidefinite: a Cholesky
    factorisation of ``m - p I`` succeeds, ``p`` above its backward error (``2 (k + 1)^2 eps max_i m_ii``)."""
    k = m.shape[-1]
    eye = torch.eye(k, dtype=F64, device=m.device)
    backward = 2 * (k + 1) ** 2 * EPS * torch.diagonal(m, dim1=-2, dim2=-1).abs().amax(-1) + TINY
    return torch.linalg.cholesky_ex(m - backward[..., None, None] * eye).info == 0


__all__ = ["quad_max", "quad_max_minus", "quad_span", "surely_semidefinite"]
