"""Recognising an ONNX graph's input prefix ``z = x - x*`` with the angle wrap ``remainder(z + pi, 2 pi) - pi``
(what ``drlyap export`` writes, :mod:`drlyap.workflows.export`), so that the rest of the graph reads the local state
(why that is sound: :mod:`drlyap.graph.from_onnx`)."""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drlyap.systems import UncertainSystem


def _const(values: dict, name: str):
    v = values.get(name)
    return v if isinstance(v, np.ndarray) else None


def _is_pi(values: dict, name: str, times: float) -> bool:
    v = _const(values, name)
    return v is not None and v.size >= 1 and bool(np.all(np.asarray(v, dtype=np.float64) == times * math.pi))


@dataclass(frozen=True)
class _Graph:
    """ONNX ``nodes`` with the node that produces each value and the nodes that consume it, the constants ``values``
    by name, and the file they came from (named in every refusal)."""

    nodes: list
    values: dict
    path: Path
    consumers: dict[str, list[int]]
    producer: dict[str, int]

    @classmethod
    def of(cls, nodes: list, values: dict, path: Path) -> _Graph:
        consumers: dict[str, list[int]] = defaultdict(list)
        producer: dict[str, int] = {}
        for i, node in enumerate(nodes):
            for name in node.input:
                consumers[name].append(i)
            for name in node.output:
                producer[name] = i
        return cls(nodes, values, path, consumers, producer)

    def not_the_wrap(self) -> ValueError:
        return ValueError(f"{self.path}: its input's angle wrap is not remainder(x - x* + pi, 2 pi) - pi, the one form "
                          "drlyap reads")

    def node_of(self, name: str, op: str) -> tuple[int, object]:
        """The index and node that produce ``name``, which must be an ``op`` (else the wrap is refused)."""
        i = self.producer.get(name)
        if i is None or self.nodes[i].op_type != op:
            raise self.not_the_wrap()
        return i, self.nodes[i]

    def is_pi(self, name: str, times: float) -> bool:
        return _is_pi(self.values, name, times)


def strip_prefix(nodes: list, values: dict, x: str, system: UncertainSystem,
                 path: Path) -> tuple[set[int], list[str], list[str]]:
    """``(indices of the prefix's nodes, the names of the values that equal the local state z, notes)`` for the
    ONNX ``nodes`` whose input is ``x`` (``values``: the constants by name); ``(set(), [], [])`` without a prefix.

    A prefix that offsets by another point than the system's equilibrium, or wraps other coordinates than its
    angles, is refused (ValueError naming ``path``)."""
    graph = _Graph.of(nodes, values, path)
    i_sub = _offset_node(graph, x, system)
    if i_sub is None:
        return set(), [], []
    z0 = nodes[i_sub].output[0]
    wheres = [i for i in graph.consumers[z0] if nodes[i].op_type == "Where" and list(nodes[i].input[2:3]) == [z0]]
    if not wheres:
        return {i_sub}, [z0], ["the input offset x - x* removed: the graph reads the local state z"]
    i_where = wheres[0]
    cond, wrapped = nodes[i_where].input[0], nodes[i_where].input[1]
    wrap = _wrap_nodes(graph, wrapped, z0)
    dims = _wrapped_dims(graph, cond, system)
    taken = {i_sub, i_where} | wrap
    inner = {out for i in taken - {i_sub, i_where} for out in nodes[i].output}
    outside = [name for name in inner if any(j not in taken for j in graph.consumers[name])]
    if outside:
        raise ValueError(f"{path}: the graph reuses its angle wrap's intermediate values {outside} elsewhere")
    angles = ", ".join(system.state_names[d] for d in dims)
    return taken, [z0, nodes[i_where].output[0]], [f"the input offset x - x* and the angle wrap of ({angles}) removed: "
                                                   "the graph reads the local state z on the closed local box"]


