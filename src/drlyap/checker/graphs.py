"""The checker's reading of an imported pair (``drlyap import``): the controller and V as the run directory holds
them, ``graphs.json`` (each a list of operations, read as data) and ``tensors.pt`` (their constants), evaluated with
the checker's own arithmetic (:mod:`drlyap.checker.arith`, :mod:`drlyap.checker.affine`), not with the library's
graph interpreter.

Each operation is one of the few the import writes (``linear add sub mul div neg square pow tanh exp identity clamp
sum select squeeze unsqueeze``); a node none of whose inputs depends on the state (``V(0)`` of a V whose minimum is
not 0, a constant offset) is evaluated on its first input lifted to the state's kind, so it is an outward-rounded
enclosure of its real value. V's gradient is forward mode: the checker's dual numbers seeded on the state, one tangent
per state, over intervals, duals or second-order forms alike. V is the graph less its first-order part at x*,
``V(z) - V(0) - grad V(0) . z`` with ``V(0)`` and ``grad V(0)`` enclosed by the checker's duals at the point x* (so
``V(x*) = 0`` and ``grad V(x*) = 0`` hold exactly, as the cube's second-order argument needs, whatever the weights),
or ``z^T P z`` for the quadratic V of a controller imported alone; a V that ``graphs.json`` marks ``"pinned": "no"`` (not
least at x*, imported as given) is the graph as it is, and only a band claim is checked for it (nothing of it rests
on x*). A band claim is about V as the file gives it, pinned or not (its levels are in V's own units).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping

import torch
from torch import Tensor

from drlyap.checker.affine import Af
from drlyap.checker.arith import F64, Du, Iv, lift
from drlyap.runs.validate import restore_infinite

OPS = {"linear", "add", "sub", "mul", "div", "neg", "square", "pow", "tanh", "exp", "identity", "clamp", "sum",
       "select", "squeeze", "unsqueeze"}


def _kind_of(z, t: Tensor | Iv):
    """The constant ``t`` (a tensor or an interval) as a value of ``z``'s kind (an interval, a dual of ``z``'s level,
    or a form)."""
    t = t if isinstance(t, Iv) else Iv.point(t)
    if isinstance(z, Af):
        return z.constant(t)
    return lift(t, z.level, z if z.level > 0 else None)


def _apply(op: str, args: list, attrs: Mapping):
    x = args[0]
    if op == "linear":
        return x.linear(args[1], args[2] if len(args) > 2 else None)
    if op in ("add", "sub", "mul", "div"):
        y = args[1]
        return x + y if op == "add" else x - y if op == "sub" else x * y if op == "mul" else x / y
    if op == "neg":
        return -x
    if op == "square":
        return x.square()
    if op == "pow":
        return x ** int(attrs["n"])
    if op == "tanh":
        return x.tanh()
    if op == "exp":
        return x.exp()
    if op == "identity":
        return x
    if op == "clamp":
        return x.clamp(args[1], args[2])
    if op == "sum":
        s = x.sum(-1)
        return s.unsqueeze(-1) if attrs.get("keepdim") else s
    if op == "select":
        return x[:, int(attrs["index"])]
    if op == "squeeze":
        return x[:, 0]
    if op == "unsqueeze":
        return x.unsqueeze(-1)
    raise ValueError(f"the checker does not read the operation {op!r}")


class GraphNet:
    """A graph of ``graphs.json`` (``input`` ``z``, ``output``, ``constants``, ``nodes``) with its constants."""

    def __init__(self, spec: Mapping, tensors: Mapping[str, Tensor]) -> None:
        if spec.get("input") != "z":
            raise ValueError("a graph's input must be 'z'")
        self.output = str(spec["output"])
        self.nodes = [(str(d["op"]), [str(i) for i in d["inputs"]], str(d["output"]), dict(d.get("attrs") or {}))
                      for d in spec["nodes"]]
        unknown = sorted({op for op, *_ in self.nodes} - OPS)
        if unknown:
            raise ValueError(f"the checker does not read the operations {unknown}")
        restored = restore_infinite(dict(tensors))
        self.constants = {name: restored[name].to(F64) for name in spec["constants"]}
        self._check()

    def _check(self) -> None:
        """What the checker's reading needs of the nodes (the library's interpreter refuses the same): real constants
        without NaN, each name defined once, an integer exponent ``n >= 0``, a clamp's bounds constant and in order."""
        for name, value in self.constants.items():
            if bool(torch.isnan(value).any()):
                raise ValueError(f"the graph's constant {name!r} contains NaN")
        defined = {"z", *self.constants}
        for op, inputs, output, attrs in self.nodes:
            if output in defined:
                raise ValueError(f"the graph redefines {output!r}")
            defined.add(output)
            if op == "pow" and not (isinstance(attrs.get("n"), int) and not isinstance(attrs.get("n"), bool)
                                    and attrs["n"] >= 0):
                raise ValueError("the graph's pow needs an integer exponent n >= 0")
            if op == "clamp":
                if len(inputs) != 3 or any(name not in self.constants for name in inputs[1:]):
                    raise ValueError("the graph's clamp needs constant bounds")
                if not bool((self.constants[inputs[1]] <= self.constants[inputs[2]]).all()):
                    raise ValueError("the graph's clamp has lower bounds above its upper ones")

    def __call__(self, z):
        env: dict = {"z": z}
        for op, inputs, output, attrs in self.nodes:
            args = [env[name] if name in env else self.constants[name] for name in inputs]
            if isinstance(args[0], Tensor):  # no input depends on z: its first one as a constant of z's kind
                args[0] = _kind_of(z, args[0])
            env[output] = _apply(op, args, attrs)
        return env[self.output]

    def to(self, device: torch.device | str) -> GraphNet:
        out = copy.copy(self)
        out.constants = {k: v.to(device) for k, v in self.constants.items()}
        return out


