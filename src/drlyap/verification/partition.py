"""The partition a branch and bound proved a condition on: a tree of boxes over the starting grid, kept so that the
proof can be written down and checked again by :mod:`drlyap.checker` without searching.

Nodes are numbered as the boxes are made: first the cells of the starting grid (in ``box_grid``'s order), then the
two halves of every box that is split, lower half first. A node records its parent (``-1`` for a grid cell), which
half of its parent it is (``side``: 0 lower, 1 upper), the axis along which it was split (``-1`` for a leaf) and,
for a leaf, the verdict the proof reached on it, with the bound behind it:

* ``PROVED``: the residual's upper bound over the box is ``bound <= 0``;
* ``INSIDE_BALL``: the box lies in the open delta-ball (not part of X_delta);
* ``ABOVE_LEVEL``: V's lower bound over the box is ``bound > level`` (a proof on ``{V <= level}``);
* ``OPEN``: nothing was proved (a proof that leaves such leaves is not verified; it keeps its partition only when
  asked to, for a proof that starts from it);
* ``INSIDE_CORE``: every vertex of the box has ``z^T P z <= c``, so the box lies in a proof's core, the ellipsoid
  ``{z^T P z <= c}`` (convex) around x* whose own certificate carries the trajectories that reach it (``bound``: the
  largest vertex value, rounded up);
* ``BELOW_LEVEL``: V's upper bound over the box is ``bound < floor`` (a proof on a band ``{floor <= V <= level}``).

The boxes themselves are not stored: they follow from the grid and the splits (halving at the midpoint), which is
what makes a dropped or an extra box visible to a checker.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import torch
from torch import Tensor

INTERNAL, PROVED, INSIDE_BALL, ABOVE_LEVEL, OPEN, INSIDE_CORE, BELOW_LEVEL = 0, 1, 2, 3, 4, 5, 6
VERDICTS = {INTERNAL: "internal", PROVED: "proved", INSIDE_BALL: "inside ball", ABOVE_LEVEL: "above level",
            OPEN: "open", INSIDE_CORE: "inside core", BELOW_LEVEL: "below level"}


@dataclass
class Partition:
    """A proof's tree of boxes (see the module docstring): ``N`` nodes over a starting grid of ``prod(grid)`` cells.

    ``parent``, ``side``, ``axis``, ``verdict``: ``(N,)`` integer tensors; ``bound``: ``(N,)`` float64 (NaN on
    internal nodes and on leaves inside the ball); ``enclosure``: how the boxes were bounded (``mean-value``, with the plain
    interval bound beside it, or ``affine``).
    """

    grid: list[int]
    parent: Tensor
    side: Tensor
    axis: Tensor
    verdict: Tensor
    bound: Tensor
    enclosure: str

    @property
    def size(self) -> int:
        return int(self.parent.shape[0])

    def counts(self) -> dict[str, int]:
        """How many nodes of each verdict (``below level`` only in a proof on a band, which has such leaves)."""
        counts = {name: int((self.verdict == code).sum()) for code, name in VERDICTS.items()}
        if not counts[VERDICTS[BELOW_LEVEL]]:
            del counts[VERDICTS[BELOW_LEVEL]]
        return counts

    def digest(self, standing: Tensor | None = None) -> str:
        """The sha256 (hex) of the tree and its verdicts, and of the leaves ``standing`` (see :meth:`state`): what a
        proof that starts from this partition depends on."""
        h = hashlib.sha256(str(self.grid).encode() + self.enclosure.encode())
        extra = () if standing is None else (standing.to(torch.bool),)
        for t in (self.parent, self.side, self.axis, self.verdict, self.bound, *extra):
            h.update(t.contiguous().cpu().numpy().tobytes())
        return h.hexdigest()

    def boxes(self, cells_lo: Tensor, cells_hi: Tensor) -> tuple[Tensor, Tensor]:
        """Every node's box ``(N, n)``, from the starting grid's cells ``(C, n)`` (``box_grid``'s) and the splits:
        each half from its parent, generation by generation (a half splits its parent's split axis at its midpoint,
        as :func:`~drlyap.regions.split` does)."""
        size, n, cells = self.size, cells_lo.shape[1], cells_lo.shape[0]
        lo = torch.full((size, n), float("nan"), dtype=torch.float64)
        hi = torch.full((size, n), float("nan"), dtype=torch.float64)
        lo[:cells], hi[:cells] = cells_lo, cells_hi
        done = torch.zeros(size, dtype=torch.bool)
        done[:cells] = True
        parent, axis, upper = self.parent.to(torch.int64), self.axis.to(torch.int64), self.side == 1
        while not bool(done.all()):
            ready = (~done & done[parent.clamp(min=0)]).nonzero().squeeze(-1)
            if not ready.numel():
                raise ValueError("the partition's tree is not connected")
            p, ax = parent[ready], axis[parent[ready]]
            rows = torch.arange(ready.shape[0])
            mid = (lo[p, ax] + hi[p, ax]) / 2
            clo, chi = lo[p].clone(), hi[p].clone()
            up = upper[ready]
            clo[rows[up], ax[up]] = mid[up]
            chi[rows[~up], ax[~up]] = mid[~up]
            lo[ready], hi[ready] = clo, chi
            done[ready] = True
        return lo, hi

    def state(self, standing: Tensor | None = None) -> dict[str, Tensor]:
        """The tree as :meth:`PartitionRecorder.state` keeps one, with its leaves left open (for a proof that starts
        from this partition: see :meth:`PartitionRecorder.restore`) but for those in the ball and above the level,
        which keep their verdicts and bounds (leaves inside a core are left open: a proof that starts here need not
        have that core), and those ``standing`` (``(N,)`` bool; None: none): leaves proved or
        open here that are proved for the condition of the proof that starts here too, kept as proved (with the bound
        they have here, NaN for an open one)."""
        internal = self.verdict == INTERNAL
        kept = (self.verdict == INSIDE_BALL) | (self.verdict == ABOVE_LEVEL)
        code = self.verdict.clone()
        if standing is not None:
            stand = standing.to(torch.bool) & ((self.verdict == PROVED) | (self.verdict == OPEN))
            kept = kept | stand
            code[stand] = PROVED
        ids = torch.arange(self.size)
        return {"tree_parent": self.parent.to(torch.int64), "tree_side": self.side.to(torch.int8),
                "tree_axis_ids": ids[internal], "tree_axis": self.axis[internal].to(torch.int8),
                "tree_leaf_ids": ids[kept], "tree_leaf_code": code[kept].to(torch.int8),
                "tree_leaf_bound": self.bound[kept].to(torch.float64)}

    def inherit_max(self, values: Tensor) -> Tensor:
        """``values (N,)`` with each node's raised to the largest of its ancestors' (a box inside a box proved at some
        value of a monotone property is proved at it too)."""
        out = values.clone()
        parent = self.parent.to(torch.int64)
        has_parent = parent >= 0
        child = has_parent.nonzero().squeeze(-1)
        while child.numel():  # each round reads the values before it: a node that rose passes it on in the next
            raised = torch.maximum(out[child], out[parent[child]])
            rose = child[raised > out[child]]
            out[child] = raised
            moved = torch.zeros(self.size, dtype=torch.bool)
            moved[rose] = True
            child = (has_parent & moved[parent.clamp(min=0)]).nonzero().squeeze(-1)
        return out


class PartitionRecorder:
    """Collects a branch and bound's tree as it runs (ids of the boxes in its queue, verdicts as they come)."""

    def __init__(self, grid: list[int], cells: int, enclosure: str) -> None:
        self.grid, self.enclosure = list(grid), enclosure
        self.roots = torch.arange(cells)
        self.count = cells
        self._parent = [torch.full((cells,), -1, dtype=torch.int64)]
        self._side = [torch.zeros(cells, dtype=torch.int8)]
        self._axis: list[tuple[Tensor, Tensor]] = []
        self._leaf: list[tuple[Tensor, int, Tensor | None]] = []

    def inside_ball(self, ids: Tensor) -> None:
        self._leaf.append((ids, INSIDE_BALL, None))

    def proved(self, ids: Tensor, bound: Tensor) -> None:
        self._leaf.append((ids, PROVED, bound))

    def inside_core(self, ids: Tensor, bound: Tensor) -> None:
        self._leaf.append((ids, INSIDE_CORE, bound))

    def above_level(self, ids: Tensor, bound: Tensor) -> None:
        self._leaf.append((ids, ABOVE_LEVEL, bound))

    def below_level(self, ids: Tensor, bound: Tensor) -> None:
        self._leaf.append((ids, BELOW_LEVEL, bound))

    def split(self, ids: Tensor, parent_hi: Tensor, lower_hi: Tensor) -> Tensor:
        """Record the split of boxes ``ids (D,)`` (upper corners ``parent_hi (D, n)``) into the halves that
        :func:`~drlyap.regions.split` returned (upper corners ``lower_hi (2D, n)``, lower halves first); returns
        the halves' ids ``(2D,)``."""
        d = ids.shape[0]
        axis = (lower_hi[:d] != parent_hi).to(torch.int8).argmax(-1)
        self._axis.append((ids, axis))
        children = torch.arange(self.count, self.count + 2 * d)
        self.count += 2 * d
        self._parent.append(ids.repeat(2))
        self._side.append(torch.cat([torch.zeros(d, dtype=torch.int8), torch.ones(d, dtype=torch.int8)]))
        return children

    def state(self) -> dict[str, Tensor]:
        """The tree so far as arrays (for a checkpoint; :meth:`restore` reads them back)."""
        axis_ids = [a for a, _ in self._axis]
        leaves = [(ids, torch.full_like(ids, code, dtype=torch.int8),
                   values.to(torch.float64) if values is not None else torch.full(ids.shape, float("nan"),
                                                                                  dtype=torch.float64))
                  for ids, code, values in self._leaf]
        empty_i, empty_b = torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.int8)
        return {"tree_parent": torch.cat(self._parent), "tree_side": torch.cat(self._side),
                "tree_axis_ids": torch.cat(axis_ids) if axis_ids else empty_i,
                "tree_axis": torch.cat([a.to(torch.int8) for _, a in self._axis]) if self._axis else empty_b,
                "tree_leaf_ids": torch.cat([x[0] for x in leaves]) if leaves else empty_i,
                "tree_leaf_code": torch.cat([x[1] for x in leaves]) if leaves else empty_b,
                "tree_leaf_bound": torch.cat([x[2] for x in leaves]) if leaves else torch.zeros(0, dtype=torch.float64)}

    def restore(self, state: dict[str, Tensor]) -> None:
        """Continue the tree of a checkpoint (:meth:`state`)."""
        self._parent, self._side = [state["tree_parent"].to(torch.int64)], [state["tree_side"].to(torch.int8)]
        self.count = int(self._parent[0].shape[0])
        self._axis = [(state["tree_axis_ids"].to(torch.int64), state["tree_axis"].to(torch.int8))]
        ids, codes, bound = state["tree_leaf_ids"].to(torch.int64), state["tree_leaf_code"], state["tree_leaf_bound"]
        self._leaf = []
        for code in (PROVED, INSIDE_BALL, ABOVE_LEVEL, INSIDE_CORE, BELOW_LEVEL):
            mine = codes == code
            if bool(mine.any()):
                self._leaf.append((ids[mine], code, None if code == INSIDE_BALL else bound[mine]))

    def finish(self) -> Partition:
        n = self.count
        axis = torch.full((n,), -1, dtype=torch.int8)
        verdict = torch.full((n,), OPEN, dtype=torch.int8)
        bound = torch.full((n,), float("nan"), dtype=torch.float64)
        for ids, ax in self._axis:
            axis[ids] = ax.to(torch.int8)
            verdict[ids] = INTERNAL
        for ids, code, values in self._leaf:
            verdict[ids] = code
            if values is not None:
                bound[ids] = values.to(torch.float64)
        return Partition(self.grid, torch.cat(self._parent), torch.cat(self._side), axis, verdict, bound,
                         self.enclosure)
