"""The ONNX operations drlyap reads (:data:`HANDLERS`), each translated into the interpreter's operations by the
reader of :mod:`drlyap.graph.from_onnx`: arithmetic on state-dependent values is emitted (never broadcast), shape
arithmetic on constants is evaluated exactly (:class:`Sym` for shapes with the batch axis), and every value a
translation makes is checked against the reader's caps first."""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from drlyap.graph.interpreter import GraphBuilder


class Reader(Protocol):
    """What a translation reads of :mod:`drlyap.graph.from_onnx`'s reader: the builder, the file's opset and
    ``onnx`` module, the node being read (as errors name it), the names and shapes of values, and the caps."""

    b: GraphBuilder
    opset: int
    onnx: Any
    current: str

    def name(self, v) -> str: ...

    def shape(self, v) -> tuple: ...

    def fits(self, dims, what: str, add: bool = False) -> int: ...

FLOAT_TYPES = {1, 10, 11, 16}  # FLOAT, FLOAT16, DOUBLE, BFLOAT16
NUMBER_TYPES = FLOAT_TYPES | {2, 3, 4, 5, 6, 7, 9, 12, 13}  # and UINT8, INT8, UINT16, INT16, INT32, INT64, BOOL, UINT32/64
MAX_WIDTH = 10**4  # values per state of a state-dependent value (a layer's width)


class Sym(tuple):
    """A shape vector (int64) some of whose entries are the batch size (None)."""


def is_const(v) -> bool:
    return isinstance(v, np.ndarray) and not isinstance(v, Sym)


def _emit_elementwise(r: Reader, op: str, a, b=None):
    """``op`` on data (dynamic or constant), checking that no state-dependent value is broadcast."""
    args = [a] if b is None else [a, b]
    integers = all(is_const(v) and np.issubdtype(v.dtype, np.integer) for v in args) and op in ("add", "sub", "mul")
    _check_broadcast(r, args, made=not integers, what="broadcasts a state-dependent value")
    if integers:
        return {"add": np.add, "sub": np.subtract, "mul": np.multiply}[op](*args)  # shape arithmetic, exact
    if op == "mul" and isinstance(a, str) and isinstance(b, str) and a == b:
        return r.b.emit("square", [a])
    return r.b.emit(op, [r.name(v) for v in args])


def _check_broadcast(r: Reader, args: list, made: bool, what: str) -> None:
    """Before an operation on ``args`` runs: its output's size is within the caps (:meth:`_Reader.fits`; counted
    among the constants where it is one the builder holds, ``made``), and no state-dependent value is broadcast
    (a ValueError starting with ``what``). Shapes that do not broadcast are left to the operation to refuse."""
    shapes = [tuple(r.shape(v)) for v in args if v is not None]
    try:
        shape = tuple(np.broadcast_shapes(*shapes))
    except ValueError:
        return
    for v in args:
        if isinstance(v, str) and r.b.is_dynamic(v) and tuple(r.shape(v)) != shape:
            raise ValueError(f"{what} of shape {tuple(r.shape(v))} to {shape}")
    dynamic = any(isinstance(v, str) and r.b.is_dynamic(v) for v in args)
    r.fits(shape, r.current, add=made and not dynamic)


def _gemm(r: Reader, ins, attrs):
    a, w, c = (ins + [None])[:3]
    if attrs.get("transA", 0):
        raise ValueError("transA = 1 is not read (the data must be the left factor, (batch, k))")
    if not is_const(w) or w.ndim != 2:
        raise ValueError("the weight must be a constant matrix")
    weight = w if attrs.get("transB", 0) else w.T
    return _linear(r, a, weight, c, float(attrs.get("alpha", 1.0)), float(attrs.get("beta", 1.0)))


