"""A network as a list of operations on named values, interpreted by torch code that also runs on enclosures.

A :class:`Graph` is the form in which drlyap holds a controller or a certificate it did not build itself (an ONNX
file, :mod:`drlyap.graph.from_onnx`; an RL agent's actor, :mod:`drlyap.runs.imported`): a straight-line program
over the local state ``z (B, n)`` whose operations (:data:`OPS`) are the few that drlyap's enclosures support,
each executed by the same torch call the built-in networks use (``F.linear`` with constant weights, ``+ - * /``,
``torch.tanh``, ``torch.exp``, :func:`drlyap.networks.clamp`, ...). So the verifier bounds an imported network
by running this interpreter on intervals, affine forms and dual numbers, exactly as it runs
:class:`drlyap.networks.Lyapunov` and :class:`~drlyap.networks.Controller`.

* Constants are float64 buffers (a float32 weight is read exactly); the claim of a proof is about the float64
  reading of the weights in real arithmetic, as for native pairs.
* A node none of whose inputs depends on ``z`` (e.g. a network evaluated at the origin, ``phi(0)``) is evaluated on
  its first input lifted to the kind of ``z`` (:func:`~drlyap.enclosures.constant_like`): on enclosures its value is
  an outward-rounded enclosure of the real value, never a float64 approximation of it.
* :meth:`Graph.value_and_grad` (a scalar graph, ``(B,)``) is reverse mode written with the same torch operations
  (so it runs on enclosures, and on tensors it is differentiable again): cotangents are kept as lists of
  contributions ``factor * base`` through the operations that are linear in them, the output's cotangent 1 is
  symbolic, and scalar factors are applied last, so that no enclosure is widened by a multiplication by 1 and
  ``2 d`` followed by ``W^T`` is computed as the built-in networks compute it.

A graph is data: :meth:`Graph.to_json` (the node list) and :meth:`Graph.tensors` (its constants); building one
(:class:`GraphBuilder`, :meth:`Graph.from_json`) checks every node against :data:`OPS` and runs it once on example
states, so a graph that does not fit ``n`` states fails when it is read, with one line.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from fractions import Fraction

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from drlyap.enclosures import constant_like, is_enclosure
from drlyap.networks import clamp

F64 = torch.float64
INPUT = "z"
"""The name of a graph's input: the local state ``z = x - x*`` ``(B, n)``."""

OPS: dict[str, tuple[int, int]] = {
    "linear": (2, 3),  # F.linear(x, W, b): W (h, k), b (h,) constants
    "add": (2, 2), "sub": (2, 2), "mul": (2, 2), "div": (2, 2),
    "neg": (1, 1), "square": (1, 1), "pow": (1, 1), "tanh": (1, 1), "exp": (1, 1), "identity": (1, 1),
    "clamp": (3, 3),  # networks.clamp(x, low, high): low, high constants (+-inf for one side)
    "sum": (1, 1),  # over the last axis; attrs keepdim
    "select": (1, 1),  # (B, k) -> (B,): column attrs index
    "squeeze": (1, 1),  # (B, 1) -> (B,)
    "unsqueeze": (1, 1),  # (B,) -> (B, 1)
}
"""The interpreter's operations: name -> (fewest, most inputs)."""

CONSTANT_INPUTS = {"linear": 1, "clamp": 1}
"""Operations whose inputs from this index on must be constants."""


@dataclass
class Node:
    """One operation: ``output = op(*inputs)`` (``attrs``: ``n`` of ``pow``, ``keepdim`` of ``sum``, ``index`` of
    ``select``)."""

    op: str
    inputs: tuple[str, ...]
    output: str
    attrs: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"op": self.op, "inputs": list(self.inputs), "output": self.output, "attrs": dict(self.attrs)}


def apply(op: str, args: Sequence, attrs: Mapping) -> object:
    """``op`` on ``args`` (tensors or enclosures), the one place each operation's arithmetic is written."""
    x = args[0]
    if op == "linear":
        return F.linear(x, args[1], args[2] if len(args) > 2 else None)
    if op == "add":
        return x + args[1]
    if op == "sub":
        return x - args[1]
    if op == "mul":
        return x * args[1]
    if op == "div":
        return x / args[1]
    if op == "neg":
        return -x
    if op == "square":
        return x.square()
    if op == "pow":
        return x ** int(attrs["n"])
    if op == "tanh":
        return torch.tanh(x)
    if op == "exp":
        return torch.exp(x)
    if op == "identity":
        return x
    if op == "clamp":
        return clamp(x, args[1], args[2])
    if op == "sum":
        s = x.sum(-1)
        return s.unsqueeze(-1) if attrs.get("keepdim") else s
    if op == "select":
        return x[:, int(attrs["index"])]
    if op == "squeeze":
        return x[:, 0]
    if op == "unsqueeze":
        return x.unsqueeze(-1)
    raise ValueError(f"unknown graph operation {op!r}; valid: {', '.join(OPS)}")


