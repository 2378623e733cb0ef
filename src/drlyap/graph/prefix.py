"""Recognising an ONNX graph's input prefix ``z = x - x*`` with the angle wrap ``remainder(z + pi, 2 pi) - pi``
(what ``drlyap export`` writes, :mod:`drlyap.workflows.export`), so that the rest of the graph reads the local state
(why that is sound: :mod:`drlyap.graph.from_onnx`)."""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from drlyap.systems import UncertainSystem


def _const(values: dict, name: str):
    v = values.get(name)
    return v if isinstance(v, np.ndarray) else None


def _is_pi(values: dict, name: str, times: float) -> bool:
    v = _const(values, name)
    return v is not None and v.size >= 1 and bool(np.all(np.asarray(v, dtype=np.float64) == times * math.pi))


def strip_prefix(nodes: list, values: dict, x: str, system: UncertainSystem,
                 path: Path) -> tuple[set[int], list[str], list[str]]:
    """``(indices of the prefix's nodes, the names of the values that equal the local state z, notes)`` for the
    ONNX ``nodes`` whose input is ``x`` (``values``: the constants by name); ``(set(), [], [])`` without a prefix.

    A prefix that offsets by another point than the system's equilibrium, or wraps other coordinates than its
    angles, is refused (ValueError naming ``path``)."""
    consumers: dict[str, list[int]] = defaultdict(list)
    producer: dict[str, int] = {}
    for i, node in enumerate(nodes):
        for name in node.input:
            consumers[name].append(i)
        for name in node.output:
            producer[name] = i
    subs = [i for i in consumers[x] if nodes[i].op_type == "Sub" and list(nodes[i].input[:1]) == [x]
            and _const(values, nodes[i].input[1]) is not None]
    if not subs:
        return set(), [], []
    i_sub = subs[0]
    offset = np.asarray(_const(values, nodes[i_sub].input[1]), dtype=np.float64)
    x_star = np.asarray(system.equilibrium, dtype=np.float64)
    if offset.size != x_star.size or offset.shape not in ((system.n,), (1, system.n)) or \
            not np.array_equal(offset.reshape(-1), x_star):
        raise ValueError(f"{path}: the graph offsets its input by {offset.reshape(-1).tolist()}, but the equilibrium "
                         f"of {system.name} is {list(system.equilibrium)}: it was made for another equilibrium")
    z0 = nodes[i_sub].output[0]
    wheres = [i for i in consumers[z0] if nodes[i].op_type == "Where" and list(nodes[i].input[2:3]) == [z0]]
    if not wheres:
        return {i_sub}, [z0], ["the input offset x - x* removed: the graph reads the local state z"]
    i_where = wheres[0]
    cond, wrapped = nodes[i_where].input[0], nodes[i_where].input[1]
    bad = ValueError(f"{path}: its input's angle wrap is not remainder(x - x* + pi, 2 pi) - pi, the one form drlyap "
                     "reads")

    def node_of(name: str, op: str) -> tuple[int, object]:
        i = producer.get(name)
        if i is None or nodes[i].op_type != op:
            raise bad
        return i, nodes[i]

    taken = {i_sub, i_where}
    i, n_shift = node_of(wrapped, "Sub")  # w = r - pi
    taken.add(i)
    if not _is_pi(values, n_shift.input[1], 1.0):
        raise bad
    r = n_shift.input[0]
    i_r = producer.get(r)
    if i_r is not None and nodes[i_r].op_type == "Mod":  # r = Mod(t, 2 pi), fmod = 0
        node = nodes[i_r]
        if not _is_pi(values, node.input[1], 2.0) or any(a.name == "fmod" and a.i for a in node.attribute):
            raise bad
        taken.add(i_r)
        t = node.input[0]
    else:  # r = t - floor(t / (2 pi)) * (2 pi)
        i, n_r = node_of(r, "Sub")
        taken.add(i)
        t, k = n_r.input
        i, n_k = node_of(k, "Mul")
        taken.add(i)
        floor_name = [v for v in n_k.input if not _is_pi(values, v, 2.0)]
        if len(floor_name) != 1:
            raise bad
        i, n_floor = node_of(floor_name[0], "Floor")
        taken.add(i)
        i, n_div = node_of(n_floor.input[0], "Div")
        taken.add(i)
        if n_div.input[0] != t or not _is_pi(values, n_div.input[1], 2.0):
            raise bad
    i, n_t = node_of(t, "Add")  # t = z + pi
    taken.add(i)
    if sorted(n_t.input, key=lambda v: v != z0)[0] != z0 or not any(_is_pi(values, v, 1.0) for v in n_t.input):
        raise bad
    mask = _const(values, cond)
    if mask is None or mask.dtype != np.bool_ or mask.size != system.n:
        raise bad
    dims = tuple(int(d) for d in np.flatnonzero(mask.reshape(-1)))
    if set(dims) != set(system.angle_dims):
        raise ValueError(f"{path}: the graph wraps coordinates {list(dims)} as angles; the angle coordinates of "
                         f"{system.name} are {list(system.angle_dims)}")
    lo, hi = system.local_box()
    for d in dims:
        if float(lo[d]) < -math.pi or float(hi[d]) > math.pi:
            raise ValueError(f"{path}: the local box of {system.name} spans [{float(lo[d]):.6g}, {float(hi[d]):.6g}] "
                             f"in the angle {system.state_names[d]}, beyond [-pi, pi]: its wrap cannot be removed")
    inner = {out for i in taken - {i_sub, i_where} for out in nodes[i].output}
    outside = [name for name in inner if any(j not in taken for j in consumers[name])]
    if outside:
        raise ValueError(f"{path}: the graph reuses its angle wrap's intermediate values {outside} elsewhere")
    angles = ", ".join(system.state_names[d] for d in dims)
    return taken, [z0, nodes[i_where].output[0]], [f"the input offset x - x* and the angle wrap of ({angles}) removed: "
                                                   "the graph reads the local state z on the closed local box"]
