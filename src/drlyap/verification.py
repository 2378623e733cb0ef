"""Sound verification of the learned decrease condition by branch and bound (SPEC §5, §6).

What is proved
--------------
For a trained pair (V, pi) and a condition residual ``c(z)`` (see :mod:`drlyap.conditions`), the
verifier proves ``c(z) <= 0`` for every local state ``z`` in ``X_delta`` (the local state box minus
the open ball ``||z|| < delta``), or finds a state where ``c(z) > 0``. The networks are the stored
weights read as float64 numbers and evaluated in exact real arithmetic; every bound below is computed
in float64 with outward rounding (each computed endpoint is widened by an error bound of the
floating-point operation that produced it), so it encloses the real value.

Machinery
---------
* :class:`Interval` -- batched interval tensors ``[lo, hi]`` (any shape), with outward rounding.
* :class:`Dual` -- forward-mode dual numbers whose value and derivative are themselves enclosures
  (intervals or duals). ``Dual(Interval)`` carries an interval value and an interval gradient over a
  box; run through the hand-written input gradient of V it encloses the Hessian of V.
  ``Dual(Dual(Interval))`` adds a second group of directions: the parameter derivative ``W = dF/dp``
  at ``p0`` together with its gradient in the state.
* Both implement ``__torch_function__`` and Python operators, so a system's ``dynamics`` written once
  with torch ops (``+ - * /``, ``**`` by an int, ``torch.sin/cos/tanh/exp/sqrt/square``,
  ``torch.stack/cat``, ``unbind``, indexing) runs unchanged on them.
* The condition is bounded over a box in two ways and the tighter bound is kept: the plain interval
  bound, and the mean-value form ``c(centre) + [grad c over the box] . (box - centre)`` (the gradient
  enclosure comes from the dual numbers; for the clamp of the controller and the norms the enclosure is
  of the Clarke generalised gradient, for which the mean-value theorem still holds).
* Branch and bound: boxes whose upper bound is ``<= 0`` are verified, a box whose centre violates the
  condition is a counterexample (re-checked with the ordinary torch code path of
  :func:`drlyap.conditions.decrease_terms`), the rest are bisected along their widest normalised
  side until a time limit, box budget or minimum box size is reached.

Entry points: :func:`verify_run` (a run directory's trained condition, the uniform DR margin, or the
true model at a user's ``xi``), :func:`verify_condition`, :func:`uniform_margin`, :func:`certified_roa`.

Limits
------
* The claim is about the float64 reading of the weights in real arithmetic; training and simulation run
  the networks in float32. Counterexamples report the residual both ways (they agreed to 4 digits on the
  runs tried).
* A box that straddles the sphere ``||z|| = delta`` is bounded as a whole, so a violation just inside the
  ball keeps it unverified down to the minimum box size (the verdict is then ``unknown``, never wrong).
* Costs grow exponentially with the state dimension (boxes); meant for 2-3 states.
* The region of attraction certificate (:func:`certified_roa`) needs ``{V <= c}`` to contain the delta-ball;
  where V rises steeply inside the ball (mountain car: delta mixes position and velocity units) none exists.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field

import torch
from torch import Tensor

from drlyap.conditions import DRPointwise, Nominal, cvar_bound, decrease_terms
from drlyap.networks import Controller, LinearController, Lyapunov, QuadraticLyapunov, TanhMLP
from drlyap.rundir import jsonable
from drlyap.systems import UncertainSystem

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
                        "torch.sin/cos/tanh/exp/sqrt/square, torch.stack/cat, unbind and indexing")


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
        if not isinstance(self.v, Interval):
            raise TypeError("clamp is supported at first order only")
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


# =========================================================================== networks and dynamics
class _NetBounds:
    """float64 copies of the weights of a :class:`TanhMLP`, evaluated on any enclosure."""

    def __init__(self, net: TanhMLP) -> None:
        self.weights = [(layer.weight.detach().to(F64).clone(), layer.bias.detach().to(F64).clone())
                        for layer in net.layers]
        self.scale = net.input_scale.detach().to(F64).clone()
        zero = Interval.const(torch.zeros(1, self.weights[0][0].shape[1], dtype=F64))
        self.anchor = self.forward(zero)[0]  # enclosure of net(0), shape (1, out)

    def forward(self, z):
        """Output and hidden activations at ``z`` (an enclosure of shape (B, in))."""
        h = z / Interval.const(self.scale)
        hidden = []
        for w, b in self.weights[:-1]:
            h = h.linear(w, b).tanh()
            hidden.append(h)
        w, b = self.weights[-1]
        return h.linear(w, b), hidden

    def vjp(self, hidden: list, v):
        """``J(z)^T v`` given the hidden activations (same formula as :meth:`TanhMLP.vjp`)."""
        g = v.linear(self.weights[-1][0].T)
        for (w, _), h in zip(reversed(self.weights[:-1]), reversed(hidden)):
            g = (g * (1.0 - h.square())).linear(w.T)
        return g / Interval.const(self.scale)


class PairBounds:
    """Enclosures of V, grad V, pi and the design/true dynamics for one pair: the trained networks, or a
    quadratic certificate / linear saturated controller (:class:`QuadraticLyapunov`, :class:`LinearController`)."""

    def __init__(self, system: UncertainSystem, lyapunov: Lyapunov | QuadraticLyapunov,
                 controller: Controller | LinearController) -> None:
        self.system = system
        self.P = lyapunov.P.detach().to(F64).clone() if isinstance(lyapunov, QuadraticLyapunov) else None
        self.K = controller.K.detach().to(F64).clone() if isinstance(controller, LinearController) else None
        if self.P is None:
            self.phi = _NetBounds(lyapunov.phi)
            self.alpha_hat = float(lyapunov.alpha_hat)
        if self.K is None:
            self.varphi = _NetBounds(controller.varphi)
        self.u_star = controller.u_star.detach().to(F64).clone()
        self.room_low = controller.room_low.detach().to(F64).clone()
        self.room_high = controller.room_high.detach().to(F64).clone()
        self.x_star = _t(system.equilibrium)
        self.p0 = _t(system.nominal_params)

    def value_and_grad(self, z):
        if self.P is not None:
            pz = z.linear(self.P)
            return (z * pz).sum(-1), pz * 2.0
        out, hidden = self.phi.forward(z)
        d = out - self.phi.anchor
        zs = z / Interval.const(self.phi.scale)
        value = d.square().sum(-1) + zs.square().sum(-1) * self.alpha_hat
        grad = self.phi.vjp(hidden, d * 2.0) + zs / Interval.const(self.phi.scale) * (2.0 * self.alpha_hat)
        return value, grad

    def value(self, z):
        if self.P is not None:
            return (z * z.linear(self.P)).sum(-1)
        out, _ = self.phi.forward(z)
        d = out - self.phi.anchor
        zs = z / Interval.const(self.phi.scale)
        return d.square().sum(-1) + zs.square().sum(-1) * self.alpha_hat

    def control(self, z):
        if self.K is not None:
            return z.linear(-self.K).clamp(self.room_low, self.room_high) + self.u_star
        raw, _ = self.varphi.forward(z)
        raw = raw - self.varphi.anchor
        return raw.clamp(self.room_low, self.room_high) + self.u_star

    def dynamics(self, x, u, xi: Tensor | None = None, want_w: bool = False):
        """``F(x, u, p0 + xi)`` and, with ``want_w``, ``W = dF/dp_uncertain`` at ``p0`` (B, n, k); ``xi`` is
        ignored with ``want_w`` (the design model is expanded at ``p0``)."""
        sys_ = self.system
        batch = x.shape[0]
        p = self.p0.expand(batch, -1).clone()
        level = max(_level(x), _level(u), 0)
        if not want_w:
            p_hi = p.clone()
            if xi is not None:  # p0 + xi, enclosed (the sum is rounded)
                idx = sys_.uncertain_index
                shifted = p[:, idx] + _t(xi)
                p[:, idx], p_hi[:, idx] = _down(shifted, REL1), _up(shifted, REL1)
            return _check_shape(sys_.dynamics(x, u, lift(Interval(p, p_hi), level)), batch, sys_.n), None
        if sys_.perturbation is not None:
            f = sys_.dynamics(x, u, lift(Interval.const(p), level))
            return _check_shape(f, batch, sys_.n), lift(sys_.perturbation(x, u), level)
        e = torch.zeros(batch, len(sys_.nominal_params), sys_.k, dtype=F64)
        for j, i in enumerate(sys_.uncertain_index):
            e[:, i, j] = 1.0
        pd = Dual(lift(Interval.const(p), level), lift(Interval.const(e), level))
        out = lift(sys_.dynamics(Dual(x, None), Dual(u, None), pd), level + 1)
        w = out.d if out.d is not None else out.v.zeros_ext(sys_.k)  # None: F does not depend on p
        return _check_shape(out.v, batch, sys_.n), w


def _check_shape(f, batch: int, n: int):
    if not isinstance(f, _Enclosure):
        raise ValueError("the system's dynamics did not return an enclosure; write it with torch ops on its inputs")
    if tuple(f.shape) != (batch, n):
        raise ValueError(f"the system's dynamics returned shape {tuple(f.shape)} on enclosures, expected {(batch, n)}")
    return f


# =========================================================================== conditions
@dataclass
class ConditionSpec:
    """Which condition to bound.

    ``kind``: ``pointwise`` (DR, per state), ``nominal`` (baseline, one xi), ``uniform`` (the DR uniform
    condition; its components are ``lip`` and ``h_j`` whose suprema are bounded separately) or ``true``
    (plain decrease on the true model at one shift ``xi``). ``xi`` is ``(N, k)`` (``(1, k)`` for ``nominal``
    and ``true``; a 1-D ``xi`` is one shift).
    """

    kind: str
    xi: Tensor
    decay_rate: float
    exp_rate: float = 0.0
    radius: float = 0.0
    risk_level: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in ("pointwise", "nominal", "uniform", "true"):
            raise ValueError(f"unknown condition kind {self.kind!r}; valid: pointwise, nominal, uniform, true")
        xi = _t(self.xi)
        if xi.ndim > 2 or xi.numel() == 0 or not bool(torch.isfinite(xi).all()):
            raise ValueError(f"xi must be a finite (N, k) array (or one (k,) shift), got shape {tuple(xi.shape)}")
        self.xi = xi.reshape(1, -1) if xi.ndim <= 1 else xi
        if self.kind in ("nominal", "true") and self.xi.shape[0] != 1:
            raise ValueError(f"the {self.kind} condition takes exactly one xi, got {self.xi.shape[0]}")
        if self.kind in ("pointwise", "uniform") and not 0 < self.risk_level < 1:
            raise ValueError(f"risk level eps must be in (0, 1), got {self.risk_level}")

    @property
    def label(self) -> str:
        return {"pointwise": "DR pointwise", "nominal": "nominal (baseline)", "uniform": "DR uniform",
                "true": "true model at xi"}[self.kind]

    def components(self, pb: PairBounds, z):
        """Per-state quantities ``(B, Q)`` whose combination is the residual (see :meth:`combine`)."""
        value, grad = pb.value_and_grad(z)
        u = pb.control(z)
        x = z + pb.x_star
        decay = norm(z) * self.decay_rate
        if self.exp_rate:
            decay = decay + value * self.exp_rate
        if self.kind == "true":
            f, _ = pb.dynamics(x, u, self.xi[0])
            return ((grad * f).sum(-1) + decay).unsqueeze(-1)
        f, w = pb.dynamics(x, u, None, want_w=True)
        gf = (grad * f).sum(-1)
        gw = (grad.unsqueeze(-1) * w).sum(-2)  # W^T grad V, (B, k)
        h = gw.linear(self.xi) + (gf + decay).unsqueeze(-1)  # Vdot_j + decay, (B, N)
        if self.kind == "nominal":
            return h
        lip = norm(gw)
        if self.kind == "pointwise":
            return h + (lip * (Interval.const(self.radius) / Interval.const(self.risk_level))).unsqueeze(-1)
        return cat([lip.unsqueeze(-1), h], -1)

    def combine(self, comp: Tensor) -> Tensor:
        """The residual from (bounds of) the components; monotone, so bounds map to bounds (padded up/down
        by the caller's choice of side)."""
        if self.kind == "pointwise":
            out = cvar_bound(comp, self.risk_level)
            return out if self.risk_level * comp.shape[-1] <= 1 else _up(out, 64 * EPS, comp.abs().amax(-1))
        if self.kind == "uniform":
            raise ValueError("the uniform condition has no per-state residual; use uniform_margin")
        return comp[..., 0]

    def combine_lower(self, comp: Tensor) -> Tensor:
        if self.kind == "pointwise" and self.risk_level * comp.shape[-1] > 1:
            return _down(cvar_bound(comp, self.risk_level), 64 * EPS, comp.abs().amax(-1))
        return self.combine(comp)

    def exact(self, system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, z: Tensor,
              dtype: torch.dtype = F64) -> Tensor:
        """The residual at local states ``z (B, n)`` by the ordinary torch code path, with the networks and
        states cast to ``dtype`` (float64 by default: the arithmetic the bounds are about)."""
        lyap, ctrl = copy.deepcopy(lyapunov).to(dtype), copy.deepcopy(controller).to(dtype)
        with torch.no_grad():
            return self.residual(system, lyap, ctrl, torch.as_tensor(z).to(dtype))

    def residual(self, system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, z: Tensor) -> Tensor:
        """The residual at local states ``z (B, n)`` with the given networks as they are (dtype of ``z``),
        differentiable in ``z`` and the weights."""
        xi = self.xi.to(z)
        if self.kind == "true":
            value, grad = lyapunov.value_and_grad(z)
            fx = system.true_dynamics(system.to_user(z), controller(z), xi[0])
            out = (grad * fx).sum(-1) + self.decay_rate * z.norm(dim=-1)
            return out + self.exp_rate * value if self.exp_rate else out
        terms = decrease_terms(system, lyapunov, controller, z, xi, self.decay_rate, self.exp_rate)
        if self.kind == "nominal":
            return Nominal().residual(terms)
        if self.kind == "pointwise":
            return DRPointwise(self.radius, self.risk_level).residual(terms)
        raise ValueError("the uniform condition has no per-state residual")


# =========================================================================== box bounds
def box_bounds(objective: Callable, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor, Interval]:
    """Lower and upper bounds ``(B, Q)`` of ``objective`` over the boxes ``[lo, hi] (B, n)``.

    The tighter of the plain interval bound and the mean-value form; also returns the enclosure of the
    objective at the box centres (an :class:`Interval` ``(B, Q)``).
    """
    batch, n = lo.shape
    centre = (lo + hi) / 2
    rad = _up(torch.maximum(hi - centre, centre - lo), REL1)
    eye = torch.eye(n, dtype=F64).expand(batch, n, n)
    over = objective(Dual(Interval(lo, hi), Interval(eye, eye)))
    at = objective(Interval(centre, centre))
    if over.d is None:
        spread = torch.zeros_like(at.lo)
    else:
        slope = torch.maximum(over.d.lo.abs(), over.d.hi.abs())
        spread = _up((slope * rad.unsqueeze(1)).sum(-1), 4 * (n + 2) * EPS)
    upper = torch.minimum(over.v.hi, _up(at.hi + spread, REL1))
    lower = torch.maximum(over.v.lo, _down(at.lo - spread, REL1))
    upper = torch.where(torch.isnan(upper), torch.inf, upper)
    lower = torch.where(torch.isnan(lower), -torch.inf, lower)
    return lower, upper, at


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


def _default_grid(n: int, target: int = 256) -> list[int]:
    return [max(2, int(round(target ** (1.0 / n))))] * n


def _far_dist(lo: Tensor, hi: Tensor) -> Tensor:
    return torch.sqrt(torch.maximum(lo * lo, hi * hi).sum(-1))


def _near_dist(lo: Tensor, hi: Tensor) -> Tensor:
    gap = torch.clamp(torch.maximum(lo, -hi), min=0.0)
    return torch.sqrt((gap * gap).sum(-1))


def inside_ball(lo: Tensor, hi: Tensor, delta: float) -> Tensor:
    """Boxes that lie entirely in the open ball ``||z|| < delta`` (conservatively)."""
    return _far_dist(lo, hi) * (1 + 1e-12) < delta


def _split(lo: Tensor, hi: Tensor, scale: Tensor) -> tuple[Tensor, Tensor]:
    """Bisect each box along its widest side (widths relative to ``scale``)."""
    dim = ((hi - lo) / scale).argmax(-1)
    rows = torch.arange(lo.shape[0])
    mid = (lo[rows, dim] + hi[rows, dim]) / 2
    hi1, lo2 = hi.clone(), lo.clone()
    hi1[rows, dim] = mid
    lo2[rows, dim] = mid
    return torch.cat([lo, lo2]), torch.cat([hi1, hi])


def _ball_volume(delta: float, n: int) -> float:
    return math.pi ** (n / 2) / math.gamma(n / 2 + 1) * delta ** n


def _region_volume(lo: Tensor, hi: Tensor, delta: float) -> float:
    """Volume of the box minus the open delta-ball (exact if the ball is inside the box, else sampled)."""
    box = float((hi - lo).prod())
    if delta <= 0:
        return box
    if bool((-lo >= delta).all() and (hi >= delta).all()):
        return box - _ball_volume(delta, lo.shape[0])
    g = torch.Generator().manual_seed(0)
    z = lo + (hi - lo) * torch.rand(200_000, lo.shape[0], generator=g, dtype=F64)
    return box * float((z.norm(dim=-1) >= delta).double().mean())


# =========================================================================== results
@dataclass
class VerificationResult:
    """Outcome of a branch-and-bound verification of a decrease condition over ``X_delta``.

    ``status``: ``verified`` (proved at every state of X_delta), ``violated`` (a state where the residual is
    > 0, re-checked by direct evaluation) or ``unknown`` (budget or time ran out, or boxes reached the
    minimum size). ``verified_fraction`` is a lower bound of the share of X_delta's volume covered by
    verified boxes (unverified boxes count whole, even where they overlap the delta-ball).
    ``sup_bounds``: ``[lower, upper]`` of the maximum of the residual over X_delta found on the way (the lower
    end from evaluated box centres, the upper end the largest bound of a leaf box; exact bounds only when
    the run finished). Counterexample states are in user coordinates, ``counterexample_local`` in local ones;
    ``counterexample_value`` is the residual there in float64, ``counterexample_value_float32`` with the
    networks in float32 as training and simulation run them.
    """

    condition: str
    status: str
    verified_fraction: float
    delta: float
    boxes_processed: int
    boxes_verified: int
    time_s: float
    counterexample: list[float] | None = None
    counterexample_local: list[float] | None = None
    counterexample_value: float | None = None
    counterexample_value_float32: float | None = None
    n_counterexample_boxes: int = 0
    n_unverified: int = 0
    unverified_boxes: list[dict] = field(default_factory=list)
    sup_bounds: list[float] = field(default_factory=list)
    stopped: str = ""

    def to_dict(self) -> dict:
        return asdict(self)


def verify_condition(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, spec: ConditionSpec,
                     delta: float, time_limit: float = 30.0, max_boxes: int = 2_000_000, min_width: float = 1e-4,
                     grid: Sequence[int] | None = None, batch: int = 4096, keep_boxes: int = 50,
                     stop_at_counterexample: bool = False, violation_width: float = 1e-2) -> VerificationResult:
    """Prove ``residual(z) <= 0`` on X_delta by branch and bound, or find where it fails.

    ``min_width``: boxes whose widest side (relative to the state box) is below it are not split further.
    ``violation_width``: a box whose centre is a confirmed counterexample is still split (to sharpen the
    verified fraction) until its widest relative side is below this. ``max_boxes``: budget of processed
    boxes. ``grid``: boxes per axis at the start. ``keep_boxes``: how many unverified boxes to list.
    ``stop_at_counterexample``: return at the first confirmed one (the fraction then counts every box not
    yet verified as unverified).
    """
    if spec.kind == "uniform":
        raise ValueError("use uniform_margin for the uniform condition")
    if not (math.isfinite(delta) and delta >= 0):
        raise ValueError(f"delta must be finite and >= 0, got {delta}")
    start = time.perf_counter()
    pb = PairBounds(system, lyapunov, controller)

    def objective(z):
        return spec.components(pb, z)

    box_lo, box_hi = system.local_box()
    scale = box_hi - box_lo
    lo, hi = box_grid(box_lo, box_hi, grid or _default_grid(system.n))
    keep = ~inside_ball(lo, hi, delta)
    lo, hi = lo[keep], hi[keep]
    region = _region_volume(box_lo, box_hi, delta)
    processed = verified_count = 0
    unverified_vol = 0.0
    leaves_lo: list[Tensor] = []
    leaves_hi: list[Tensor] = []
    sup_lo, sup_hi = -math.inf, -math.inf
    cex: tuple[float, Tensor] | None = None
    n_cex_boxes = 0
    stopped = "finished"
    while lo.shape[0]:
        if time.perf_counter() - start > time_limit:
            stopped = "time limit"
            break
        if processed >= max_boxes:
            stopped = "box budget"
            break
        clo, chi, lo, hi = lo[:batch], hi[:batch], lo[batch:], hi[batch:]
        _, ub_c, at = box_bounds(objective, clo, chi)
        processed += clo.shape[0]
        ub = spec.combine(ub_c)
        centre = (clo + chi) / 2
        centre_lb = spec.combine_lower(at.lo)
        in_region = centre.norm(dim=-1) >= delta * (1 + 1e-12)
        if in_region.any():
            sup_lo = max(sup_lo, float(centre_lb[in_region].max()))
        ok = ub <= 0
        verified_count += int(ok.sum())
        if ok.any():
            sup_hi = max(sup_hi, float(ub[ok].max()))
        bad = ~ok & in_region & (centre_lb > 0)
        if bad.any():
            values = spec.exact(system, lyapunov, controller, centre[bad])
            confirmed = values > 0
            if confirmed.any():
                best = int(values.argmax())
                if cex is None or float(values[best]) > cex[0]:
                    cex = (float(values[best]), centre[bad][best])
                n_cex_boxes += int(confirmed.sum())
                idx = bad.nonzero().squeeze(-1)[confirmed]
                bad = torch.zeros_like(bad)
                bad[idx] = True
            else:
                bad = torch.zeros_like(bad)
        if bad.any() and stop_at_counterexample:
            stopped = "counterexample"
            unverified_vol += float((chi[~ok] - clo[~ok]).prod(-1).sum())
            leaves_lo.append(clo[~ok])
            leaves_hi.append(chi[~ok])
            sup_hi = math.inf
            break
        rel_width = ((chi - clo) / scale).amax(-1)
        bad = bad & (rel_width < violation_width)  # violating boxes still wide enough are split like the rest
        if bad.any():
            unverified_vol += float((chi[bad] - clo[bad]).prod(-1).sum())
            sup_hi = max(sup_hi, float(ub[bad].max()))
            leaves_lo.append(clo[bad])
            leaves_hi.append(chi[bad])
        rest = ~ok & ~bad
        small = rest & (rel_width < min_width)
        if small.any():
            unverified_vol += float((chi[small] - clo[small]).prod(-1).sum())
            sup_hi = max(sup_hi, float(ub[small].max()))
            leaves_lo.append(clo[small])
            leaves_hi.append(chi[small])
        split = rest & ~small
        if split.any():
            nlo, nhi = _split(clo[split], chi[split], scale)
            keep = ~inside_ball(nlo, nhi, delta)
            lo, hi = torch.cat([lo, nlo[keep]]), torch.cat([hi, nhi[keep]])
    if lo.shape[0]:
        unverified_vol += float((hi - lo).prod(-1).sum())
        leaves_lo.append(lo)
        leaves_hi.append(hi)
        sup_hi = math.inf
    left_lo = torch.cat(leaves_lo) if leaves_lo else torch.empty(0, system.n, dtype=F64)
    left_hi = torch.cat(leaves_hi) if leaves_hi else torch.empty(0, system.n, dtype=F64)
    if cex is not None:
        status = "violated"
    elif left_lo.shape[0] == 0:
        status = "verified"
    else:
        status = "unknown"
    fraction = max(0.0, min(1.0, 1.0 - unverified_vol / region)) if region > 0 else 1.0
    if status == "verified":
        fraction = 1.0
    boxes = [{"lo": system.to_user(a[None])[0].tolist(), "hi": system.to_user(b[None])[0].tolist()}
             for a, b in zip(left_lo[:keep_boxes], left_hi[:keep_boxes])]
    result = VerificationResult(
        condition=spec.label, status=status, verified_fraction=fraction, delta=float(delta),
        boxes_processed=processed, boxes_verified=verified_count, time_s=time.perf_counter() - start,
        n_unverified=int(left_lo.shape[0]), unverified_boxes=boxes, n_counterexample_boxes=n_cex_boxes,
        sup_bounds=[sup_lo, sup_hi], stopped=stopped)
    if cex is not None:
        result.counterexample_value = cex[0]
        result.counterexample_value_float32 = float(spec.exact(system, lyapunov, controller, cex[1][None], torch.float32)[0])
        result.counterexample_local = cex[1].tolist()
        result.counterexample = system.to_user(cex[1][None])[0].tolist()
    return result


# =========================================================================== suprema
def maximize(objective: Callable, lo: Tensor, hi: Tensor, scale: Tensor, *, centre_ok: Callable | None = None,
             box_ok: Callable | None = None, time_limit: float = 2.0, rel_tol: float = 1e-3, abs_tol: float = 1e-9,
             min_width: float = 1e-4, max_boxes: int = 1_000_000, batch: int = 4096) -> tuple[Tensor, Tensor, dict]:
    """Bounds ``lower <= sup <= upper`` (each ``(Q,)``) of every component of ``objective`` over a union of boxes.

    The upper bound is sound over the boxes (kept by ``box_ok``); the lower bound comes from box centres
    accepted by ``centre_ok`` (points of the set). Boxes that may still raise some component's supremum
    by more than the tolerance are split, widest side first, until time, budget or minimum size.
    """
    start = time.perf_counter()
    closed: Tensor | None = None
    best: Tensor | None = None
    processed = 0
    stopped = "finished"
    if box_ok is not None:
        keep = box_ok(lo, hi)
        lo, hi = lo[keep], hi[keep]
    while lo.shape[0]:
        if time.perf_counter() - start > time_limit or processed >= max_boxes:
            stopped = "time limit" if processed < max_boxes else "box budget"
            break
        clo, chi, lo, hi = lo[:batch], hi[:batch], lo[batch:], hi[batch:]
        _, ub, at = box_bounds(objective, clo, chi)
        processed += clo.shape[0]
        centre = (clo + chi) / 2
        good = centre_ok(centre) if centre_ok is not None else torch.ones(clo.shape[0], dtype=torch.bool)
        if good.any():
            cand = at.lo[good].amax(0)
            best = cand if best is None else torch.maximum(best, cand)
        ref = best if best is not None else torch.full_like(ub[0], -torch.inf)
        tol = torch.clamp(rel_tol * ref.abs(), min=abs_tol)
        refine = (ub > ref + tol).any(-1) & (((chi - clo) / scale).amax(-1) >= min_width)
        done = ~refine
        if done.any():
            cand = ub[done].amax(0)
            closed = cand if closed is None else torch.maximum(closed, cand)
        if refine.any():
            nlo, nhi = _split(clo[refine], chi[refine], scale)
            if box_ok is not None:
                keep = box_ok(nlo, nhi)
                nlo, nhi = nlo[keep], nhi[keep]
            lo, hi = torch.cat([lo, nlo]), torch.cat([hi, nhi])
    if lo.shape[0]:
        _, ub, _ = box_bounds(objective, lo, hi) if lo.shape[0] <= 4 * batch else (None, None, None)
        if ub is None:
            rest = torch.full_like(closed if closed is not None else best, torch.inf)
        else:
            rest = ub.amax(0)
        closed = rest if closed is None else torch.maximum(closed, rest)
    if closed is None:
        raise ValueError("the set to maximise over is empty")
    if best is None:
        best = torch.full_like(closed, -torch.inf)
    return best, closed, {"boxes_processed": processed, "time_s": time.perf_counter() - start, "stopped": stopped}


def uniform_margin(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, xi_samples: Tensor,
                   decay_rate: float, exp_rate: float, radius: float, risk_level: float, delta: float,
                   time_limit: float = 3.0, rel_tol: float = 1e-3, min_width: float = 1e-4) -> dict:
    """Bounds of the uniform DR condition's left side over X_delta (``eq: dr_clf_constraint_relaxed``)::

        margin = (r/eps) sup_z ||W^T grad V(z)|| + CVaR_eps_j sup_z (Vdot_j(z) + decay(z))

    ``margin_upper`` is a sound upper bound (the condition is proved when it is <= 0); ``margin_lower`` is a
    value attained by evaluated states (the condition fails when it is > 0).
    """
    spec = ConditionSpec("uniform", xi_samples, decay_rate, exp_rate, radius, risk_level)
    pb = PairBounds(system, lyapunov, controller)
    box_lo, box_hi = system.local_box()
    lo, hi = box_grid(box_lo, box_hi, _default_grid(system.n))
    lower, upper, info = maximize(
        lambda z: spec.components(pb, z), lo, hi, box_hi - box_lo,
        centre_ok=lambda c: c.norm(dim=-1) >= delta * (1 + 1e-12), box_ok=lambda a, b: ~inside_ball(a, b, delta),
        time_limit=time_limit, rel_tol=rel_tol, min_width=min_width)
    coef = radius / risk_level
    m_up = _up(coef * upper[0], 8 * EPS) + spec_cvar(upper[1:], risk_level, up=True)
    m_lo = coef * lower[0] + spec_cvar(lower[1:], risk_level, up=False)
    m_up, m_lo = float(_up(_t(m_up), 8 * EPS)), float(_down(_t(m_lo), 8 * EPS))
    status = "verified" if m_up <= 0 else ("violated" if m_lo > 0 else "unknown")
    return {"condition": "DR uniform", "status": status, "margin_upper": m_up, "margin_lower": m_lo,
            "lipschitz_sup": [float(lower[0]), float(upper[0])],
            "h_sup": [[float(a), float(b)] for a, b in zip(lower[1:], upper[1:])],
            "lipschitz_term": [coef * float(lower[0]), coef * float(upper[0])], "delta": float(delta), **info}


def spec_cvar(h: Tensor, risk_level: float, up: bool) -> Tensor:
    out = cvar_bound(h, risk_level)
    return _up(out, 64 * EPS, h.abs().amax()) if up else _down(out, 64 * EPS, h.abs().amax())


# =========================================================================== region of attraction
def _faces(lo: Tensor, hi: Tensor, per_axis: Sequence[int]) -> tuple[Tensor, Tensor]:
    """Boxes covering the boundary of the box ``[lo, hi]`` (one coordinate pinned per face)."""
    out_lo, out_hi = [], []
    for i in range(lo.shape[0]):
        per = list(per_axis)
        per[i] = 1
        for side in (lo[i], hi[i]):
            flo, fhi = box_grid(lo, hi, per)
            flo[:, i] = side
            fhi[:, i] = side
            out_lo.append(flo)
            out_hi.append(fhi)
    return torch.cat(out_lo), torch.cat(out_hi)


def certified_roa(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, spec: ConditionSpec,
                  delta: float, time_limit: float = 10.0, min_width: float = 1e-4, samples_per_axis: int = 400,
                  batch: int = 4096) -> dict:
    """The largest level ``c`` (up to the search's resolution) such that, for ``S = {z in box: V(z) <= c}``:

    * ``V > c`` on the boundary of the state box (so S is a sublevel set inside the box, not cut by it), and
    * the decrease condition of ``spec`` is proved on ``S`` minus the open delta-ball.

    A single branch and bound: a box is dropped once a lower bound of V on it exceeds the current level;
    an undecidable box (minimum size) lowers the level below V on it, a confirmed counterexample below V at
    that state. ``contains_ball`` says whether ``c`` exceeds an upper bound of V on the delta-ball; only then
    is S forward invariant with trajectories from S entering ``{V <= v_ball}``, and ``certified`` is True.
    ``share_of_box`` is the share of the box volume in S, estimated on a grid (``samples_per_axis`` per axis,
    n <= 3) or by sampling.
    """
    start = time.perf_counter()
    pb = PairBounds(system, lyapunov, controller)
    box_lo, box_hi = system.local_box()
    scale = box_hi - box_lo
    grid = _default_grid(system.n)

    def vobj(z):
        return pb.value(z).unsqueeze(-1)

    # 1. min of V on the boundary of the box
    flo, fhi = _faces(box_lo, box_hi, grid)
    _, neg_up, _ = maximize(lambda z: -vobj(z), flo, fhi, scale, time_limit=time_limit / 4,
                            min_width=min_width)
    boundary_min_lower = float(-neg_up[0])
    # 2. max of V on the delta-ball
    ball_max_upper = 0.0
    if delta > 0:
        blo = torch.maximum(box_lo, torch.full_like(box_lo, -delta))
        bhi = torch.minimum(box_hi, torch.full_like(box_hi, delta))
        glo, ghi = box_grid(blo, bhi, grid)
        _, up, _ = maximize(vobj, glo, ghi, scale, time_limit=time_limit / 4,
                            box_ok=lambda a, b: _near_dist(a, b) < delta, min_width=min_width)
        ball_max_upper = float(up[0])
    # 3. the decrease condition on the sublevel set
    level = boundary_min_lower
    limited_by = "box boundary"

    def objective(z):
        return cat([spec.components(pb, z), pb.value(z).unsqueeze(-1)], -1)

    lo, hi = box_grid(box_lo, box_hi, grid)
    keep = ~inside_ball(lo, hi, delta)
    lo, hi = lo[keep], hi[keep]
    processed = 0
    deadline = start + time_limit
    cex = None
    while lo.shape[0]:
        if time.perf_counter() > deadline:
            v_min = -math.inf
            if lo.shape[0] <= 16 * batch:
                v_min = min(float(box_bounds(vobj, lo[i:i + batch], hi[i:i + batch])[0].min())
                            for i in range(0, lo.shape[0], batch))
            if v_min < level:
                level, limited_by = v_min, "time limit"
            break
        clo, chi, lo, hi = lo[:batch], hi[:batch], lo[batch:], hi[batch:]
        lb, ub, at = box_bounds(objective, clo, chi)
        processed += clo.shape[0]
        v_lb = lb[:, -1]
        active = v_lb <= level
        res_ub = spec.combine(ub[:, :-1])
        centre = (clo + chi) / 2
        in_region = centre.norm(dim=-1) >= delta * (1 + 1e-12)
        open_ = active & (res_ub > 0)
        bad = open_ & in_region & (spec.combine_lower(at.lo[:, :-1]) > 0)
        if bad.any():
            values = spec.exact(system, lyapunov, controller, centre[bad])
            if (values > 0).any():
                v_at = at.hi[:, -1][bad][values > 0]
                j = int(v_at.argmin())
                if float(v_at[j]) < level:
                    level, limited_by = float(v_at[j]), "counterexample"
                    cex = centre[bad][values > 0][j]
        small = open_ & (((chi - clo) / scale).amax(-1) < min_width)
        if small.any() and float(v_lb[small].min()) < level:
            level, limited_by = float(v_lb[small].min()), "unverified box at minimum size"
        split = open_ & ~small & (v_lb <= level)
        if split.any():
            nlo, nhi = _split(clo[split], chi[split], scale)
            keep = ~inside_ball(nlo, nhi, delta)
            lo, hi = torch.cat([lo, nlo[keep]]), torch.cat([hi, nhi[keep]])
    c = float(_down(_t(level), REL1)) if math.isfinite(level) else level
    share = 0.0
    if c > 0:
        if system.n <= 3:
            per = samples_per_axis if system.n <= 2 else 60
            axes = [box_lo[i] + scale[i] * (torch.arange(per, dtype=F64) + 0.5) / per for i in range(system.n)]
            z = torch.cartesian_prod(*axes).reshape(-1, system.n)
        else:
            g = torch.Generator().manual_seed(0)
            z = box_lo + scale * torch.rand(100_000, system.n, generator=g, dtype=F64)
        lyap = copy.deepcopy(lyapunov).to(F64)
        with torch.no_grad():
            values = torch.cat([lyap(z[i:i + 50_000]) for i in range(0, z.shape[0], 50_000)])
        share = float((values <= c).double().mean())
    return {"level": c, "certified": c > 0 and c > ball_max_upper, "contains_ball": c > ball_max_upper, "limited_by": limited_by,
            "boundary_min_lower": boundary_min_lower, "ball_max_upper": ball_max_upper, "share_of_box": share,
            "counterexample": None if cex is None else system.to_user(cex[None])[0].tolist(),
            "boxes_processed": processed, "time_s": time.perf_counter() - start, "delta": float(delta),
            "condition": spec.label}


# =========================================================================== runs
def run_condition(run, xi: Sequence[float] | Tensor | None = None) -> ConditionSpec:
    """The condition a run was trained on (``xi is None``), or plain decrease on the true model at ``xi``."""
    cfg = run.config
    if xi is not None:
        shift = run.system.check_xi(xi)
        return ConditionSpec("true", shift[None], cfg.decay_rate, cfg.exp_rate)
    kind = "nominal" if cfg.method == "baseline" else cfg.loss
    return ConditionSpec(kind, run.xi_train, cfg.decay_rate, cfg.exp_rate, cfg.wasserstein_radius, cfg.risk_level)


def verify_run(run, delta: float | None = None, xi: Sequence[float] | Tensor | None = None, time_limit: float = 30.0,
               roa: bool = False, min_width: float = 1e-4, uniform_time: float = 3.0) -> dict:
    """Verify a loaded run (:func:`drlyap.rundir.load_run`) on X_delta.

    Returns a JSON-friendly dict: ``trained`` (the run's own condition: pointwise / nominal through
    :func:`verify_condition`, uniform through :func:`uniform_margin`), ``uniform`` (always: the uniform DR
    margin bounds at the run's radius, risk level and samples), ``true_model`` (with ``xi``: plain decrease
    on the true model at that shift) and ``roa`` (with ``roa=True``: :func:`certified_roa` for the main
    condition). The top-level ``status``, ``verified_fraction``, ``counterexample`` and ``time_s`` are those
    of the main check: the true model when ``xi`` is given, else the trained condition. Non-finite bounds
    are reported as None (strict JSON).
    """
    cfg = run.config
    delta = float(cfg.delta if delta is None else delta)
    if not (math.isfinite(delta) and delta >= 0):
        raise ValueError(f"delta must be finite and >= 0, got {delta}")
    box_lo, box_hi = run.system.local_box()
    if _region_volume(box_lo, box_hi, delta) <= 0:
        raise ValueError(f"delta = {delta} covers the whole state box: X_delta is empty, nothing to verify")
    system, lyap, ctrl = run.system, run.lyapunov_net, run.controller_net
    trained_spec = run_condition(run)
    out: dict = {"run_dir": str(run.path), "system": system.name, "method": cfg.method,
                 "loss": cfg.loss if cfg.method == "dr" else None, "delta": delta}
    if trained_spec.kind == "uniform":
        trained = uniform_margin(system, lyap, ctrl, trained_spec.xi, cfg.decay_rate, cfg.exp_rate,
                                 cfg.wasserstein_radius, cfg.risk_level, delta, time_limit=time_limit,
                                 min_width=min_width)
        uniform = trained
    else:
        trained = verify_condition(system, lyap, ctrl, trained_spec, delta, time_limit=time_limit,
                                   min_width=min_width).to_dict()
        uniform = uniform_margin(system, lyap, ctrl, run.xi_samples, cfg.decay_rate, cfg.exp_rate, cfg.wasserstein_radius,
                                 cfg.risk_level, delta, time_limit=uniform_time, min_width=min_width)
    out["trained"] = trained
    out["uniform"] = uniform
    main, main_spec = trained, trained_spec
    if xi is not None:
        main_spec = run_condition(run, xi)
        main = verify_condition(system, lyap, ctrl, main_spec, delta, time_limit=time_limit,
                                min_width=min_width).to_dict()
        main["xi"] = main_spec.xi[0].tolist()
        out["true_model"] = main
    out["roa"] = None
    if roa:
        if main_spec.kind == "uniform":
            out["roa"] = {"error": "no per-state residual for the uniform condition; no sublevel-set certificate"}
        else:
            out["roa"] = certified_roa(system, lyap, ctrl, main_spec, delta, time_limit=time_limit, min_width=min_width)
    out["status"] = main["status"]
    out["condition"] = main["condition"]
    out["verified_fraction"] = main.get("verified_fraction")
    out["counterexample"] = main.get("counterexample")
    out["counterexample_value"] = main.get("counterexample_value")
    out["time_s"] = main["time_s"]
    return jsonable(out)
