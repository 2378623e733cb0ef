"""Rewrites of a graph's node list that are identities in real arithmetic, so that an imported network is bounded
as tightly as the built-in one it may have been exported from (:func:`simplify`):

* ``clamp(clamp(v, l1, h1), l2, h2)`` -> ``clamp(v, max(l1, l2), min(h1, h2))`` where the two ranges overlap (what
  ONNX writes as ``Max(Min(v, h), l)`` is one clamp again);
* ``a + (b - a)`` -> ``b`` (a straight-through saturation, ``v + (clamp(v) - v).detach()``, exported as arithmetic:
  on enclosures the long form would be wider than the clamp it equals);
* a clamp whose input provably lies within its bounds (ranges propagated exactly, in rational arithmetic, through
  clamps, ``tanh``, and additions and products with constants) is the identity and is dropped;
* with ``box`` (a controller's input set U): a clamp to U is appended unless the output provably lies in U, so
  the loop's controller never leaves U;
* identities and every node the output does not need are removed.
"""

from __future__ import annotations

from fractions import Fraction

import torch
from torch import Tensor

from drlyap.graph.interpreter import Node

Bound = Fraction | None  # None: unbounded on that side
Range = tuple[list[Bound], list[Bound]]  # (low, high) along the last axis, length k or 1 (broadcast)


def _resolve(alias: dict[str, str], name: str) -> str:
    while name in alias:
        name = alias[name]
    return name


def _vector(t: Tensor, limit: int = 4096) -> list[float] | None:
    """A constant as a list along the last axis (length k or 1), or None when it varies along another axis."""
    if t.numel() > limit or (t.ndim > 1 and any(s != 1 for s in t.shape[:-1])):
        return None
    return [float(v) for v in t.reshape(-1)]


def _frac(v: float, side: str) -> Bound:
    if v == float("inf") and side == "hi" or v == float("-inf") and side == "lo":
        return None
    if v in (float("inf"), float("-inf")) or v != v:
        raise ValueError("an infinite constant where a finite one is needed")
    return Fraction(v)


def _broadcast(*lists: list) -> list[list] | None:
    k = max(len(v) for v in lists)
    if any(len(v) not in (1, k) for v in lists):
        return None
    return [v * k if len(v) == 1 else v for v in lists]


def _shift(r: Range, c: list[float], sign: int) -> Range | None:
    """``r + sign * c``."""
    b = _broadcast(r[0], r[1], c)
    if b is None or any(abs(v) == float("inf") for v in c):
        return None
    lo, hi, c = b
    cf = [Fraction(v) * sign for v in c]
    return ([None if a is None else a + d for a, d in zip(lo, cf)], [None if a is None else a + d for a, d in zip(hi, cf)])


def _times(r: Range, c: list[Fraction]) -> Range | None:
    """``r * c`` elementwise."""
    b = _broadcast(r[0], r[1], c)
    if b is None:
        return None
    lo, hi, c = b
    out_lo, out_hi = [], []
    for a, h, f in zip(lo, hi, c):
        if f == 0:
            out_lo.append(Fraction(0))
            out_hi.append(Fraction(0))
            continue
        ends = (a * f if a is not None else None, h * f if h is not None else None)
        if f > 0:
            out_lo.append(ends[0])
            out_hi.append(ends[1])
        else:
            out_lo.append(ends[1])
            out_hi.append(ends[0])
    return out_lo, out_hi


def _within(r: Range, low: list[float], high: list[float]) -> bool:
    """Whether every value in ``r`` lies in ``[low, high]``."""
    b = _broadcast(r[0], r[1], low, high)
    if b is None:
        return False
    lo, hi, low, high = b
    return all((ll == float("-inf") or (a is not None and a >= Fraction(ll))) and
               (hh == float("inf") or (h is not None and h <= Fraction(hh)))
               for a, h, ll, hh in zip(lo, hi, low, high))


def ranges(nodes: list[Node], constants: dict[str, Tensor]) -> dict[str, Range]:
    """What is known exactly about the values of the nodes, wherever the operations allow (module docstring)."""
    known: dict[str, Range] = {}
    for node in nodes:
        ins = node.inputs
        r = known.get(ins[0]) if ins else None
        out: Range | None = None
        if node.op == "clamp":
            low, high = _vector(constants[ins[1]]), _vector(constants[ins[2]])
            if low is not None and high is not None:
                base = r or ([None], [None])
                b = _broadcast(base[0], base[1], low, high)
                if b is not None:
                    lo, hi, low, high = b
                    lo = [_max(a, _frac(v, "lo")) for a, v in zip(lo, low)]
                    hi = [_min(a, _frac(v, "hi")) for a, v in zip(hi, high)]
                    out = (lo, hi)
        elif node.op == "tanh":
            out = ([Fraction(-1)], [Fraction(1)])
        elif node.op in ("identity", "squeeze", "unsqueeze") and r is not None:
            out = r
        elif node.op == "neg" and r is not None:
            out = _times(r, [Fraction(-1)])
        elif node.op in ("add", "sub", "mul", "div"):
            out = _binary(node, known, constants)
        if out is not None:
            known[node.output] = out
    return known


def _max(a: Bound, b: Bound) -> Bound:
    return b if a is None else a if b is None else max(a, b)


def _min(a: Bound, b: Bound) -> Bound:
    return b if a is None else a if b is None else min(a, b)


