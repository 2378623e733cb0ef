"""Batched affine forms over the noise symbols of a batch of boxes, with an exact quadratic part (second-order
Taylor models), outward rounded."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from drlyap.enclosures.affine_functions import AffineFunctions
from drlyap.enclosures.base import Enclosure, fix_index, normdim
from drlyap.enclosures.interval import Interval
from drlyap.enclosures.quadratic import max_lin_quad, quadratic_span, sym_outer
from drlyap.enclosures.rounding import EPS, F64, REL1, TINY, as_f64, round_down, round_up, sum_up


class Affine(AffineFunctions, Enclosure, kind="affine"):
    """A batch of affine forms (first-order Taylor models) over the noise symbols of a batch of boxes, with an
    optional exact quadratic part::

        x = c + sum_k g[..., k] e_k + sum_kl q[..., k, l] e_k e_l + r,    e_k in [-1, 1],  r in [r.lo, r.hi]

    ``c``: float64 tensor ``(B, ...)``; ``g``: coefficients ``(B, ..., K)`` of the ``K`` noise symbols (None: a
    constant, no linear part); ``q``: ``(B, ..., K, K)`` or None, the products of linear parts that ``x * y``
    keeps (so that sums of products, such as ``grad V . f``, cancel before they are bounded: measured 13x
    narrower on a cart-pole's open boxes than bounding each product separately); ``r``: an :class:`Interval`
    ``(B, ...)``, the remainder that collects the linearisation errors of nonlinear operations and the rounding
    errors of every coefficient (each computed coefficient's rounding error is bounded and added to ``r``, so
    the form encloses the real values).

    Axis 0 is the batch of boxes and every box has its own symbols (``g[b, ..., k]`` multiplies ``e_{b,k}``),
    so no operation may mix entries along axis 0: summing, unbinding, stacking at or moving axis 0 of a
    non-constant form raises, and two non-constant forms combine only with the same size of axis 0.

    How each operation is enclosed: the package docstring (:mod:`drlyap.enclosures`). :meth:`box` makes the form
    of a batch of boxes; :meth:`to_interval` encloses a form.
    """

    __slots__ = ("c", "g", "r", "q", "_qr", "_dv")
    level = 0

    def __init__(self, c: Tensor, g: Tensor | None = None, r: Interval | None = None,
                 q: Tensor | None = None) -> None:
        shape = c.shape
        if r is not None and r.shape != shape:
            shape = torch.broadcast_shapes(shape, r.shape)
        if g is not None and g.shape[:-1] != shape:
            shape = torch.broadcast_shapes(shape, g.shape[:-1])
        if q is not None and q.shape[:-2] != shape:
            shape = torch.broadcast_shapes(shape, q.shape[:-2])
        self.c = c if c.shape == shape else c.expand(shape)
        self.g = g if g is None or g.shape[:-1] == shape else g.expand(*shape, g.shape[-1])
        self.q = q if q is None or q.shape[:-2] == shape else q.expand(*shape, *q.shape[-2:])
        self._qr: Interval | None = None  # the range of the quadratic part, once computed
        self._dv: Interval | None = None  # the range of x - c, once computed
        if r is None:
            z = torch.zeros((), dtype=F64, device=c.device).expand(shape)
            r = Interval(z, z)
        elif r.shape != shape:
            r = Interval(r.lo.expand(shape), r.hi.expand(shape))
        self.r = r

    @staticmethod
    def box(lo: Tensor, hi: Tensor) -> Affine:
        """The boxes ``[lo, hi] (B, n)`` as forms ``centre + diag(radius) e`` with ``n`` noise symbols each."""
        lo, hi = as_f64(lo), as_f64(hi)
        c = (lo + hi) / 2
        rad = round_up(torch.maximum(hi - c, c - lo), REL1)
        return Affine(c, torch.diag_embed(rad))

    @staticmethod
    def const(x) -> Affine:
        """A constant (no linear part) enclosing ``x``: a tensor, a number or an :class:`Interval`."""
        if isinstance(x, Affine):
            return x
        if isinstance(x, Interval):
            if x.lo is x.hi:
                return Affine(x.lo)
            c = x.mid
            return Affine(c, None, Interval(round_down(x.lo - c, REL1), round_up(x.hi - c, REL1)))
        return Affine(as_f64(x))

    @property
    def shape(self) -> torch.Size:
        return self.c.shape

    @property
    def device(self) -> torch.device:
        return self.c.device

    @property
    def n_symbols(self) -> int:
        """``K``, the number of noise symbols (0 for a constant)."""
        return 0 if self.g is None else self.g.shape[-1]

    def _quad(self) -> Interval:
        """An interval ``(B, ...)`` of the quadratic part ``e^T q e`` over ``e in [-1, 1]^K``: the diagonal terms
        ``q_kk e_k^2`` range over ``[min(0, q_kk), max(0, q_kk)]``, the others over ``+-|q_kl|`` (``q`` is kept
        symmetric, so this is ``+-|q_kl + q_lk|`` per pair)."""
        q = self.q
        if q is None:
            z = torch.zeros_like(self.c)
            return Interval(z, z)
        if self._qr is None:
            k = q.shape[-1]
            diag = torch.diagonal(q, dim1=-2, dim2=-1)
            total = q.abs().sum((-2, -1))
            off = torch.clamp(total - diag.abs().sum(-1), min=0.0)  # sum_{k != l} |q_kl| >= |off-diagonal part|
            pad = 4 * (k * k + 4) * EPS * total + TINY  # the sums' rounding
            self._qr = Interval(torch.clamp(diag, max=0.0).sum(-1) - off - pad,
                                torch.clamp(diag, min=0.0).sum(-1) + off + pad)
        return self._qr

    def _lin(self) -> Tensor:
        """An upper bound ``(B, ...)`` of ``|g . e|`` over ``[-1, 1]^K`` (0 without a linear part)."""
        return torch.zeros_like(self.c) if self.g is None else sum_up(self.g.abs())

    def _higher(self) -> Interval:
        """An interval of the part above first order: the quadratic part plus the remainder, ``(B, ...)``."""
        return self.r if self.q is None else self.r + self._quad()

    def _dev(self) -> Interval:
        """An interval of ``x - c`` (the linear and quadratic parts over ``[-1, 1]^K`` plus the remainder),
        ``(B, ...)``."""
        if self.g is None or self.q is None:
            if self.g is None and self.q is None:
                return self.r
            s = self._lin()
            h = self._higher()
            return Interval(round_down(h.lo - s, REL1), round_up(h.hi + s, REL1))
        if self._dv is None:  # each symbol's g_k e_k + q_kk e_k^2 bounded jointly, the cross terms by |q_kl|
            q, k = self.q, self.q.shape[-1]
            diag = torch.diagonal(q, dim1=-2, dim2=-1)
            total = q.abs().sum((-2, -1))
            off = torch.clamp(total - diag.abs().sum(-1), min=0.0)
            hi = max_lin_quad(self.g, diag).sum(-1) + off
            lo = -max_lin_quad(self.g, -diag).sum(-1) - off
            pad = 8 * (k * k + 4) * EPS * (self.g.abs().sum(-1) + total) + TINY
            self._dv = Interval(round_down(lo - pad + self.r.lo, REL1), round_up(hi + pad + self.r.hi, REL1))
        return self._dv

    def _about_middle(self, higher: Interval, within: Interval | None = None) -> tuple[Tensor, Interval]:
        """``c' = c + mid(H)``, ``H`` the quadratic part plus the remainder (``higher``: its range, :meth:`_higher`;
        ``c`` where that is not finite; moved into ``within`` where given), and an enclosure of ``c - c'``: the form
        written about the middle of its part above first order."""
        m = higher.mid
        cp = self.c + torch.where(torch.isfinite(m), m, 0.0)
        if within is not None:
            cp = torch.minimum(torch.maximum(cp, within.lo), within.hi)
        return cp, Interval.const(self.c) - Interval.const(cp)

    def to_interval(self) -> Interval:
        """The interval enclosure ``(B, ...)`` of the forms."""
        return Interval.const(self.c) + self._dev()

    def tight_interval(self, max_symbols: int = 8, lower: slice | None = None) -> Interval:
        """:meth:`to_interval` with the linear and quadratic parts bounded jointly over the cube's vertices
        (:func:`quadratic_max`; the cross terms then cancel where they can) when there are at most
        ``max_symbols`` symbols: ``2^K`` evaluations per entry, for final results rather than every step.

        ``lower``: the entries of the forms' last axis whose lower end is read (None: all); the others' lower end
        is :meth:`to_interval`'s (their upper ends are the same either way)."""
        if self.q is None or self.g is None or self.n_symbols > max_symbols:
            return self.to_interval()
        read = True
        if lower is not None:
            read = torch.zeros(self.shape[-1], dtype=torch.bool, device=self.device)
            read[lower] = True
        lo, hi = quadratic_span(self.g, self.q, read)
        dev = Interval(round_down(lo + self.r.lo, REL1), round_up(hi + self.r.hi, REL1))
        tight, plain = Interval.const(self.c) + dev, self.to_interval()
        return Interval(torch.maximum(tight.lo, plain.lo), torch.minimum(tight.hi, plain.hi))

    @property
    def lo(self) -> Tensor:
        """Lower end of :meth:`to_interval`."""
        return self.to_interval().lo

    @property
    def hi(self) -> Tensor:
        """Upper end of :meth:`to_interval`."""
        return self.to_interval().hi

    def contains(self, x: Tensor) -> Tensor:
        return self.to_interval().contains(x)

    def zeros_ext(self, k: int) -> Affine:
        return Affine(torch.zeros(*self.shape, k, dtype=F64, device=self.device))

    def __repr__(self) -> str:
        return f"Affine(c={self.c}, g={self.g}, q={self.q}, r={self.r!r})"

    @staticmethod
    def _centred(const: Interval, g: Tensor | None, pad, q: Tensor | None = None) -> Affine:
        """The form ``const + g . e + e^T q e`` re-centred at the midpoint of ``const``, ``pad`` (a bound of the
        rounding error of the coefficients' parts) added to the remainder on both sides."""
        c = const.mid
        return Affine(c, g, Interval(round_down(const.lo - c - pad, REL1), round_up(const.hi - c + pad, REL1)), q)

    @staticmethod
    def _qpad(q: Tensor | None, rel: float = REL1):
        """A bound of the value error of a quadratic part whose every coefficient carries a relative error
        ``rel`` (``|e_k e_l| <= 1``)."""
        return 0.0 if q is None else rel * sum_up(sum_up(q.abs()))

    @staticmethod
    def _where(mask: Tensor, a: Affine, b: Affine) -> Affine:
        """Elementwise ``a`` where ``mask``, else ``b`` (forms of one shape and the same symbols)."""
        c = torch.where(mask, a.c, b.c)
        if a.g is None and b.g is None:
            g = None
        else:
            ga = a.g if a.g is not None else torch.zeros_like(b.g)
            gb = b.g if b.g is not None else torch.zeros_like(a.g)
            g = torch.where(mask.unsqueeze(-1), ga, gb)
        if a.q is None and b.q is None:
            q = None
        else:
            qa = a.q if a.q is not None else torch.zeros_like(b.q)
            qb = b.q if b.q is not None else torch.zeros_like(a.q)
            q = torch.where(mask[..., None, None], qa, qb)
        return Affine(c, g, Interval(torch.where(mask, a.r.lo, b.r.lo), torch.where(mask, a.r.hi, b.r.hi)), q)

    def _guard(self, fallback: Interval) -> Affine:
        """Elementwise this form, or the constant form of ``fallback`` (an interval enclosure of the same
        values) where this form's remainder alone is at least as wide as ``fallback`` (the linear and quadratic
        parts then carry nothing the interval does not) or the form is not finite. (Comparing whole widths would
        always pick the interval: a form's own range is never narrower than the exact range of one function
        of it; its value lies in the correlations it keeps.)"""
        mine = self.to_interval()
        worse = ~((self.r.hi - self.r.lo) < (fallback.hi - fallback.lo)) | ~torch.isfinite(mine.hi - mine.lo)
        if not bool(worse.any()):
            return self
        return Affine._where(worse, Affine.const(fallback), self)

    # ---- structure
    def _batch_check(self, what: str) -> None:
        if self.g is not None or self.q is not None:
            raise ValueError(f"{what} axis 0 of an affine form would mix the noise symbols of different boxes")

    def __getitem__(self, idx) -> Affine:
        idx = fix_index(idx, self.ndim)
        return Affine(self.c[idx], None if self.g is None else self.g[idx], self.r[idx],
                      None if self.q is None else self.q[idx])

    def unbind(self, dim: int = 0) -> tuple:
        dim = normdim(dim, self.ndim)
        if dim == 0:
            self._batch_check("unbinding")
        gs = self.g.unbind(dim) if self.g is not None else (None,) * self.c.shape[dim]
        qs = self.q.unbind(dim) if self.q is not None else (None,) * self.c.shape[dim]
        return tuple(Affine(c, g, r, q) for c, g, r, q in zip(self.c.unbind(dim), gs, self.r.unbind(dim), qs))

    def unsqueeze(self, dim: int) -> Affine:
        dim = normdim(dim, self.ndim + 1)
        if dim == 0:
            self._batch_check("moving")
        return Affine(self.c.unsqueeze(dim), None if self.g is None else self.g.unsqueeze(dim), self.r.unsqueeze(dim),
                      None if self.q is None else self.q.unsqueeze(dim))

    def transpose(self, a: int, b: int) -> Affine:
        a, b = normdim(a, self.ndim), normdim(b, self.ndim)
        if a != b and 0 in (a, b):
            self._batch_check("moving")
        return Affine(self.c.transpose(a, b), None if self.g is None else self.g.transpose(a, b), self.r.transpose(a, b),
                      None if self.q is None else self.q.transpose(a, b))

    def expand(self, *shape) -> Affine:
        c = self.c.expand(*shape)
        if c.ndim != self.ndim or c.shape[0] != self.c.shape[0]:
            self._batch_check("expanding")
        return Affine(c, None if self.g is None else self.g.expand(*c.shape, -1), self.r.expand(*c.shape),
                      None if self.q is None else self.q.expand(*c.shape, -1, -1))

    def reshape(self, *shape) -> Affine:
        c = self.c.reshape(*shape)
        if c.ndim == 0 or c.shape[0] != self.c.shape[0]:
            self._batch_check("reshaping")
        g = None if self.g is None else self.g.reshape(*c.shape, self.g.shape[-1])
        q = None if self.q is None else self.q.reshape(*c.shape, *self.q.shape[-2:])
        return Affine(c, g, self.r.reshape(*c.shape), q)

    @staticmethod
    def _join(items: list, dim: int, fn: Callable) -> Affine:
        """``torch.stack`` or ``torch.cat`` (``fn``) of forms along ``dim``."""
        dim = normdim(dim, items[0].ndim + (1 if fn is torch.stack else 0))
        with_g = [s for s in items if s.g is not None]
        g = None
        if with_g:
            if fn is torch.stack and dim == 0:
                with_g[0]._batch_check("stacking at")
            k = with_g[0].g.shape[-1]
            if any(s.g.shape[-1] != k for s in with_g):
                raise ValueError("affine forms over different noise symbols")
            g = fn([s.g if s.g is not None else torch.zeros(*s.shape, k, dtype=F64, device=s.device)
                    for s in items], dim)
        q = None
        with_q = [s for s in items if s.q is not None]
        if with_q:
            k = with_q[0].q.shape[-1]
            q = fn([s.q if s.q is not None else torch.zeros(*s.shape, k, k, dtype=F64, device=s.device)
                    for s in items], dim)
        r = Interval(fn([s.r.lo for s in items], dim), fn([s.r.hi for s in items], dim))
        return Affine(fn([s.c for s in items], dim), g, r, q)

    # ---- arithmetic
    @staticmethod
    def _gsum(a: Tensor | None, b: Tensor | None) -> tuple[Tensor | None, object]:
        """``a + b`` of coefficient tensors (None = 0) and a bound of its rounding error summed over symbols."""
        if a is None or b is None:
            return (b if a is None else a), 0.0
        if a.shape[-1] != b.shape[-1] or a.ndim != b.ndim or a.shape[0] != b.shape[0]:
            raise ValueError(f"affine forms of different boxes or symbols cannot be combined: coefficient shapes "
                             f"{tuple(a.shape)} and {tuple(b.shape)}")
        g = a + b
        return g, REL1 * sum_up(g.abs())

    @staticmethod
    def _qsum(a: Tensor | None, b: Tensor | None) -> tuple[Tensor | None, object]:
        """``a + b`` of quadratic parts (None = 0) and a bound of its rounding error's value."""
        if a is None or b is None:
            return (b if a is None else a), 0.0
        if a.shape[-1] != b.shape[-1] or a.ndim != b.ndim or a.shape[0] != b.shape[0]:
            raise ValueError(f"affine forms of different boxes or symbols cannot be combined: quadratic shapes "
                             f"{tuple(a.shape)} and {tuple(b.shape)}")
        q = a + b
        return q, Affine._qpad(q)

    def _add(self, o: Affine) -> Affine:
        g, pad = Affine._gsum(self.g, o.g)
        q, qpad = Affine._qsum(self.q, o.q)
        c = self.c + o.c
        const = Interval(round_down(c, REL1), round_up(c, REL1)) + (self.r + o.r)
        return Affine._centred(const, g, pad + qpad, q)

    def _sub(self, o: Affine) -> Affine:
        return self._add(o._neg())

    def _neg(self) -> Affine:
        return Affine(-self.c, None if self.g is None else -self.g, -self.r, None if self.q is None else -self.q)

    def _scale_shift(self, lam: Tensor, k: Interval) -> Affine:
        """``lam * x + k``: ``lam`` a float64 tensor of (or broadcastable to) the shape, ``k`` an :class:`Interval`."""
        lam = lam.expand(self.shape) if lam.shape != self.shape else lam
        const = Interval.const(lam) * (Interval.const(self.c) + self.r) + k
        q = None if self.q is None else lam[..., None, None] * self.q
        if self.g is None:
            return Affine._centred(const, None, Affine._qpad(q), q)
        g = lam.unsqueeze(-1) * self.g
        return Affine._centred(const, g, REL1 * sum_up(g.abs()) + Affine._qpad(q), q)

    def _mul(self, o: Affine) -> Affine:
        if self.g is None and o.g is None and self.q is None and o.q is None:
            return Affine.const(self.to_interval() * o.to_interval())
        # x = cx + Lx + Hx (linear part; quadratic part plus remainder), written about cx' = cx + mid(Hx) so that its
        # part above first order, Hx' = Hx + (cx - cx'), ranges over an interval centred at 0 (a quadratic part is
        # often one-signed: a square's is), and the same for y; then
        # x y = cx' cy' + (cx' Ly + cy' Lx) + (cx' Qy + cy' Qx + Lx Ly) + cx' (ry + cy - cy') + cy' (rx + cx - cx')
        #       + Lx Hy' + Hx' (y - cy'),
        # the last two (third order and above) bounded by intervals, which the centring narrows
        hx, hy = self._higher(), o._higher()
        (cxp, sx), (cyp, sy) = self._about_middle(hx), o._about_middle(hy)
        t1 = None if self.g is None else cyp.unsqueeze(-1) * self.g
        t2 = None if o.g is None else cxp.unsqueeze(-1) * o.g
        g, pad = Affine._gsum(t1, t2)
        if g is not None:
            pad = pad + REL1 * sum_up(g.abs())  # the products' own rounding
        parts = [cyp[..., None, None] * self.q if self.q is not None else None,
                 cxp[..., None, None] * o.q if o.q is not None else None,
                 sym_outer(self.g, o.g) if self.g is not None and o.g is not None else None]
        q = None
        for part in parts:
            if part is not None:
                q = part if q is None else q + part
        if q is not None:
            pad = pad + Affine._qpad(q, 4 * REL1)  # each entry: up to three products and two sums
        cx, cy = Interval.const(cxp), Interval.const(cyp)
        lx = self._lin()
        const = (cx * cy + cx * (o.r + sy) + cy * (self.r + sx) + Interval(-lx, lx) * (hy + sy)
                 + (hx + sx) * (o._dev() + sy))
        return Affine._centred(const, g, pad, q)

    def _div(self, o: Affine) -> Affine:
        return self._mul(o.reciprocal())

    def square(self) -> Affine:
        """``x * x`` (its quadratic part exact), or the secant form where that is narrower."""
        fallback = self.to_interval().square()
        if self.g is None:
            return Affine.const(fallback)
        return self._mul(self)._guard(fallback)

    def pow_int(self, n: int) -> Affine:
        if n == 0:
            return Affine(torch.ones_like(self.c))
        if n == 1:
            return self
        if n == 2:
            return self.square()
        half = self.pow_int(n // 2).square()
        return half if n % 2 == 0 else half * self

    def sum(self, dim: int | None = None) -> Affine:
        if dim is None:
            self._batch_check("summing over")
            return Affine.const(self.r.sum(None) + Interval.const(self.c).sum(None))
        dim = normdim(dim, self.ndim)
        if dim == 0:
            self._batch_check("summing over")
        rel = 2 * (self.c.shape[dim] + 2) * EPS
        c = self.c.sum(dim)
        mag = self.c.abs().sum(dim)
        const = Interval(round_down(c, rel, mag), round_up(c, rel, mag)) + self.r.sum(dim)
        q = None if self.q is None else self.q.sum(dim)
        qpad = 0.0 if q is None else rel * sum_up(sum_up(self.q.abs().sum(dim)))
        if self.g is None:
            return Affine._centred(const, None, qpad, q)
        g = self.g.sum(dim)
        return Affine._centred(const, g, rel * sum_up(self.g.abs().sum(dim)) + qpad, q)

    def linear(self, weight: Tensor, bias: Tensor | None = None) -> Affine:
        """``x @ weight.T + bias`` along the last axis, with a constant (exact) ``weight (out, in)``."""
        rel = 4 * (weight.shape[1] + 4) * EPS
        w_abs = weight.abs().T
        c = self.c @ weight.T
        mag = self.c.abs() @ w_abs
        if bias is not None:
            c = c + bias
            mag = mag + bias.abs()
        const = Interval(round_down(c, rel, mag), round_up(c, rel, mag)) + self.r.linear(weight)
        q, qpad = None, 0.0
        if self.q is not None:
            k = self.q.shape[-1]
            q = torch.matmul(weight, self.q.flatten(-2)).unflatten(-1, (k, k))  # (out, in) @ (..., in, K K)
            qpad = rel * round_up(sum_up(sum_up(self.q.abs())) @ w_abs, rel)
        if self.g is None:
            return Affine._centred(const, None, qpad, q)
        g = torch.matmul(weight, self.g)  # (out, in) @ (..., in, K)
        pad = rel * round_up(sum_up(self.g.abs()) @ w_abs, rel)
        return Affine._centred(const, g, pad + qpad, q)

    def norm(self, dim: int = -1) -> Affine:
        """Euclidean norm along ``dim``."""
        return self.square().sum(dim).sqrt()
