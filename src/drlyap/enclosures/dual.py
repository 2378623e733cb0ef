"""Forward-mode dual numbers whose value and derivative are themselves enclosures (intervals, affine forms or
duals): ``Dual(Interval)`` over a box encloses a function's value and gradient there; ``Dual(Dual(Interval))``
adds a second group of directions (parameter derivatives, or the Hessian)."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from drlyap.enclosures.affine import Affine
from drlyap.enclosures.base import Enclosure, fix_index, join, normdim
from drlyap.enclosures.interval import Interval


class Dual(Enclosure, kind="dual"):
    """Forward-mode dual number: value ``v`` and derivative ``d`` (shape ``v.shape + (D,)``, None = 0).

    ``v`` and ``d`` are enclosures of the next level down (an :class:`Interval` or a :class:`Dual`), so a
    ``Dual`` over a box encloses the value and the gradient of a function over that box.
    """

    __slots__ = ("v", "d")

    def __init__(self, v, d=None) -> None:
        self.v = v
        self.d = d

    @property
    def level(self) -> int:  # type: ignore[override]
        return self.v.level + 1

    @property
    def shape(self) -> torch.Size:
        return self.v.shape

    @property
    def device(self) -> torch.device:
        return self.v.device

    def zeros_ext(self, k: int) -> Dual:
        return Dual(self.v.zeros_ext(k), None)

    def __repr__(self) -> str:
        return f"Dual(v={self.v!r}, d={self.d!r})"

    # ---- structure
    def __getitem__(self, idx) -> Dual:
        idx = fix_index(idx, self.ndim)
        return Dual(self.v[idx], None if self.d is None else self.d[idx])

    def unbind(self, dim: int = 0) -> tuple:
        dim = normdim(dim, self.ndim)
        vs = self.v.unbind(dim)
        ds = self.d.unbind(dim) if self.d is not None else (None,) * len(vs)
        return tuple(Dual(a, b) for a, b in zip(vs, ds))

    def unsqueeze(self, dim: int) -> Dual:
        dim = normdim(dim, self.ndim + 1)
        return Dual(self.v.unsqueeze(dim), None if self.d is None else self.d.unsqueeze(dim))

    def transpose(self, a: int, b: int) -> Dual:
        a, b = normdim(a, self.ndim), normdim(b, self.ndim)
        return Dual(self.v.transpose(a, b), None if self.d is None else self.d.transpose(a, b))

    def sum(self, dim: int | None = None) -> Dual:
        if dim is None:
            raise ValueError("sum over all axes of a dual number is not supported; give dim")
        dim = normdim(dim, self.ndim)
        return Dual(self.v.sum(dim), None if self.d is None else self.d.sum(dim))

    # ---- arithmetic
    def _add(self, o: Dual) -> Dual:
        return Dual(self.v + o.v, _dsum(self.d, o.d))

    def _sub(self, o: Dual) -> Dual:
        return Dual(self.v - o.v, _dsum(self.d, None if o.d is None else -o.d))

    def _neg(self) -> Dual:
        return Dual(-self.v, None if self.d is None else -self.d)

    def _mul(self, o: Dual) -> Dual:
        d1 = None if self.d is None else self.d * o.v.unsqueeze(-1)
        d2 = None if o.d is None else self.v.unsqueeze(-1) * o.d
        return Dual(self.v * o.v, _dsum(d1, d2))

    def _div(self, o: Dual) -> Dual:
        if o.d is None:
            return Dual(self.v / o.v, None if self.d is None else self.d / o.v.unsqueeze(-1))
        q = self.v / o.v
        num = -(q.unsqueeze(-1) * o.d) if self.d is None else self.d - q.unsqueeze(-1) * o.d
        return Dual(q, num / o.v.unsqueeze(-1))

    def _chain(self, value, slope) -> Dual:
        return Dual(value, None if self.d is None else slope.unsqueeze(-1) * self.d)

    def square(self) -> Dual:
        return self._chain(self.v.square(), self.v * 2.0)

    def pow_int(self, n: int) -> Dual:
        if n == 0:
            return Dual(self.v.pow_int(0), None)
        return self._chain(self.v.pow_int(n), self.v.pow_int(n - 1) * float(n))

    def abs(self) -> Dual:
        raise TypeError("abs is not differentiable; not supported on dual numbers")

    def sin(self) -> Dual:
        return self._chain(self.v.sin(), self.v.cos())

    def cos(self) -> Dual:
        return self._chain(self.v.cos(), -self.v.sin())

    def tanh(self) -> Dual:
        t = self.v.tanh()
        return self._chain(t, 1.0 - t.square())

    def exp(self) -> Dual:
        e = self.v.exp()
        return self._chain(e, e)

    def sqrt(self) -> Dual:
        s = self.v.sqrt()
        return self._chain(s, 0.5 / s)

    def linear(self, weight: Tensor, bias: Tensor | None = None) -> Dual:
        d = None if self.d is None else self.d.transpose(-1, -2).linear(weight).transpose(-1, -2)
        return Dual(self.v.linear(weight, bias), d)

    def clamp(self, low: Tensor, high: Tensor) -> Dual:
        box = self.base
        if bool(((box.lo > low) & (box.hi < high)).all()):  # strictly inside: the clamp is the identity here
            return self
        if not isinstance(self.v, (Interval, Affine)):
            raise TypeError("clamp is supported at first order only (or where it is provably inactive)")
        return self._chain(self.v.clamp(low, high), self.v.clamp_slope(low, high))

    @property
    def base(self):
        return self.v.base

    def norm(self, dim: int = -1) -> Dual:
        """Euclidean norm along ``dim`` with a Clarke-gradient enclosure (sound also where the vector is 0); first
        order only (over an interval or an affine form)."""
        if not isinstance(self.v, (Interval, Affine)):
            raise TypeError("norm is supported on intervals, affine forms and first-order duals")
        dim = normdim(dim, self.ndim)
        value = self.v.square().sum(dim).sqrt()
        if self.d is None:
            return Dual(value, None)
        # d||x|| = (x / ||x||) . dx, with x / ||x|| in [-1, 1] componentwise (the unit ball at x = 0)
        xv, val = self.v.to_interval(), value.to_interval()
        unit = Interval(-torch.ones_like(xv.lo), torch.ones_like(xv.lo))
        pos = val.lo.unsqueeze(dim) > 0
        safe = Interval(torch.where(pos, val.lo.unsqueeze(dim), 1.0), torch.where(pos, val.hi.unsqueeze(dim), 1.0))
        q = (xv / safe).intersect(-1.0, 1.0)
        q = Interval(torch.where(pos, q.lo, unit.lo), torch.where(pos, q.hi, unit.hi))
        return Dual(value, (q.unsqueeze(-1) * self.d).sum(dim))

    @staticmethod
    def _join(items: list, dim: int, fn: Callable) -> Dual:
        """``torch.stack`` or ``torch.cat`` (``fn``) of duals of one level along ``dim``."""
        d = normdim(dim, items[0].ndim + (1 if fn is torch.stack else 0))
        dirs = [s.d.shape[-1] for s in items if s.d is not None]
        if not dirs:
            return Dual(join([s.v for s in items], d, fn), None)
        k = dirs[0]
        return Dual(join([s.v for s in items], d, fn),
                    join([s.d if s.d is not None else s.v.zeros_ext(k) for s in items], d, fn))


def _dsum(a, b):
    if a is None:
        return b
    if b is None:
        return a
    return a + b
