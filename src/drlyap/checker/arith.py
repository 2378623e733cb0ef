"""The checker's own arithmetic: float64 intervals with outward rounding (:class:`Iv`) and forward-mode dual numbers
over them (:class:`Du`), written apart from :mod:`drlyap.enclosures` so that a certificate is re-checked by other
code than the code that found it.

Rounding: every elementary result is moved one float64 step outward (``nextafter``) after round-to-nearest, which
encloses the real result of ``+ - * /`` on float64 operands; sums of ``n`` products (``linear``) are padded by
``(n + 2) eps`` times their magnitude; library transcendentals (``sin cos tanh exp sqrt``) by ``8 eps`` of their
magnitude and one more step. Any NaN widens to the whole line, so a failed operation never proves anything.

:class:`Du` carries a value and a list of tangents, each of the same kind (an :class:`Iv` or a :class:`Du` of a
lower level), so duals nest: the checker differentiates the design model in the parameters (inner level) and the
whole residual in the state (outer level). The derivative rules enclose the Clarke gradient where a function has
kinks (``clamp``, ``abs``, the norm at 0), for which the mean-value theorem still holds.
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

F64 = torch.float64
EPS = 2.0 ** -52
TINY = 1e-300
INF = math.inf


@functools.cache
def _infinity(sign: float, device: torch.device) -> Tensor:
    """``sign * inf`` on ``device`` (``nextafter`` takes its direction from the device of its input)."""
    return torch.tensor(sign * INF, dtype=F64, device=device)


def _down(x: Tensor) -> Tensor:
    """One float64 step down; NaN becomes ``-inf``."""
    return torch.nextafter(x, _infinity(-1.0, x.device)).nan_to_num(nan=-INF, posinf=INF, neginf=-INF)


def _up(x: Tensor) -> Tensor:
    """One float64 step up; NaN becomes ``inf``."""
    return torch.nextafter(x, _infinity(1.0, x.device)).nan_to_num(nan=INF, posinf=INF, neginf=-INF)


def _pad_down(x: Tensor, rel: float, mag: Tensor) -> Tensor:
    return _down(x - rel * mag - TINY)


def _pad_up(x: Tensor, rel: float, mag: Tensor) -> Tensor:
    return _up(x + rel * mag + TINY)


def _t(x, device: torch.device | None = None) -> Tensor:
    return torch.as_tensor(x, dtype=F64, device=device)


def level(x) -> int:
    """0 for an interval, 1 + the level of its value for a dual, -1 for a tensor or number."""
    return x.level if isinstance(x, _Ops) else -1


def lift(x, lv: int, like=None, device: torch.device | None = None):
    """``x`` as a constant of level ``lv`` (``like``: a dual of that level, whose number of tangents is used), on
    ``like``'s device or ``device`` (None: a tensor's own, a number's the CPU's)."""
    if level(x) == lv:
        return x
    device = like.device if like is not None else device
    if lv == 0:
        return Iv.point(x, device)
    inner = lift(x, lv - 1, None if like is None else like.v, device)
    zero = inner * 0.0
    return Du(inner, [zero] * (len(like.d) if like is not None else 0))


def _binary(a, b, op: str):
    la, lb = level(a), level(b)
    if la < 0 and lb < 0:
        return getattr(_t(a), op)(b)
    if la >= lb:
        if la > lb and la > 0:  # b is a constant for a's tangents
            return getattr(a, op + "_const")(b)
        a, b = a, lift(b, la, a if la > 0 else None, a.device)
    else:
        if lb > 0:
            return getattr(b, "r" + op + "_const")(a)
        a = lift(a, lb, None, b.device)
    if getattr(b, "affine", False) and not getattr(a, "affine", False):  # an interval with an affine form
        if op in ("add", "mul"):
            return getattr(b, op)(a)
        a = b.promote(a)
    return getattr(a, op)(b)


class _Ops:
    """Python operators and the ``__torch_function__`` bridge for the functions a system's dynamics may use."""

    def __add__(self, o):
        return _binary(self, o, "add")

    def __radd__(self, o):
        return _binary(self, o, "add")

    def __sub__(self, o):
        return _binary(self, o, "sub")

    def __rsub__(self, o):
        return _binary(o, self, "sub")

    def __mul__(self, o):
        return _binary(self, o, "mul")

    def __rmul__(self, o):
        return _binary(self, o, "mul")

    def __truediv__(self, o):
        return _binary(self, o, "div")

    def __rtruediv__(self, o):
        return _binary(o, self, "div")

    def __neg__(self):
        return self.neg()

    def __pow__(self, k):
        if isinstance(k, Tensor):
            k = k.item()
        if isinstance(k, float) and k.is_integer():
            k = int(k)
        if not isinstance(k, int) or k < 0:
            raise TypeError(f"the checker supports powers by non-negative integers only, got {k!r}")
        if k == 0:
            return self * 0.0 + 1.0
        if k == 2:
            return self.square()
        out = self
        for _ in range(k - 1):
            out = out * self
        return out

    def __len__(self) -> int:
        return self.shape[0]

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def dtype(self):
        return F64

    @property
    def device(self) -> torch.device:
        """Where the value's bounds live (a user's dynamics may make its tensors there)."""
        x = self
        while isinstance(x, Du):
            x = x.v
        return x.lo.device if isinstance(x, Iv) else x.c.device

    def dim(self) -> int:
        return self.ndim

    def size(self, d=None):
        return self.shape if d is None else self.shape[d]

    @classmethod
    def __torch_function__(cls, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in (torch.stack, torch.cat, torch.concat):
            dim = kwargs.get("dim", args[1] if len(args) > 1 else 0)
            return join(list(args[0]), dim, func is torch.stack)
        if func in (torch.unbind, Tensor.unbind):
            return args[0].unbind(kwargs.get("dim", args[1] if len(args) > 1 else 0))
        unary = {"sin", "cos", "tanh", "exp", "sqrt", "square", "abs", "neg"}
        name = getattr(func, "__name__", "")
        if name in unary and len(args) == 1 and not kwargs:
            return getattr(args[0], name)()
        binary = {"add": "__add__", "sub": "__sub__", "mul": "__mul__", "div": "__truediv__",
                  "true_divide": "__truediv__", "__add__": "__add__", "__sub__": "__sub__", "__mul__": "__mul__",
                  "__truediv__": "__truediv__", "__radd__": "__radd__", "__rsub__": "__rsub__",
                  "__rmul__": "__rmul__", "__rtruediv__": "__rtruediv__", "__rdiv__": "__rtruediv__",
                  "__div__": "__truediv__", "__neg__": "__neg__"}
        if name in binary and not kwargs:
            a, *rest = args
            if not isinstance(a, _Ops):  # tensor OP checker value: the checker value is the other operand
                swapped = {"__add__": "__radd__", "__sub__": "__rsub__", "__mul__": "__rmul__",
                           "__truediv__": "__rtruediv__", "__radd__": "__add__", "__rsub__": "__sub__",
                           "__rmul__": "__mul__", "__rtruediv__": "__truediv__"}
                return getattr(rest[0], swapped[binary[name]])(a)
            return getattr(a, binary[name])(*rest)
        if name in ("pow", "__pow__") and isinstance(args[0], _Ops):
            return args[0] ** args[1]
        if name == "sum" and isinstance(args[0], _Ops) and set(kwargs) <= {"dim"}:
            return args[0].sum(kwargs.get("dim", args[1] if len(args) > 1 else None))
        raise TypeError(f"the checker's arithmetic does not support {name or func}: use +, -, *, /, ** int, "
                        "torch.sin/cos/tanh/exp/sqrt/square/abs, torch.stack/cat, unbind and indexing")


def join(items: list, dim: int, new_axis: bool):
    """``torch.stack`` (``new_axis``) or ``torch.cat`` of checker values, tensors and numbers along ``dim``."""
    lv = max(level(x) for x in items)
    like = next((x for x in items if level(x) == lv), None) if lv > 0 else None
    device = next((x.device for x in items if isinstance(x, (_Ops, Tensor))), None)
    items = [lift(x if level(x) >= 0 else _t(x, device), lv, like, device) for x in items]
    affine = next((x for x in items if getattr(x, "affine", False)), None)
    if lv == 0 and affine is not None:
        return type(affine).join([affine.promote(x) for x in items], dim, new_axis)
    if lv == 0:
        f = torch.stack if new_axis else torch.cat
        return Iv(f([x.lo for x in items], dim), f([x.hi for x in items], dim))
    return Du(join([x.v for x in items], dim, new_axis),
              [join([x.d[i] for x in items], dim, new_axis) for i in range(len(like.d))])


class Iv(_Ops):
    """Float64 intervals ``[lo, hi]`` of one shape, outward rounded."""

    __slots__ = ("lo", "hi")
    level = 0

    def __init__(self, lo: Tensor, hi: Tensor) -> None:
        self.lo, self.hi = _t(lo), _t(hi)

    @staticmethod
    def point(x, device: torch.device | None = None) -> Iv:
        """The exact interval ``[x, x]`` (on ``device``: None, a tensor's own, a number's the CPU's)."""
        x = _t(x, device)
        return Iv(x, x)

    @property
    def shape(self):
        return self.lo.shape

    def __repr__(self) -> str:
        return f"Iv({self.lo}, {self.hi})"

    def __getitem__(self, idx) -> Iv:
        return Iv(self.lo[idx], self.hi[idx])

    def unbind(self, dim: int = 0) -> tuple:
        return tuple(Iv(a, b) for a, b in zip(self.lo.unbind(dim), self.hi.unbind(dim)))

    def unsqueeze(self, dim: int) -> Iv:
        return Iv(self.lo.unsqueeze(dim), self.hi.unsqueeze(dim))

    def mag(self) -> Tensor:
        return torch.maximum(self.lo.abs(), self.hi.abs())

    def contains_zero(self) -> Tensor:
        return (self.lo <= 0) & (self.hi >= 0)

    # ---- arithmetic
    def add(self, o: Iv) -> Iv:
        return Iv(_down(self.lo + o.lo), _up(self.hi + o.hi))

    def sub(self, o: Iv) -> Iv:
        return Iv(_down(self.lo - o.hi), _up(self.hi - o.lo))

    def neg(self) -> Iv:
        return Iv(-self.hi, -self.lo)

    def mul(self, o: Iv) -> Iv:
        p = torch.stack([self.lo * o.lo, self.lo * o.hi, self.hi * o.lo, self.hi * o.hi])
        return Iv(_down(p.amin(0)), _up(p.amax(0)))  # a NaN product (0 inf) propagates: the whole line

    def div(self, o: Iv) -> Iv:
        zero = o.contains_zero()
        safe = Iv(torch.where(zero, 1.0, o.lo), torch.where(zero, 1.0, o.hi))
        q = torch.stack([self.lo / safe.lo, self.lo / safe.hi, self.hi / safe.lo, self.hi / safe.hi])
        return Iv(torch.where(zero, -INF, _down(q.amin(0))), torch.where(zero, INF, _up(q.amax(0))))

    def square(self) -> Iv:
        a, b = self.lo * self.lo, self.hi * self.hi
        lo = torch.where(self.contains_zero(), 0.0, _down(torch.minimum(a, b)).clamp(min=0.0))
        return Iv(lo, _up(torch.maximum(a, b)))

    def abs(self) -> Iv:
        lo = torch.where(self.contains_zero(), 0.0, torch.minimum(self.lo.abs(), self.hi.abs()))
        return Iv(lo, self.mag())

    # ---- library functions: padded outward by 8 eps of the value and one step
    def _monotone(self, f) -> Iv:
        a, b = f(self.lo), f(self.hi)
        return Iv(_pad_down(a, 8 * EPS, a.abs()), _pad_up(b, 8 * EPS, b.abs()))

    def tanh(self) -> Iv:
        out = self._monotone(torch.tanh)
        return Iv(out.lo.clamp(min=-1.0), out.hi.clamp(max=1.0))

    def exp(self) -> Iv:
        out = self._monotone(torch.exp)
        return Iv(out.lo.clamp(min=0.0), out.hi)

    def sqrt(self) -> Iv:
        """sqrt over ``[lo, hi]``; where the interval reaches below 0 (outside the domain) the whole line."""
        out = Iv(self.lo.clamp(min=0.0), self.hi)._monotone(torch.sqrt)
        outside = self.lo < 0
        return Iv(torch.where(outside, -INF, out.lo.clamp(min=0.0)), torch.where(outside, INF, out.hi))

    def _periodic(self, f, peak: float) -> Iv:
        """``f`` (sin or cos) over ``[lo, hi]``: the endpoint values, and 1 (-1) where the interval may hold a
        maximum ``peak + 2 pi k`` (a minimum ``peak + pi + 2 pi k``), decided with a margin so that a doubtful case
        includes the extremum."""
        a, b = f(self.lo), f(self.hi)
        lo, hi = torch.minimum(a, b), torch.maximum(a, b)
        two_pi = 2 * math.pi
        slack = 1e-9 * (1 + self.lo.abs() + self.hi.abs())

        def holds(c: float) -> Tensor:
            k = torch.floor((self.hi + slack - c) / two_pi)
            return c + two_pi * k >= self.lo - slack

        wide = ~((self.hi - self.lo) < two_pi)  # also NaN and inf ends
        hi = torch.where(holds(peak) | wide, 1.0, _pad_up(hi, 8 * EPS, hi.abs() + 1.0))
        lo = torch.where(holds(peak + math.pi) | wide, -1.0, _pad_down(lo, 8 * EPS, lo.abs() + 1.0))
        return Iv(lo.clamp(min=-1.0), hi.clamp(max=1.0))

    def sin(self) -> Iv:
        return self._periodic(torch.sin, math.pi / 2)

    def cos(self) -> Iv:
        return self._periodic(torch.cos, 0.0)

    def clamp(self, low: Tensor, high: Tensor) -> Iv:
        return Iv(torch.minimum(torch.maximum(self.lo, low), high), torch.minimum(torch.maximum(self.hi, low), high))

    # ---- linear algebra with constant (float64) matrices
    def linear(self, weight: Tensor, bias: Tensor | None = None) -> Iv:
        """``x W^T + b`` for ``x (..., a)``, ``W (c, a)``: centre-radius form, padded by ``(a + 2) eps`` of the
        magnitudes."""
        mid = (self.lo + self.hi) / 2
        rad = _up(torch.maximum(self.hi - mid, mid - self.lo))
        wa = weight.abs()
        centre = mid @ weight.T
        spread = rad @ wa.T
        mag = mid.abs() @ wa.T + spread
        if bias is not None:
            centre = centre + bias
            mag = mag + bias.abs()
        rel = (weight.shape[1] + 3) * EPS
        return Iv(_pad_down(centre - spread, rel, mag), _pad_up(centre + spread, rel, mag))

    def sum(self, dim=None) -> Iv:
        if dim is None:
            return Iv(self.lo.reshape(-1), self.hi.reshape(-1)).sum(0)
        count = self.lo.shape[dim]
        rel = (count + 2) * EPS
        return Iv(_pad_down(self.lo.sum(dim), rel, self.lo.abs().sum(dim)),
                  _pad_up(self.hi.sum(dim), rel, self.hi.abs().sum(dim)))

    def norm(self) -> Iv:
        """The Euclidean norm along the last axis (the sum of squares is >= 0: its padded lower end is raised to 0,
        not read as leaving sqrt's domain)."""
        total = self.square().sum(-1)
        return Iv(total.lo.clamp(min=0.0), total.hi).sqrt()


class Du(_Ops):
    """A dual number: value ``v`` and tangents ``d[i]`` (each of ``v``'s kind and shape)."""

    __slots__ = ("v", "d")

    def __init__(self, v, d: list) -> None:
        self.v, self.d = v, list(d)

    @property
    def level(self) -> int:
        return self.v.level + 1

    @property
    def shape(self):
        return self.v.shape

    @staticmethod
    def seed(x, count: int, axis_tangents: list[int]) -> Du:
        """``x (B, n)`` (an interval, a dual or a second-order form) as the free variable of ``count`` tangents:
        tangent ``i`` is 1 in column ``axis_tangents[i]`` (the others 0)."""
        zero = x * 0.0
        tangents = []
        for i in range(count):
            e = torch.zeros(x.shape, dtype=F64, device=x.c.device if hasattr(x, "c") else _base(x).lo.device)
            e[..., axis_tangents[i]] = 1.0
            tangents.append(zero + e)
        return Du(x, tangents)

    def _map(self, f) -> Du:
        return Du(f(self.v), [f(t) for t in self.d])

    def __getitem__(self, idx) -> Du:
        return self._map(lambda t: t[idx])

    def unbind(self, dim: int = 0) -> tuple:
        vs = self.v.unbind(dim)
        ds = [t.unbind(dim) for t in self.d]
        return tuple(Du(vs[j], [d[j] for d in ds]) for j in range(len(vs)))

    def unsqueeze(self, dim: int) -> Du:
        return self._map(lambda t: t.unsqueeze(dim))

    def sum(self, dim=None) -> Du:
        return self._map(lambda t: t.sum(dim))

    # ---- same-level arithmetic (product rules)
    def add(self, o: Du) -> Du:
        return Du(self.v + o.v, [a + b for a, b in zip(self.d, o.d)])

    def sub(self, o: Du) -> Du:
        return Du(self.v - o.v, [a - b for a, b in zip(self.d, o.d)])

    def neg(self) -> Du:
        return self._map(lambda t: -t)

    def mul(self, o: Du) -> Du:
        return Du(self.v * o.v, [a * o.v + self.v * b for a, b in zip(self.d, o.d)])

    def div(self, o: Du) -> Du:
        q = self.v / o.v
        return Du(q, [(a - q * b) / o.v for a, b in zip(self.d, o.d)])

    # ---- with a constant of a lower level (no tangents of this level)
    def add_const(self, c) -> Du:
        return Du(self.v + c, self.d)

    def radd_const(self, c) -> Du:
        return self.add_const(c)

    def sub_const(self, c) -> Du:
        return Du(self.v - c, self.d)

    def rsub_const(self, c) -> Du:
        return Du(c - self.v, [-t for t in self.d])

    def mul_const(self, c) -> Du:
        return Du(self.v * c, [t * c for t in self.d])

    def rmul_const(self, c) -> Du:
        return self.mul_const(c)

    def div_const(self, c) -> Du:
        return Du(self.v / c, [t / c for t in self.d])

    def rdiv_const(self, c) -> Du:
        q = c / self.v
        return Du(q, [-(q / self.v) * t for t in self.d])

    # ---- functions: f(v), f'(v) * tangent
    def _chain(self, value, slope) -> Du:
        return Du(value, [slope * t for t in self.d])

    def square(self) -> Du:
        return self._chain(self.v.square(), self.v * 2.0)

    def tanh(self) -> Du:
        t = self.v.tanh()
        return self._chain(t, 1.0 - t.square())

    def exp(self) -> Du:
        e = self.v.exp()
        return self._chain(e, e)

    def sqrt(self) -> Du:
        s = self.v.sqrt()
        return self._chain(s, 0.5 / s)

    def sin(self) -> Du:
        return self._chain(self.v.sin(), self.v.cos())

    def cos(self) -> Du:
        return self._chain(self.v.cos(), -self.v.sin())

    def abs(self) -> Du:
        _first_order(self, "abs")
        return self._chain(self.v.abs(), _sign(self.v))

    def clamp(self, low: Tensor, high: Tensor) -> Du:
        """The clamp's Clarke derivative: 1 strictly inside, 0 strictly outside, [0, 1] where the value may touch
        a bound. Differentiated twice only where every value is strictly inside (the identity) or strictly outside
        one bound (a constant)."""
        base = _base(self.v)
        inside = (base.lo > low) & (base.hi < high)
        outside = (base.hi < low) | (base.lo > high)
        if not isinstance(self.v, Iv):
            if bool(inside.all()):
                return self
            if not bool(outside.all()):
                raise TypeError("the checker takes clamp of first-order duals only where it may touch a bound")
            return lift(self.v.clamp(low, high), self.level, self)
        slope = Iv(torch.where(inside, 1.0, 0.0), torch.where(outside, 0.0, 1.0))
        return self._chain(self.v.clamp(low, high), slope)

    def linear(self, weight: Tensor, bias: Tensor | None = None) -> Du:
        return Du(self.v.linear(weight, bias), [t.linear(weight) for t in self.d])

    def norm(self) -> Du:
        """``||v||`` along the last axis. Its tangent is ``u . t`` with ``u = v / ||v||`` a unit vector (the Clarke
        gradient at 0 is the unit ball), enclosed where ``||v|| > 0`` surely by the intersection of ``(v . t) /
        ||v||`` and ``u . t`` with ``u``'s components in ``[-1, 1]``, and everywhere by ``[-||t||, ||t||]``."""
        value = self.v.norm()
        positive = _base(value).lo > 0
        unit = None
        if isinstance(self.v, Iv):
            safe = Iv(torch.where(positive, value.lo, 1.0), torch.where(positive, value.hi, 1.0))
            unit = self.v / safe.unsqueeze(-1)
            unit = Iv(unit.lo.clamp(-1.0, 1.0), unit.hi.clamp(-1.0, 1.0))
        out = []
        for t in self.d:
            mag = _base(t).mag()
            bound = mag.square().sum(-1).sqrt()  # n squares summed and a root: (n + 4) eps of the result covers both
            bound = _up(bound + (mag.shape[-1] + 4) * EPS * bound + TINY)
            slope = (self.v * t).sum(-1) / value
            if unit is not None and isinstance(t, Iv):
                slope = _meet(slope, (unit * t).sum(-1))
            out.append(_hull_where(positive, _meet(slope, Iv(-bound, bound)), bound))
        return Du(value, out)


def _first_order(x: Du, what: str) -> None:
    if not isinstance(x.v, Iv):  # a kink differentiated twice has no bounded derivative to enclose
        raise TypeError(f"the checker takes {what} of first-order duals only")


def _base(x) -> Iv:
    while isinstance(x, Du):
        x = x.v
    return x


def _sign(v) -> Iv:
    b = _base(v)
    return Iv(torch.where(b.lo > 0, 1.0, -1.0), torch.where(b.hi < 0, -1.0, 1.0))


def _meet(a, b: Iv) -> Iv:
    """The intersection of two enclosures of the same quantity (a NaN end yields to the other's)."""
    if not isinstance(a, Iv):
        raise TypeError("the checker takes norms of first-order duals only")
    return Iv(torch.fmax(a.lo, b.lo), torch.fmin(a.hi, b.hi))


def _hull_where(positive: Tensor, slope, bound: Tensor) -> Iv:
    """``slope`` where ``positive``, else ``[-bound, bound]``."""
    if not isinstance(slope, Iv):
        raise TypeError("the checker takes norms of first-order duals only")
    return Iv(torch.where(positive, slope.lo, -bound), torch.where(positive, slope.hi, bound))


def norm(x):
    """The Euclidean norm of ``x`` along its last axis (an :class:`Iv` or :class:`Du`)."""
    return x.norm()
