"""The checker's second-order forms: enclosures that keep how every quantity depends on the box's coordinates to
second order, so that ``V``, its gradient and the dynamics are bounded with their correlations (an interval or a
mean-value bound loses them). Written apart from :mod:`drlyap.enclosures`, on the checker's own rounding rules
(:mod:`.arith`).

A form of shape ``S`` over boxes with ``k`` coordinates is ``c + l . e + e^T q e + r`` for one ``e in [-1, 1]^k`` per
box (shared by every form of the same box): ``c (S)``, ``l (S, k)``, ``q (S, k, k)`` and a remainder interval ``r``
(an :class:`~drlyap.checker.arith.Iv` of shape ``S``). Every operation returns a form that holds each real value
the operation can take:

* linear operations act on ``c``, ``l``, ``q`` exactly; a product keeps ``c1 c2``, ``c1 l2 + c2 l1`` and the
  quadratic part ``l1 l2^T + c1 q2 + c2 q1``, and bounds the rest (cubic, quartic and remainder terms) with the
  ranges of its parts in interval arithmetic, each form first written about the midpoint of its part above first
  order (a square's quadratic part is one-signed: centred, the products with it are half as wide);
* a function ``f`` of a form with range ``[a, b]`` is ``s x + g`` with ``g`` an interval holding ``f(x) - s x`` on
  ``[a, b]`` (``tanh``: the minimum-range slope; ``sqrt``: the chord, concave remainder; ``clamp``: the chord,
  piecewise-linear remainder; ``1/x``: the midpoint's derivative and a second-derivative bound), or a second-order
  Taylor form at the midpoint with a third-derivative bound (``tanh sin cos exp``); where the interval enclosure of
  ``f`` is three times narrower, that interval as a constant form;
* the range of ``l . e + e^T q e`` is bounded by :func:`.quadratic.quad_max` (every corner of the cube, after replacing the
  concave diagonal terms by tangents; for final bounds also a dual bound through a semidefinite ``t I - q``), and
  inside products by the cheaper :func:`_quick_span`;
* rounding: the coefficients are computed with round-to-nearest, and the remainder grows by a bound of their
  rounding errors (``(m + 2) eps`` times the magnitudes of the ``m`` terms each was summed from); the remainder's
  own arithmetic is outward rounded. A NaN or infinity anywhere makes the remainder the whole line.
"""

from __future__ import annotations

import torch
from torch import Tensor

from drlyap.checker.arith import EPS, F64, INF, TINY, Iv, _down, _Ops, _t, _up
from drlyap.checker.quadratic import _quick_spans, quad_max, quad_span

PICK_RATIO = 3.0
"""A function's interval enclosure replaces its form where it is this many times narrower: the form keeps the
dependence on the box (a norm whose argument reaches 0 is worth a form twice as wide as its interval, once the
residual sums it with the rest)."""
BEST_RATIO = 1.5
"""Of two forms of a function, the one with the smaller remainder unless it is this many times wider."""


def _nonneg_sum(*terms: Tensor) -> Tensor:
    """An upper bound of the real sum of nonnegative float terms (each already an upper bound)."""
    total = terms[0]
    for t in terms[1:]:
        total = total + t
    return _up(total * (1 + (len(terms) + 2) * EPS) + TINY)