def _binary(node: Node, known: dict[str, Range], constants: dict[str, Tensor]) -> Range | None:
    a, b = node.inputs
    if a in known and b in constants:
        r, c, first = known[a], _vector(constants[b]), True
    elif b in known and a in constants:
        r, c, first = known[b], _vector(constants[a]), False
    else:
        return None
    if c is None or any(v != v for v in c):
        return None
    if node.op == "add":
        return _shift(r, c, 1)
    if node.op == "sub":  # x - c, or c - x = (-x) + c
        if first:
            return _shift(r, c, -1)
        neg = _times(r, [Fraction(-1)])
        return None if neg is None else _shift(neg, c, 1)
    if any(abs(v) == float("inf") for v in c):
        return None
    if node.op == "mul":
        return _times(r, [Fraction(v) for v in c])
    if node.op == "div" and first and all(v != 0 for v in c):
        return _times(r, [1 / Fraction(v) for v in c])
    return None


def simplify(nodes: list[Node], constants: dict[str, Tensor], output: str,
             box: tuple[list[float], list[float]] | None = None) -> tuple[list[Node], dict[str, Tensor], str, list[str]]:
    """The rewritten nodes, the constants they use, the output's name and one note per kind of rewrite made."""
    alias: dict[str, str] = {}
    constants = dict(constants)
    notes: list[str] = []
    producer: dict[str, Node] = {}
    out_nodes: list[Node] = []
    fused = straight = 0
    for node in nodes:
        node = Node(node.op, tuple(_resolve(alias, i) for i in node.inputs), node.output, dict(node.attrs))
        if node.op == "identity":
            alias[node.output] = node.inputs[0]
            continue
        inner = producer.get(node.inputs[0])
        if node.op == "clamp" and inner is not None and inner.op == "clamp":
            merged = _merge_clamps(inner, node, constants)
            if merged is not None:
                node, fused = merged, fused + 1
        if node.op == "add":
            a, b = node.inputs
            for x, s in ((a, b), (b, a)):
                sub = producer.get(s)
                if sub is not None and sub.op == "sub" and sub.inputs[1] == x:
                    alias[node.output] = sub.inputs[0]
                    straight += 1
                    break
            if node.output in alias:
                continue
        producer[node.output] = node
        out_nodes.append(node)
    output = _resolve(alias, output)
    if fused:
        notes.append(f"{fused} pair(s) of one-sided bounds (Min/Max) read as one clamp")
    if straight:
        notes.append(f"{straight} straight-through form(s) a + (b - a) read as b")
    out_nodes, output, dropped = _drop_inactive_clamps(_needed(out_nodes, output), constants, output)
    if dropped:
        notes.append(f"{dropped} clamp(s) dropped: their input provably lies within their bounds")
    if box is not None:
        known = ranges(out_nodes, constants)
        if output in known and _within(known[output], *box):
            notes.append("the output provably lies in U: no clamp added")
        else:
            lo = _name(constants, "u_low", torch.tensor(box[0], dtype=torch.float64))
            hi = _name(constants, "u_high", torch.tensor(box[1], dtype=torch.float64))
            node = Node("clamp", (output, lo, hi), _fresh(out_nodes, "u"))
            out_nodes.append(node)
            output = node.output
            notes.append("a clamp to U added: the output is not provably inside U")
    out_nodes = _needed(out_nodes, output)
    used = {i for node in out_nodes for i in node.inputs}
    return out_nodes, {k: v for k, v in constants.items() if k in used}, output, notes


def _name(constants: dict[str, Tensor], base: str, value: Tensor) -> str:
    name = base
    while name in constants:
        name += "_"
    constants[name] = value
    return name


def _fresh(nodes: list[Node], base: str) -> str:
    taken = {node.output for node in nodes}
    name = base
    while name in taken:
        name += "_"
    return name


def _merge_clamps(inner: Node, outer: Node, constants: dict[str, Tensor]) -> Node | None:
    l1, h1 = constants[inner.inputs[1]], constants[inner.inputs[2]]
    l2, h2 = constants[outer.inputs[1]], constants[outer.inputs[2]]
    try:
        low, high = torch.maximum(l1, l2), torch.minimum(h1, h2)
    except RuntimeError:
        return None
    if not bool((low <= high).all()):
        return None
    lo = _name(constants, f"{outer.output}_low", low)
    hi = _name(constants, f"{outer.output}_high", high)
    return Node("clamp", (inner.inputs[0], lo, hi), outer.output)


def _drop_inactive_clamps(nodes: list[Node], constants: dict[str, Tensor], output: str) -> tuple[list[Node], str, int]:
    alias: dict[str, str] = {}
    out, dropped = [], 0
    known: dict[str, Range] = {}
    for node in nodes:
        node = Node(node.op, tuple(_resolve(alias, i) for i in node.inputs), node.output, dict(node.attrs))
        if node.op == "clamp" and node.inputs[0] in known:
            low, high = _vector(constants[node.inputs[1]]), _vector(constants[node.inputs[2]])
            if low is not None and high is not None and _within(known[node.inputs[0]], low, high):
                alias[node.output] = node.inputs[0]
                dropped += 1
                continue
        out.append(node)
        known = ranges(out, constants)
    return out, _resolve(alias, output), dropped


def _needed(nodes: list[Node], output: str) -> list[Node]:
    need = {output}
    keep = []
    for node in reversed(nodes):
        if node.output in need:
            keep.append(node)
            need.update(node.inputs)
    return keep[::-1]