# ----------------------------------------------------------------------------------------------- reverse mode
ONE = None
"""The symbolic cotangent 1 (of the output): multiplying by it is skipped, not computed."""


def _exact_product(a: float, b: float) -> float | None:
    """``a * b`` when float64 represents it exactly (a factor kept aside must be a real number, not a rounding)."""
    p = a * b
    return p if math.isfinite(p) and Fraction(a) * Fraction(b) == Fraction(p) else None


def _scalar(t) -> float | None:
    """The value of a one-element constant tensor, else None."""
    return float(t.reshape(-1)[0]) if isinstance(t, Tensor) and t.numel() == 1 else None


class _Cotangents:
    """The reverse pass of one evaluation: contributions ``(factor, base)`` per value, ``base`` ONE or a value."""

    def __init__(self, z, env: dict) -> None:
        self.z, self.env = z, env

    def lift(self, t: Tensor, shape) -> object:
        """A constant cotangent as a value of ``z``'s kind, broadcast to ``shape``."""
        dtype = self.z.dtype if isinstance(self.z, Tensor) else F64
        return constant_like(self.z, torch.broadcast_to(t.to(dtype), tuple(shape)).clone())

    def one(self, shape, factor: float = 1.0) -> object:
        dtype = self.z.dtype if isinstance(self.z, Tensor) else F64
        return constant_like(self.z, torch.full(tuple(shape), factor, dtype=dtype))

    def value(self, contribs: list, shape) -> object:
        """The sum of the contributions as one value of ``shape`` (in their order)."""
        total = None
        for f, base in contribs:
            part = self.one(shape, f) if base is ONE else (base if f == 1.0 else base * f)
            total = part if total is None else total + part
        return total

    def combined(self, contribs: list, shape) -> list:
        """One contribution: a pure ``f * ONE`` stays symbolic, anything else is summed."""
        if all(b is ONE for _, b in contribs):
            total = Fraction(0)
            for f, _ in contribs:
                total += Fraction(f)
            if float(total) == total:
                return [(float(total), ONE)]
        return [(1.0, self.value(contribs, shape))]

    @staticmethod
    def neg(contribs: list) -> list:
        return [(-f, b) for f, b in contribs]

    def scale(self, contribs: list, c, shape) -> list:
        """Contributions times a constant or z-independent ``c``: scalar factors kept aside where exact."""
        s = _scalar(c) if isinstance(c, Tensor) else None
        out = []
        for f, b in contribs:
            p = None if s is None else _exact_product(f, s)
            if p is not None:
                out.append((p, b))
            elif b is ONE:
                out.append((f, self.lift(c, shape) if isinstance(c, Tensor) else c))
            else:
                out.append((f, b * c))
        return out

    def divide(self, contribs: list, c, shape) -> list:
        """Contributions divided by a constant or z-independent ``c`` (factors stay aside: the division is linear)."""
        return [(f, (self.one(shape) if b is ONE else b) / c) for f, b in contribs]

    def times(self, contribs: list, value, shape) -> list:
        """Contributions times a z-dependent ``value``: one product."""
        (f, b), = self.combined(contribs, shape)
        return [(f, value if b is ONE else b * value)]

    def vjp(self, node: Node, args: list, out, g: list, dynamic: list[bool]) -> list[tuple[int, list]]:
        """``[(input index, contributions)]`` for the z-dependent inputs of ``node``, given its output's ``g``."""
        op, shape = node.op, out.shape
        x = args[0]
        if op in ("identity",):
            return [(0, g)]
        if op == "add":
            return [(0, g), (1, g)]
        if op == "sub":
            return [(0, g), (1, self.neg(g))]
        if op == "neg":
            return [(0, self.neg(g))]
        if op == "mul":
            if dynamic[0] and dynamic[1]:
                return [(0, self.times(g, args[1], shape)), (1, self.times(g, x, shape))]
            i = 0 if dynamic[0] else 1
            return [(i, self.scale(g, args[1 - i], shape))]
        if op == "div":
            out_list = []
            if dynamic[0]:
                out_list.append((0, self.divide(g, args[1], shape) if not dynamic[1] else
                                 [(1.0, self.value(g, shape) / args[1])]))
            if dynamic[1]:
                out_list.append((1, [(-1.0, (self.value(g, shape) * out) / args[1])]))
            return out_list
        if op == "square":
            (f, b), = self.combined(g, shape)
            if b is ONE and _exact_product(f, 2.0) is not None:
                return [(0, [(2.0 * f, x)])]
            return [(0, [(1.0, (self.value([(f, b)], shape) * x) * 2.0)])]
        if op == "pow":
            n = int(node.attrs["n"])
            return [(0, self.times(g, x ** (n - 1) * float(n), shape))] if n else []
        if op == "tanh":
            return [(0, self.times(g, 1 - out.square(), shape))]
        if op == "exp":
            return [(0, self.times(g, out, shape))]
        if op == "clamp":
            return self._clamp(x, args[1], args[2], g, shape)
        if op == "sum":
            k = x.shape[-1]
            spread = [(f, b if b is ONE else torch.cat([b if node.attrs.get("keepdim") else b.unsqueeze(-1)] * k, -1))
                      for f, b in g]
            return [(0, spread)]
        if op == "select":  # the cotangent in column index, zeros elsewhere (joined exactly)
            i, k = int(node.attrs["index"]), x.shape[-1]
            col = self.value(self.combined(g, shape), shape)
            zero = self.one(shape, 0.0)
            return [(0, [(1.0, torch.stack([col if j == i % k else zero for j in range(k)], -1))])]
        if op == "squeeze":
            return [(0, [(f, b if b is ONE else b.unsqueeze(-1)) for f, b in g])]
        if op == "unsqueeze":
            return [(0, [(f, b if b is ONE else b[:, 0]) for f, b in g])]
        if op == "linear":
            cot = self.value(self.combined(g, shape), shape)
            return [(0, [(1.0, F.linear(cot, args[1].T))])]
        raise ValueError(f"no reverse mode for graph operation {op!r}")

    def _clamp(self, x, low: Tensor, high: Tensor, g: list, shape) -> list:
        """The clamp's (Clarke) derivative: 1 inside, 0 outside, [0, 1] where a box meets a bound."""
        if not is_enclosure(x):
            return [(0, self.times(g, ((x > low) & (x < high)).to(x.dtype), shape))]
        box = x.base
        if bool(((box.lo > low) & (box.hi < high)).all()):  # inactive over the whole box: the identity
            return [(0, g)]
        if bool(((box.hi < low) | (box.lo > high)).all()):  # saturated everywhere: no derivative
            return []
        if x.level > 0:
            raise TypeError("clamp is supported at first order only (or where it is provably inactive)")
        return [(0, self.times(g, x.clamp_slope(low, high), shape))]


