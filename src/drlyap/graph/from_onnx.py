"""Reading an ONNX file as data into a :class:`~drlyap.graph.Graph` on local states (:func:`read_onnx`).

The file is parsed with the ``onnx`` package (protobuf: nothing in it runs); tensors stored outside the file are
refused. Only the operations in :data:`SUPPORTED` are read, each into the interpreter's operations
(:mod:`drlyap.graph.onnx_ops`); anything else is refused with one line naming the operation and the file, as is a
file that declares a tensor of more than :data:`MAX_ELEMENTS` elements (:data:`MAX_TOTAL` in all; layers wider than
``onnx_ops.MAX_WIDTH``), checked on the declared dimensions before anything is allocated, or whose data do not fill
them. What is read:

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
from drlyap.graph.onnx_ops import FLOAT_TYPES, HANDLERS, NUMBER_TYPES, Sym, constant, is_const
from drlyap.graph.passes import simplify
from drlyap.graph.prefix import strip_prefix
from drlyap.systems import UncertainSystem

SUPPORTED = ("Add", "Cast", "Clip", "Concat", "Constant", "ConstantOfShape", "Div", "Exp", "Flatten", "Gather",
             "Gemm", "Identity", "MatMul", "Max", "Min", "Mul", "Neg", "Pow", "ReduceSum", "Relu", "Reshape", "Shape",
             "Sigmoid", "Squeeze", "Sub", "Tanh", "Transpose", "Unsqueeze")
"""The ONNX operations drlyap reads (``Where``, ``Floor``, ``Mod`` only as the input's angle wrap)."""

ROLES = ("controller", "lyapunov")

# What a file may declare, checked before anything is allocated: elements of one tensor (a weight, a constant a node
# makes; a layer of width 1000 has 10^6 weights), of all its constants, the axes of a tensor, the values per state of
# a state-dependent value (a layer's width: the proofs evaluate it on thousands of states and boxes at once), and the
# file's size (512 MB: more than MAX_TOTAL float64 numbers).
MAX_ELEMENTS, MAX_TOTAL, MAX_RANK, MAX_FILE_BYTES = 10**7, 5 * 10**7, 8, 2**29


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
        if is_const(value) and id(value) not in self.counted:
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
                    self.values[node.output[0]] = constant(self, [], self.attrs(node, i))
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
            out = HANDLERS[op](self, ins, self.attrs(node, index))
            self.count(out, self.current)
        except ValueError as err:
            msg = str(err)
            raise (err if msg.startswith(str(self.path)) else self.fail(f"{op} (node {node.name or index}): {msg}")) \
                from None
        except (RuntimeError, IndexError) as err:
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise self.fail(f"{op} (node {node.name or index}) does not fit its inputs ({first})") from None
        self.values[node.output[0]] = out


__all__ = ["ROLES", "SUPPORTED", "read_onnx"]
