"""The state region a certificate is trained and proved on: X_delta, the state box minus a ball around x*.

One :class:`Region` object serves every consumer: training samples its states from it, the acceptance
check builds its validation grid from it, CEGIS projects falsified states into it, and the verifier takes
its starting boxes, its ball test and its volume from it. Everything is in local coordinates
``z = x - x*`` (see :meth:`drlyap.systems.UncertainSystem.to_local`), float64.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

F64 = torch.float64


def box_grid(lo: Tensor, hi: Tensor, per_axis: Sequence[int]) -> tuple[Tensor, Tensor]:
    """Split the box ``[lo, hi]`` (n,) into ``prod(per_axis)`` cells: their ``(lo, hi)``, each ``(C, n)``."""
    axes_lo, axes_hi = [], []
    for i, k in enumerate(per_axis):
        edges = lo[i] + (hi[i] - lo[i]) * torch.arange(k + 1, dtype=F64) / k
        edges[-1] = hi[i]
        axes_lo.append(edges[:-1])
        axes_hi.append(edges[1:])
    glo = torch.cartesian_prod(*axes_lo).reshape(-1, len(per_axis))
    ghi = torch.cartesian_prod(*axes_hi).reshape(-1, len(per_axis))
    return glo, ghi


def default_grid(n: int, target: int = 256) -> list[int]:
    """Boxes per axis for a starting grid of about ``target`` boxes in ``n`` dimensions."""
    return [max(2, int(round(target ** (1.0 / n))))] * n


def far_dist(lo: Tensor, hi: Tensor) -> Tensor:
    """Largest distance from the origin to a point of each box ``(B,)``."""
    return torch.sqrt(torch.maximum(lo * lo, hi * hi).sum(-1))


def near_dist(lo: Tensor, hi: Tensor) -> Tensor:
    """Smallest distance from the origin to a point of each box ``(B,)``."""
    gap = torch.clamp(torch.maximum(lo, -hi), min=0.0)
    return torch.sqrt((gap * gap).sum(-1))


def inside_ball(lo: Tensor, hi: Tensor, radius: float) -> Tensor:
    """Boxes that lie entirely in the open ball ``||z|| < radius`` (conservatively)."""
    return far_dist(lo, hi) * (1 + 1e-12) < radius


def split(lo: Tensor, hi: Tensor, scale: Tensor, sensitivity: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Bisect each box ``(B, n)`` along its widest side (widths relative to ``scale``): ``(2B, n)`` boxes.

    ``sensitivity (B, n)``: bisect instead the side that adds most to the bound (e.g. ``box_bounds``'s
    sensitivity), among the sides at least 1/16 as wide (relatively) as the widest, so that every side
    keeps shrinking.
    """
    rel = (hi - lo) / scale
    dim = rel.argmax(-1)
    if sensitivity is not None:
        wide = rel >= rel.amax(-1, keepdim=True) / 16
        score = torch.where(wide, torch.nan_to_num(sensitivity, nan=torch.inf), -1.0)
        dim = torch.where(score.amax(-1) > 0, score.argmax(-1), dim)
    rows = torch.arange(lo.shape[0])
    mid = (lo[rows, dim] + hi[rows, dim]) / 2
    hi1, lo2 = hi.clone(), lo.clone()
    hi1[rows, dim] = mid
    lo2[rows, dim] = mid
    return torch.cat([lo, lo2]), torch.cat([hi1, hi])


@dataclass
class Domain:
    """A set a branch and bound searches, as a union of boxes: the starting boxes ``lo, hi (B, n)``, ``scale (n,)``
    (the widths box sides are measured against), ``meets(lo, hi) -> (B,)`` the boxes that may hold points of the set
    (None: every box; the others are dropped when split) and ``contains(z) -> (B,)`` the points that lie in it (None:
    every point)."""

    lo: Tensor
    hi: Tensor
    scale: Tensor
    meets: Callable[[Tensor, Tensor], Tensor] | None = None
    contains: Callable[[Tensor], Tensor] | None = None

    def boxes_meeting(self, lo: Tensor, hi: Tensor) -> Tensor:
        """The boxes ``(B,)`` that may hold points of the set."""
        return self.meets(lo, hi) if self.meets is not None else torch.ones(lo.shape[0], dtype=torch.bool,
                                                                             device=lo.device)

    def points_in(self, z: Tensor) -> Tensor:
        """The points ``(B,)`` of ``z (B, n)`` that lie in the set."""
        return self.contains(z) if self.contains is not None else torch.ones(z.shape[0], dtype=torch.bool,
                                                                              device=z.device)