def _linear(r: Reader, a, weight: np.ndarray, c, alpha: float = 1.0, beta: float = 1.0):
    k = r.shape(a)[-1] if len(r.shape(a)) == 2 else None
    if k != weight.shape[1]:
        raise ValueError(f"its input has shape {r.shape(a)}, its weight expects (batch, {weight.shape[1]})")
    h = weight.shape[0]
    if isinstance(a, str) and r.b.is_dynamic(a):
        if h > MAX_WIDTH:
            raise ValueError(f"makes {h:,} values per state, more than the {MAX_WIDTH:,} drlyap reads")
    else:
        r.fits((r.shape(a)[0], h), r.current, add=True)
    bias = None
    if c is not None and alpha == 1.0 and beta == 1.0 and is_const(c) and c.size in (1, h) and \
            (c.ndim <= 1 or (c.ndim == 2 and c.shape[0] == 1)):
        bias = np.broadcast_to(c.reshape(-1), (h,)).copy()
        c = None
    out = r.b.emit("linear", [r.name(a), r.name(np.ascontiguousarray(weight))] + ([] if bias is None else [r.name(bias)]))
    if alpha != 1.0:
        out = r.b.emit("mul", [out, r.name(np.array(alpha))])
    if c is not None:
        term = c if beta == 1.0 else _emit_elementwise(r, "mul", c, np.array(beta))
        out = _emit_elementwise(r, "add", out, term)
    return out


def _matmul(r: Reader, ins, attrs):
    a, w = ins
    if not is_const(w) or w.ndim not in (1, 2):
        raise ValueError("the right factor must be a constant matrix or vector")
    if w.ndim == 1:  # (B, k) @ (k,) -> (B,)
        return r.b.emit("squeeze", [_linear(r, a, w.reshape(1, -1), None)])
    return _linear(r, a, w.T, None)


def _clamp(r: Reader, x, low, high):
    lo = np.array(-np.inf) if low is None else np.asarray(low, dtype=np.float64)
    hi = np.array(np.inf) if high is None else np.asarray(high, dtype=np.float64)
    if not (is_const(lo) and is_const(hi)):
        raise ValueError("its bounds must be constants")
    if np.isnan(lo).any() or np.isnan(hi).any():
        raise ValueError("a bound is NaN")
    if (lo > hi).any():
        raise ValueError("a lower bound exceeds its upper bound (min > max)")
    _check_broadcast(r, [x, lo, hi], made=True, what="its bounds broadcast the state-dependent value")
    return r.b.emit("clamp", [r.name(x), r.name(lo), r.name(hi)])


def _minmax(r: Reader, ins, which: str):
    if len(ins) != 2:
        raise ValueError(f"{which} of {len(ins)} inputs; two (a value and a constant) are read")
    a, b = ins
    if not is_const(a) and not is_const(b):
        raise ValueError(f"{which} of two state-dependent values is not read; one side must be a constant")
    x, c = (b, a) if is_const(a) and not is_const(b) else (a, b)
    return _clamp(r, x, None, c) if which == "Min" else _clamp(r, x, c, None)


def _clip(r: Reader, ins, attrs):
    if r.opset >= 11:
        low = ins[1] if len(ins) > 1 else None
        high = ins[2] if len(ins) > 2 else None
    else:
        low, high = attrs.get("min"), attrs.get("max")
    return _clamp(r, ins[0], low, high)


def _sigmoid(r: Reader, ins, attrs):
    half = np.array(0.5)
    t = r.b.emit("tanh", [_emit_elementwise(r, "mul", ins[0], half)])
    return _emit_elementwise(r, "add", _emit_elementwise(r, "mul", t, half), half)


def _pow(r: Reader, ins, attrs):
    x, e = ins
    if not is_const(e) or e.size != 1 or float(e.reshape(-1)[0]) != int(e.reshape(-1)[0]) or e.reshape(-1)[0] < 1:
        raise ValueError("only a constant integer exponent >= 1 is read")
    n = int(e.reshape(-1)[0])
    if n == 1:
        return x
    return r.b.emit("square", [r.name(x)]) if n == 2 else r.b.emit("pow", [r.name(x)], {"n": n})


def _cast(r: Reader, ins, attrs):
    x, to = ins[0], int(attrs.get("to", 1))
    if isinstance(x, Sym):
        return x
    if isinstance(x, str):
        if to in FLOAT_TYPES:
            return x  # a float <-> float cast is the identity in the float64 reading
        raise ValueError(f"a cast of a state-dependent value to the non-float type {to}")
    value = np.asarray(x)
    if to not in NUMBER_TYPES:  # strings and the like: not numbers, and a costly copy
        raise ValueError(f"a cast of a constant to the non-numeric type {to}")
    if to in FLOAT_TYPES and np.issubdtype(value.dtype, np.floating):
        return value  # the float64 reading keeps the constant's value
    return value.astype(r.onnx.helper.tensor_dtype_to_np_dtype(to))


