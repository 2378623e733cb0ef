"""The affine forms' nonlinear functions (:class:`~drlyap.enclosures.affine.Affine` inherits them): a second-order
Taylor form about the middle of the argument's range (``tanh sin cos exp`` and the reciprocal, third-order
remainder), or where the argument is wide a secant form (``f(x) = lam x + err``: a convex function's chord, a
piecewise-linear function's kinks, the minimum-range slope); both outward rounded."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Self

import torch
from torch import Tensor

from drlyap.enclosures.interval import Interval
from drlyap.enclosures.rounding import REL1, as_f64, sum_up
from drlyap.enclosures.univariate import convex_error, drecip, dsqrt, dtanh, secant


class AffineFunctions:
    """The nonlinear functions of :class:`~drlyap.enclosures.affine.Affine` (see the module docstring)."""

    __slots__ = ()

    def reciprocal(self) -> Self:
        iv = self.to_interval()
        if not bool(((iv.lo > 0) | (iv.hi < 0)).all()):
            raise ValueError("affine division by a form whose range contains 0")
        fallback = iv.reciprocal()
        if self.g is None:
            return self.const(fallback)

        def first() -> Self:
            # on the positive range [a, b] of |x|, 1/y is convex; 1/x = s (1/y) with y = s x, s = sign: so
            # 1/x = lam x + s e(y) with the slope lam and error e of 1/y
            neg = iv.hi < 0
            a, b = torch.where(neg, -iv.hi, iv.lo), torch.where(neg, -iv.lo, iv.hi)
            lam = -1.0 / (a * b)  # the secant of 1/y over [a, b]
            err = convex_error(Interval.reciprocal, drecip, a, b, lam, torch.clamp(torch.sqrt(a * b), a, b))
            return self._scale_shift(lam, Interval(torch.where(neg, -err.hi, err.lo), torch.where(neg, -err.lo, err.hi)))

        def at(c: Interval) -> tuple[Interval, Interval, Interval]:  # (1/x)' = -1/x^2, (1/x)'' / 2 = 1/x^3
            rc = c.reciprocal()
            rc2 = rc.square()
            return rc, -rc2, rc2 * rc

        second = self._second_order(at, fallback.square().square() * -6.0)
        near = torch.minimum(iv.lo.abs(), iv.hi.abs())
        return self._pick(second, first, (iv.hi - iv.lo) > near * 0.5)._guard(fallback)

    def _second_order(self, at: Callable[[Interval], tuple[Interval, Interval, Interval]], d3: Interval) -> Self:
        """The second-order Taylor form about ``c' = c + mid(H)`` (``H``: the quadratic part plus the remainder,
        whose range about ``c'`` is centred at 0; ``c'`` is kept inside the range of ``x``, over which ``d3``
        holds), with ``d = x - c'``::

            f(x) = f(c') + f'(c') d + f''(c') d^2 / 2 + f'''(xi) d^3 / 6

        ``d = L + H'`` (linear part; ``H' = H + c - c'``): ``f'(c') (L + Q)`` and ``f''(c') L^2 / 2`` are kept
        (linear and quadratic parts), everything else is bounded by intervals. ``at(t)``: enclosures of ``f(t),
        f'(t), f''(t) / 2`` at the points ``t``; ``d3``: of ``f'''`` over the range (all outward rounded)."""
        higher, lin = self._higher(), self._lin()
        cp, shift = self._about_middle(higher, self.to_interval())  # where d3 holds
        f0, s1, s2 = at(Interval.const(cp))
        a1, a2 = s1.mid, s2.mid
        dev, higher = self._dev() + shift, higher + shift
        a1_, a2_ = Interval.const(a1), Interval.const(a2)
        rest_sq = Interval(-lin, lin) * higher * 2.0 + higher.square()  # d^2 - L^2
        const = (f0 + (s1 - a1_) * dev + a1_ * (self.r + shift) + (s2 - a2_) * dev.square() + a2_ * rest_sq
                 + d3 * dev.pow_int(3) * (1.0 / 6.0))
        g = a1.unsqueeze(-1) * self.g
        q = (a2.unsqueeze(-1) * self.g).unsqueeze(-1) * self.g.unsqueeze(-2)
        if self.q is not None:
            q = q + a1[..., None, None] * self.q
        return self._centred(const, g, REL1 * sum_up(g.abs()) + self._qpad(q, 4 * REL1), q)

    @staticmethod
    def _pick(second: AffineFunctions, first: Callable[[], AffineFunctions], wide: Tensor) -> AffineFunctions:
        """``second`` (a second-order form of a function), or where an input is ``wide`` and the second-order
        remainder is at least as wide as the first-order form's part above first order, ``first()`` (elsewhere the
        third-order remainder is the smaller). Each entry's choice is its own, so that a box's bound does not
        depend on the boxes bounded beside it (nor on the number of workers)."""
        if not bool(wide.any()):
            return second
        lin1 = first()
        h1 = lin1._higher()
        return type(second)._where(~wide | ((second.r.hi - second.r.lo) < (h1.hi - h1.lo)), second, lin1)

    def _convex_fn(self, f: Callable, df: Callable, root: Callable, fallback: Interval, convex: bool = True,
                   f_point: Callable | None = None) -> Self:
        """``f`` convex (or concave) on the range: secant slope, error bound by :func:`convex_error`."""
        iv = self.to_interval()
        if self.g is None:
            return self.const(fallback)
        a, b = iv.lo, iv.hi
        fp = f_point if f_point is not None else (lambda t: f(Interval.const(t)).mid)
        lam = secant(fp, lambda t: df(Interval.const(t)).mid, a, b)
        err = convex_error(f, df, a, b, lam, torch.clamp(root(lam), a, b), convex)
        return self._scale_shift(lam, err)._guard(fallback)

    def exp(self) -> Self:
        iv = self.to_interval()
        fallback = iv.exp()
        if self.g is None:
            return self.const(fallback)
        second = self._second_order(lambda t: (t.exp(), t.exp(), t.exp() * 0.5), fallback)
        return self._pick(second, lambda: self._convex_fn(Interval.exp, Interval.exp, torch.log, fallback,
                                                            f_point=torch.exp), (iv.hi - iv.lo) > 1.0)._guard(fallback)

    def sqrt(self) -> Self:
        """Square root of ``max(x, 0)`` (as :meth:`Interval.sqrt`: the argument is taken to be non-negative)."""
        iv = self.to_interval()
        fallback = iv.sqrt()
        if self.g is None:
            return self.const(fallback)
        a, b = torch.clamp(iv.lo, min=0.0), torch.clamp(iv.hi, min=0.0)
        wide = b > a
        lam = torch.where(wide, (torch.sqrt(b) - torch.sqrt(a)) / torch.where(wide, b - a, 1.0), 0.0)
        xt = torch.clamp(torch.where(lam > 0, 0.25 / (lam * lam), b), a, b)
        err = convex_error(Interval.sqrt, dsqrt, a, b, lam, xt, convex=False)
        zero = b <= 0  # the range is {0}
        err = Interval(torch.where(zero, 0.0, err.lo), torch.where(zero, 0.0, err.hi))
        return self._scale_shift(lam, err)._guard(fallback)

    def tanh(self) -> Self:
        iv = self.to_interval()
        fallback = iv.tanh()
        if self.g is None:
            return self.const(fallback)

        def first() -> Self:
            a, b = iv.lo, iv.hi
            lam = torch.clamp(secant(torch.tanh, lambda t: 1.0 - torch.tanh(t) ** 2, a, b), 0.0, 1.0)
            root = torch.atanh(torch.sqrt(torch.clamp(1.0 - lam, 0.0, 1.0)))  # tanh'(+-root) = lam
            zero = torch.zeros_like(a)
            q1 = torch.maximum(torch.minimum(b, zero), a)  # tanh is convex on [a, q1] (x <= 0, or the point a)
            p2 = torch.minimum(torch.maximum(a, zero), b)  # and concave on [p2, b]
            e1 = convex_error(Interval.tanh, dtanh, a, q1, lam, torch.clamp(-root, a, q1), convex=True)
            e2 = convex_error(Interval.tanh, dtanh, p2, b, lam, torch.clamp(root, p2, b), convex=False)
            return self._scale_shift(lam, e1.hull(e2))

        def at(c: Interval) -> tuple[Interval, Interval, Interval]:  # tanh' = 1 - t^2, tanh'' / 2 = -t (1 - t^2)
            t = c.tanh()
            s1 = 1.0 - t.square()
            return t, s1, -(t * s1)

        t2 = fallback.square()  # tanh''' = -2 (1 - t^2)(1 - 3 t^2) over the range
        second = self._second_order(at, (1.0 - t2) * (1.0 - t2 * 3.0) * -2.0)
        return self._pick(second, first, (iv.hi - iv.lo) > 1.0)._guard(fallback)

    def _taylor2(self, f: Callable, df: Callable, d2f: Callable, d3f: Callable, fallback: Interval) -> Self:
        """The second-order form (:meth:`_second_order`, ``d3f`` the third derivative); where the range is wide,
        or where narrower, the midpoint slope with a second-order Lagrange remainder:
        ``f(x) = f(m) + f'(m)(x - m) + f''(xi)(x - m)^2 / 2`` with ``f''`` enclosed over the range."""
        iv = self.to_interval()
        if self.g is None:
            return self.const(fallback)

        def first() -> Self:
            m = iv.mid
            mm = Interval.const(m)
            slope = df(mm)
            lam = slope.mid
            dev = iv - mm
            err = f(mm) + (slope - Interval.const(lam)) * dev + d2f(iv) * dev.square() * 0.5  # f(x) - lam (x - m)
            return self._scale_shift(lam, err - Interval.const(lam) * mm)

        second = self._second_order(lambda t: (f(t), df(t), d2f(t) * 0.5), d3f(iv))
        return self._pick(second, first, (iv.hi - iv.lo) > 1.0)._guard(fallback)

    def sin(self) -> Self:
        return self._taylor2(Interval.sin, Interval.cos, lambda x: -x.sin(), lambda x: -x.cos(),
                             self.to_interval().sin())

    def cos(self) -> Self:
        return self._taylor2(Interval.cos, lambda x: -x.sin(), lambda x: -x.cos(), Interval.sin,
                             self.to_interval().cos())

    def _piecewise_linear(self, f: Callable, breaks: Sequence[Tensor], fallback: Interval) -> Self:
        """``f`` continuous and piecewise linear with kinks at ``breaks`` (exact in float64): the error of
        the secant is piecewise linear too, so its range is its hull at the ends and the kinks in range."""
        iv = self.to_interval()
        if self.g is None:
            return self.const(fallback)
        a, b = iv.lo, iv.hi
        lam = secant(f, lambda t: torch.zeros_like(t), a, b)
        lam_ = Interval.const(lam)
        err = None
        for t in [a, b, *(torch.clamp(br.expand(a.shape), a, b) for br in breaks)]:
            e = Interval.const(f(t)) - lam_ * Interval.const(t)
            err = e if err is None else err.hull(e)
        return self._scale_shift(lam, err)._guard(fallback)

    def abs(self) -> Self:
        iv = self.to_interval()
        out = self._piecewise_linear(torch.abs, [torch.zeros_like(iv.lo)], iv.abs())
        if self.g is None:
            return out
        return self._where(iv.lo >= 0, self, self._where(iv.hi <= 0, -self, out))

    def clamp(self, low: Tensor, high: Tensor) -> Self:
        iv = self.to_interval()
        low, high = as_f64(low).to(iv.lo.device), as_f64(high).to(iv.lo.device)
        out = self._piecewise_linear(lambda t: torch.clamp(t, low, high), [low, high], iv.clamp(low, high))
        if self.g is None:
            return out
        return self._where((iv.lo >= low) & (iv.hi <= high), self, out)  # inactive: the identity, exactly

    def clamp_slope(self, low: Tensor, high: Tensor) -> Interval:
        """Enclosure of the (Clarke) derivative of ``clamp(., low, high)`` over the range (see :class:`Interval`)."""
        return self.to_interval().clamp_slope(low, high)
