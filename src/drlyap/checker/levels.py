"""The checker's bounds of V over the sets a claim's level rests on, by its own bisection: ``V > level`` on the state
box's faces (a sublevel set ``{V <= level}`` that does not reach them, :func:`faces_above`), or the true model's flow
entering the box wherever ``V <= level`` on them (:func:`faces_inward`), ``V <= level`` on the
open delta-ball (practical stability: trajectories end up in ``{V <= level}``, :func:`ball_below`) and ``V > 0`` on
the box outside it (what makes a decrease ``Vdot + alpha V <= 0`` strict there, :func:`outside_positive`). None is in
the certificate file."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from drlyap.checker.arith import F64, Iv
from drlyap.checker.model import Pair, Residual, value_bounds


def grid_cells(lo: Tensor, hi: Tensor, grid: list[int]) -> tuple[Tensor, Tensor]:
    """The cells ``(C, n)`` of the box ``[lo, hi]`` split into ``grid[i]`` equal parts along axis i (grid order)."""
    axes_lo, axes_hi = [], []
    for i, k in enumerate(grid):
        edges = lo[i] + (hi[i] - lo[i]) * torch.arange(k + 1, dtype=F64) / k
        edges[0], edges[-1] = lo[i], hi[i]
        axes_lo.append(edges[:-1])
        axes_hi.append(edges[1:])
    return (torch.cartesian_prod(*axes_lo).reshape(-1, len(grid)),
            torch.cartesian_prod(*axes_hi).reshape(-1, len(grid)))


def widest_split(lo: Tensor, hi: Tensor, scale: Tensor) -> tuple[Tensor, Tensor]:
    """Each box ``[lo, hi] (B, n)`` halved along its widest side relative to ``scale``: the lower halves, then the
    upper halves."""
    dim = ((hi - lo) / scale).argmax(-1)
    rows = torch.arange(lo.shape[0], device=lo.device)
    mid = (lo[rows, dim] + hi[rows, dim]) / 2
    hi1, lo2 = hi.clone(), lo.clone()
    hi1[rows, dim] = mid
    lo2[rows, dim] = mid
    return torch.cat([lo, lo2]), torch.cat([hi1, hi])


@dataclass(frozen=True)
class _ValueClaim:
    """What a bisection proves of V on a set of boxes: its lower bound ``> level`` (``above``; else its upper bound
    ``<= level``) on every box that ``keep(lo, hi)`` says meets the set (None: all) and that ``settled(lo, hi)`` (a
    ``(B,)`` mask; None: never) does not settle otherwise; a centre in the set (``member(z)``; None: every centre)
    where V breaks the bound refutes it."""

    level: float
    above: bool
    keep: Callable[[Tensor, Tensor], Tensor] | None = None
    member: Callable[[Tensor], Tensor] | None = None
    settled: Callable[[Tensor, Tensor], Tensor] | None = None


def _bisect(pair: Pair, qlo: Tensor, qhi: Tensor, scale: Tensor, claim: _ValueClaim, max_boxes: int,
            batch: int) -> tuple[bool, float, int]:
    """Bisect the boxes ``[qlo, qhi]`` (along their widest side relative to ``scale``) until ``claim`` holds on each,
    a centre breaks it (the claim is then false) or ``max_boxes`` are spent. Returns (holds, the bound closest to the
    level kept, boxes bounded)."""
    level, above, keep, member, settled = claim.level, claim.above, claim.keep, claim.member, claim.settled
    sign = 1.0 if above else -1.0
    closest, spent = math.inf, 0
    while qlo.shape[0]:
        a, b, qlo, qhi = qlo[:batch], qhi[:batch], qlo[batch:], qhi[batch:]
        if keep is not None:
            meets = keep(a, b)
            a, b = a[meets], b[meets]
        spent += a.shape[0]
        lower, upper = value_bounds(pair, a, b)
        bound = sign * (lower if above else upper)  # > sign * level where it holds
        fine = bound > sign * level
        if fine.any():
            closest = min(closest, float(bound[fine].min()))
        if settled is not None and not bool(fine.all()):
            fine = fine | settled(a, b)
        if not bool(fine.all()):
            mid = (a + b) / 2
            at = pair.value_and_grad(Iv.point(mid))[0]
            broken = sign * (at.hi if above else at.lo) <= sign * level
            if member is not None:
                broken = broken & member(mid)
            if bool(broken[~fine].any()) or spent >= max_boxes:
                return False, sign * float(bound[~fine].min()), spent
            slo, shi = widest_split(a[~fine], b[~fine], scale)
            qlo, qhi = torch.cat([qlo, slo]), torch.cat([qhi, shi])
    return True, sign * closest, spent


def faces_above(pair: Pair, lo: Tensor, hi: Tensor, level: float, max_boxes: int = 200_000,
                batch: int = 4096) -> tuple[bool, float, int]:
    """Whether ``V > level`` on every face of the box ``[lo, hi]`` (``(n,)``), by bisecting face boxes (4 cells per free
    axis at the start) until V's lower bound exceeds the level on each, a face point has ``V <= level`` (the claim is
    then false) or ``max_boxes`` are spent. Returns (holds, the smallest lower bound of V kept, boxes bounded)."""
    flo, fhi = _face_boxes(lo, hi)
    scale = torch.where(hi > lo, hi - lo, 1.0)
    return _bisect(pair, flo, fhi, scale, _ValueClaim(level, above=True), max_boxes, batch)


def _face_boxes(lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """Boxes ``(F, n)`` covering the faces of the box ``[lo, hi]`` (``(n,)``): 4 cells per free axis on each face."""
    n = lo.shape[0]
    flo, fhi = [], []
    for i in range(n):
        grid = [4] * n
        grid[i] = 1
        for side in (lo[i], hi[i]):
            a, b = grid_cells(lo, hi, grid)
            a[:, i], b[:, i] = side, side
            flo.append(a)
            fhi.append(b)
    return torch.cat(flo), torch.cat(fhi)


def faces_inward(residual: Residual, lo: Tensor, hi: Tensor, level: float, max_boxes: int = 200_000,
                 batch: int = 4096) -> tuple[bool, float, int]:
    """Whether on every face of the box ``[lo, hi]`` (``(n,)``) the flow of each of the claim's models (the true model
    at its shifts, or at every shift of its box) points strictly into the box wherever ``V <= level``: face boxes are
    bisected (as by :func:`faces_above`) until V's lower bound exceeds the level or each flow's outward component is
    bounded below 0 on each, a face point with ``V <= level`` where some flow's outward component is at least 0 is
    found (the claim is then false) or ``max_boxes`` are spent. Returns (holds, the smallest lower bound of V kept
    where V settled it, boxes bounded)."""
    if residual.model != "true":
        raise ValueError("the flow through the box's faces is checked on the true model only")

    def outward(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:  # (B, N) bounds of s F_i on face i, side s
        upper, lower = (a == hi) & (b == hi), (a == lo) & (b == lo)
        axis = (upper | lower).to(torch.int8).argmax(-1).long()
        rows = torch.arange(a.shape[0], device=a.device)
        flows = residual.fields(Iv(a, b))
        lows = torch.stack([f.lo[rows, axis] for f in flows], -1)
        highs = torch.stack([f.hi[rows, axis] for f in flows], -1)
        up = upper[rows, axis][:, None]
        out_lo, out_hi = torch.where(up, lows, -highs), torch.where(up, highs, -lows)
        return torch.nan_to_num(out_lo, nan=-math.inf), torch.nan_to_num(out_hi, nan=math.inf)

    def enters(a: Tensor, b: Tensor) -> Tensor:
        return (outward(a, b)[1] < 0).all(-1)

    def leaves(z: Tensor) -> Tensor:
        return (outward(z, z)[0] >= 0).any(-1)

    flo, fhi = _face_boxes(lo, hi)
    scale = torch.where(hi > lo, hi - lo, 1.0)
    return _bisect(residual.pair, flo, fhi, scale, _ValueClaim(level, above=True, member=leaves, settled=enters),
                   max_boxes, batch)


def ball_below(pair: Pair, lo: Tensor, hi: Tensor, delta: float, level: float, max_boxes: int = 200_000,
               batch: int = 4096) -> tuple[bool, float, int]:
    """Whether ``V <= level`` at every state of the box ``[lo, hi]`` (``(n,)``, the delta-ball's box) in the open ball
    ``||z|| < delta``, by bisecting (4 cells per axis at the start) the boxes that meet the ball until V's upper bound
    is at most the level on each, a centre has ``V > level`` or ``max_boxes`` are spent. Returns (holds, the largest
    upper bound of V kept, boxes bounded)."""
    d2 = Iv.point(delta) * Iv.point(delta)

    def meets(a: Tensor, b: Tensor) -> Tensor:  # the nearest point's squared distance, rounded down, below delta^2
        near = torch.where((a <= 0) & (b >= 0), 0.0, torch.minimum(a.abs(), b.abs()))
        return Iv(near, near).square().sum(-1).lo < d2.hi

    def inside(z: Tensor) -> Tensor:  # a centre's squared distance, rounded up, below delta^2
        return Iv(z, z).square().sum(-1).hi < d2.lo

    a, b = grid_cells(lo, hi, [4] * lo.shape[0])
    return _bisect(pair, a, b, hi - lo, _ValueClaim(level, above=False, keep=meets, member=inside), max_boxes, batch)


def outside_positive(pair: Pair, lo: Tensor, hi: Tensor, delta: float, max_boxes: int = 1_000_000,
                     batch: int = 4096) -> tuple[bool, float, int]:
    """Whether ``V > 0`` at every state of the box ``[lo, hi]`` (``(n,)``) outside the open ball ``||z|| < delta``, by
    bisecting (4 cells per axis at the start) the boxes that reach outside the ball until V's lower bound is positive
    on each, a centre outside the ball has ``V <= 0`` or ``max_boxes`` are spent. Returns (holds, the smallest lower
    bound of V kept, boxes bounded)."""
    d2 = Iv.point(delta) * Iv.point(delta)

    def reaches(a: Tensor, b: Tensor) -> Tensor:  # the farthest corner's squared distance, rounded up, at least delta^2
        far = torch.maximum(a.abs(), b.abs())
        return Iv(far, far).square().sum(-1).hi >= d2.lo

    def outside(z: Tensor) -> Tensor:  # a centre's squared distance, rounded down, at least delta^2
        return Iv(z, z).square().sum(-1).lo >= d2.hi

    a, b = grid_cells(lo, hi, [4] * lo.shape[0])
    return _bisect(pair, a, b, hi - lo, _ValueClaim(0.0, above=True, keep=reaches, member=outside), max_boxes, batch)


def boxes_below(pair: Pair, lo: Tensor, hi: Tensor, scale: Tensor, level: float, max_boxes: int,
                batch: int = 4096) -> tuple[bool, float, int]:
    """Whether ``V < level`` at every state of the boxes ``[lo, hi] (B, n)``, by bisecting each (along its widest side
    relative to ``scale``) until V's upper bound is below the level on every piece, a centre has ``V >= level`` or
    ``max_boxes`` are spent. Returns (holds, the largest upper bound of V kept, boxes bounded)."""
    return _bisect(pair, lo, hi, scale, _ValueClaim(level, above=False), max_boxes, batch)