class GraphPair:
    """V and pi of an imported run, from ``graphs.json`` and ``tensors.pt`` (the interface of
    :class:`~drlyap.checker.model.Pair`)."""

    def __init__(self, graphs: Mapping, tensors: Mapping, n: int) -> None:
        self.n = n
        self.controller_net = GraphNet(graphs["controller"], tensors["controller"])
        spec = graphs["lyapunov"]
        self.p = None
        if spec.get("kind") == "quadratic":
            self.p = tensors["lyapunov"]["P"].to(F64)
            self.v_net = None
        else:
            self.v_net = GraphNet(spec, tensors["lyapunov"])
            self.pinned = spec.get("pinned") != "no"  # a V imported as given (not least at x*) is not pinned
            self._v0, self._g0 = self._origin()

    def _origin(self) -> tuple[Iv, Iv]:
        """Enclosures of V's value ``(1,)`` and gradient ``(1, n)`` at x*, by the checker's duals at that point."""
        device = self.v_net.constants[next(iter(self.v_net.constants))].device if self.v_net.constants else "cpu"
        at = self.v_net(Du.seed(Iv.point(torch.zeros(1, self.n, dtype=F64, device=device)), self.n,
                                list(range(self.n))))
        return at.v, torch.stack(at.d, -1)

    def as_given(self) -> GraphPair:
        """The same pair with V as the file gives it, not pinned at x* (what a band claim is about)."""
        out = copy.copy(self)
        out.pinned = False
        return out

    def to(self, device: torch.device | str) -> GraphPair:
        out = copy.copy(self)
        out.controller_net = self.controller_net.to(device)
        if self.v_net is not None:
            out.v_net = self.v_net.to(device)
            out._v0, out._g0 = out._origin()
        if self.p is not None:
            out.p = self.p.to(device)
        return out

    def value(self, z):
        if self.p is not None:
            return (z.linear(self.p) * z).sum(-1)
        if not self.pinned:
            return self.v_net(z)
        return self.v_net(z) - _kind_of(z, self._v0) - (_kind_of(z, self._g0) * z).sum(-1)

    def value_and_grad(self, z) -> tuple[object, object]:
        seeded = Du.seed(z, self.n, list(range(self.n)))
        out = self.value(seeded)
        return out.v, torch.stack(out.d, -1)

    def controller(self, z):
        return self.controller_net(z)
