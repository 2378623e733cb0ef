"""Batched real intervals ``[lo, hi]``, float64, outward rounded: every computed endpoint is widened by an error
bound of the floating-point operation that produced it, so it encloses the real value."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from drlyap.enclosures.base import Enclosure
from drlyap.enclosures.rounding import EPS, F64, REL1, RELT, TINY, as_f64, round_down, round_up


class Interval(Enclosure, kind="interval"):
    """A batch of real intervals ``[lo, hi]`` (float64 tensors of one shape), outward rounded."""

    __slots__ = ("lo", "hi")
    level = 0

    def __init__(self, lo: Tensor, hi: Tensor | None = None) -> None:
        self.lo = lo
        self.hi = lo if hi is None else hi

    @staticmethod
    def const(x, device: torch.device | None = None) -> Interval:
        """The exact interval ``[x, x]`` of a tensor or number (on ``device``: None, a tensor's own, else the CPU)."""
        if isinstance(x, Interval):
            return x
        t = as_f64(x, device)
        return Interval(t, t)

    @property
    def shape(self) -> torch.Size:
        return self.lo.shape

    @property
    def mid(self) -> Tensor:
        return (self.lo + self.hi) / 2

    def zeros_ext(self, k: int) -> Interval:
        z = torch.zeros(*self.shape, k, dtype=F64, device=self.lo.device)
        return Interval(z, z)

    @property
    def device(self) -> torch.device:
        return self.lo.device

    def contains(self, x: Tensor) -> Tensor:
        return (self.lo <= x) & (x <= self.hi)

    def to_interval(self) -> Interval:
        return self

    def __repr__(self) -> str:
        return f"Interval(lo={self.lo}, hi={self.hi})"

    # ---- structure
    def __getitem__(self, idx) -> Interval:
        return Interval(self.lo[idx], self.hi[idx])

    def unbind(self, dim: int = 0) -> tuple:
        return tuple(Interval(a, b) for a, b in zip(self.lo.unbind(dim), self.hi.unbind(dim)))

    def unsqueeze(self, dim: int) -> Interval:
        return Interval(self.lo.unsqueeze(dim), self.hi.unsqueeze(dim))

    def transpose(self, a: int, b: int) -> Interval:
        return Interval(self.lo.transpose(a, b), self.hi.transpose(a, b))

    def expand(self, *shape) -> Interval:
        return Interval(self.lo.expand(*shape), self.hi.expand(*shape))

    def reshape(self, *shape) -> Interval:
        return Interval(self.lo.reshape(*shape), self.hi.reshape(*shape))

    # ---- arithmetic
    def _add(self, o: Interval) -> Interval:
        return Interval(round_down(self.lo + o.lo, REL1), round_up(self.hi + o.hi, REL1))

    def _sub(self, o: Interval) -> Interval:
        return Interval(round_down(self.lo - o.hi, REL1), round_up(self.hi - o.lo, REL1))

    def _neg(self) -> Interval:
        return Interval(-self.hi, -self.lo)

    def _mul(self, o: Interval) -> Interval:
        if o.lo is o.hi or self.lo is self.hi:  # a point factor (a constant): two products suffice
            a, c = (self, o.lo) if o.lo is o.hi else (o, self.lo)
            p1, p2 = a.lo * c, a.hi * c
            return Interval(round_down(torch.minimum(p1, p2), REL1), round_up(torch.maximum(p1, p2), REL1))
        p = torch.stack(torch.broadcast_tensors(self.lo * o.lo, self.lo * o.hi, self.hi * o.lo, self.hi * o.hi))
        return Interval(round_down(p.amin(0), REL1), round_up(p.amax(0), REL1))

    def reciprocal(self) -> Interval:
        if not bool(((self.lo > 0) | (self.hi < 0)).all()):
            raise ValueError("interval division by an interval that contains 0")
        return Interval(round_down(1.0 / self.hi, REL1), round_up(1.0 / self.lo, REL1))

    def _div(self, o: Interval) -> Interval:
        return self._mul(o.reciprocal())

    def square(self) -> Interval:
        a, b = self.lo * self.lo, self.hi * self.hi
        lo = torch.where((self.lo <= 0) & (self.hi >= 0), torch.zeros_like(a), torch.minimum(a, b))
        return Interval(torch.clamp(round_down(lo, REL1), min=0.0), round_up(torch.maximum(a, b), REL1))

    def abs(self) -> Interval:
        a, b = self.lo.abs(), self.hi.abs()
        lo = torch.where((self.lo <= 0) & (self.hi >= 0), torch.zeros_like(a), torch.minimum(a, b))
        return Interval(lo, torch.maximum(a, b))

    def pow_int(self, n: int) -> Interval:
        if n == 0:
            one = torch.ones_like(self.lo)
            return Interval(one, one)
        if n == 1:
            return self
        if n == 2:
            return self.square()
        base = self.abs() if n % 2 == 0 else self
        rel = 2 * n * EPS
        return Interval(round_down(base.lo ** n, rel), round_up(base.hi ** n, rel))

    def sqrt(self) -> Interval:
        lo = torch.clamp(self.lo, min=0.0)
        return Interval(torch.clamp(round_down(torch.sqrt(lo), RELT), min=0.0),
                        round_up(torch.sqrt(torch.clamp(self.hi, min=0.0)), RELT))

    def exp(self) -> Interval:
        return Interval(torch.clamp(round_down(torch.exp(self.lo), RELT), min=0.0), round_up(torch.exp(self.hi), RELT))

    def tanh(self) -> Interval:
        return Interval(torch.clamp(round_down(torch.tanh(self.lo), RELT), min=-1.0),
                        torch.clamp(round_up(torch.tanh(self.hi), RELT), max=1.0))

    def _periodic(self, fn: Callable, max_at: float, min_at: float) -> Interval:
        a, b = fn(self.lo), fn(self.hi)
        lo = round_down(torch.minimum(a, b), RELT)
        hi = round_up(torch.maximum(a, b), RELT)
        two_pi = 2 * math.pi
        slack = 1e-9

        def hits(at: float) -> Tensor:  # (conservatively) is at + 2 k pi inside [lo, hi] for some integer k?
            t_lo = (self.lo - at) / two_pi - slack * (1 + self.lo.abs())
            t_hi = (self.hi - at) / two_pi + slack * (1 + self.hi.abs())
            return torch.floor(t_hi) >= torch.ceil(t_lo)

        wide = (self.hi - self.lo) >= two_pi - 1e-9
        hi = torch.where(wide | hits(max_at), torch.ones_like(hi), torch.clamp(hi, max=1.0))
        lo = torch.where(wide | hits(min_at), -torch.ones_like(lo), torch.clamp(lo, min=-1.0))
        return Interval(lo, hi)

    def sin(self) -> Interval:
        return self._periodic(torch.sin, math.pi / 2, -math.pi / 2)

    def cos(self) -> Interval:
        return self._periodic(torch.cos, 0.0, math.pi)

    def sum(self, dim: int | None = None) -> Interval:
        if dim is None:
            return self.reshape(-1).sum(0)
        k = self.lo.shape[dim]
        mag = torch.maximum(self.lo.abs(), self.hi.abs()).sum(dim)
        rel = 2 * (k + 2) * EPS
        return Interval(round_down(self.lo.sum(dim), rel, mag), round_up(self.hi.sum(dim), rel, mag))

    def linear(self, weight: Tensor, bias: Tensor | None = None) -> Interval:
        """``x @ weight.T + bias`` along the last axis, with a constant (exact) ``weight (out, in)``."""
        mid = (self.lo + self.hi) / 2
        rad = round_up(torch.maximum(self.hi - mid, mid - self.lo), REL1)
        out_mid = mid @ weight.T
        w_abs = weight.abs().T
        out_rad = rad @ w_abs
        mag = mid.abs() @ w_abs + out_rad
        if bias is not None:
            out_mid = out_mid + bias
            mag = mag + bias.abs()
        rel = 4 * (weight.shape[1] + 4) * EPS
        pad = rel * mag + TINY
        return Interval(out_mid - out_rad - pad, out_mid + out_rad + pad)

    def clamp(self, low: Tensor, high: Tensor) -> Interval:
        return Interval(torch.minimum(torch.maximum(self.lo, low), high), torch.minimum(torch.maximum(self.hi, low), high))

    def clamp_slope(self, low: Tensor, high: Tensor) -> Interval:
        """Enclosure of the (Clarke) derivative of ``clamp(., low, high)`` over the interval: 1, 0 or [0, 1]."""
        inside = (self.lo > low) & (self.hi < high)
        outside = (self.hi < low) | (self.lo > high)
        lo = torch.where(inside, 1.0, 0.0).to(F64)
        hi = torch.where(outside, 0.0, 1.0).to(F64)
        return Interval(lo, hi)

    def hull(self, other: Interval) -> Interval:
        return Interval(torch.minimum(self.lo, other.lo), torch.maximum(self.hi, other.hi))

    def intersect(self, low: float, high: float) -> Interval:
        return Interval(torch.clamp(self.lo, min=low, max=high), torch.clamp(self.hi, min=low, max=high))

    def norm(self, dim: int = -1) -> Interval:
        """Euclidean norm along ``dim``."""
        return self.square().sum(dim).sqrt()

    @staticmethod
    def _join(items: list, dim: int, fn) -> Interval:
        return Interval(fn([s.lo for s in items], dim), fn([s.hi for s in items], dim))
