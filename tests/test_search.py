"""The one branch-and-bound loop (drlyap.verification.search): its queue, its stopping rules, pruning and
checkpoints, on a one-dimensional toy search (no networks)."""

import math

import pytest
import torch

from drlyap.verification.search import (
    BOX_BUDGET,
    FINISHED,
    GAVE_UP,
    TIME_LIMIT,
    Boxes,
    Checkpointing,
    DomainQueue,
    Stopping,
    Taking,
    branch_and_bound,
    in_process,
)


def boxes(edges, known=None):
    lo = torch.tensor(edges[:-1], dtype=torch.float64)[:, None]
    hi = torch.tensor(edges[1:], dtype=torch.float64)[:, None]
    return Boxes(lo, hi, torch.arange(lo.shape[0]), None if known is None else torch.tensor(known, dtype=torch.float64))


def test_the_queue_takes_the_first_boxes_or_those_of_lowest_known_bound_in_their_order():
    queue = DomainQueue(boxes([0, 1, 2, 3, 4, 5], known=[4.0, 1.0, 3.0, 0.0, 2.0]))
    assert queue.take(2).ids.tolist() == [0, 1]
    assert queue.take(2, lowest=True).ids.tolist() == [3, 4]  # known 0 and 2, in their queued order
    assert queue.queued.ids.tolist() == [2]
    assert len(queue) == 1


def test_boxes_that_bring_a_bound_give_the_queued_ones_none_known():
    queue = DomainQueue(boxes([0, 1, 2]))
    queue.push(Boxes(torch.zeros(1, 1), torch.ones(1, 1), torch.tensor([7]), torch.tensor([[0.5, 1.5]])))
    assert queue.queued.known.shape == (3, 2)
    assert torch.isinf(queue.queued.known[:2]).all() and queue.queued.known[2].tolist() == [0.5, 1.5]


def bisect_until(width):
    """A toy search: each box is 'proved' once narrower than ``width``, else split in halves."""
    proved = []

    def sort(taken, bounds):
        narrow = bounds <= width
        proved.extend(taken.select(narrow).lo[:, 0].tolist())
        wide = taken.select(~narrow)
        mid = (wide.lo + wide.hi) / 2
        queue.push(Boxes(torch.cat([wide.lo, mid]), torch.cat([mid, wide.hi]), torch.cat([wide.ids, wide.ids])))
        return None

    queue = DomainQueue(boxes([0.0, 1.0]))
    return queue, sort, proved, in_process(lambda b: (b.hi - b.lo)[:, 0])


def test_a_search_runs_until_its_queue_is_empty_and_counts_every_box_it_took():
    queue, sort, proved, bound = bisect_until(1 / 8)
    outcome = branch_and_bound(queue, bound, sort, Stopping(boxes=100, seconds=math.inf), Taking(3))
    assert outcome.stopped == FINISHED
    assert sorted(proved) == [i / 8 for i in range(8)]
    assert outcome.taken == 1 + 2 + 4 + 8  # the tree's nodes, each bounded once
    assert len(queue) == 0 and not queue.flight


def test_the_box_budget_is_checked_before_the_time_cap_and_counts_earlier_runs():
    queue, sort, _, bound = bisect_until(1 / 64)
    outcome = branch_and_bound(queue, bound, sort, Stopping(boxes=10, seconds=-1.0, taken=10), Taking(4))
    assert outcome.stopped == BOX_BUDGET and outcome.taken == 10  # spent before: nothing taken now
    outcome = branch_and_bound(queue, bound, sort, Stopping(boxes=10, seconds=-1.0), Taking(4))
    assert outcome.stopped == TIME_LIMIT and outcome.taken == 0
    outcome = branch_and_bound(queue, bound, sort, Stopping(boxes=5, seconds=math.inf), Taking(4))
    assert outcome.stopped == BOX_BUDGET and outcome.taken == 7  # 1 box, its 2 halves, their 4: 7 >= 5, no more
    assert len(queue) > 0


def test_a_search_gives_up_when_more_boxes_are_queued_than_its_budget_has_left():
    queue, sort, _, bound = bisect_until(1 / 1024)
    outcome = branch_and_bound(queue, bound, sort, Stopping(boxes=8, seconds=math.inf, give_up=True), Taking(1))
    assert outcome.stopped == GAVE_UP
    assert len(queue) > 8 - outcome.taken


