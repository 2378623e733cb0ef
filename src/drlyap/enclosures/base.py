"""What every enclosure type shares: the Python operators, the ``__torch_function__`` bridge, and lifting values
of different kinds to a common one before they meet.

The kinds are ordered: plain tensors and numbers < :class:`~drlyap.enclosures.Interval` <
:class:`~drlyap.enclosures.Affine` (both level 0) < :class:`~drlyap.enclosures.Dual` (level 1 over level-0
values, level 2 over level-1 duals, ...). An operation lifts the lower operand to the kind of the higher one
(a constant of that kind) and calls the higher kind's own method. The concrete types register themselves in
:attr:`Enclosure.kinds` as they are defined, so this module imports none of them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from typing import ClassVar

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor

from drlyap.enclosures.rounding import F64

_WEIGHT_GRADIENTS: ContextVar[bool] = ContextVar("weight_gradients", default=False)


@contextmanager
def weight_gradients() -> Iterator[None]:
    """Within this block the weights an enclosure meets in ``linear`` keep their autograd graph (read as float64 by
    a differentiable cast, the same numbers), so that a bound computed here can be differentiated in the networks'
    weights (certified training). Outside it they are detached: the verifier's bounds build no graph."""
    token = _WEIGHT_GRADIENTS.set(True)
    try:
        yield
    finally:
        _WEIGHT_GRADIENTS.reset(token)


class Enclosure:
    """Common operator plumbing and the ``__torch_function__`` bridge of the enclosure types.

    A concrete type declares its kind (``class Interval(Enclosure, kind="interval")``) and implements ``_add``,
    ``_sub``, ``_mul``, ``_div``, ``_neg``, ``pow_int``, the unary functions, ``linear``, ``sum``, ``norm``,
    ``unbind`` and ``_join`` (stacking and concatenation of items of its own kind).
    """

    level = 0
    kinds: ClassVar[dict[str, type]] = {}

    def __init_subclass__(cls, kind: str | None = None, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        if kind is not None:
            Enclosure.kinds[kind] = cls

    # ---- python operators
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
    def base(self) -> Enclosure:
        """The innermost level-0 enclosure (the enclosure of the value)."""
        return self

    @property
    def device(self) -> torch.device:
        return self.base.device

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
            if not _WEIGHT_GRADIENTS.get():
                weight, bias = weight.detach(), None if bias is None else bias.detach()
            return args[0].linear(weight.to(F64), None if bias is None else bias.to(F64))
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
        if name in ("pow", "__pow__") and len(args) == 2 and isinstance(args[0], Enclosure):
            return args[0] ** args[1]
        if name in ("sum",) and isinstance(args[0], Enclosure):
            dim = kwargs.get("dim", args[1] if len(args) > 1 else None)
            return args[0].sum(dim)
        raise TypeError(f"interval/dual arithmetic does not support {name or func}; use +, -, *, /, ** int, "
                        "torch.sin/cos/tanh/exp/sqrt/square, torch.stack/cat, unbind, indexing, "
                        "torch.nn.functional.linear and torch.linalg.vector_norm")


def is_enclosure(x) -> bool:
    """True for intervals, affine forms and dual numbers (False for tensors and numbers)."""
    return isinstance(x, Enclosure)


def level_of(x) -> int:
    """The nesting level of an enclosure (0: an interval or affine form), -1 for tensors and numbers."""
    return x.level if isinstance(x, Enclosure) else -1


def lift(x, level: int, device: torch.device | None = None):
    """``x`` (a tensor, number or enclosure of a level up to ``level``) as a constant of the given level, on
    ``device`` (None: a tensor's own, a number's the CPU's)."""
    lv = level_of(x)
    if lv == level:
        return x
    if lv > level:
        raise ValueError("cannot lower an enclosure")
    if level == 0:
        return Enclosure.kinds["interval"].const(x, device)
    return Enclosure.kinds["dual"](lift(x, level - 1, device), None)


def device_of(*items) -> torch.device | None:
    """Where the first enclosure among ``items`` lives (else the first tensor's; None for numbers alone): the device
    a constant that meets them is made on."""
    for kind in (Enclosure, Tensor):
        for x in items:
            if isinstance(x, kind):
                return x.device
    return None


def constant_like(x, value) -> object:
    """``value`` (a tensor or number) as a constant of the same kind as ``x``, on its device: itself for a tensor
    ``x``, an exact enclosure of the same level otherwise."""
    return lift(value, level_of(x), x.device) if isinstance(x, Enclosure) else value


def lift_pair(a, b):
    """``a`` and ``b`` lifted to their common kind (an interval that meets an affine form becomes one), a constant
    on the other's device."""
    level, device = max(level_of(a), level_of(b), 0), device_of(a, b)
    a, b = lift(a, level, device), lift(b, level, device)
    if level == 0:
        affine = Enclosure.kinds["affine"]
        if isinstance(a, affine) != isinstance(b, affine):
            a, b = affine.const(a), affine.const(b)
    return a, b


def normdim(dim: int, ndim: int) -> int:
    """``dim`` as a non-negative axis of ``ndim`` axes, or an IndexError."""
    if not -ndim <= dim < ndim:
        raise IndexError(f"dimension {dim} out of range for {ndim} dimensions")
    return dim % ndim


def join(seq: Sequence, dim: int, fn: Callable):
    """``fn`` (``torch.stack`` or ``torch.cat``) of enclosures and tensors, lifted to their common kind."""
    level, device = max(max(level_of(s) for s in seq), 0), device_of(*seq)
    items = [lift(s, level, device) for s in seq]
    if level == 0:
        affine = Enclosure.kinds["affine"]
        if any(isinstance(s, affine) for s in items):
            items = [affine.const(s) for s in items]
    return type(items[0])._join(items, dim, fn)


def stack(seq: Sequence, dim: int = 0):
    """``torch.stack`` of enclosures (and tensors)."""
    return join(seq, dim, torch.stack)


def cat(seq: Sequence, dim: int = 0):
    """``torch.cat`` of enclosures (and tensors)."""
    return join(seq, dim, torch.cat)


def norm(x, dim: int = -1):
    """Euclidean norm of an enclosure along ``dim`` (for a dual number with a Clarke-gradient enclosure, sound
    also where the vector is 0)."""
    if not isinstance(x, Enclosure):
        raise TypeError("norm is supported on intervals, affine forms and first-order duals")
    return x.norm(dim)


def fix_index(idx, ndim: int) -> tuple:
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