def _reduce_sum(r: Reader, ins, attrs):
    x = ins[0]
    axes = attrs.get("axes") if r.opset < 13 else (None if len(ins) < 2 or ins[1] is None else list(ins[1]))
    keep = bool(attrs.get("keepdims", 1))
    rank = len(r.shape(x))
    if not isinstance(x, str) or rank != 2 or axes is None or [a % rank for a in axes] != [1]:
        raise ValueError("only a sum over the last axis of a (batch, k) value is read")
    return r.b.emit("sum", [x], {"keepdim": keep})


def _batch_reshape(r: Reader, x: str, target: tuple) -> object:
    """A reshape of ``x (B, ...)`` to ``target`` (with the batch axis first) as the interpreter's operations."""
    shape = r.shape(x)
    if target == shape:
        return x
    if shape[1:] == (1,) and target == shape[:1]:
        return r.b.emit("squeeze", [x])
    if len(shape) == 1 and target == shape + (1,):
        return r.b.emit("unsqueeze", [x])
    raise ValueError(f"reshapes {shape[1:]} per state into {target[1:]}; only (k,) <-> (k,) and (1,) <-> () are read")


def _reshape(r: Reader, ins, attrs):
    x, spec = ins
    if is_const(x):
        if not is_const(spec):
            raise ValueError("a constant reshaped by a batch-dependent shape")
        return np.reshape(x, [d if d != 0 else x.shape[i] for i, d in enumerate(spec.tolist())])
    shape = r.shape(x)
    dims = list(spec) if isinstance(spec, Sym) else spec.tolist()
    target = []
    for i, d in enumerate(dims):
        target.append(shape[0] if d is None else (shape[i] if d == 0 and i < len(shape) else d))
    if -1 in target:
        rest = int(np.prod([d for d in target if d != -1]))
        target[target.index(-1)] = int(np.prod(shape)) // max(rest, 1)
    if not target or (dims[0] not in (None, 0) and not (dims[0] == -1 and int(np.prod(target[1:])) ==
                                                          int(np.prod(shape[1:])))):
        raise ValueError("the reshape does not keep the batch axis first")
    return _batch_reshape(r, x, tuple(target))


def _axes(ins, attrs, opset: int) -> list[int] | None:
    if opset >= 13:
        return None if len(ins) < 2 or ins[1] is None else [int(a) for a in np.asarray(ins[1]).reshape(-1)]
    return attrs.get("axes")


def _squeeze(r: Reader, ins, attrs):
    x, axes = ins[0], _axes(ins, attrs, r.opset)
    if is_const(x):
        return np.squeeze(x, axis=None if axes is None else tuple(axes))
    shape = r.shape(x)
    if len(shape) == 2 and shape[1] == 1 and (axes is None or [a % 2 for a in axes] == [1]):
        return r.b.emit("squeeze", [x])
    raise ValueError(f"only the last axis of a (batch, 1) value is squeezed, not axes {axes} of {shape}")


def _unsqueeze(r: Reader, ins, attrs):
    x, axes = ins[0], _axes(ins, attrs, r.opset)
    if isinstance(x, Sym):
        if axes != [0] or len(x) != 0:
            raise ValueError("unsqueezes a batch-dependent shape")
        return Sym(x)
    if is_const(x):
        out = x
        for a in sorted(axes):
            out = np.expand_dims(out, a)
        return out
    if len(r.shape(x)) == 1 and axes in ([1], [-1]):
        return r.b.emit("unsqueeze", [x])
    raise ValueError(f"only (batch,) -> (batch, 1) is read, not axes {axes} of {r.shape(x)}")


def _flatten(r: Reader, ins, attrs):
    x, axis = ins[0], int(attrs.get("axis", 1))
    if is_const(x):
        return x.reshape(int(np.prod(x.shape[:axis])), -1)
    shape = r.shape(x)
    if axis != 1:
        raise ValueError(f"only Flatten(axis=1) is read, got axis {axis}")
    return _batch_reshape(r, x, (shape[0], int(np.prod(shape[1:]))))