def test_a_sort_that_returns_a_reason_stops_the_search_with_it():
    queue = DomainQueue(boxes([0, 1, 2, 3]))
    outcome = branch_and_bound(queue, in_process(lambda b: None), lambda b, _: "counterexample",
                               Stopping(boxes=100, seconds=math.inf), Taking(2))
    assert outcome.stopped == "counterexample" and outcome.taken == 2
    assert queue.queued.ids.tolist() == [2]


def test_pruned_boxes_are_neither_bounded_nor_counted():
    queue = DomainQueue(boxes([0, 1, 2, 3, 4, 5]))
    seen = []
    outcome = branch_and_bound(queue, in_process(lambda b: seen.extend(b.ids.tolist())), lambda b, _: None,
                               Stopping(boxes=100, seconds=math.inf),
                               Taking(2, prune=lambda b: b.select(b.ids % 2 == 0)))
    assert seen == [0, 2, 4] and outcome.taken == 3 and outcome.stopped == FINISHED


def test_prefetched_batches_go_back_to_the_front_of_the_queue_when_the_search_stops():
    queue = DomainQueue(boxes([0, 1, 2, 3, 4, 5, 6]))

    def ahead(take, can_prefetch):  # like workers: a second batch is taken before the first one's bounds come back
        first = take()
        second = take() if can_prefetch() else None
        yield first, None
        if second is not None:
            yield second, None

    outcome = branch_and_bound(queue, ahead, lambda b, _: "stop", Stopping(boxes=100, seconds=math.inf), Taking(2))
    assert outcome.stopped == "stop"
    assert queue.queued.ids.tolist() == [2, 3, 4, 5] and not queue.flight


def test_an_interrupted_search_saves_its_checkpoint_between_batches_and_raises_again():
    queue = DomainQueue(boxes([0, 1, 2, 3]))
    saved = []

    def sort(taken, bounds):
        if len(saved) == 0 and int(taken.ids[0]) == 2:
            raise KeyboardInterrupt
        return None

    def interrupt_after_first(take, can_prefetch):
        yield take(), None
        taken = take()
        yield taken, None

    checkpoint = Checkpointing(lambda seconds: saved.append(len(queue.everything())), every=math.inf)
    with pytest.raises(KeyboardInterrupt):
        branch_and_bound(queue, interrupt_after_first, sort, Stopping(boxes=100, seconds=math.inf), Taking(2),
                         checkpoint=checkpoint)
    assert saved == []  # interrupted while sorting: the state is not whole, nothing saved

    queue = DomainQueue(boxes([0, 1, 2, 3, 4]))

    def interrupted(take, can_prefetch):
        yield take(), None
        raise KeyboardInterrupt

    checkpoint = Checkpointing(lambda seconds: saved.append(len(queue.everything())), every=math.inf)
    with pytest.raises(KeyboardInterrupt):
        branch_and_bound(queue, interrupted, lambda b, _: None, Stopping(boxes=100, seconds=math.inf), Taking(2),
                         checkpoint=checkpoint)
    assert saved == [2]  # between batches: saved, with the boxes not yet sorted


def test_a_checkpoint_is_saved_every_so_often():
    queue, sort, _, bound = bisect_until(1 / 16)
    times = []
    branch_and_bound(queue, bound, sort, Stopping(boxes=100, seconds=math.inf), Taking(1),
                     checkpoint=Checkpointing(times.append, every=0.0))
    assert len(times) == 31 and times == sorted(times)  # after every batch (every 0 s), the seconds growing


def test_joining_boxes_with_and_without_inherited_bounds_keeps_both():
    """A batch taken before any bound was known, put back in front of a queue that holds bounds, keeps them (+inf for
    its own): a prefetched batch landing after the first split must not drop the queue's bounds."""
    queue = DomainQueue(boxes([0, 1, 2, 3]))
    first = queue.take(1)
    queue.push(Boxes(torch.zeros(1, 1), torch.ones(1, 1), torch.tensor([9]), torch.tensor([[0.5]])))
    queue.flight.append(first)
    queue.land()
    assert queue.queued.ids.tolist() == [0, 1, 2, 9]
    assert queue.queued.known[:, 0].tolist() == [math.inf, math.inf, math.inf, 0.5]
