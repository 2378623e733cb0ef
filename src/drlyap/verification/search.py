"""The one branch-and-bound loop of the verifier: a queue of boxes, taken a batch at a time, bounded (in this process
or on workers), and sorted by the caller's rule, until the queue is empty, the box budget is spent or the time cap is
reached.

Every search of the verifier runs on it: a condition's proof (:func:`~drlyap.verification.branch_and_bound.
verify_condition`), the suprema of functions over a set (:func:`~drlyap.verification.branch_and_bound.maximize`) and
the level search of a region of attraction (:func:`~drlyap.verification.roa.levels.level_search`). What differs between
them is plugged in: how a batch is bounded (``bound``: :func:`in_process`, or :func:`~drlyap.verification.bounding.
run_batches` for a job that workers may run), how its bounds are sorted (``sort``: record what is proved, confirm
violations, push the boxes to split back into the queue), which boxes are taken first (in the order they were queued,
or those of the lowest inherited bound) and which are pruned before they are bounded. Budgets are in boxes, so that a
search's result does not depend on the machine's speed; the seconds are a cap, and a search that reaches it says so.
A checkpoint (the caller's state, saved by :class:`Checkpointing`) is written every so many seconds and when the loop
is interrupted between batches.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import torch
from torch import Tensor

FINISHED = "finished"
BOX_BUDGET = "box budget"
TIME_LIMIT = "time limit"
GAVE_UP = "more boxes queued than the budget has left"


@dataclass
class Boxes:
    """Boxes ``lo, hi (B, n)`` in local coordinates, ``ids (B,)`` their nodes in a partition's tree (zeros where no
    tree is kept) and ``known`` ``(B,)`` or ``(B, Q)``, a bound each inherited from its parent (None: none kept)."""

    lo: Tensor
    hi: Tensor
    ids: Tensor
    known: Tensor | None = None

    def __len__(self) -> int:
        return int(self.lo.shape[0])

    def select(self, which: Tensor) -> Boxes:
        """The boxes a bool mask or an index tensor ``which`` picks, in their order."""
        return Boxes(self.lo[which], self.hi[which], self.ids[which], None if self.known is None else self.known[which])

    @staticmethod
    def join(parts: list[Boxes]) -> Boxes:
        """The boxes of ``parts``, one after the other. Where some parts bring a ``known`` bound and others none, those
        without get ``+inf`` (no bound known); ``known`` is None only where no part has one."""
        ref = next((p.known for p in parts if p.known is not None), None)
        known = None if ref is None else torch.cat([
            p.known if p.known is not None else torch.full((len(p), *ref.shape[1:]), torch.inf, dtype=ref.dtype,
                                                           device=ref.device) for p in parts])
        return Boxes(torch.cat([p.lo for p in parts]), torch.cat([p.hi for p in parts]), torch.cat([p.ids for p in parts]),
                     known)


class DomainQueue:
    """The boxes a search has yet to decide (``queued``), and the batches taken from it whose bounds have not come
    back yet (``flight``, oldest first): a checkpoint holds both, the batches in flight first, as they were taken."""

    def __init__(self, boxes: Boxes) -> None:
        self.queued = boxes
        self.flight: list[Boxes] = []

    def __len__(self) -> int:
        return len(self.queued)

    def take(self, count: int, lowest: bool = False) -> Boxes:
        """Remove and return ``count`` boxes: the first ones queued, or with ``lowest`` those of the lowest ``known``
        bound (in their queued order; the rest keep theirs)."""
        if lowest and len(self) > count:
            picked = torch.zeros(len(self), dtype=torch.bool)
            picked[torch.topk(self.queued.known, count, largest=False).indices] = True
            batch, self.queued = self.queued.select(picked), self.queued.select(~picked)
            return batch
        batch, self.queued = self.queued.select(slice(0, count)), self.queued.select(slice(count, None))
        return batch

    def push(self, boxes: Boxes) -> None:
        """Queue ``boxes`` behind the others (:meth:`Boxes.join`: boxes that bring a ``known`` bound where the queue
        holds none give the queued ones ``+inf``)."""
        self.queued = Boxes.join([self.queued, boxes])

    def keep(self, which: Tensor) -> None:
        """Keep only the queued boxes a bool mask ``which`` marks."""
        self.queued = self.queued.select(which)

    def everything(self) -> Boxes:
        """The batches in flight, then the queued boxes: the order a search started again takes them in."""
        return Boxes.join([*self.flight, self.queued]) if self.flight else self.queued

    def land(self) -> None:
        """Put the batches still in flight back at the front of the queue."""
        if self.flight:
            self.queued, self.flight = self.everything(), []


@dataclass
class Stopping:
    """When a search stops taking boxes: after ``boxes`` boxes in all (counting those of earlier runs of the same
    search, ``taken``), or ``seconds`` of its time (counting ``spent_s``); with ``give_up``, as soon as more boxes are
    queued than the budget has left (it cannot finish within it)."""

    boxes: int
    seconds: float
    give_up: bool = False
    taken: int = 0
    spent_s: float = 0.0


@dataclass
class Taking:
    """How a search takes its boxes: ``batch`` at a time, the first queued or with ``lowest_first`` those of the lowest
    inherited bound, and without those ``prune`` removes (boxes that need no bounds; None: none)."""

    batch: int
    lowest_first: bool = False
    prune: Callable[[Boxes], Boxes] | None = None


@dataclass
class Checkpointing:
    """How a search keeps its progress: ``save(seconds)`` writes the caller's state (its queue included) and the
    seconds the search has spent, at least ``every`` seconds apart, and more apart where saving takes long (``spacing``
    times its own time)."""

    save: Callable[[float], None]
    every: float
    spacing: float = 1.0


@dataclass
class Outcome:
    """How a run of the loop ended: ``stopped`` (:data:`FINISHED`, :data:`BOX_BUDGET`, :data:`TIME_LIMIT`,
    :data:`GAVE_UP`, or what the caller's ``sort`` returned), ``taken`` the boxes taken in all (with the earlier runs')
    and ``seconds`` the time spent in all."""

    stopped: str
    taken: int
    seconds: float = 0.0


Bound = Callable[[Callable[[], Boxes | None], Callable[[], bool]], Iterator[tuple[Boxes, object]]]
"""How a search's batches are bounded: called with the loop's ``take()`` (the next batch, or None) and
``can_prefetch()`` (whether the next batch is fixed before the bounds in flight come back), it yields each batch with
its bounds, in the order taken."""


def in_process(bound_batch: Callable[[Boxes], object]) -> Bound:
    """A :data:`Bound` that bounds each batch whole, in this process, when it is taken."""

    def bound(take: Callable[[], Boxes | None], can_prefetch: Callable[[], bool]) -> Iterator[tuple[Boxes, object]]:
        while (batch := take()) is not None:
            yield batch, bound_batch(batch)

    return bound


def branch_and_bound(queue: DomainQueue, bound: Bound, sort: Callable[[Boxes, object], str | None],
                     stopping: Stopping, taking: Taking, *, bar=None, checkpoint: Checkpointing | None = None) -> Outcome:
    """Take batches of boxes from ``queue`` as ``taking`` says (a batch its pruning leaves empty is not counted), bound
    them with ``bound`` and hand each batch with its bounds to ``sort``, which records what it decides and pushes the
    boxes to split back into ``queue``; a ``sort`` that returns a reason stops the search with it.

    The loop stops taking boxes when the queue is empty or ``stopping`` says so (the box budget is checked before the
    time cap: a search that spent both is limited by its boxes). Batches prefetched for workers when it stops are put
    back at the front of the queue. ``bar``: a progress bar, advanced by each batch's boxes. ``checkpoint``: saved every
    so many seconds between batches, and on an interruption (Ctrl-C) between them, before it is raised again."""
    start = time.perf_counter()
    saved_at = start
    state = Outcome(FINISHED, stopping.taken)
    spacing = None if checkpoint is None else checkpoint.every

    def spent() -> float:
        return stopping.spent_s + time.perf_counter() - start

    def take() -> Boxes | None:
        while True:
            if not len(queue):
                state.stopped = FINISHED
                return None
            if state.taken >= stopping.boxes:
                state.stopped = BOX_BUDGET
                return None
            if spent() > stopping.seconds:
                state.stopped = TIME_LIMIT
                return None
            if stopping.give_up and len(queue) > stopping.boxes - state.taken:
                state.stopped = GAVE_UP
                return None
            taken = queue.take(taking.batch, taking.lowest_first)
            if taking.prune is not None:
                taken = taking.prune(taken)
            if len(taken):
                state.taken += len(taken)
                queue.flight.append(taken)
                return taken

    sorting = False
    try:
        for taken, bounds in bound(take, lambda: len(queue) >= taking.batch):
            sorting = True
            queue.flight.pop(0)
            if bar is not None:
                bar.update(len(taken))
            reason = sort(taken, bounds)
            if reason is not None:
                state.stopped = reason
                break
            sorting = False
            if checkpoint is not None and time.perf_counter() - saved_at >= spacing:
                tic = time.perf_counter()
                checkpoint.save(spent())
                saved_at = time.perf_counter()
                spacing = max(checkpoint.every, checkpoint.spacing * (saved_at - tic))
    except KeyboardInterrupt:
        if checkpoint is not None and not sorting:  # between batches the state is whole: keep it, to resume here
            checkpoint.save(spent())
        raise
    queue.land()
    state.seconds = spent()
    if len(queue) and state.stopped == FINISHED:  # a search that stopped on its own has none queued
        state.stopped = BOX_BUDGET
    return state
