"""Enclosure arithmetic: batched intervals and forward-mode dual numbers over them, outward rounded.

A leaf numeric module (it imports only torch). The networks, the systems' dynamics and the decrease
conditions are written once with torch operations; run on these types instead of tensors, the same code
returns sound enclosures of its values and derivatives over boxes. That is how the verifier bounds
exactly what training minimises (no second encoding of any formula).

* :class:`Interval` -- batched interval tensors ``[lo, hi]`` (any shape), float64, outward rounded: every
  computed endpoint is widened by an error bound of the floating-point operation that produced it, so it
  encloses the real value.
* :class:`Affine` -- batched affine forms ``c + sum_k g_k e_k + sum_kl q_kl e_k e_l + [r_lo, r_hi]`` over
  noise symbols ``e_k in [-1, 1]`` (one per box dimension, separate for every box of the batch), with an
  optional exact quadratic part (second-order Taylor models): linear operations are exact on the linear and
  quadratic parts, products keep the product of the linear parts, smooth functions keep their second-order
  Taylor terms, and what is left is bounded soundly in the remainder ``[r_lo, r_hi]``; coefficients and
  remainders are outward rounded as intervals are. Much tighter than intervals over boxes because
  correlations between the coordinates survive.
* :class:`Dual` -- forward-mode dual numbers whose value and derivative are themselves enclosures
  (intervals, affine forms or duals). ``Dual(Interval)`` over a box encloses a function's value and gradient there;
  ``Dual(Dual(Interval))`` adds a second group of directions (e.g. parameter derivatives, or the Hessian).
* All implement ``__torch_function__`` and the Python operators, so code written with ``+ - * /``,
  ``**`` by an int, ``torch.sin/cos/tanh/exp/sqrt/square``, ``torch.stack/cat``, ``unbind``, indexing,
  ``torch.nn.functional.linear`` (so ``nn.Linear`` layers) and ``torch.linalg.vector_norm`` runs
  unchanged on them. Weights met in ``linear`` are read as float64 numbers (exactly).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor

F64 = torch.float64
EPS = 2.0 ** -52  # float64 machine epsilon (unit roundoff is EPS / 2)
TINY = 1e-290  # absolute pad: covers underflow of any single operation
REL1 = 4 * EPS  # relative pad of one correctly rounded operation (generous)
RELT = 16 * EPS  # relative pad of a library transcendental (sin, cos, tanh, exp, sqrt: a few ulps at most)


def _t(x) -> Tensor:
    return torch.as_tensor(x, dtype=F64)


def _down(x: Tensor, rel: float, mag: Tensor | None = None) -> Tensor:
    return x - rel * (x.abs() if mag is None else mag) - TINY


def _up(x: Tensor, rel: float, mag: Tensor | None = None) -> Tensor:
    return x + rel * (x.abs() if mag is None else mag) + TINY


# =========================================================================== enclosure types
class _Enclosure:
    """Common operator plumbing and the ``__torch_function__`` bridge of :class:`Interval`, :class:`Affine` and
    :class:`Dual`."""

    level = 0

    # ---- python operators (the concrete classes implement _add, _sub, _mul, _div, _neg)
    def __add__(self, other):
        return self._binary("_add", other, False)

    def __radd__(self, other):
        return self._binary("_add", other, True)

    def __sub__(self, other):
        return self._binary("_sub", other, False)

    def __rsub__(self, other):
        return self._binary("_sub", other, True)

    def __mul__(self, other):
        return self._binary("_mul", other, False)

    def __rmul__(self, other):
        return self._binary("_mul", other, True)

    def __truediv__(self, other):
        return self._binary("_div", other, False)

    def __rtruediv__(self, other):
        return self._binary("_div", other, True)

    def __neg__(self):
        return self._neg()

    def __pos__(self):
        return self

    def __pow__(self, n):
        if isinstance(n, Tensor) and n.numel() == 1:
            n = n.item()
        if isinstance(n, float) and n.is_integer():
            n = int(n)
        if not isinstance(n, int) or n < 0:
            raise ValueError(f"interval arithmetic supports powers by non-negative integers only, got {n!r}")
        return self.pow_int(n)

    def _binary(self, name: str, other, reflected: bool):
        a, b = lift_pair(self, other)
        if reflected:
            a, b = b, a
        return getattr(a, name)(b)

    def __len__(self) -> int:
        return self.shape[0]

    def __iter__(self):
        return iter(self.unbind(0))

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def dtype(self) -> torch.dtype:
        return F64

    @property
    def device(self) -> torch.device:
        return self.base.device

    @property
    def base(self) -> Interval:
        """The innermost interval (the enclosure of the value)."""
        x = self
        while isinstance(x, Dual):
            x = x.v
        return x

    def dim(self) -> int:
        return self.ndim

    def size(self, d: int | None = None):
        return self.shape if d is None else self.shape[d]

    # ---- torch functions
    @classmethod
    def __torch_function__(cls, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        if func in (torch.stack, torch.cat, torch.concat, torch.concatenate):
            seq = args[0]
            dim = kwargs.get("dim", args[1] if len(args) > 1 else 0)
            return stack(seq, dim) if func is torch.stack else cat(seq, dim)
        if func is F.linear:
            weight = args[1] if len(args) > 1 else kwargs["weight"]
            bias = args[2] if len(args) > 2 else kwargs.get("bias")
            return args[0].linear(weight.detach().to(F64), None if bias is None else bias.detach().to(F64))
        if func is torch.linalg.vector_norm:
            dim = kwargs.get("dim", args[2] if len(args) > 2 else None)
            if dim is None or isinstance(dim, (tuple, list)) or kwargs.get("ord", 2) != 2 or kwargs.get("keepdim"):
                raise TypeError("enclosures support torch.linalg.vector_norm(x, dim=d) (2-norm along one axis) only")
            return norm(args[0], dim)
        if func in (torch.unbind, Tensor.unbind):
            dim = kwargs.get("dim", args[1] if len(args) > 1 else 0)
            return args[0].unbind(dim)
        unary = {torch.sin: "sin", torch.cos: "cos", torch.tanh: "tanh", torch.exp: "exp", torch.sqrt: "sqrt",
                 torch.square: "square", torch.neg: "_neg", torch.abs: "abs",
                 Tensor.sin: "sin", Tensor.cos: "cos", Tensor.tanh: "tanh", Tensor.exp: "exp", Tensor.sqrt: "sqrt",
                 Tensor.square: "square", Tensor.neg: "_neg", Tensor.abs: "abs", Tensor.__neg__: "_neg"}
        if func in unary and not kwargs and len(args) == 1:
            return getattr(args[0], unary[func])()
        binary = {"add": "_add", "sub": "_sub", "mul": "_mul", "div": "_div", "true_divide": "_div",
                  "multiply": "_mul", "subtract": "_sub", "__add__": "_add", "__sub__": "_sub", "__mul__": "_mul",
                  "__truediv__": "_div", "__radd__": "r_add", "__rsub__": "r_sub", "__rmul__": "r_mul",
                  "__rtruediv__": "r_div", "__rdiv__": "r_div", "__div__": "_div"}
        if name in binary and len(args) == 2 and not kwargs:
            op = binary[name]
            a, b = args
            if op.startswith("r"):
                a, b, op = b, a, op[1:]
            a, b = lift_pair(a, b)
            return getattr(a, op)(b)
        if name in ("pow", "__pow__") and len(args) == 2 and isinstance(args[0], _Enclosure):
            return args[0] ** args[1]
        if name in ("sum",) and isinstance(args[0], _Enclosure):
            dim = kwargs.get("dim", args[1] if len(args) > 1 else None)
            return args[0].sum(dim)
        raise TypeError(f"interval/dual arithmetic does not support {name or func}; use +, -, *, /, ** int, "
                        "torch.sin/cos/tanh/exp/sqrt/square, torch.stack/cat, unbind, indexing, "
                        "torch.nn.functional.linear and torch.linalg.vector_norm")


def is_enclosure(x) -> bool:
    """True for :class:`Interval`, :class:`Affine` and :class:`Dual` (False for tensors and numbers)."""
    return isinstance(x, _Enclosure)


def constant_like(x, value) -> object:
    """``value`` (a tensor or number) as a constant of the same kind as ``x``: itself for a tensor ``x``,
    an exact enclosure of the same level otherwise."""
    return lift(value, _level(x)) if isinstance(x, _Enclosure) else value


def _level(x) -> int:
    return x.level if isinstance(x, _Enclosure) else -1


def lift(x, level: int):
    """Wrap ``x`` (a tensor, number, :class:`Interval` or :class:`Dual`) as a constant of the given level."""
    lv = _level(x)
    if lv == level:
        return x
    if lv > level:
        raise ValueError("cannot lower an enclosure")
    if level == 0:
        return Interval.const(x)
    return Dual(lift(x, level - 1), None)


def lift_pair(a, b):
    level = max(_level(a), _level(b), 0)
    a, b = lift(a, level), lift(b, level)
    if level == 0 and isinstance(a, Affine) != isinstance(b, Affine):  # an interval meets an affine form
        a, b = Affine.const(a), Affine.const(b)
    return a, b


def _normdim(dim: int, ndim: int) -> int:
    if not -ndim <= dim < ndim:
        raise IndexError(f"dimension {dim} out of range for {ndim} dimensions")
    return dim % ndim


def stack(seq: Sequence, dim: int = 0):
    level = max(max(_level(s) for s in seq), 0)
    items = [lift(s, level) for s in seq]
    if level == 0:
        if any(isinstance(s, Affine) for s in items):
            return Affine.join([Affine.const(s) for s in items], _normdim(dim, items[0].ndim + 1), torch.stack)
        return Interval(torch.stack([s.lo for s in items], dim), torch.stack([s.hi for s in items], dim))
    d = _normdim(dim, items[0].ndim + 1)
    return Dual(stack([s.v for s in items], d), _stack_derivs(items, lambda ds: stack(ds, d)))


def cat(seq: Sequence, dim: int = 0):
    level = max(max(_level(s) for s in seq), 0)
    items = [lift(s, level) for s in seq]
    if level == 0:
        if any(isinstance(s, Affine) for s in items):
            return Affine.join([Affine.const(s) for s in items], _normdim(dim, items[0].ndim), torch.cat)
        return Interval(torch.cat([s.lo for s in items], dim), torch.cat([s.hi for s in items], dim))
    d = _normdim(dim, items[0].ndim)
    return Dual(cat([s.v for s in items], d), _stack_derivs(items, lambda ds: cat(ds, d)))


def _fix_index(idx, ndim: int) -> tuple:
    """``idx`` as a tuple without Ellipsis, so that it addresses the leading axes of a tensor that has
    trailing extra axes (the directions of a dual number, the noise symbols of an affine form)."""
    if not isinstance(idx, tuple):
        idx = (idx,)
    if any(i is None for i in idx):
        raise IndexError("None (new axis) indexing is not supported on dual numbers and affine forms; use unsqueeze")
    if any(i is Ellipsis for i in idx):
        pos = idx.index(Ellipsis)
        fill = ndim - (len(idx) - 1)
        idx = idx[:pos] + (slice(None),) * fill + idx[pos + 1:]
    return idx


def _stack_derivs(items: list, join: Callable):
    dirs = [s.d.shape[-1] for s in items if s.d is not None]
    if not dirs:
        return None
    k = dirs[0]
    return join([s.d if s.d is not None else s.v.zeros_ext(k) for s in items])


# --------------------------------------------------------------------------- intervals
class Interval(_Enclosure):
    """A batch of real intervals ``[lo, hi]`` (float64 tensors of one shape), outward rounded."""

    __slots__ = ("lo", "hi")
    level = 0

    def __init__(self, lo: Tensor, hi: Tensor | None = None) -> None:
        self.lo = lo
        self.hi = lo if hi is None else hi

    @staticmethod
    def const(x) -> Interval:
        if isinstance(x, Interval):
            return x
        t = _t(x)
        return Interval(t, t)

    @property
    def shape(self) -> torch.Size:
        return self.lo.shape

    @property
    def mid(self) -> Tensor:
        return (self.lo + self.hi) / 2

    def zeros_ext(self, k: int) -> Interval:
        z = torch.zeros(*self.shape, k, dtype=F64)
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
        return Interval(_down(self.lo + o.lo, REL1), _up(self.hi + o.hi, REL1))

    def _sub(self, o: Interval) -> Interval:
        return Interval(_down(self.lo - o.hi, REL1), _up(self.hi - o.lo, REL1))

    def _neg(self) -> Interval:
        return Interval(-self.hi, -self.lo)

    def _mul(self, o: Interval) -> Interval:
        if o.lo is o.hi or self.lo is self.hi:  # a point factor (a constant): two products suffice
            a, c = (self, o.lo) if o.lo is o.hi else (o, self.lo)
            p1, p2 = a.lo * c, a.hi * c
            return Interval(_down(torch.minimum(p1, p2), REL1), _up(torch.maximum(p1, p2), REL1))
        p = torch.stack(torch.broadcast_tensors(self.lo * o.lo, self.lo * o.hi, self.hi * o.lo, self.hi * o.hi))
        return Interval(_down(p.amin(0), REL1), _up(p.amax(0), REL1))

    def reciprocal(self) -> Interval:
        if not bool(((self.lo > 0) | (self.hi < 0)).all()):
            raise ValueError("interval division by an interval that contains 0")
        return Interval(_down(1.0 / self.hi, REL1), _up(1.0 / self.lo, REL1))

    def _div(self, o: Interval) -> Interval:
        return self._mul(o.reciprocal())

    def square(self) -> Interval:
        a, b = self.lo * self.lo, self.hi * self.hi
        lo = torch.where((self.lo <= 0) & (self.hi >= 0), torch.zeros_like(a), torch.minimum(a, b))
        return Interval(torch.clamp(_down(lo, REL1), min=0.0), _up(torch.maximum(a, b), REL1))

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
        return Interval(_down(base.lo ** n, rel), _up(base.hi ** n, rel))

    def sqrt(self) -> Interval:
        lo = torch.clamp(self.lo, min=0.0)
        return Interval(torch.clamp(_down(torch.sqrt(lo), RELT), min=0.0), _up(torch.sqrt(torch.clamp(self.hi, min=0.0)), RELT))

    def exp(self) -> Interval:
        return Interval(torch.clamp(_down(torch.exp(self.lo), RELT), min=0.0), _up(torch.exp(self.hi), RELT))

    def tanh(self) -> Interval:
        return Interval(torch.clamp(_down(torch.tanh(self.lo), RELT), min=-1.0),
                        torch.clamp(_up(torch.tanh(self.hi), RELT), max=1.0))

    def _periodic(self, fn: Callable, max_at: float, min_at: float) -> Interval:
        a, b = fn(self.lo), fn(self.hi)
        lo = _down(torch.minimum(a, b), RELT)
        hi = _up(torch.maximum(a, b), RELT)
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
        return Interval(_down(self.lo.sum(dim), rel, mag), _up(self.hi.sum(dim), rel, mag))

    def linear(self, weight: Tensor, bias: Tensor | None = None) -> Interval:
        """``x @ weight.T + bias`` along the last axis, with a constant (exact) ``weight (out, in)``."""
        mid = (self.lo + self.hi) / 2
        rad = _up(torch.maximum(self.hi - mid, mid - self.lo), REL1)
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


# --------------------------------------------------------------------------- affine forms
def _sum_up(t: Tensor, dim: int = -1) -> Tensor:
    """An upper bound of the real sum of the non-negative ``t`` along ``dim``."""
    return _up(t.sum(dim), 2 * (t.shape[dim] + 2) * EPS)


def _secant(f: Callable, df: Callable, a: Tensor, b: Tensor) -> Tensor:
    """The slope ``(f(b) - f(a)) / (b - a)`` in float64 (``df(a)`` where ``b == a``): any float is sound as the
    slope of a linearisation (its error bound is computed for the slope actually used)."""
    wide = b > a
    sec = (f(b) - f(a)) / torch.where(wide, b - a, torch.ones_like(a))
    return torch.where(wide, sec, df(a))


def _convex_error(f: Callable, df: Callable, p: Tensor, q: Tensor, lam: Tensor, xt: Tensor,
                  convex: bool = True) -> Interval:
    """An interval containing ``e(x) = f(x) - lam x`` for every ``x`` in ``[p, q]`` where ``f`` is convex
    (``convex=False``: concave) on ``[p, q]``.

    ``f``, ``df``: the function and its derivative on :class:`Interval` (outward rounded). ``xt``: a point of
    ``[p, q]``, best where ``f' = lam``. A convex ``e`` is largest at an end of ``[p, q]`` and lies above its
    tangent at ``xt``: ``e(x) >= e(xt) + e'(xt) (x - xt)``, whose least value over ``[p, q]`` bounds ``e`` below
    (concave: mirrored). All of it in interval arithmetic, so rounding is covered.
    """
    lam_ = Interval.const(lam)
    pp, qq, xx = Interval.const(p), Interval.const(q), Interval.const(xt)
    ep, eq, ex = f(pp) - lam_ * pp, f(qq) - lam_ * qq, f(xx) - lam_ * xx
    tangent = ex + (df(xx) - lam_) * (Interval(p, q) - xx)
    if convex:
        return Interval(tangent.lo, torch.maximum(ep.hi, eq.hi))
    return Interval(torch.minimum(ep.lo, eq.lo), tangent.hi)


def _dtanh(x: Interval) -> Interval:
    return 1.0 - x.tanh().square()


def _dsqrt(x: Interval) -> Interval:
    s = x.sqrt()
    with torch.no_grad():
        return Interval(_down(0.5 / s.hi, REL1), _up(0.5 / s.lo, REL1))  # 0.5 / 0 = inf (then a fallback)


def _drecip(x: Interval) -> Interval:
    return -x.reciprocal().square()


def quadratic_max(g: Tensor, q: Tensor) -> Tensor:
    """An upper bound ``(...)`` of ``max over e in [-1, 1]^K of g . e + e^T q e`` for ``g (..., K)`` and a
    symmetric ``q (..., K, K)``, exact up to rounding when ``q``'s diagonal is non-negative.

    The smaller of two bounds. Vertices: each concave diagonal term (``q_kk < 0``) is replaced by its tangent at
    ``t_k`` (``q_kk e^2 <= q_kk (2 t_k e - t_k^2)``, ``t_k`` the one-coordinate maximiser); what is left is convex
    in every coordinate separately, so its maximum over the cube is at one of the ``2^K`` vertices, all evaluated
    (two matrix products), padded outward for the rounding of the float64 sums. Dual: :func:`_dual_max`, for a
    ``q`` curved downward along mixed directions (measured on the cart-pole's default pair: its proof in 114,200
    boxes instead of 168,403).
    """
    k = g.shape[-1]
    verts = _vertices(k, g.device)  # (2^K, K)
    diag = torch.diagonal(q, dim1=-2, dim2=-1)
    neg = torch.clamp(diag, max=0.0)
    t = torch.where(neg < 0, torch.clamp(g / (-2.0 * torch.where(neg < 0, neg, -1.0)), -1.0, 1.0), 0.0)
    g_t = g + 2.0 * neg * t
    q_t = q - torch.diag_embed(neg)
    outer = (verts.unsqueeze(-1) * verts.unsqueeze(-2)).flatten(1)  # (2^K, K^2)
    values = g_t @ verts.T + q_t.flatten(-2) @ outer.T  # (..., 2^K)
    best = values.amax(-1) - (neg * t * t).sum(-1)
    mag = g.abs().sum(-1) + 2.0 * q.abs().sum((-2, -1))
    vertex = best + 4 * (k * k + k + 4) * EPS * mag + TINY
    return torch.minimum(vertex, _dual_max(g, q))


def _dual_max(g: Tensor, q: Tensor) -> Tensor:
    """A second upper bound of ``max over e in [-1, 1]^K of g . e + e^T q e``, tight where the vertex bound is
    not: ``q`` strongly curved downward along directions that mix the coordinates (a stiff closed loop's
    ``Vdot`` near x*, where the linear part's growth along the stiff direction is cancelled by the quadratic's
    curvature, which a bound term by term cannot see).

    For ``t >= lambda_max(q)``, ``M = t I - q`` is positive semidefinite and, for any vector ``y``,
    ``g . e + e^T q e = t |e|^2 - (e - y)^T M (e - y) + (g - 2 M y) . e + y^T M y
    <= max(t, 0) K + sum_k |g - 2 M y|_k + y^T M y``. ``t`` is the best of a geometric grid for the
    eigendecomposition's estimate, ``y = M^-1 g / 2``; the bound holds for any ``y``, so only ``M``'s
    semidefiniteness is checked (its smallest computed eigenvalue above a pad for the eigensolver's error) and the
    few sums are padded for rounding. ``inf`` where the check fails or an input is not finite.
    """
    k = g.shape[-1]
    finite = torch.isfinite(g).all(-1) & torch.isfinite(q).flatten(-2).all(-1)
    g = torch.where(finite[..., None], g, 0.0)
    q = torch.where(finite[..., None, None], q, 0.0)
    asym = EPS * q.abs().sum((-2, -1))  # e'qe = e'q_sym e; rounding of the symmetrised entries
    q = (q + q.mT) * 0.5  # eigh reads one triangle
    lam, u = torch.linalg.eigh(q)
    gu = (u.mT @ g.unsqueeze(-1)).squeeze(-1)
    size = q.flatten(-2).norm(dim=-1)
    steps = torch.pow(2.0, torch.arange(-14, 15, dtype=F64, device=g.device))
    t = (lam[..., -1:] + (g.norm(dim=-1, keepdim=True) / (2 * math.sqrt(k))).clamp_min(1e-300) * steps
         + 2e-11 * size[..., None] + 1e-300)  # (..., J): t - lambda_max > 0 up to the eigensolver's error
    estimate = t.clamp_min(0) * k + 0.25 * (gu.unsqueeze(-2).square() / (t[..., None] - lam.unsqueeze(-2))).sum(-1)
    t = t.gather(-1, estimate.argmin(-1, keepdim=True))[..., 0]
    y = 0.5 * (u @ (gu / (t[..., None] - lam)).unsqueeze(-1)).squeeze(-1)
    m = t[..., None, None] * torch.eye(k, dtype=F64, device=g.device) - q
    my = (m @ y.unsqueeze(-1)).squeeze(-1)
    m_y = (m.abs() @ y.abs().unsqueeze(-1)).squeeze(-1)
    value = t.clamp_min(0) * k + (g - 2 * my).abs().sum(-1) + (y * my).sum(-1)
    pad = 8 * (k + 2) * EPS * (g.abs().sum(-1) + 2 * m_y.sum(-1) + (y.abs() * m_y).sum(-1) + t.abs() * k) + TINY
    semidefinite = torch.linalg.eigvalsh(m)[..., 0] > 1e-11 * m.flatten(-2).norm(dim=-1) + 4 * EPS * t.abs() + 1e-300
    value = value + pad + asym
    return torch.where(finite & semidefinite & torch.isfinite(value), value, torch.inf)


_VERTS: dict = {}


def _vertices(k: int, device) -> Tensor:
    key = (k, str(device))
    if key not in _VERTS:
        _VERTS[key] = torch.cartesian_prod(*[torch.tensor([-1.0, 1.0], dtype=F64)] * k).reshape(-1, k).to(device)
    return _VERTS[key]


def _max_lin_quad(g: Tensor, d: Tensor) -> Tensor:
    """``max over e in [-1, 1] of g e + d e^2`` for each symbol, ``(..., K)`` (the vertex ``-g / 2d`` where it
    lies inside and ``d < 0``, else an end); float64, not yet padded for rounding."""
    a = g.abs()
    inner = (d < 0) & (a < -2.0 * d)
    return torch.where(inner, a * a / (-4.0 * torch.where(inner, d, -1.0)), a + d)


def _sym_outer(a: Tensor, b: Tensor) -> Tensor:
    """``(a b^T + b a^T) / 2`` over the last axis, ``(..., K) -> (..., K, K)``: the symmetric coefficients of
    ``(a . e)(b . e)`` (quadratic parts are kept symmetric, so their range needs no symmetrising)."""
    if a is b:
        return a.unsqueeze(-1) * a.unsqueeze(-2)
    ab = a.unsqueeze(-1) * b.unsqueeze(-2)
    return (ab + ab.transpose(-1, -2)) * 0.5


class Affine(_Enclosure):
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

    Linear operations (``+ -``, products with constants, ``linear``, ``sum``, stacking, indexing) are exact
    on the linear and quadratic parts. ``x * y`` keeps both first-order parts and the product of the linear
    parts (as ``q``), and bounds the other products of deviations (third order and remainders) by intervals.
    The smooth unary functions (``tanh``, ``sin``, ``cos``, ``exp``, ``1 / x``) use the second-order Taylor form
    about the centre (:meth:`_second_order`: ``f'(c) (x - c)`` and ``f''(c) L^2 / 2`` kept, a third-order
    Lagrange remainder over the range); where an input's range is wide, elementwise the first-order form
    instead when its error is the smaller (a secant slope with an exact-by-convexity error bound for ``tanh``,
    ``exp``, ``1 / x``; the midpoint slope with a second-order remainder for ``sin``, ``cos``). ``square`` is
    ``x * x``; ``sqrt`` keeps the secant form (its quadratic input part passes through scaled by the slope).
    Every function falls back elementwise to the interval enclosure where its remainder alone is as wide.
    ``clamp`` and ``abs`` use the secant with the error's exact range (it is piecewise
    linear). :meth:`box` makes the form of a batch of boxes; :meth:`to_interval` encloses a form.
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
        lo, hi = _t(lo), _t(hi)
        c = (lo + hi) / 2
        rad = _up(torch.maximum(hi - c, c - lo), REL1)
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
            return Affine(c, None, Interval(_down(x.lo - c, REL1), _up(x.hi - c, REL1)))
        return Affine(_t(x))

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
        return torch.zeros_like(self.c) if self.g is None else _sum_up(self.g.abs())

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
            return Interval(_down(h.lo - s, REL1), _up(h.hi + s, REL1))
        if self._dv is None:  # each symbol's g_k e_k + q_kk e_k^2 bounded jointly, the cross terms by |q_kl|
            q, k = self.q, self.q.shape[-1]
            diag = torch.diagonal(q, dim1=-2, dim2=-1)
            total = q.abs().sum((-2, -1))
            off = torch.clamp(total - diag.abs().sum(-1), min=0.0)
            hi = _max_lin_quad(self.g, diag).sum(-1) + off
            lo = -_max_lin_quad(self.g, -diag).sum(-1) - off
            pad = 8 * (k * k + 4) * EPS * (self.g.abs().sum(-1) + total) + TINY
            self._dv = Interval(_down(lo - pad + self.r.lo, REL1), _up(hi + pad + self.r.hi, REL1))
        return self._dv

    def to_interval(self) -> Interval:
        """The interval enclosure ``(B, ...)`` of the forms."""
        return Interval.const(self.c) + self._dev()

    def tight_interval(self, max_symbols: int = 8) -> Interval:
        """:meth:`to_interval` with the linear and quadratic parts bounded jointly over the cube's vertices
        (:func:`quadratic_max`; the cross terms then cancel where they can) when there are at most
        ``max_symbols`` symbols: ``2^K`` evaluations per entry, for final results rather than every step."""
        if self.q is None or self.g is None or self.n_symbols > max_symbols:
            return self.to_interval()
        hi = quadratic_max(self.g, self.q)
        lo = -quadratic_max(-self.g, -self.q)
        dev = Interval(_down(lo + self.r.lo, REL1), _up(hi + self.r.hi, REL1))
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
        return Affine(c, g, Interval(_down(const.lo - c - pad, REL1), _up(const.hi - c + pad, REL1)), q)

    @staticmethod
    def _qpad(q: Tensor | None, rel: float = REL1):
        """A bound of the value error of a quadratic part whose every coefficient carries a relative error
        ``rel`` (``|e_k e_l| <= 1``)."""
        return 0.0 if q is None else rel * _sum_up(_sum_up(q.abs()))

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
        idx = _fix_index(idx, self.ndim)
        return Affine(self.c[idx], None if self.g is None else self.g[idx], self.r[idx],
                      None if self.q is None else self.q[idx])

    def unbind(self, dim: int = 0) -> tuple:
        dim = _normdim(dim, self.ndim)
        if dim == 0:
            self._batch_check("unbinding")
        gs = self.g.unbind(dim) if self.g is not None else (None,) * self.c.shape[dim]
        qs = self.q.unbind(dim) if self.q is not None else (None,) * self.c.shape[dim]
        return tuple(Affine(c, g, r, q) for c, g, r, q in zip(self.c.unbind(dim), gs, self.r.unbind(dim), qs))

    def unsqueeze(self, dim: int) -> Affine:
        dim = _normdim(dim, self.ndim + 1)
        if dim == 0:
            self._batch_check("moving")
        return Affine(self.c.unsqueeze(dim), None if self.g is None else self.g.unsqueeze(dim), self.r.unsqueeze(dim),
                      None if self.q is None else self.q.unsqueeze(dim))

    def transpose(self, a: int, b: int) -> Affine:
        a, b = _normdim(a, self.ndim), _normdim(b, self.ndim)
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
    def join(items: list, dim: int, fn: Callable) -> Affine:
        """``torch.stack`` or ``torch.cat`` (``fn``) of forms along a non-negative ``dim``."""
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
        return g, REL1 * _sum_up(g.abs())

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
        const = Interval(_down(c, REL1), _up(c, REL1)) + (self.r + o.r)
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
        return Affine._centred(const, g, REL1 * _sum_up(g.abs()) + Affine._qpad(q), q)

    def _mul(self, o: Affine) -> Affine:
        if self.g is None and o.g is None and self.q is None and o.q is None:
            return Affine.const(self.to_interval() * o.to_interval())
        # with x = cx + Lx + Qx + rx (linear, quadratic, remainder):
        # x y = cx cy + (cx Ly + cy Lx) + (cx Qy + cy Qx + Lx Ly) + cx ry + cy rx + Lx (Qy + ry) + (Qx + rx)(y - cy)
        t1 = None if self.g is None else o.c.unsqueeze(-1) * self.g
        t2 = None if o.g is None else self.c.unsqueeze(-1) * o.g
        g, pad = Affine._gsum(t1, t2)
        if g is not None:
            pad = pad + REL1 * _sum_up(g.abs())  # the products' own rounding
        parts = [o.c[..., None, None] * self.q if self.q is not None else None,
                 self.c[..., None, None] * o.q if o.q is not None else None,
                 _sym_outer(self.g, o.g) if self.g is not None and o.g is not None else None]
        q = None
        for part in parts:
            if part is not None:
                q = part if q is None else q + part
        if q is not None:
            pad = pad + Affine._qpad(q, 4 * REL1)  # each entry: up to three products and two sums
        cx, cy = Interval.const(self.c), Interval.const(o.c)
        lx = self._lin()
        const = (cx * cy + cx * o.r + cy * self.r + Interval(-lx, lx) * o._higher()
                 + self._higher() * o._dev())
        return Affine._centred(const, g, pad, q)

    def reciprocal(self) -> Affine:
        iv = self.to_interval()
        if not bool(((iv.lo > 0) | (iv.hi < 0)).all()):
            raise ValueError("affine division by a form whose range contains 0")
        fallback = iv.reciprocal()
        if self.g is None:
            return Affine.const(fallback)

        def first() -> Affine:
            # on the positive range [a, b] of |x|, 1/y is convex; 1/x = s (1/y) with y = s x, s = sign: so
            # 1/x = lam x + s e(y) with the slope lam and error e of 1/y
            neg = iv.hi < 0
            a, b = torch.where(neg, -iv.hi, iv.lo), torch.where(neg, -iv.lo, iv.hi)
            lam = -1.0 / (a * b)  # the secant of 1/y over [a, b]
            err = _convex_error(Interval.reciprocal, _drecip, a, b, lam, torch.clamp(torch.sqrt(a * b), a, b))
            return self._scale_shift(lam, Interval(torch.where(neg, -err.hi, err.lo), torch.where(neg, -err.lo, err.hi)))

        rc = Interval.const(self.c).reciprocal()
        rc2 = rc.square()
        second = self._second_order(rc, -rc2, rc2 * rc, fallback.square().square() * -6.0)
        near = torch.minimum(iv.lo.abs(), iv.hi.abs())
        return Affine._pick(second, first, (iv.hi - iv.lo) > near * 0.5)._guard(fallback)

    def _div(self, o: Affine) -> Affine:
        return self._mul(o.reciprocal())

    def _second_order(self, f0: Interval, s1: Interval, s2: Interval, d3: Interval) -> Affine:
        """The second-order Taylor form about the centre ``c``, with ``d = x - c``::

            f(x) = f(c) + f'(c) d + f''(c) d^2 / 2 + f'''(xi) d^3 / 6

        ``d = L + H`` (linear part; quadratic part plus remainder): ``f'(c) (L + Q)`` and ``f''(c) L^2 / 2`` are
        kept (linear and quadratic parts), everything else is bounded by intervals. ``f0, s1, s2``: enclosures
        of ``f(c), f'(c), f''(c) / 2``; ``d3``: of ``f'''`` over the range (all outward rounded)."""
        a1, a2 = s1.mid, s2.mid
        dev, higher, lin = self._dev(), self._higher(), self._lin()
        a1_, a2_ = Interval.const(a1), Interval.const(a2)
        rest_sq = Interval(-lin, lin) * higher * 2.0 + higher.square()  # d^2 - L^2
        const = (f0 + (s1 - a1_) * dev + a1_ * self.r + (s2 - a2_) * dev.square() + a2_ * rest_sq
                 + d3 * dev.pow_int(3) * (1.0 / 6.0))
        g = a1.unsqueeze(-1) * self.g
        q = (a2.unsqueeze(-1) * self.g).unsqueeze(-1) * self.g.unsqueeze(-2)
        if self.q is not None:
            q = q + a1[..., None, None] * self.q
        return Affine._centred(const, g, REL1 * _sum_up(g.abs()) + Affine._qpad(q, 4 * REL1), q)

    @staticmethod
    def _pick(second: Affine, first: Callable[[], Affine], wide: Tensor) -> Affine:
        """``second`` (a second-order form of a function), or where its remainder is at least as wide as the
        first-order form's part above first order, ``first()``: computed only when some input is ``wide``
        (elsewhere the third-order remainder is the smaller; early in a branch and bound, on wide boxes, the
        secant's error is)."""
        if not bool(wide.any()):
            return second
        lin1 = first()
        h1 = lin1._higher()
        return Affine._where((second.r.hi - second.r.lo) < (h1.hi - h1.lo), second, lin1)

    def _convex_fn(self, f: Callable, df: Callable, root: Callable, fallback: Interval, convex: bool = True,
                   f_point: Callable | None = None) -> Affine:
        """``f`` convex (or concave) on the range: secant slope, error bound by :func:`_convex_error`."""
        iv = self.to_interval()
        if self.g is None:
            return Affine.const(fallback)
        a, b = iv.lo, iv.hi
        fp = f_point if f_point is not None else (lambda t: f(Interval.const(t)).mid)
        lam = _secant(fp, lambda t: df(Interval.const(t)).mid, a, b)
        err = _convex_error(f, df, a, b, lam, torch.clamp(root(lam), a, b), convex)
        return self._scale_shift(lam, err)._guard(fallback)

    def square(self) -> Affine:
        """``x * x`` (its quadratic part exact), or the secant form where that is narrower."""
        fallback = self.to_interval().square()
        if self.g is None:
            return Affine.const(fallback)
        return self._mul(self)._guard(fallback)

    def exp(self) -> Affine:
        iv = self.to_interval()
        fallback = iv.exp()
        if self.g is None:
            return Affine.const(fallback)
        ec = Interval.const(self.c).exp()
        second = self._second_order(ec, ec, ec * 0.5, fallback)
        return Affine._pick(second, lambda: self._convex_fn(Interval.exp, Interval.exp, torch.log, fallback,
                                                            f_point=torch.exp), (iv.hi - iv.lo) > 1.0)._guard(fallback)

    def sqrt(self) -> Affine:
        """Square root of ``max(x, 0)`` (as :meth:`Interval.sqrt`: the argument is taken to be non-negative)."""
        iv = self.to_interval()
        fallback = iv.sqrt()
        if self.g is None:
            return Affine.const(fallback)
        a, b = torch.clamp(iv.lo, min=0.0), torch.clamp(iv.hi, min=0.0)
        wide = b > a
        lam = torch.where(wide, (torch.sqrt(b) - torch.sqrt(a)) / torch.where(wide, b - a, 1.0), 0.0)
        xt = torch.clamp(torch.where(lam > 0, 0.25 / (lam * lam), b), a, b)
        err = _convex_error(Interval.sqrt, _dsqrt, a, b, lam, xt, convex=False)
        zero = b <= 0  # the range is {0}
        err = Interval(torch.where(zero, 0.0, err.lo), torch.where(zero, 0.0, err.hi))
        return self._scale_shift(lam, err)._guard(fallback)

    def tanh(self) -> Affine:
        iv = self.to_interval()
        fallback = iv.tanh()
        if self.g is None:
            return Affine.const(fallback)

        def first() -> Affine:
            a, b = iv.lo, iv.hi
            lam = torch.clamp(_secant(torch.tanh, lambda t: 1.0 - torch.tanh(t) ** 2, a, b), 0.0, 1.0)
            root = torch.atanh(torch.sqrt(torch.clamp(1.0 - lam, 0.0, 1.0)))  # tanh'(+-root) = lam
            zero = torch.zeros_like(a)
            q1 = torch.maximum(torch.minimum(b, zero), a)  # tanh is convex on [a, q1] (x <= 0, or the point a)
            p2 = torch.minimum(torch.maximum(a, zero), b)  # and concave on [p2, b]
            e1 = _convex_error(Interval.tanh, _dtanh, a, q1, lam, torch.clamp(-root, a, q1), convex=True)
            e2 = _convex_error(Interval.tanh, _dtanh, p2, b, lam, torch.clamp(root, p2, b), convex=False)
            return self._scale_shift(lam, e1.hull(e2))

        t = Interval.const(self.c).tanh()  # tanh' = 1 - t^2, tanh'' / 2 = -t (1 - t^2), tanh''' = -2 (1 - t^2)(1 - 3 t^2)
        s1, t2 = 1.0 - t.square(), fallback.square()
        second = self._second_order(t, s1, -(t * s1), (1.0 - t2) * (1.0 - t2 * 3.0) * -2.0)
        return Affine._pick(second, first, (iv.hi - iv.lo) > 1.0)._guard(fallback)

    def _taylor2(self, f: Callable, df: Callable, d2f: Callable, d3f: Callable, fallback: Interval) -> Affine:
        """The second-order form (:meth:`_second_order`, ``d3f`` the third derivative); where the range is wide,
        or where narrower, the midpoint slope with a second-order Lagrange remainder:
        ``f(x) = f(m) + f'(m)(x - m) + f''(xi)(x - m)^2 / 2`` with ``f''`` enclosed over the range."""
        iv = self.to_interval()
        if self.g is None:
            return Affine.const(fallback)

        def first() -> Affine:
            m = iv.mid
            mm = Interval.const(m)
            slope = df(mm)
            lam = slope.mid
            dev = iv - mm
            err = f(mm) + (slope - Interval.const(lam)) * dev + d2f(iv) * dev.square() * 0.5  # f(x) - lam (x - m)
            return self._scale_shift(lam, err - Interval.const(lam) * mm)

        cc = Interval.const(self.c)
        second = self._second_order(f(cc), df(cc), d2f(cc) * 0.5, d3f(iv))
        return Affine._pick(second, first, (iv.hi - iv.lo) > 1.0)._guard(fallback)

    def sin(self) -> Affine:
        return self._taylor2(Interval.sin, Interval.cos, lambda x: -x.sin(), lambda x: -x.cos(),
                             self.to_interval().sin())

    def cos(self) -> Affine:
        return self._taylor2(Interval.cos, lambda x: -x.sin(), lambda x: -x.cos(), Interval.sin,
                             self.to_interval().cos())

    def _piecewise_linear(self, f: Callable, breaks: Sequence[Tensor], fallback: Interval) -> Affine:
        """``f`` continuous and piecewise linear with kinks at ``breaks`` (exact in float64): the error of
        the secant is piecewise linear too, so its range is its hull at the ends and the kinks in range."""
        iv = self.to_interval()
        if self.g is None:
            return Affine.const(fallback)
        a, b = iv.lo, iv.hi
        lam = _secant(f, lambda t: torch.zeros_like(t), a, b)
        lam_ = Interval.const(lam)
        err = None
        for t in [a, b, *(torch.clamp(br.expand(a.shape), a, b) for br in breaks)]:
            e = Interval.const(f(t)) - lam_ * Interval.const(t)
            err = e if err is None else err.hull(e)
        return self._scale_shift(lam, err)._guard(fallback)

    def abs(self) -> Affine:
        iv = self.to_interval()
        out = self._piecewise_linear(torch.abs, [torch.zeros_like(iv.lo)], iv.abs())
        if self.g is None:
            return out
        return Affine._where(iv.lo >= 0, self, Affine._where(iv.hi <= 0, -self, out))

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
        dim = _normdim(dim, self.ndim)
        if dim == 0:
            self._batch_check("summing over")
        rel = 2 * (self.c.shape[dim] + 2) * EPS
        c = self.c.sum(dim)
        mag = self.c.abs().sum(dim)
        const = Interval(_down(c, rel, mag), _up(c, rel, mag)) + self.r.sum(dim)
        q = None if self.q is None else self.q.sum(dim)
        qpad = 0.0 if q is None else rel * _sum_up(_sum_up(self.q.abs().sum(dim)))
        if self.g is None:
            return Affine._centred(const, None, qpad, q)
        g = self.g.sum(dim)
        return Affine._centred(const, g, rel * _sum_up(self.g.abs().sum(dim)) + qpad, q)

    def linear(self, weight: Tensor, bias: Tensor | None = None) -> Affine:
        """``x @ weight.T + bias`` along the last axis, with a constant (exact) ``weight (out, in)``."""
        rel = 4 * (weight.shape[1] + 4) * EPS
        w_abs = weight.abs().T
        c = self.c @ weight.T
        mag = self.c.abs() @ w_abs
        if bias is not None:
            c = c + bias
            mag = mag + bias.abs()
        const = Interval(_down(c, rel, mag), _up(c, rel, mag)) + self.r.linear(weight)
        q, qpad = None, 0.0
        if self.q is not None:
            k = self.q.shape[-1]
            q = torch.matmul(weight, self.q.flatten(-2)).unflatten(-1, (k, k))  # (out, in) @ (..., in, K K)
            qpad = rel * _up(_sum_up(_sum_up(self.q.abs())) @ w_abs, rel)
        if self.g is None:
            return Affine._centred(const, None, qpad, q)
        g = torch.matmul(weight, self.g)  # (out, in) @ (..., in, K)
        pad = rel * _up(_sum_up(self.g.abs()) @ w_abs, rel)
        return Affine._centred(const, g, pad + qpad, q)

    def clamp(self, low: Tensor, high: Tensor) -> Affine:
        iv = self.to_interval()
        low, high = _t(low).to(iv.lo.device), _t(high).to(iv.lo.device)
        out = self._piecewise_linear(lambda t: torch.clamp(t, low, high), [low, high], iv.clamp(low, high))
        if self.g is None:
            return out
        return Affine._where((iv.lo >= low) & (iv.hi <= high), self, out)  # inactive: the identity, exactly

    def clamp_slope(self, low: Tensor, high: Tensor) -> Interval:
        """Enclosure of the (Clarke) derivative of ``clamp(., low, high)`` over the range (see :class:`Interval`)."""
        return self.to_interval().clamp_slope(low, high)


# --------------------------------------------------------------------------- dual numbers
class Dual(_Enclosure):
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
        idx = _fix_index(idx, self.ndim)
        return Dual(self.v[idx], None if self.d is None else self.d[idx])

    def unbind(self, dim: int = 0) -> tuple:
        dim = _normdim(dim, self.ndim)
        vs = self.v.unbind(dim)
        ds = self.d.unbind(dim) if self.d is not None else (None,) * len(vs)
        return tuple(Dual(a, b) for a, b in zip(vs, ds))

    def unsqueeze(self, dim: int) -> Dual:
        dim = _normdim(dim, self.ndim + 1)
        return Dual(self.v.unsqueeze(dim), None if self.d is None else self.d.unsqueeze(dim))

    def transpose(self, a: int, b: int) -> Dual:
        a, b = _normdim(a, self.ndim), _normdim(b, self.ndim)
        return Dual(self.v.transpose(a, b), None if self.d is None else self.d.transpose(a, b))

    def sum(self, dim: int | None = None) -> Dual:
        if dim is None:
            raise ValueError("sum over all axes of a dual number is not supported; give dim")
        dim = _normdim(dim, self.ndim)
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


def _dsum(a, b):
    if a is None:
        return b
    if b is None:
        return a
    return a + b


def norm(x, dim: int = -1):
    """Euclidean norm along ``dim`` with a Clarke-gradient enclosure (sound also where the vector is 0)."""
    if isinstance(x, (Interval, Affine)):
        return x.square().sum(dim).sqrt()
    if not (isinstance(x, Dual) and isinstance(x.v, (Interval, Affine))):
        raise TypeError("norm is supported on intervals, affine forms and first-order duals")
    dim = _normdim(dim, x.ndim)
    value = x.v.square().sum(dim).sqrt()
    if x.d is None:
        return Dual(value, None)
    # d||x|| = (x / ||x||) . dx, with x / ||x|| in [-1, 1] componentwise (the unit ball at x = 0)
    xv, val = x.v.to_interval(), value.to_interval()
    unit = Interval(-torch.ones_like(xv.lo), torch.ones_like(xv.lo))
    pos = val.lo.unsqueeze(dim) > 0
    safe = Interval(torch.where(pos, val.lo.unsqueeze(dim), 1.0), torch.where(pos, val.hi.unsqueeze(dim), 1.0))
    q = (xv / safe).intersect(-1.0, 1.0)
    q = Interval(torch.where(pos, q.lo, unit.lo), torch.where(pos, q.hi, unit.hi))
    return Dual(value, (q.unsqueeze(-1) * x.d).sum(dim))