# ----------------------------------------------------------------------------------------------- the module
class Graph(nn.Module):
    """A network given as operations on named values (module docstring): ``forward(z (B, n))`` -> ``(B, m)`` or
    ``(B,)``; :meth:`value_and_grad` for a scalar graph.

    ``nodes`` in order of evaluation; ``constants`` name -> tensor (stored as float64 buffers); ``output`` the name
    of the result; ``n`` the state dimension; ``source`` names the graph in error messages.
    """

    def __init__(self, nodes: Sequence[Node], constants: Mapping[str, Tensor], output: str, n: int,
                 source: str = "graph") -> None:
        super().__init__()
        self.source, self.n, self.output = source, int(n), output
        self.nodes = list(nodes)
        self._buffer: dict[str, str] = {}
        for i, (name, value) in enumerate(constants.items()):
            t = torch.as_tensor(value).detach().to(F64).clone()
            if bool(torch.isnan(t).any()):
                raise ValueError(f"{source}: constant {name!r} contains NaN")
            self._buffer[name] = f"const_{i}"
            self.register_buffer(f"const_{i}", t)
        self._dynamic = self._check()
        self.out_shape = self._check_example()

    # ---------------------------------------------------------------- checks
    def _check(self) -> list[list[bool]]:
        """Every node well formed; returns, per node, which inputs depend on ``z``."""
        known = {INPUT: True} | {name: False for name in self._buffer}
        dynamic = []
        for i, node in enumerate(self.nodes):
            where = f"{self.source}: node {i} ({node.op})"
            if node.op not in OPS:
                raise ValueError(f"{where}: unknown operation; valid: {', '.join(OPS)}")
            low, high = OPS[node.op]
            if not low <= len(node.inputs) <= high:
                raise ValueError(f"{where}: takes {low}-{high} inputs, got {len(node.inputs)}")
            missing = [name for name in node.inputs if name not in known]
            if missing:
                raise ValueError(f"{where}: uses {missing}, which no earlier node defines")
            first_constant = CONSTANT_INPUTS.get(node.op)
            if first_constant is not None and any(name not in self._buffer for name in node.inputs[first_constant:]):
                raise ValueError(f"{where}: its weights/bounds must be constants")
            if node.output in known:
                raise ValueError(f"{where}: redefines {node.output!r}")
            if node.op == "pow" and not (isinstance(node.attrs.get("n"), int) and node.attrs["n"] >= 0):
                raise ValueError(f"{where}: needs an integer exponent n >= 0")
            if node.op == "select" and not isinstance(node.attrs.get("index"), int):
                raise ValueError(f"{where}: needs an integer column index")
            flags = [known[name] for name in node.inputs]
            dynamic.append(flags)
            known[node.output] = any(flags)
        if self.output not in known:
            raise ValueError(f"{self.source}: its output {self.output!r} is not computed")
        if not known[self.output]:
            raise ValueError(f"{self.source}: its output does not depend on the state")
        return dynamic

    def _check_example(self) -> tuple[int, ...]:
        """Run once on example states; the output's shape without the batch axis (``(m,)`` or ``()``)."""
        z = torch.linspace(-1, 1, 2 * self.n, dtype=F64).reshape(2, self.n)
        try:
            with torch.no_grad():
                env = self._run(z)
                out = env[self.output]
        except (RuntimeError, ValueError, IndexError, TypeError) as err:
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise ValueError(f"{self.source}: does not run on states of dimension {self.n} ({first})") from None
        self._check_shapes(env)
        if not isinstance(out, Tensor) or out.ndim not in (1, 2) or out.shape[0] != 2:
            raise ValueError(f"{self.source}: its output must be (batch,) or (batch, m), got "
                             f"{tuple(getattr(out, 'shape', ()))} for a batch of 2")
        return tuple(out.shape[1:])

    def _check_shapes(self, env: dict) -> None:
        """What reverse mode and the enclosures need of each node at the example states: a clamp's bounds in order,
        ``squeeze`` of a last axis of 1 and ``unsqueeze`` of ``(B,)``, and no state-dependent input widened by
        broadcasting (its cotangent would not be summed back to its shape)."""
        for i, (node, flags) in enumerate(zip(self.nodes, self._dynamic)):
            where = f"{self.source}: node {i} ({node.op})"
            args = [env[name] if name in env else self.const(name) for name in node.inputs]
            if node.op == "clamp" and not bool((torch.as_tensor(args[1]) <= torch.as_tensor(args[2])).all()):
                raise ValueError(f"{where}: its lower bounds must not exceed its upper ones")
            if node.op == "squeeze" and not (args[0].ndim == 2 and args[0].shape[-1] == 1):
                raise ValueError(f"{where}: squeezes a last axis of 1 only, got {tuple(args[0].shape)}")
            if node.op == "unsqueeze" and args[0].ndim != 1:
                raise ValueError(f"{where}: takes (batch,), got {tuple(args[0].shape)}")
            shape = tuple(env[node.output].shape)
            if node.op in ("add", "sub", "mul", "div") and any(
                    flag and tuple(torch.as_tensor(a).shape) != shape for flag, a in zip(flags, args)):
                raise ValueError(f"{where}: broadcasts an input that depends on the state to {shape}")

    def const(self, name: str) -> Tensor:
        return getattr(self, self._buffer[name])

    # ---------------------------------------------------------------- evaluation
    def _run(self, z) -> dict:
        env: dict = {INPUT: z}
        for node, flags in zip(self.nodes, self._dynamic):
            args = [env[name] if name in env else self.const(name) for name in node.inputs]
            if not any(flags) and not is_enclosure(args[0]):  # independent of z: its value is enclosed, not rounded
                args[0] = constant_like(z, args[0])
            env[node.output] = apply(node.op, args, node.attrs)
        return env

    def forward(self, z):
        """``z (B, n)`` (a tensor or an enclosure) -> the output ``(B, m)`` or ``(B,)``."""
        return self._run(z)[self.output]

    def value_and_grad(self, z) -> tuple:
        """``V (B,)`` and ``grad V (B, n)`` at ``z (B, n)`` by reverse mode (module docstring); a scalar graph only."""
        if self.out_shape != ():
            raise ValueError(f"{self.source}: value_and_grad needs a scalar output (batch,), got (batch, "
                             f"{', '.join(map(str, self.out_shape))})")
        env = self._run(z)
        rev = _Cotangents(z, env)
        cot: dict[str, list] = {self.output: [(1.0, ONE)]}
        for node, flags in zip(reversed(self.nodes), reversed(self._dynamic)):
            g = cot.pop(node.output, None)
            if g is None or not any(flags):
                continue
            args = [env[name] if name in env else self.const(name) for name in node.inputs]
            for i, contribs in rev.vjp(node, args, env[node.output], g, flags):
                if flags[i] and contribs:
                    cot.setdefault(node.inputs[i], []).extend(contribs)
        contribs = cot.get(INPUT)
        grad = rev.value(contribs, z.shape) if contribs else rev.one(z.shape, 0.0)
        if tuple(grad.shape) != tuple(z.shape):  # only broadcast constants reached z: spread them over the batch
            grad = grad + rev.one(z.shape, 0.0)
        return env[self.output], grad

    # ---------------------------------------------------------------- data
    def to_json(self) -> dict:
        """The node list (constants by name: :meth:`tensors`)."""
        return {"input": INPUT, "output": self.output, "n": self.n, "constants": list(self._buffer),
                "nodes": [node.to_dict() for node in self.nodes]}

    def tensors(self) -> dict[str, Tensor]:
        return {name: self.const(name).detach().cpu().clone() for name in self._buffer}

    @classmethod
    def from_json(cls, data: dict, tensors: Mapping[str, Tensor], source: str = "graph") -> Graph:
        """The graph :meth:`to_json` describes, with its constants; a malformed description is refused."""
        try:
            if data["input"] != INPUT:
                raise ValueError(f"input must be {INPUT!r}")
            names = list(data["constants"])
            nodes = [Node(str(d["op"]), tuple(str(i) for i in d["inputs"]), str(d["output"]), dict(d.get("attrs", {})))
                     for d in data["nodes"]]
            missing = [name for name in names if name not in tensors]
            if missing:
                raise ValueError(f"constants {missing} are missing")
            return cls(nodes, {name: tensors[name] for name in names}, str(data["output"]), int(data["n"]), source)
        except (KeyError, TypeError) as err:
            raise ValueError(f"{source}: malformed graph ({type(err).__name__}: {err})") from None

    def describe(self) -> str:
        """``'12 operations: linear x3, tanh x2, ...'``."""
        counts = Counter(node.op for node in self.nodes)
        return f"{len(self.nodes)} operations: " + ", ".join(f"{op} x{k}" for op, k in counts.most_common())

    def extra_repr(self) -> str:
        return f"{self.source}, n={self.n}, {self.describe()}"