class Af(_Ops):
    """Second-order forms ``c + l . e + e^T q e + r`` over a batch of boxes (see the module's docstring)."""

    __slots__ = ("c", "l", "q", "r", "_range", "_qabs")
    level = 0
    affine = True

    def __init__(self, c: Tensor, lin: Tensor, q: Tensor, r: Iv, qabs: Tensor | None = None) -> None:
        """``qabs``: ``sum |q_ij|`` per element where the caller has it (kept: pads and cheap bounds read it)."""
        total = c + lin.sum(-1) + (q.flatten(-2).sum(-1) if qabs is None else qabs)  # NaN or inf stays non-finite
        bad = ~torch.isfinite(total) | torch.isnan(r.lo) | torch.isnan(r.hi)
        self._range: Iv | None = None
        self.c, self.l, self.q, self.r, self._qabs = c, lin, q, r, qabs
        if bool(bad.any()):
            self.c = torch.where(bad, 0.0, c)
            self.l = torch.where(bad[..., None], 0.0, lin)
            self.q = torch.where(bad[..., None, None], 0.0, q)
            self.r = Iv(torch.where(bad, -INF, r.lo), torch.where(bad, INF, r.hi))
            self._qabs = None

    # ---- construction
    @staticmethod
    def seed(lo: Tensor, hi: Tensor) -> Af:
        """The boxes ``[lo, hi] (B, k)`` themselves: coordinate ``i`` is ``mid_i + rad_i e_i`` (``rad`` rounded up,
        so that the form holds the whole box)."""
        lo, hi = _t(lo), _t(hi)
        mid = (lo + hi) / 2
        rad = _up(torch.maximum(hi - mid, mid - lo))
        k = lo.shape[-1]
        return Af(mid, torch.diag_embed(rad), torch.zeros(*mid.shape, k, k, dtype=F64, device=mid.device),
                  Iv.point(torch.zeros_like(mid)))

    def constant(self, x) -> Af:
        """``x`` (an :class:`Iv`, a tensor or a number) as a form of this form's ``k``: its midpoint, and the rest
        as the remainder."""
        if isinstance(x, Af):
            return x
        x = x if isinstance(x, Iv) else Iv.point(x)
        k = self.l.shape[-1]
        mid = (x.lo + x.hi) / 2
        mid = torch.where(torch.isfinite(mid), mid, 0.0)
        return Af(mid, torch.zeros(*mid.shape, k, dtype=F64, device=mid.device),
                  torch.zeros(*mid.shape, k, k, dtype=F64, device=mid.device), x - Iv.point(mid))

    def promote(self, x) -> Af:
        return self.constant(x)

    # ---- reading
    @property
    def shape(self):
        return self.c.shape

    def _lmag(self) -> Tensor:
        return self.l.abs().sum(-1)

    def _qmag(self) -> Tensor:
        if self._qabs is None:
            self._qabs = self.q.abs().flatten(-2).sum(-1)
        return self._qabs

    def _span(self, dual: bool = False) -> Iv:
        """Bounds of ``l . e + e^T q e`` over ``e in [-1, 1]^k`` (:func:`quad_max` of it and of its negation)."""
        if not dual:
            return quad_span(self.l, self.q, self._qmag())
        return Iv(-quad_max(-self.l, -self.q, True), quad_max(self.l, self.q, True))

    def interval(self, dual: bool = False) -> Iv:
        """The form's range; ``dual``: with the tighter, costlier bound of its quadratic part (:func:`quad_max`)."""
        if dual:
            return Iv.point(self.c) + self._span(True) + self.r
        if self._range is None:  # forms are not changed once made: their range is kept
            self._range = Iv.point(self.c) + self._span() + self.r
        return self._range

    @property
    def lo(self) -> Tensor:
        return self.interval().lo

    @property
    def hi(self) -> Tensor:
        return self.interval().hi

    def rough_width(self) -> Tensor:
        """An upper bound of the width from magnitudes alone (cheap: what chooses between forms, not a bound)."""
        return 2 * (self._lmag() + self._qmag()) + (self.r.hi - self.r.lo)

    def mag(self) -> Tensor:
        return self.interval().mag()

    def __repr__(self) -> str:
        return f"Af(c={self.c}, l={self.l}, q={self.q}, r={self.r})"

    # ---- shape (``l`` has one trailing axis more than ``c``, ``q`` two)
    @staticmethod
    def _dims(dim: int) -> tuple[int, int]:
        return (dim - 1, dim - 2) if dim < 0 else (dim, dim)

    def __getitem__(self, idx) -> Af:
        tup = idx if isinstance(idx, tuple) else (idx,)
        ellipsis = any(t is Ellipsis for t in tup)
        lidx = tup + (slice(None),) if ellipsis else tup
        qidx = tup + (slice(None), slice(None)) if ellipsis else tup
        return Af(self.c[idx], self.l[lidx], self.q[qidx], self.r[idx])

    def unbind(self, dim: int = 0) -> tuple:
        ld, qd = self._dims(dim)
        return tuple(Af(c, lin, q, r) for c, lin, q, r in
                     zip(self.c.unbind(dim), self.l.unbind(ld), self.q.unbind(qd), self.r.unbind(dim)))

    def unsqueeze(self, dim: int) -> Af:
        ld, qd = self._dims(dim)
        return Af(self.c.unsqueeze(dim), self.l.unsqueeze(ld), self.q.unsqueeze(qd), self.r.unsqueeze(dim))

    @staticmethod
    def join(items: list[Af], dim: int, new_axis: bool) -> Af:
        f = torch.stack if new_axis else torch.cat
        ld, qd = Af._dims(dim)
        r = Iv(f([x.r.lo for x in items], dim), f([x.r.hi for x in items], dim))
        return Af(f([x.c for x in items], dim), f([x.l for x in items], ld), f([x.q for x in items], qd), r)

    # ---- linear operations: the coefficients in float64, their rounding errors into the remainder
    @staticmethod
    def _padded(r: Iv, pad: Tensor) -> Iv:
        pad = _up(pad + TINY)
        return Iv(_down(r.lo - pad), _up(r.hi + pad))

    @staticmethod
    def _mags(c: Tensor, lin: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
        """``|c| + |l|_1 + |q|_1`` and ``|q|_1``."""
        qabs = q.abs().flatten(-2).sum(-1)
        return c.abs() + lin.abs().sum(-1) + qabs, qabs

    def neg(self) -> Af:
        return Af(-self.c, -self.l, -self.q, -self.r)

    def add(self, o) -> Af:
        if isinstance(o, Af):
            c, lin, q = self.c + o.c, self.l + o.l, self.q + o.q
            mag, qabs = self._mags(c, lin, q)
            return Af(c, lin, q, self._padded(self.r + o.r, 2 * EPS * mag), qabs)
        o = o if isinstance(o, Iv) else Iv.point(o)
        mid = (o.lo + o.hi) / 2
        mid = torch.where(torch.isfinite(mid), mid, 0.0)
        c = self.c + mid  # the constant's midpoint joins c; the rest, and c's rounding, the remainder
        return Af(c, self.l, self.q, self._padded(self.r + (o - Iv.point(mid)), EPS * c.abs()))

    def sub(self, o) -> Af:
        return self.add(o.neg() if isinstance(o, (Af, Iv)) else -_t(o))

    def _scale(self, t: Tensor) -> Af:
        """Times a float tensor ``t`` (broadcast to the shape)."""
        c, lin, q = self.c * t, self.l * t[..., None], self.q * t[..., None, None]
        mag, qabs = self._mags(c, lin, q)
        return Af(c, lin, q, self._padded(self.r * Iv.point(t), 2 * EPS * mag), qabs)

    def mul(self, o) -> Af:
        """The product of ``x = cx + Lx + Qx + Rx`` (constant, linear, quadratic, remainder) and ``y``: ``cx cy``,
        ``cx Ly + cy Lx``, ``cx Qy + cy Qx + Lx Ly``, and the remainder
        ``cx Ry + cy Rx + Lx (Qy + Ry) + (Qx + Rx) (y - cy)`` bounded with the ranges of its parts, each form written
        about the midpoint of its ``Q + R`` first (:meth:`_centred`)."""
        if not isinstance(o, (Af, Iv)):
            return self._scale(_t(o))
        if isinstance(o, Iv) and bool(torch.equal(o.lo, o.hi)):
            return self._scale(o.lo)
        y = self if o is self else self.constant(o)
        q2, lq2 = _quick_spans(y.l, y.q, y._qmag())  # the parts' ranges by the cheap bound: a hot path
        q1 = q2 if y is self else _quick_spans(self.l, self.q, self._qmag(), with_lin=False)[0]
        x = self._centred(q1)
        return x._product(x if y is self else y._centred(q2), q1, q2, lq2)

    def _centred(self, q_span: Iv) -> Af:
        """The same values with the midpoint of the part above first order (``e^T q e + r``; ``q_span``: the range of
        ``e^T q e``) moved into ``c``."""
        higher = q_span + self.r
        mid = (higher.lo + higher.hi) / 2
        c = self.c + torch.where(torch.isfinite(mid), mid, 0.0)
        return Af(c, self.l, self.q, self.r + (Iv.point(self.c) - Iv.point(c)), self._qabs)

    def _product(self, o: Af, q1: Iv, q2: Iv, lq2: Iv) -> Af:
        """``self * o`` (see :meth:`mul`), given the ranges of ``e^T q e`` of both and of ``o``'s ``l . e + e^T q e``
        (which centring leaves as they are)."""
        c1, c2 = self.c, o.c
        c = c1 * c2
        lin = c1[..., None] * o.l + c2[..., None] * self.l
        q = self.l[..., :, None] * o.l[..., None, :] + c1[..., None, None] * o.q + c2[..., None, None] * self.q
        a1 = self._lmag()
        rest = (Iv.point(c1) * o.r + Iv.point(c2) * self.r + Iv(-a1, a1) * (q2 + o.r) + (q1 + self.r) * (lq2 + o.r))
        mag, qabs = self._mags(c, lin, q)
        return Af(c, lin, q, self._padded(rest, 4 * EPS * mag), qabs)

    def square(self) -> Af:
        return self.mul(self)

    def linear(self, weight: Tensor, bias: Tensor | None = None) -> Af:
        """``x W^T + b`` for ``x (..., a)`` and a constant ``W (o, a)``."""
        a, k = weight.shape[1], self.l.shape[-1]
        wa = weight.abs()
        c = self.c @ weight.T
        mag = self.c.abs() @ wa.T
        if bias is not None:
            c = c + bias
            mag = mag + bias.abs()
        lin = torch.matmul(weight, self.l)
        flat = self.q.reshape(*self.q.shape[:-2], k * k)
        q = torch.matmul(weight, flat).reshape(*flat.shape[:-2], weight.shape[0], k, k)
        mag = mag + (self._lmag() + self._qmag()) @ wa.T
        return Af(c, lin, q, self._padded(self.r.linear(weight), (a + 3) * EPS * mag))

    def sum(self, dim=None) -> Af:
        k = self.l.shape[-1]
        if dim is None:
            flat = Af(self.c.reshape(-1), self.l.reshape(-1, k), self.q.reshape(-1, k, k),
                      Iv(self.r.lo.reshape(-1), self.r.hi.reshape(-1)))
            return flat.sum(0)
        count = self.c.shape[dim]
        ld, qd = self._dims(dim)
        c, lin, q = self.c.sum(dim), self.l.sum(ld), self.q.sum(qd)
        mag = (self.c.abs() + self._lmag() + self._qmag()).sum(dim)
        return Af(c, lin, q, self._padded(self.r.sum(dim), (count + 2) * EPS * mag))

    # ---- nonlinear functions: f(x) = s x + g(x), g enclosed on the form's range
    def _affine_map(self, s: Tensor, g: Iv) -> Af:
        """``s x + g`` with ``s`` a float tensor of the shape and ``g`` an interval holding ``f(x) - s x``."""
        out = self._scale(s)
        return out.add(g)

    def _pick(self, form: Af, enclosure: Iv) -> Af:
        """Per element, ``form``, or the interval ``enclosure`` as a constant form where that is :data:`PICK_RATIO`
        times narrower (the form keeps the dependence on the box's coordinates, worth a wider range: a monotone
        function's minimum-range form is exactly as wide as its interval)."""
        flat = self.constant(enclosure)
        return _where(form.rough_width() <= PICK_RATIO * flat.rough_width(), form, flat)

    def _taylor(self, f, df, d2_mag, enclosure: Iv) -> Af:
        """``f`` linearised at the range's midpoint ``m``: ``g = f(m) - s m +- (M2 rad^2 / 2 + |f'(m) - s| rad)`` with
        ``M2 >= |f''|`` on the range (``d2_mag``: the range -> that bound) and ``s = f'(m)`` as computed."""
        rng = self.interval()
        m = (rng.lo + rng.hi) / 2
        rad = _up(torch.maximum(rng.hi - m, m - rng.lo))
        s = df(m)
        s = torch.where(torch.isfinite(s), s, 0.0)
        fm = f(Iv.point(m))
        base = fm - Iv.point(m) * Iv.point(s)
        slack = _nonneg_sum(d2_mag(rng) * rad * rad / 2 * (1 + 4 * EPS), (16 * EPS * s.abs() + TINY) * rad)
        g = Iv(base.lo - slack, base.hi + slack)
        g = Iv(_down(g.lo), _up(g.hi))
        return self._pick(self._affine_map(s, g), enclosure)

    def _taylor2(self, f, d1, d2, d3_mag) -> Af:
        """``f`` to second order at the range's midpoint ``m``: ``f(m) + s1 dx + s2 dx^2 +- (M3 rad^3 / 6 + |f'(m) -
        s1| rad + |f''(m) / 2 - s2| rad^2)`` with ``dx = x - m``, ``s1, s2`` the computed ``f'(m), f''(m) / 2`` and
        ``M3`` at least the third derivative's magnitude on the range (``d3_mag``: the range -> that bound)."""
        rng = self.interval()
        m = (rng.lo + rng.hi) / 2
        rad = _up(torch.maximum(rng.hi - m, m - rng.lo))
        s1, s2 = d1(m), d2(m) / 2
        s1, s2 = torch.where(torch.isfinite(s1), s1, 0.0), torch.where(torch.isfinite(s2), s2, 0.0)
        dx = self.sub(Iv.point(m))
        out = dx._scale(s1).add(dx.mul(dx)._scale(s2))
        slack = _nonneg_sum(d3_mag(rng) * rad * rad * rad / 6 * (1 + 8 * EPS), (16 * EPS * s1.abs() + TINY) * rad,
                            (16 * EPS * s2.abs() + TINY) * rad * rad)
        fm = f(Iv.point(m))
        return out.add(Iv(fm.lo - slack, fm.hi + slack))

    def _best(self, forms: list[Af], enclosure: Iv) -> Af:
        """Per element, of ``forms`` the one with the smallest remainder ``r`` (the part that has lost its
        dependence on the box) unless it is much wider than the first, or the interval where that is much narrower
        (see :meth:`_pick`)."""
        best = forms[0]
        for other in forms[1:]:
            smaller = (other.r.hi - other.r.lo) < (best.r.hi - best.r.lo)
            best = _where(smaller & (other.rough_width() <= BEST_RATIO * best.rough_width()), other, best)
        return self._pick(best, enclosure)

    def tanh(self) -> Af:
        """The narrower of two forms: minimum-range (a slope ``s <= min tanh'`` on ``[a, b]`` makes ``tanh(x) - s x``
        non-decreasing there) and second order (the third derivative ``-2 (1 - t^2) (1 - 3 t^2)``, ``t = tanh x``,
        enclosed over the range)."""
        rng = self.interval()
        ends = torch.stack([1 - torch.tanh(rng.lo) ** 2, 1 - torch.tanh(rng.hi) ** 2]).amin(0)
        s = (ends * (1 - 64 * EPS) - TINY).clamp(min=0.0)
        s = torch.where(torch.isfinite(s), s, 0.0)
        ga = Iv.point(rng.lo).tanh() - Iv.point(rng.lo) * Iv.point(s)
        gb = Iv.point(rng.hi).tanh() - Iv.point(rng.hi) * Iv.point(s)
        min_range = self._affine_map(s, Iv(ga.lo, gb.hi))

        def d3(r: Iv) -> Tensor:  # the third derivative -2 (1 - t^2) (1 - 3 t^2), t = tanh(x), over the range
            t2 = r.tanh().square()
            one = Iv.point(torch.ones_like(t2.lo))
            return torch.minimum(torch.full_like(t2.lo, 2.0), ((one - t2) * (one - t2 * 3.0)).mag() * 2.0)

        def d2(m: Tensor) -> Tensor:
            return -2 * torch.tanh(m) * (1 - torch.tanh(m) ** 2)

        second = self._taylor2(lambda v: v.tanh(), lambda m: 1 - torch.tanh(m) ** 2, d2, d3)
        return self._best([min_range, second], rng.tanh())

    def sin(self) -> Af:
        return self._best([self._taylor2(lambda v: v.sin(), torch.cos, lambda m: -torch.sin(m),
                                         lambda r: r.cos().mag())], self.interval().sin())

    def cos(self) -> Af:
        return self._best([self._taylor2(lambda v: v.cos(), lambda m: -torch.sin(m), lambda m: -torch.cos(m),
                                         lambda r: r.sin().mag())], self.interval().cos())

    def exp(self) -> Af:
        return self._best([self._taylor2(lambda v: v.exp(), torch.exp, torch.exp, lambda r: r.exp().hi)],
                          self.interval().exp())

    def sqrt(self, nonnegative: bool = False) -> Af:
        """Square root with the chord's slope ``s`` over the range ``[a, b]``: ``g = sqrt(x) - s x`` is concave, at
        least ``min(g(a), g(b))`` there and at most its tangent bound at ``t = 1 / (4 s^2)`` (where ``g' = 0``),
        ``sqrt(t) - s t + |1 / (2 sqrt(t)) - s| b``. ``nonnegative``: the argument is known to be ``>= 0`` (a sum of
        squares), so a range reaching below 0 is read from 0; otherwise there it is outside the domain (the whole
        line)."""
        rng = self.interval()
        outside = (rng.lo < 0) & (not nonnegative)
        a, b = rng.lo.clamp(min=0.0), rng.hi.clamp(min=0.0)
        wide = b > a
        ra, rb = Iv.point(a).sqrt(), Iv.point(b).sqrt()
        s = torch.where(wide, (torch.sqrt(b) - torch.sqrt(a)) / torch.where(wide, b - a, 1.0), 0.0)
        s = torch.where(torch.isfinite(s) & (s > 0), s, 0.0)
        sp = Iv.point(s)
        low = torch.minimum((ra - Iv.point(a) * sp).lo, (rb - Iv.point(b) * sp).lo)
        t = torch.where(s > 0, (0.25 / torch.where(s > 0, s * s, 1.0)).clamp(min=TINY), b.clamp(min=TINY))
        rt = Iv.point(t).sqrt()
        slope_gap = (Iv.point(0.5, rt.device) / rt - sp).abs().hi
        high = (rt - Iv.point(t) * sp).hi + _up(slope_gap * b * (1 + 4 * EPS))
        high = torch.maximum(high, torch.maximum((ra - Iv.point(a) * sp).hi, (rb - Iv.point(b) * sp).hi))
        point = ~wide
        g = Iv(torch.where(point, ra.lo, low), torch.where(point, rb.hi, _up(high)))
        form = _where(point, self.constant(Iv(ra.lo, rb.hi)), self._affine_map(s, g))
        enclosure = Iv(a, b).sqrt()
        out = self._pick(form, enclosure)
        everything = Iv(torch.full_like(a, -INF), torch.full_like(a, INF))
        return _where(outside, self.constant(everything), out)

    def reciprocal(self) -> Af:
        def d2(r: Iv) -> Tensor:  # |(1/x)''| = 2 / |x|^3, largest at the end nearest 0; unbounded across 0
            near = torch.minimum(r.lo.abs(), r.hi.abs())
            return torch.where(r.contains_zero(), INF, _up(2.0 / (near * near * near) * (1 + 16 * EPS)))

        one = Iv.point(torch.ones_like(self.c))
        return self._taylor(lambda v: one / v, lambda m: -1.0 / (m * m), d2, one / self.interval())

    def div(self, o) -> Af:
        if isinstance(o, Af):
            return self.mul(o.reciprocal())
        o = o if isinstance(o, Iv) else Iv.point(o)
        return self.mul(Iv.point(torch.ones_like(o.lo)) / o)

    def abs(self) -> Af:
        rng = self.interval()
        positive, negative = rng.lo >= 0, rng.hi <= 0
        sign = torch.where(positive, 1.0, torch.where(negative, -1.0, 0.0))
        exact = self._scale(sign)
        flat = self.constant(rng.abs())
        return _where(positive | negative, exact, flat)

    def clamp(self, low: Tensor, high: Tensor) -> Af:
        """The chord's slope ``s = (clamp(b) - clamp(a)) / (b - a)`` in ``[0, 1]``; ``clamp(x) - s x`` is piecewise
        linear, so its range on ``[a, b]`` is taken at ``a``, ``b`` and the bounds that lie between."""
        rng = self.interval()
        low, high = _t(low).expand_as(rng.lo), _t(high).expand_as(rng.lo)
        a, b = rng.lo, rng.hi
        ca, cb = torch.minimum(torch.maximum(a, low), high), torch.minimum(torch.maximum(b, low), high)
        width = b - a
        s = torch.where(width > 0, (cb - ca) / torch.where(width > 0, width, 1.0), 1.0).clamp(0.0, 1.0)
        s = torch.where(torch.isfinite(s), s, 0.0)
        points = [a, b, torch.minimum(torch.maximum(low, a), b), torch.minimum(torch.maximum(high, a), b)]
        values = [Iv.point(torch.minimum(torch.maximum(p, low), high)) - Iv.point(p) * Iv.point(s) for p in points]
        g = Iv(torch.stack([v.lo for v in values]).amin(0), torch.stack([v.hi for v in values]).amax(0))
        return self._pick(self._affine_map(s, g), rng.clamp(low, high))

    def norm(self) -> Af:
        """The Euclidean norm along the last axis: the square root of the sum of squares, read as ``>= 0``."""
        return self.square().sum(-1).sqrt(nonnegative=True)


def _where(mask: Tensor, a: Af, b: Af) -> Af:
    """``a`` where ``mask``, else ``b`` (elementwise over the forms' shape)."""
    return Af(torch.where(mask, a.c, b.c), torch.where(mask[..., None], a.l, b.l),
              torch.where(mask[..., None, None], a.q, b.q),
              Iv(torch.where(mask, a.r.lo, b.r.lo), torch.where(mask, a.r.hi, b.r.hi)))


__all__ = ["Af"]