def ball_volume(radius: float, n: int) -> float:
    return math.pi ** (n / 2) / math.gamma(n / 2 + 1) * radius ** n


class Region:
    """``X_delta = {z in [lo, hi] : ||z|| >= delta}`` in local coordinates.

    ``lo``, ``hi``: ``(n,)`` float64 corners of the state box (local coordinates); ``delta >= 0`` the radius of
    the excluded open ball around x* (``z = 0``).
    """

    def __init__(self, lo: Tensor, hi: Tensor, delta: float) -> None:
        self.lo, self.hi = torch.as_tensor(lo, dtype=F64), torch.as_tensor(hi, dtype=F64)
        if not (math.isfinite(delta) and delta >= 0):
            raise ValueError(f"delta must be finite and >= 0, got {delta}")
        self.delta = float(delta)
        if self.volume() <= 0:
            raise ValueError(f"delta = {delta} covers the whole state box: X_delta is empty")

    @classmethod
    def of(cls, system, delta: float) -> Region:
        """The region of a system (:class:`drlyap.systems.UncertainSystem`) for a ball radius ``delta``."""
        lo, hi = system.local_box()
        return cls(lo, hi, delta)

    @property
    def n(self) -> int:
        return int(self.lo.shape[0])

    @property
    def scale(self) -> Tensor:
        """Side lengths of the box ``(n,)`` (widths are measured relative to them)."""
        return self.hi - self.lo

    def with_delta(self, delta: float) -> Region:
        return Region(self.lo, self.hi, delta)

    def ball_box(self, inner: float) -> Region:
        """The box of the delta-ball inside the state box, ``[max(lo, -delta), min(hi, delta)]``, minus the open ball
        of radius ``inner``."""
        delta = self.delta
        return Region(torch.maximum(self.lo, torch.full_like(self.lo, -delta)),
                      torch.minimum(self.hi, torch.full_like(self.hi, delta)), inner)

    # ------------------------------------------------------------------ points
    def contains(self, z: Tensor) -> Tensor:
        """``(B,)``: states ``z (B, n)`` in X_delta."""
        return ((z >= self.lo) & (z <= self.hi)).all(-1) & (z.norm(dim=-1) >= self.delta)

    def _outside_ball(self, count: int, draw) -> Tensor:
        """``count`` states kept from batches ``draw(k) -> (k, n)`` of states of the box: those outside the ball."""
        out = torch.empty(0, self.n, dtype=F64)
        for _ in range(100):
            z = draw(2 * count)
            out = torch.cat([out, z[z.norm(dim=-1) >= self.delta]])
            if out.shape[0] >= count:
                return out[:count]
        raise ValueError(f"delta = {self.delta} leaves (almost) nothing of the state box; choose a smaller delta")

    def sample(self, count: int, generator: torch.Generator) -> Tensor:
        """``count`` states ``(count, n)`` uniform in X_delta (rejection sampling)."""
        return self._outside_ball(
            count, lambda k: self.lo + self.scale * torch.rand(k, self.n, generator=generator, dtype=F64))

    def sample_near(self, count: int, generator: torch.Generator) -> Tensor:
        """``count`` states ``(count, n)`` of X_delta spread evenly over the distance from x*.

        A direction uniform on the unit sphere, scaled per coordinate by the box's half-extents on that
        side of x*, times a radius uniform in ``[0, 1]`` (states closer than ``delta`` are redrawn): every
        shell ``rho <= |z / s| < rho + d rho`` gets the same share, whereas a uniform draw gives the shells
        near x* a share ``~ rho^(n-1)`` that vanishes with the dimension (in 4 states, 0.25% of uniform
        states lie within a quarter of the half-width of x*). Every state lies in the box.
        """

        def draw(k: int) -> Tensor:
            d = torch.randn(k, self.n, generator=generator, dtype=F64)
            d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-300)
            rho = torch.rand(k, 1, generator=generator, dtype=F64)
            return rho * torch.where(d >= 0, d * self.hi, -d * self.lo)

        return self._outside_ball(count, draw)

    def sample_faces(self, count: int, generator: torch.Generator) -> Tensor:
        """``count`` states ``(count, n)`` uniform on the boundary of the box: a face (coordinate and side)
        drawn with probability proportional to its area, a uniform state on it."""
        area = (self.scale.prod() / self.scale).repeat(2)  # faces at lo (first n), then at hi
        face = torch.multinomial(area, count, replacement=True, generator=generator)
        axis, upper = face % self.n, face >= self.n
        z = self.lo + self.scale * torch.rand(count, self.n, generator=generator, dtype=F64)
        rows = torch.arange(count)
        z[rows, axis] = torch.where(upper, self.hi[axis], self.lo[axis])
        return z

    def grid(self, per_axis: int = 200, count: int = 40000) -> Tensor:
        """A dense set of states of X_delta: a cell-centred grid for n <= 3, else a scrambled Sobol set of
        ``count`` states plus ``count // 4`` states spread over the distance from x* (:meth:`sample_near`,
        fixed seed): in 4 or more states a uniform set has almost no states near x*."""
        if self.n <= 3:
            per = per_axis if self.n <= 2 else 40
            axes = [self.lo[i] + self.scale[i] * (torch.arange(per, dtype=F64) + 0.5) / per for i in range(self.n)]
            z = torch.cartesian_prod(*axes).reshape(-1, self.n)
        else:
            sobol = torch.quasirandom.SobolEngine(self.n, scramble=True, seed=12345)
            z = self.lo + self.scale * sobol.draw(count, dtype=F64)
            z = torch.cat([z, self.sample_near(count // 4, torch.Generator().manual_seed(12345))])
        return z[z.norm(dim=-1) >= self.delta]

    def project(self, z: Tensor) -> Tensor:
        """Project states ``z (B, n)`` onto X_delta: clamp into the box, push states inside the ball to its sphere."""
        z = torch.minimum(torch.maximum(z, self.lo), self.hi)
        norm = z.norm(dim=-1, keepdim=True)
        inside = (norm < self.delta) & (norm > 0)
        if bool(inside.any()):
            pushed = z * (self.delta * (1 + 1e-9) / norm.clamp_min(1e-300))
            z = torch.where(inside, torch.minimum(torch.maximum(pushed, self.lo), self.hi), z)
        return z

    def distinct(self, z: Tensor, resolution: float = 1e-6) -> Tensor:
        """The states of ``z (B, n)`` without near-duplicates: states that agree to ``resolution`` of the box's width
        in every coordinate count once (the first one is kept, in the order of ``z``)."""
        if z.shape[0] == 0:
            return z
        keys = torch.round(z / (self.scale * resolution)).to(torch.int64)
        _, idx = torch.unique(keys, dim=0, return_inverse=True)
        first = torch.full((int(idx.max()) + 1,), z.shape[0], dtype=torch.int64)
        first = first.scatter_reduce(0, idx, torch.arange(z.shape[0]), reduce="amin")
        return z[first.sort().values]

    def ascent_step(self, z: Tensor, grad: Tensor, rate: float) -> Tensor:
        """One step of projected ascent from states ``z (B, n)`` with gradients ``grad (B, n)``: ``rate`` of the box's
        width along the width-scaled, normalised gradient, then projected onto X_delta (:meth:`project`). Computed in
        the region's float64 (the result is float64 on its device)."""
        z, grad = z.to(self.lo), grad.to(self.lo)
        width = self.scale
        direction = grad * width
        direction = direction / direction.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        return self.project(z + rate * direction * width)

    # ------------------------------------------------------------------ boxes
    def boxes(self, per_axis: Sequence[int] | None = None) -> tuple[Tensor, Tensor]:
        """A grid of boxes ``(lo, hi)``, each ``(C, n)``, covering X_delta (boxes inside the ball dropped)."""
        lo, hi = box_grid(self.lo, self.hi, per_axis or default_grid(self.n))
        return self.keep(lo, hi)

    def meets(self, lo: Tensor, hi: Tensor) -> Tensor:
        """``(B,)``: the boxes that meet X_delta (not entirely inside the open ball)."""
        return ~inside_ball(lo, hi, self.delta)

    def keep(self, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
        """The boxes that meet X_delta (those entirely inside the open ball are dropped)."""
        keep = self.meets(lo, hi)
        return lo[keep], hi[keep]

    def in_region(self, points: Tensor) -> Tensor:
        """``(B,)``: points (e.g. box centres) outside the open ball, with a hair of slack inward."""
        return points.norm(dim=-1) >= self.delta * (1 + 1e-12)

    def volume(self) -> float:
        """Volume of X_delta (exact if the ball lies inside the box, else estimated by sampling)."""
        box = float(self.scale.prod())
        if self.delta <= 0:
            return box
        if bool((-self.lo >= self.delta).all() and (self.hi >= self.delta).all()):
            return box - ball_volume(self.delta, self.n)
        g = torch.Generator().manual_seed(0)
        z = self.lo + self.scale * torch.rand(200_000, self.n, generator=g, dtype=F64)
        return box * float((z.norm(dim=-1) >= self.delta).double().mean())
