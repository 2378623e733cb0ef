"""Reading an ONNX file as data into a :class:`~drlyap.graph.Graph` on local states (:func:`read_onnx`).

The file is parsed with the ``onnx`` package (protobuf: nothing in it runs); tensors stored outside the file are
refused. Only the operations in :data:`SUPPORTED` are read, each into the interpreter's operations; anything else
is refused with one line naming the operation and the file, as is a file that declares a tensor of more than
:data:`MAX_ELEMENTS` elements (:data:`MAX_TOTAL` in all; layers wider than :data:`MAX_WIDTH`), checked on the declared
dimensions before anything is allocated, or whose data do not fill them. What is read:

* ``Gemm``, ``MatMul`` with constant weights -> ``F.linear``; ``Add``, ``Sub``, ``Mul``, ``Div``, ``Neg``, ``Tanh``,
  ``Exp``, ``Pow`` by a constant integer; ``Relu`` -> a clamp at 0; ``Sigmoid`` -> ``0.5 + 0.5 tanh(x / 2)``;
  ``Clip``, and ``Min``/``Max`` with a constant -> clamps; ``ReduceSum`` over the last axis;
* ``Cast`` between float types and ``Identity`` are the identity: numerically a no-op in the float64 reading of
  the weights that every proof is about (a float32 model runs in float32; the claim is about its float64
  reading, as for drlyap's own pairs); ``Reshape``, ``Squeeze``, ``Unsqueeze`` and ``Flatten`` only where they keep
  the batch axis (``(B, k)`` unchanged, or ``(B, 1)`` <-> ``(B,)``);
* shape arithmetic (``Shape``, ``Gather``, ``Concat``, ``ConstantOfShape``, ``Constant``, ``Transpose`` of a
  constant) is evaluated when the file is read, exactly; arithmetic on constants is not: it is evaluated with the
  state's kind (an enclosure of its real value on enclosures).

**The input prefix.** ``drlyap export`` writes models on user coordinates that begin with ``z = x - x*`` and, for
angle coordinates, ``remainder(z + pi, 2 pi) - pi`` (``Where``/``Floor``/``Mod``). When that prefix offsets by the
system's own equilibrium and wraps exactly the system's angle coordinates, it is removed and the rest of the graph
becomes a function of the local state ``z`` on the closed local box. That is sound for the wrapped model: every
state the deployed model sees is wrapped into ``[-pi, pi)`` first, and there (the local box's angle sides lie in
``[-pi, pi]``, checked) the wrap is the identity, so the unwrapped network equals the wrapped one at every wrapped
state; what the verifier proves on the closed box (which also holds the unwrapped point ``+pi``) covers them all.
A prefix that offsets by another point or wraps other coordinates is refused. A graph without the prefix reads
the user state ``x = x* + z``.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch

from drlyap.graph.interpreter import INPUT, Graph, GraphBuilder
from drlyap.graph.passes import simplify
from drlyap.graph.prefix import strip_prefix
from drlyap.systems import UncertainSystem

SUPPORTED = ("Add", "Cast", "Clip", "Concat", "Constant", "ConstantOfShape", "Div", "Exp", "Flatten", "Gather",
             "Gemm", "Identity", "MatMul", "Max", "Min", "Mul", "Neg", "Pow", "ReduceSum", "Relu", "Reshape", "Shape",
             "Sigmoid", "Squeeze", "Sub", "Tanh", "Transpose", "Unsqueeze")
"""The ONNX operations drlyap reads (``Where``, ``Floor``, ``Mod`` only as the input's angle wrap)."""

FLOAT_TYPES = {1, 10, 11, 16}  # FLOAT, FLOAT16, DOUBLE, BFLOAT16
NUMBER_TYPES = FLOAT_TYPES | {2, 3, 4, 5, 6, 7, 9, 12, 13}  # and UINT8, INT8, UINT16, INT16, INT32, INT64, BOOL, UINT32/64
ROLES = ("controller", "lyapunov")

# What a file may declare, checked before anything is allocated: elements of one tensor (a weight, a constant a node
# makes; a layer of width 1000 has 10^6 weights), of all its constants, the axes of a tensor, the values per state of
# a state-dependent value (a layer's width: the proofs evaluate it on thousands of states and boxes at once), and the
# file's size (512 MB: more than MAX_TOTAL float64 numbers).
MAX_ELEMENTS, MAX_TOTAL, MAX_RANK, MAX_WIDTH, MAX_FILE_BYTES = 10**7, 5 * 10**7, 8, 10**4, 2**29


class Sym(tuple):
    """A shape vector (int64) some of whose entries are the batch size (None)."""


def _onnx():
    try:
        import onnx
        from onnx import numpy_helper
    except ImportError:
        raise ValueError("reading ONNX needs onnx: pip install 'drlyap[export]'") from None
    return onnx, numpy_helper


def read_onnx(path: str | os.PathLike, system: UncertainSystem, role: str) -> tuple[Graph, list[str]]:
    """The ``role`` network (``controller``: ``(B, n) -> (B, m)``; ``lyapunov``: ``(B, n) -> (B,)``) of ``system`` in the
    ONNX file at ``path``, as a graph on local states, and notes on how it was read (the prefix removed, the
    rewrites of :func:`~drlyap.graph.passes.simplify`). A file that drlyap cannot read soundly is refused with a
    ValueError of one line naming the file."""
    if role not in ROLES:
        raise ValueError(f"unknown role {role!r}; valid: {', '.join(ROLES)}")
    onnx, numpy_helper = _onnx()
    path = Path(path)
    size = path.stat().st_size if path.is_file() else 0  # else onnx.load says what is wrong
    if size > MAX_FILE_BYTES:
        raise ValueError(f"{path}: the file is {size / 2**20:.0f} MB, more than the {MAX_FILE_BYTES // 2**20} MB "
                         "drlyap reads")
    try:
        model = onnx.load(str(path), load_external_data=False)
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file") from None
    except Exception as err:  # protobuf's decode errors have many types: any is a damaged file
        raise ValueError(f"{path}: not a readable ONNX model ({type(err).__name__})") from None
    try:
        return _Reader(model, path, system, role, onnx, numpy_helper).read()
    except ValueError:
        raise
    except Exception as err:  # onnx's own checks (ValidationError...) on a malformed graph: a damaged file
        first = (str(err).splitlines() or [""])[0]
        raise ValueError(f"{path}: not a readable ONNX model ({type(err).__name__}: {first})") from None


class _Reader:
    def __init__(self, model, path: Path, system: UncertainSystem, role: str, onnx, numpy_helper) -> None:
        self.model, self.path, self.system, self.role = model, path, system, role
        self.onnx, self.nh = onnx, numpy_helper
        self.opset = max([o.version for o in model.opset_import if o.domain in ("", "ai.onnx")] or [0])
        self.b = GraphBuilder(system.n, f"{path}")
        self.values: dict[str, object] = {}  # ONNX name -> np.ndarray (constant), Sym, or a builder name (str)
        self.const_names: dict[int, tuple[object, str]] = {}
        self.elements = 0  # of the constants held (MAX_TOTAL)
        self.counted: dict[int, object] = {}  # id -> the array counted (kept alive, so that its id is not reused)
        self.node_attrs: dict[int, dict] = {}  # node index -> its attributes, read once
        self.current = "the graph"  # the node being read, as errors name it

    def fail(self, what: str) -> ValueError:
        return ValueError(f"{self.path}: {what}")

    # ------------------------------------------------------------------ sizes
    def fits(self, dims, what: str, add: bool = False) -> int:
        """The element count of a tensor of shape ``dims`` that ``what`` (a tensor, a node) would make, checked
        before it is made: rank, no negative dimension, :data:`MAX_ELEMENTS`, and :data:`MAX_TOTAL` with the
        constants held (counted among them with ``add``); a ValueError naming the file, ``what`` and the cap."""
        if len(dims) > MAX_RANK:
            raise self.fail(f"{what} has {len(dims)} axes; drlyap reads tensors of at most {MAX_RANK}")
        dims = [int(d) for d in dims]
        if any(d < 0 for d in dims):
            raise self.fail(f"{what} has a negative dimension {dims}")
        count = math.prod(dims)
        if count > MAX_ELEMENTS:
            raise self.fail(f"{what} has {count:,} elements {dims}, more than the {MAX_ELEMENTS:,} drlyap reads in "
                            "one tensor")
        if self.elements + count > MAX_TOTAL:
            raise self.fail(f"{what} brings the file's constants to {self.elements + count:,} elements, more than the "
                            f"{MAX_TOTAL:,} drlyap reads in all")
        self.elements += count if add else 0
        return count

    def count(self, value, what: str) -> None:
        """Count a constant array (once) among those held, within :data:`MAX_TOTAL`."""
        if _is_const(value) and id(value) not in self.counted:
            self.fits(value.shape, what, add=True)
            self.counted[id(value)] = value

    def tensor(self, t, what: str) -> np.ndarray:
        """A TensorProto of the file as an array, its declared dimensions (:meth:`fits`), type and data length
        checked before anything is allocated; a ValueError naming the file and ``what`` otherwise."""
        if self.onnx.external_data_helper.uses_external_data(t):
            raise self.fail(f"{what} is stored outside the file; drlyap reads self-contained models only")
        if t.data_type not in NUMBER_TYPES:
            name = {v: k for k, v in self.onnx.TensorProto.DataType.items()}.get(t.data_type, t.data_type)
            raise self.fail(f"{what} has data type {name}; drlyap reads numbers (float, int, bool) only")
        count = self.fits(t.dims, what)
        if t.raw_data:
            size = np.dtype(self.onnx.helper.tensor_dtype_to_np_dtype(t.data_type)).itemsize
            if len(t.raw_data) != count * size:
                raise self.fail(f"{what} declares {count:,} elements {list(t.dims)} ({count * size:,} bytes) but "
                                f"holds {len(t.raw_data):,} bytes")
        else:
            held = sum(len(f) for f in (t.float_data, t.int32_data, t.int64_data, t.double_data, t.uint64_data))
            if held != count:
                raise self.fail(f"{what} declares {count:,} elements {list(t.dims)} but holds {held:,}")
        self.count(value := self.nh.to_array(t), what)
        return value

    # ------------------------------------------------------------------ the file
    def read(self) -> tuple[Graph, list[str]]:
        graph = self.model.graph
        for t in graph.initializer:
            self.values[t.name] = self.tensor(t, f"tensor {t.name!r}")
        inputs = [i for i in graph.input if i.name not in self.values]
        if len(inputs) != 1 or len(graph.output) != 1:
            raise self.fail(f"a {self.role} model needs one input (the state) and one output, got {len(inputs)} and "
                            f"{len(graph.output)}")
        self._check_input(inputs[0])
        x = inputs[0].name
        nodes = list(graph.node)
        for i, node in enumerate(nodes):  # constants the prefix compares with (pi, 2 pi) are Constant nodes
            if node.op_type == "Constant" and node.domain in ("", "ai.onnx") and len(node.output) == 1:
                try:
                    self.values[node.output[0]] = _constant(self, [], self.attrs(node, i))
                except ValueError:
                    pass  # refused where the node is read
        prefix, local, notes = strip_prefix(nodes, self.values, x, self.system, self.path)
        for name in local:
            self.values[name] = INPUT
        users = [i for i, node in enumerate(nodes) if i not in prefix and x in node.input]
        if users:  # the rest of the graph reads the user state x = x* + z
            x_star = torch.tensor(self.system.equilibrium, dtype=torch.float64)
            self.values[x] = INPUT if not bool(x_star.any()) else self.b.emit("add", [INPUT, self.b.constant(x_star, "x_star")])
            if not local:
                notes.append("no offset to x* at the input: the graph reads user coordinates x = x* + z")
        for i, node in enumerate(nodes):
            if i in prefix:
                continue
            if node.domain not in ("", "ai.onnx"):
                raise self.fail(f"unsupported ONNX op {node.domain}.{node.op_type} (a custom domain)")
            self._node(node, i)
        out = self.values.get(graph.output[0].name)
        if not isinstance(out, str) or not self.b.is_dynamic(out):
            raise self.fail("its output does not depend on the state")
        out = self._output_shape(out)
        box = None
        if self.role == "controller":
            box = tuple(list(b) for b in self.system.input_box)
        nodes, constants, output, more = simplify(self.b.nodes, self.b.constants, out, box)
        return Graph(nodes, constants, output, self.system.n, str(self.path)), notes + more

    def _check_input(self, value) -> None:
        t = value.type.tensor_type
        if t.elem_type not in FLOAT_TYPES:
            raise self.fail(f"its input {value.name!r} must be a float tensor (batch, {self.system.n})")
        dims = [d.dim_value if d.HasField("dim_value") else None for d in t.shape.dim] if t.HasField("shape") else None
        if dims is not None and (len(dims) != 2 or dims[1] not in (None, self.system.n)):
            shown = ", ".join("batch" if d is None else str(d) for d in dims)
            raise self.fail(f"the graph expects states of shape ({shown}); system {self.system.name} has n = "
                            f"{self.system.n} states ({', '.join(self.system.state_names)})")

    def _output_shape(self, out: str) -> str:
        shape = tuple(self.b.example(out).shape)
        m = self.system.m
        if self.role == "controller":
            if shape == (2,) and m == 1:
                return self.b.emit("unsqueeze", [out])
            if shape != (2, m):
                raise self.fail(f"a controller of {self.system.name} must output (batch, {m}), got (batch, "
                                f"{', '.join(map(str, shape[1:]))})")
            return out
        if shape == (2, 1):
            return self.b.emit("squeeze", [out])
        if shape != (2,):
            raise self.fail(f"a Lyapunov function V must output (batch,) or (batch, 1), got (batch, "
                            f"{', '.join(map(str, shape[1:]))})")
        return out

    # ------------------------------------------------------------------ values
    def name(self, v) -> str:
        """A builder name for a value (a constant becomes one, once)."""
        if isinstance(v, str):
            return v
        if isinstance(v, Sym):
            raise self.fail("a shape that depends on the batch size is used as data")
        key = id(v)  # the entry keeps v alive, so its id is not reused by another array
        if key not in self.const_names:
            self.const_names[key] = (v, self.b.constant(torch.tensor(np.asarray(v, dtype=np.float64))))
        return self.const_names[key][1]

    def shape(self, v) -> tuple:
        return tuple(self.b.example(v).shape) if isinstance(v, str) else np.shape(v)

    def attrs(self, node, index: int) -> dict:
        """The attributes of the node at ``index`` (read once: tensors checked by :meth:`tensor`)."""
        if index in self.node_attrs:
            return self.node_attrs[index]
        out = {}
        for a in node.attribute:
            value = self.onnx.helper.get_attribute_value(a)
            if isinstance(value, self.onnx.TensorProto):
                value = self.tensor(value, f"attribute {a.name!r} of node {node.name or index} ({node.op_type})")
            elif isinstance(value, list) and len(value) > MAX_ELEMENTS:
                raise self.fail(f"attribute {a.name!r} of node {node.name or index} has {len(value):,} entries, more "
                                f"than the {MAX_ELEMENTS:,} drlyap reads")
            out[a.name] = value
        self.node_attrs[index] = out
        return out

    # ------------------------------------------------------------------ nodes
    def _node(self, node, index: int) -> None:
        op = node.op_type
        if op in ("Where", "Floor", "Mod"):
            raise self.fail(f"unsupported ONNX op {op} (node {node.name or index}) outside the input's angle wrap "
                            "(remainder(x - x* + pi, 2 pi) - pi), the one place drlyap reads it")
        if op not in SUPPORTED:
            raise self.fail(f"unsupported ONNX op {op} (node {node.name or index}); drlyap reads "
                            f"{', '.join(SUPPORTED)}")
        missing = [i for i in node.input if i and i not in self.values]
        if missing:
            raise self.fail(f"node {node.name or index} ({op}) reads {missing} before they are made")
        ins = [self.values[i] if i else None for i in node.input]
        self.current = f"node {node.name or index} ({op})"
        if len([o for o in node.output if o]) != 1:
            raise self.fail(f"node {node.name or index} ({op}) has {len(node.output)} outputs; one is read")
        try:
            out = _HANDLERS[op](self, ins, self.attrs(node, index))
            self.count(out, self.current)
        except ValueError as err:
            msg = str(err)
            raise (err if msg.startswith(str(self.path)) else self.fail(f"{op} (node {node.name or index}): {msg}")) \
                from None
        except (RuntimeError, IndexError) as err:
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise self.fail(f"{op} (node {node.name or index}) does not fit its inputs ({first})") from None
        self.values[node.output[0]] = out


def _is_const(v) -> bool:
    return isinstance(v, np.ndarray) and not isinstance(v, Sym)


def _emit_elementwise(r: _Reader, op: str, a, b=None):
    """``op`` on data (dynamic or constant), checking that no state-dependent value is broadcast."""
    args = [a] if b is None else [a, b]
    integers = all(_is_const(v) and np.issubdtype(v.dtype, np.integer) for v in args) and op in ("add", "sub", "mul")
    _check_broadcast(r, args, made=not integers, what="broadcasts a state-dependent value")
    if integers:
        return {"add": np.add, "sub": np.subtract, "mul": np.multiply}[op](*args)  # shape arithmetic, exact
    if op == "mul" and isinstance(a, str) and isinstance(b, str) and a == b:
        return r.b.emit("square", [a])
    return r.b.emit(op, [r.name(v) for v in args])


def _check_broadcast(r: _Reader, args: list, made: bool, what: str) -> None:
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


def _gemm(r: _Reader, ins, attrs):
    a, w, c = (ins + [None])[:3]
    if attrs.get("transA", 0):
        raise ValueError("transA = 1 is not read (the data must be the left factor, (batch, k))")
    if not _is_const(w) or w.ndim != 2:
        raise ValueError("the weight must be a constant matrix")
    weight = w if attrs.get("transB", 0) else w.T
    return _linear(r, a, weight, c, float(attrs.get("alpha", 1.0)), float(attrs.get("beta", 1.0)))


def _linear(r: _Reader, a, weight: np.ndarray, c, alpha: float = 1.0, beta: float = 1.0):
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
    if c is not None and alpha == 1.0 and beta == 1.0 and _is_const(c) and c.size in (1, h) and \
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


def _matmul(r: _Reader, ins, attrs):
    a, w = ins
    if not _is_const(w) or w.ndim not in (1, 2):
        raise ValueError("the right factor must be a constant matrix or vector")
    if w.ndim == 1:  # (B, k) @ (k,) -> (B,)
        return r.b.emit("squeeze", [_linear(r, a, w.reshape(1, -1), None)])
    return _linear(r, a, w.T, None)


def _clamp(r: _Reader, x, low, high):
    lo = np.array(-np.inf) if low is None else np.asarray(low, dtype=np.float64)
    hi = np.array(np.inf) if high is None else np.asarray(high, dtype=np.float64)
    if not (_is_const(lo) and _is_const(hi)):
        raise ValueError("its bounds must be constants")
    if np.isnan(lo).any() or np.isnan(hi).any():
        raise ValueError("a bound is NaN")
    if (lo > hi).any():
        raise ValueError("a lower bound exceeds its upper bound (min > max)")
    _check_broadcast(r, [x, lo, hi], made=True, what="its bounds broadcast the state-dependent value")
    return r.b.emit("clamp", [r.name(x), r.name(lo), r.name(hi)])


def _minmax(r: _Reader, ins, which: str):
    if len(ins) != 2:
        raise ValueError(f"{which} of {len(ins)} inputs; two (a value and a constant) are read")
    a, b = ins
    if not _is_const(a) and not _is_const(b):
        raise ValueError(f"{which} of two state-dependent values is not read; one side must be a constant")
    x, c = (b, a) if _is_const(a) and not _is_const(b) else (a, b)
    return _clamp(r, x, None, c) if which == "Min" else _clamp(r, x, c, None)


def _clip(r: _Reader, ins, attrs):
    if r.opset >= 11:
        low = ins[1] if len(ins) > 1 else None
        high = ins[2] if len(ins) > 2 else None
    else:
        low, high = attrs.get("min"), attrs.get("max")
    return _clamp(r, ins[0], low, high)


def _sigmoid(r: _Reader, ins, attrs):
    half = np.array(0.5)
    t = r.b.emit("tanh", [_emit_elementwise(r, "mul", ins[0], half)])
    return _emit_elementwise(r, "add", _emit_elementwise(r, "mul", t, half), half)


def _pow(r: _Reader, ins, attrs):
    x, e = ins
    if not _is_const(e) or e.size != 1 or float(e.reshape(-1)[0]) != int(e.reshape(-1)[0]) or e.reshape(-1)[0] < 1:
        raise ValueError("only a constant integer exponent >= 1 is read")
    n = int(e.reshape(-1)[0])
    if n == 1:
        return x
    return r.b.emit("square", [r.name(x)]) if n == 2 else r.b.emit("pow", [r.name(x)], {"n": n})


def _cast(r: _Reader, ins, attrs):
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


def _reduce_sum(r: _Reader, ins, attrs):
    x = ins[0]
    axes = attrs.get("axes") if r.opset < 13 else (None if len(ins) < 2 or ins[1] is None else list(ins[1]))
    keep = bool(attrs.get("keepdims", 1))
    rank = len(r.shape(x))
    if not isinstance(x, str) or rank != 2 or axes is None or [a % rank for a in axes] != [1]:
        raise ValueError("only a sum over the last axis of a (batch, k) value is read")
    return r.b.emit("sum", [x], {"keepdim": keep})


def _batch_reshape(r: _Reader, x: str, target: tuple) -> object:
    """A reshape of ``x (B, ...)`` to ``target`` (with the batch axis first) as the interpreter's operations."""
    shape = r.shape(x)
    if target == shape:
        return x
    if shape[1:] == (1,) and target == shape[:1]:
        return r.b.emit("squeeze", [x])
    if len(shape) == 1 and target == shape + (1,):
        return r.b.emit("unsqueeze", [x])
    raise ValueError(f"reshapes {shape[1:]} per state into {target[1:]}; only (k,) <-> (k,) and (1,) <-> () are read")


def _reshape(r: _Reader, ins, attrs):
    x, spec = ins
    if _is_const(x):
        if not _is_const(spec):
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


def _squeeze(r: _Reader, ins, attrs):
    x, axes = ins[0], _axes(ins, attrs, r.opset)
    if _is_const(x):
        return np.squeeze(x, axis=None if axes is None else tuple(axes))
    shape = r.shape(x)
    if len(shape) == 2 and shape[1] == 1 and (axes is None or [a % 2 for a in axes] == [1]):
        return r.b.emit("squeeze", [x])
    raise ValueError(f"only the last axis of a (batch, 1) value is squeezed, not axes {axes} of {shape}")


def _unsqueeze(r: _Reader, ins, attrs):
    x, axes = ins[0], _axes(ins, attrs, r.opset)
    if isinstance(x, Sym):
        if axes != [0] or len(x) != 0:
            raise ValueError("unsqueezes a batch-dependent shape")
        return Sym(x)
    if _is_const(x):
        out = x
        for a in sorted(axes):
            out = np.expand_dims(out, a)
        return out
    if len(r.shape(x)) == 1 and axes in ([1], [-1]):
        return r.b.emit("unsqueeze", [x])
    raise ValueError(f"only (batch,) -> (batch, 1) is read, not axes {axes} of {r.shape(x)}")


def _flatten(r: _Reader, ins, attrs):
    x, axis = ins[0], int(attrs.get("axis", 1))
    if _is_const(x):
        return x.reshape(int(np.prod(x.shape[:axis])), -1)
    shape = r.shape(x)
    if axis != 1:
        raise ValueError(f"only Flatten(axis=1) is read, got axis {axis}")
    return _batch_reshape(r, x, (shape[0], int(np.prod(shape[1:]))))


def _shape(r: _Reader, ins, attrs):
    x = ins[0]
    if _is_const(x):
        dims = list(x.shape)
    else:
        shape = r.shape(x)
        dims = [None, *shape[1:]] if r.b.is_dynamic(x) else list(shape)
    dims = dims[attrs.get("start", 0):attrs.get("end", len(dims))]
    return Sym(dims) if None in dims else np.array(dims, dtype=np.int64)


def _gather(r: _Reader, ins, attrs):
    data, idx = ins
    axis = int(attrs.get("axis", 0))
    if isinstance(data, str) and _is_const(idx) and idx.ndim == 0 and len(r.shape(data)) == 2 and axis in (1, -1):
        k = r.shape(data)[1]
        if not -k <= int(idx) < k:
            raise ValueError(f"column {int(idx)} of a value with {k} columns")
        return r.b.emit("select", [data], {"index": int(idx) % k})  # x[:, i]
    if not _is_const(idx) or axis != 0 or isinstance(data, str):
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


def _concat(r: _Reader, ins, attrs):
    if any(isinstance(v, str) for v in ins):
        raise ValueError("only the concatenation of shapes and constants is read")
    r.fits((sum(int(np.size(v)) for v in ins),), r.current)
    if any(isinstance(v, Sym) for v in ins):
        return Sym([d for v in ins for d in (v if isinstance(v, Sym) else np.asarray(v).reshape(-1).tolist())])
    return np.concatenate(ins, axis=int(attrs.get("axis", 0)))


def _constant_of_shape(r: _Reader, ins, attrs):
    shape = ins[0]
    if isinstance(shape, Sym) or not _is_const(shape):
        raise ValueError("a constant whose shape depends on the batch size")
    dims = shape.reshape(-1)
    r.fits(dims, r.current)
    value = attrs.get("value", np.zeros(1, dtype=np.float32))
    return np.full([int(d) for d in dims], np.asarray(value).reshape(-1)[0], dtype=np.asarray(value).dtype)


def _transpose(r: _Reader, ins, attrs):
    if not _is_const(ins[0]):
        raise ValueError("only constants are transposed")
    return np.transpose(ins[0], attrs.get("perm"))


def _constant(r: _Reader, ins, attrs):
    for key in ("value", "value_float", "value_floats", "value_int", "value_ints"):
        if key in attrs:
            return np.asarray(attrs[key])
    raise ValueError(f"a Constant with {sorted(attrs)} is not read")


_HANDLERS = {
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
    "Concat": _concat, "ConstantOfShape": _constant_of_shape, "Transpose": _transpose, "Constant": _constant,
}


__all__ = ["ROLES", "SUPPORTED", "read_onnx"]