def _shape(r: Reader, ins, attrs):
    x = ins[0]
    if is_const(x):
        dims = list(x.shape)
    else:
        shape = r.shape(x)
        dims = [None, *shape[1:]] if r.b.is_dynamic(x) else list(shape)
    dims = dims[attrs.get("start", 0):attrs.get("end", len(dims))]
    return Sym(dims) if None in dims else np.array(dims, dtype=np.int64)


def _gather(r: Reader, ins, attrs):
    data, idx = ins
    axis = int(attrs.get("axis", 0))
    if isinstance(data, str) and is_const(idx) and idx.ndim == 0 and len(r.shape(data)) == 2 and axis in (1, -1):
        k = r.shape(data)[1]
        if not -k <= int(idx) < k:
            raise ValueError(f"column {int(idx)} of a value with {k} columns")
        return r.b.emit("select", [data], {"index": int(idx) % k})  # x[:, i]
    if not is_const(idx) or axis != 0 or isinstance(data, str):
        raise ValueError("only one column of a (batch, k) value, or constant entries of a shape or a constant, "
                         "are gathered")
    if isinstance(data, Sym):
        r.fits(np.shape(idx), r.current)
        picked = [data[int(i)] for i in np.asarray(idx).reshape(-1)]
        if None in picked:
            return Sym(picked) if np.ndim(idx) else picked[0]
        out = np.array(picked, dtype=np.int64)
        return out if np.ndim(idx) else out.reshape(())
    r.fits(list(np.shape(idx)) + list(np.shape(data)[1:]), r.current)
    return np.take(data, idx, axis=0)


def _concat(r: Reader, ins, attrs):
    if any(isinstance(v, str) for v in ins):
        raise ValueError("only the concatenation of shapes and constants is read")
    r.fits((sum(int(np.size(v)) for v in ins),), r.current)
    if any(isinstance(v, Sym) for v in ins):
        return Sym([d for v in ins for d in (v if isinstance(v, Sym) else np.asarray(v).reshape(-1).tolist())])
    return np.concatenate(ins, axis=int(attrs.get("axis", 0)))


def _constant_of_shape(r: Reader, ins, attrs):
    shape = ins[0]
    if isinstance(shape, Sym) or not is_const(shape):
        raise ValueError("a constant whose shape depends on the batch size")
    dims = shape.reshape(-1)
    r.fits(dims, r.current)
    value = attrs.get("value", np.zeros(1, dtype=np.float32))
    return np.full([int(d) for d in dims], np.asarray(value).reshape(-1)[0], dtype=np.asarray(value).dtype)


def _transpose(r: Reader, ins, attrs):
    if not is_const(ins[0]):
        raise ValueError("only constants are transposed")
    return np.transpose(ins[0], attrs.get("perm"))


def constant(r: Reader, ins, attrs):
    for key in ("value", "value_float", "value_floats", "value_int", "value_ints"):
        if key in attrs:
            return np.asarray(attrs[key])
    raise ValueError(f"a Constant with {sorted(attrs)} is not read")


HANDLERS = {
    "Add": lambda r, ins, a: _emit_elementwise(r, "add", *ins),
    "Sub": lambda r, ins, a: _emit_elementwise(r, "sub", *ins),
    "Mul": lambda r, ins, a: _emit_elementwise(r, "mul", *ins),
    "Div": lambda r, ins, a: _emit_elementwise(r, "div", *ins),
    "Neg": lambda r, ins, a: _emit_elementwise(r, "neg", ins[0]),
    "Tanh": lambda r, ins, a: _emit_elementwise(r, "tanh", ins[0]),
    "Exp": lambda r, ins, a: _emit_elementwise(r, "exp", ins[0]),
    "Relu": lambda r, ins, a: _clamp(r, ins[0], np.array(0.0), None),
    "Sigmoid": _sigmoid, "Pow": _pow, "Gemm": _gemm, "MatMul": _matmul, "Clip": _clip,
    "Min": lambda r, ins, a: _minmax(r, ins, "Min"), "Max": lambda r, ins, a: _minmax(r, ins, "Max"),
    "Cast": _cast, "Identity": lambda r, ins, a: ins[0], "ReduceSum": _reduce_sum, "Reshape": _reshape,
    "Squeeze": _squeeze, "Unsqueeze": _unsqueeze, "Flatten": _flatten, "Shape": _shape, "Gather": _gather,
    "Concat": _concat, "ConstantOfShape": _constant_of_shape, "Transpose": _transpose, "Constant": constant,
}