def _offset_node(graph: _Graph, x: str, system: UncertainSystem) -> int | None:
    """The index of the node ``z = x - x*`` (a Sub of a constant from the input), None without one; an offset by
    another point than the system's equilibrium is refused."""
    nodes = graph.nodes
    subs = [i for i in graph.consumers[x] if nodes[i].op_type == "Sub" and list(nodes[i].input[:1]) == [x]
            and _const(graph.values, nodes[i].input[1]) is not None]
    if not subs:
        return None
    offset = np.asarray(_const(graph.values, nodes[subs[0]].input[1]), dtype=np.float64)
    x_star = np.asarray(system.equilibrium, dtype=np.float64)
    if offset.size != x_star.size or offset.shape not in ((system.n,), (1, system.n)) or \
            not np.array_equal(offset.reshape(-1), x_star):
        raise ValueError(f"{graph.path}: the graph offsets its input by {offset.reshape(-1).tolist()}, but the "
                         f"equilibrium of {system.name} is {list(system.equilibrium)}: it was made for another "
                         "equilibrium")
    return subs[0]


def _wrap_nodes(graph: _Graph, wrapped: str, z0: str) -> set[int]:
    """The indices of the nodes that compute ``wrapped = remainder(z0 + pi, 2 pi) - pi``; another form is refused."""
    i, n_shift = graph.node_of(wrapped, "Sub")  # w = r - pi
    taken = {i}
    if not graph.is_pi(n_shift.input[1], 1.0):
        raise graph.not_the_wrap()
    remainder, t = _remainder_nodes(graph, n_shift.input[0])
    taken |= remainder
    i, n_t = graph.node_of(t, "Add")  # t = z + pi
    taken.add(i)
    if sorted(n_t.input, key=lambda v: v != z0)[0] != z0 or not any(graph.is_pi(v, 1.0) for v in n_t.input):
        raise graph.not_the_wrap()
    return taken


def _remainder_nodes(graph: _Graph, r: str) -> tuple[set[int], str]:
    """The indices of the nodes that compute ``r = remainder(t, 2 pi)``, as a Mod (fmod = 0) or as
    ``t - floor(t / (2 pi)) * (2 pi)``, and the name of ``t``."""
    nodes = graph.nodes
    i_r = graph.producer.get(r)
    if i_r is not None and nodes[i_r].op_type == "Mod":  # r = Mod(t, 2 pi), fmod = 0
        node = nodes[i_r]
        if not graph.is_pi(node.input[1], 2.0) or any(a.name == "fmod" and a.i for a in node.attribute):
            raise graph.not_the_wrap()
        return {i_r}, node.input[0]
    # r = t - floor(t / (2 pi)) * (2 pi)
    i, n_r = graph.node_of(r, "Sub")
    taken = {i}
    t, k = n_r.input
    i, n_k = graph.node_of(k, "Mul")
    taken.add(i)
    floor_name = [v for v in n_k.input if not graph.is_pi(v, 2.0)]
    if len(floor_name) != 1:
        raise graph.not_the_wrap()
    i, n_floor = graph.node_of(floor_name[0], "Floor")
    taken.add(i)
    i, n_div = graph.node_of(n_floor.input[0], "Div")
    taken.add(i)
    if n_div.input[0] != t or not graph.is_pi(n_div.input[1], 2.0):
        raise graph.not_the_wrap()
    return taken, t


def _wrapped_dims(graph: _Graph, cond: str, system: UncertainSystem) -> tuple[int, ...]:
    """The coordinates the wrap's mask ``cond`` picks: they must be the system's angles, on a local box within
    ``[-pi, pi]`` (where the wrap is the identity and can be removed)."""
    mask = _const(graph.values, cond)
    if mask is None or mask.dtype != np.bool_ or mask.size != system.n:
        raise graph.not_the_wrap()
    dims = tuple(int(d) for d in np.flatnonzero(mask.reshape(-1)))
    if set(dims) != set(system.angle_dims):
        raise ValueError(f"{graph.path}: the graph wraps coordinates {list(dims)} as angles; the angle coordinates of "
                         f"{system.name} are {list(system.angle_dims)}")
    lo, hi = system.local_box()
    for d in dims:
        if float(lo[d]) < -math.pi or float(hi[d]) > math.pi:
            raise ValueError(f"{graph.path}: the local box of {system.name} spans [{float(lo[d]):.6g}, "
                             f"{float(hi[d]):.6g}] in the angle {system.state_names[d]}, beyond [-pi, pi]: its wrap "
                             "cannot be removed")
    return dims
