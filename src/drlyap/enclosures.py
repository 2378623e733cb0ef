"""Enclosure arithmetic: batched intervals and forward-mode dual numbers over them, outward rounded.

A leaf numeric module (it imports only torch). The networks, the systems' dynamics and the decrease
conditions are written once with torch operations; run on these types instead of tensors, the same code
returns sound enclosures of its values and derivatives over boxes. That is how the verifier bounds
exactly what training minimises (no second encoding of any formula).

* :class:`Interval` -- batched interval tensors ``[lo, hi]`` (any shape), float64, outward rounded: every
  computed endpoint is widened by an error bound of the floating-point operation that produced it, so it
  encloses the real value.
* :class:`Dual` -- forward-mode dual numbers whose value and derivative are themselves enclosures
  (intervals or duals). ``Dual(Interval)`` over a box encloses a function's value and gradient there;
  ``Dual(Dual(Interval))`` adds a second group of directions (e.g. parameter derivatives, or the Hessian).
* Both implement ``__torch_function__`` and the Python operators, so code written with ``+ - * /``,
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
    """Common operator plumbing and the ``__torch_function__`` bridge of :class:`Interval` and :class:`Dual`."""

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
        return self.base.lo.device

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
    """True for :class:`Interval` and :class:`Dual` (False for tensors and numbers)."""
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
    return lift(a, level), lift(b, level)


def _normdim(dim: int, ndim: int) -> int:
    if not -ndim <= dim < ndim:
        raise IndexError(f"dimension {dim} out of range for {ndim} dimensions")
    return dim % ndim


def stack(seq: Sequence, dim: int = 0):
    level = max(max(_level(s) for s in seq), 0)
    items = [lift(s, level) for s in seq]
    if level == 0:
        return Interval(torch.stack([s.lo for s in items], dim), torch.stack([s.hi for s in items], dim))
    d = _normdim(dim, items[0].ndim + 1)
    return Dual(stack([s.v for s in items], d), _stack_derivs(items, lambda ds: stack(ds, d)))


def cat(seq: Sequence, dim: int = 0):
    level = max(max(_level(s) for s in seq), 0)
    items = [lift(s, level) for s in seq]
    if level == 0:
        return Interval(torch.cat([s.lo for s in items], dim), torch.cat([s.hi for s in items], dim))
    d = _normdim(dim, items[0].ndim)
    return Dual(cat([s.v for s in items], d), _stack_derivs(items, lambda ds: cat(ds, d)))


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

    def contains(self, x: Tensor) -> Tensor:
        return (self.lo <= x) & (x <= self.hi)

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

    def zeros_ext(self, k: int) -> Dual:
        return Dual(self.v.zeros_ext(k), None)

    def __repr__(self) -> str:
        return f"Dual(v={self.v!r}, d={self.d!r})"

    # ---- structure
    def _fix_index(self, idx):
        if not isinstance(idx, tuple):
            idx = (idx,)
        if any(i is None for i in idx):
            raise IndexError("None (new axis) indexing is not supported on dual numbers; use unsqueeze")
        if any(i is Ellipsis for i in idx):
            pos = idx.index(Ellipsis)
            fill = self.ndim - (len(idx) - 1)
            idx = idx[:pos] + (slice(None),) * fill + idx[pos + 1:]
        return idx

    def __getitem__(self, idx) -> Dual:
        idx = self._fix_index(idx)
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
        if not isinstance(self.v, Interval):
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
    if isinstance(x, Interval):
        return x.square().sum(dim).sqrt()
    if not (isinstance(x, Dual) and isinstance(x.v, Interval)):
        raise TypeError("norm is supported on intervals and first-order duals")
    dim = _normdim(dim, x.ndim)
    value = x.v.square().sum(dim).sqrt()
    if x.d is None:
        return Dual(value, None)
    # d||x|| = (x / ||x||) . dx, with x / ||x|| in [-1, 1] componentwise (the unit ball at x = 0)
    unit = Interval(-torch.ones_like(x.v.lo), torch.ones_like(x.v.lo))
    pos = value.lo.unsqueeze(dim) > 0
    safe = Interval(torch.where(pos, value.lo.unsqueeze(dim), 1.0), torch.where(pos, value.hi.unsqueeze(dim), 1.0))
    q = (x.v / safe).intersect(-1.0, 1.0)
    q = Interval(torch.where(pos, q.lo, unit.lo), torch.where(pos, q.hi, unit.hi))
    return Dual(value, (q.unsqueeze(-1) * x.d).sum(dim))