class GraphBuilder:
    """Builds a :class:`Graph` node by node, running each on example states as it is added (for shapes)."""

    def __init__(self, n: int, source: str = "graph") -> None:
        self.n, self.source = int(n), source
        self.nodes: list[Node] = []
        self.constants: dict[str, Tensor] = {}
        self.examples: dict[str, Tensor] = {INPUT: torch.linspace(-0.9, 0.7, 2 * n, dtype=F64).reshape(2, n)}
        self.depends: dict[str, bool] = {INPUT: True}

    def constant(self, value, name: str | None = None) -> str:
        """A constant's name (an equal constant already held is shared)."""
        t = torch.as_tensor(value).detach().to(F64)
        for key, held in self.constants.items():
            if held.shape == t.shape and torch.equal(held, t) and (name is None or key == name):
                return key
        name = name or f"c{len(self.constants)}"
        while name in self.constants or name in self.examples:
            name += "_"
        self.constants[name] = torch.as_tensor(value).detach().to(F64).clone()
        return name

    def example(self, name: str) -> Tensor:
        return self.constants[name] if name in self.constants else self.examples[name]

    def is_dynamic(self, name: str) -> bool:
        return self.depends.get(name, False)

    def is_constant(self, name: str) -> bool:
        return name in self.constants

    def emit(self, op: str, inputs: Sequence[str], attrs: Mapping | None = None) -> str:
        """Add ``op(*inputs)``; returns the output's name."""
        name = f"v{len(self.nodes)}"
        node = Node(op, tuple(inputs), name, dict(attrs or {}))
        with torch.no_grad():
            self.examples[name] = apply(op, [self.example(i) for i in inputs], node.attrs)
        self.depends[name] = any(self.is_dynamic(i) for i in inputs)
        self.nodes.append(node)
        return name

    def build(self, output: str) -> Graph:
        return Graph(self.nodes, self.constants, output, self.n, self.source)
