"""What a branch and bound computes for each batch of boxes, as a job that runs in this process (on its device) or on
worker processes (:mod:`drlyap.parallel`).

:class:`ConditionJob` bounds a decrease condition over boxes: the residual's upper bound (on a sublevel set
``{V <= level}`` only, with V's bounds), a lower bound of the residual at the box centres and each coordinate's share of
the bounds' spread (where to split). It holds the closed loop, the condition, the level and the enclosure; it is
picklable, so that workers receive it once and then only boxes. :func:`run_batches` submits a branch and bound's
batches and hands their bounds back in order; each batch is bounded in chunks of :data:`CHUNK` boxes, in this process
and on workers alike (:func:`chunk_sizes`), so that every box's bounds are the same bits for any number of workers.
"""

from __future__ import annotations

import copy
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from drlyap.compute import Compute
from drlyap.enclosures import Interval
from drlyap.parallel import check_device, discard_pool, pool_for, run_in_chunks
from drlyap.verification.bounds import (
    box_bounds,
    combine_lower,
    combine_upper,
    condition_and_value_objective,
    condition_objective,
    sublevel_upper,
)
from drlyap.verification.search import Boxes

CHUNK = 1024
"""Boxes of a batch bounded in one call of the job, in this process (on the CPU) or on a worker. A chunk's bounds are
the same bits wherever it is bounded, whereas a box's bounds may differ in their last bits with the number of boxes
bounded beside it (a float64 matrix product takes another kernel for the rows beyond a multiple of its block): one
chunk per worker gave another certificate for every number of workers. A full batch (4,096 boxes) is 4 chunks, 8 in
flight with the batch sent ahead, which is as many workers as one proof keeps busy. One process's proof of the
cart-pole costs about the same (CPU time +2% with 1,024, -7% with 2,048, +23% with 512: each call has a fixed cost of
about 50 ms, and fewer boxes a call are cheaper per box)."""

def chunk_sizes(boxes: int) -> list[int]:
    """The chunks a batch of ``boxes`` boxes is bounded in, one call of the job each, in order: as few as chunks of
    :data:`CHUNK` allow, of about equal size (a batch of 1,134 boxes: 567 and 567, not 1,024 and 110, which kept one
    worker busy and the other idle; at the frontier of a search, where the queue is short, such batches hold a quarter
    of the cart-pole's boxes). It depends on the batch alone, so the chunks (and their bounds' bits) are the same in
    this process and on any number of workers."""
    parts = max(1, -(-boxes // CHUNK))
    size, extra = divmod(boxes, parts)
    return [size + 1] * extra + [size] * (parts - extra)


@dataclass
class ConditionBounds:
    """What bounding a batch of boxes ``(B, n)`` gives a branch and bound, ``(B,)`` tensors: ``upper`` (the residual's
    upper bound, +inf where undefined), ``centre_lower`` (a lower bound of the residual at the centre),
    ``sensitivity (B, n)`` (how much each side adds to the bounds) and, with a level, ``value_lower`` (V's lower bound
    over the box) and ``centre_value_upper`` (V's upper bound at the centre); on a band under the level also
    ``value_upper`` and ``centre_value_lower`` (None where not asked). Workers send it as :meth:`as_dict`."""

    upper: Tensor
    centre_lower: Tensor
    sensitivity: Tensor
    value_lower: Tensor | None = None
    centre_value_upper: Tensor | None = None
    value_upper: Tensor | None = None
    centre_value_lower: Tensor | None = None

    def as_dict(self) -> dict[str, Tensor]:
        """The tensors that are set, on the CPU (what a worker sends back; chunks join entry by entry)."""
        return {f.name: getattr(self, f.name).cpu() for f in fields(self) if getattr(self, f.name) is not None}


class ConditionJob:
    """Bounds of ``condition``'s residual for the closed loop ``loop`` (its float64 view) over boxes; with ``level``,
    on the part of each box where ``V <= level``, with V's bounds beside.

    Called on boxes ``lo, hi (B, n)`` it returns :class:`ConditionBounds` as a dict (:meth:`ConditionBounds.as_dict`);
    with ``band`` (a proof on a band under the level) V's upper bounds too."""

    def __init__(self, loop, condition, level: float | None, enclosure: str, device: str = "cpu",
                 band: bool = False) -> None:
        self.loop, self.condition, self.level, self.enclosure, self.device = loop, condition, level, enclosure, device
        self.band = band

    def on(self, device: str) -> ConditionJob:
        """The same job with the networks and the condition's samples on ``device``."""
        if device == self.device:
            return self
        check_device(device)
        job = copy.copy(self)
        job.loop = _loop_on(self.loop, device)
        job.condition = _condition_on(self.condition, device)
        job.device = device
        return job

    def __call__(self, lo: Tensor, hi: Tensor) -> dict[str, Tensor]:
        device = torch.device(self.device)
        return bound_condition(self.loop, self.condition, self.level, self.enclosure, lo.to(device), hi.to(device),
                               self.band).as_dict()


def bound_condition(loop, condition, level: float | None, enclosure: str, lo: Tensor, hi: Tensor,
                    band: bool = False) -> ConditionBounds:
    """What a :class:`ConditionJob` returns for the boxes ``lo, hi (B, n)`` (local coordinates, on the networks'
    device), computed with ``loop``'s networks as they are: the verifier passes float64 copies; training passes its
    live networks within :func:`~drlyap.enclosures.weight_gradients`, and ``upper`` is then the verifier's bound,
    differentiable in the weights."""
    make = condition_objective if level is None else condition_and_value_objective
    read = slice(0, 0) if level is None else slice(-1, None)  # of the lower bounds, V's alone is read (with a level)
    lb_c, ub_c, at, sens, form = box_bounds(make(loop, condition), lo, hi, enclosure, sensitivity=True,
                                            keep_form=True, read_lower=read)
    value: dict[str, Tensor] = {}
    at_lo = at.lo
    if level is not None:  # the last component is V
        value.update(value_lower=lb_c[:, -1], centre_value_upper=at.hi[:, -1])
        if band:  # only a band's proof reads them: nothing more to send back from the workers otherwise
            value.update(value_upper=ub_c[:, -1], centre_value_lower=at.lo[:, -1])
        ub_c, at_lo = ub_c[:, :-1], at_lo[:, :-1]
    upper = combine_upper(condition, ub_c)
    if level is not None and form is not None:  # the S-procedure where the plain bound proves nothing yet
        need = ((upper > 0) & (value["value_lower"] <= level)).nonzero().squeeze(-1)
        if need.numel():
            upper = upper.index_put((need,), torch.minimum(upper[need], sublevel_upper(condition, form[need], level)))
    return ConditionBounds(upper, combine_lower(condition, at_lo), sens, **value)


def _loop_on(loop, device: str):
    from drlyap.closed_loop import ClosedLoop

    lyapunov = copy.deepcopy(loop.lyapunov).to(device)
    controller = copy.deepcopy(loop.controller).to(device)
    return ClosedLoop(loop.system, lyapunov, controller)


def _condition_on(condition, device: str):
    moved = copy.copy(condition)
    xi = condition.xi
    if isinstance(xi, Tensor):
        moved.xi = xi.to(device)
    elif isinstance(xi, Interval):
        moved.xi = Interval(xi.lo.to(device), xi.hi.to(device))
    moved._xi_cache = {}
    return moved


def run_batches(job: Callable, compute: Compute, take: Callable[[], Boxes | None],
                can_prefetch: Callable[[], bool]) -> Iterator[tuple[Boxes, dict[str, Tensor]]]:
    """Bound the batches a branch and bound takes, in the order it takes them: yields ``(batch, bounds)``, a
    :data:`~drlyap.verification.search.Bound` for a job that workers may run.

    ``take()`` returns the next batch (:class:`~drlyap.verification.search.Boxes`; None: no more); ``can_prefetch()``
    says whether the next batch is already fixed before the bounds of the batches in flight come back (its boxes are in
    the queue, not among their children), so that workers may start on it while this process sorts the last one out. In
    this process (``compute`` without workers) each batch is bounded when it is taken, on ``compute.device``. Each batch
    is bounded in the chunks :func:`chunk_sizes` gives (each a call of ``job``), the same chunks in this process and on
    any number of workers, so that the bounds are the same bits; on a GPU (one process only) in one call.
    """
    pool = pool_for(compute)
    if pool is None:
        local = job.on(compute.device) if hasattr(job, "on") else job
        whole = compute.device != "cpu"  # a GPU bounds a whole batch at once: no workers' bits to agree with
        while (batch := take()) is not None:
            bounds = (local(batch.lo, batch.hi) if whole else
                      run_in_chunks(local, (batch.lo, batch.hi), chunk_sizes(len(batch))))
            yield batch, bounds
        return
    flight: deque = deque()
    try:
        while True:
            while len(flight) < 2 and (not flight or can_prefetch()):
                batch = take()
                if batch is None:
                    break
                flight.append((batch, pool.submit(job, batch.lo, batch.hi, chunk=chunk_sizes(len(batch)))))
            if not flight:
                return
            batch, pending = flight.popleft()
            yield batch, pending.result()
    except GeneratorExit:  # the caller stopped early (a counterexample): collect what is still in flight
        for _, pending in flight:
            pending.result()
        raise
    except BaseException:
        discard_pool(pool)  # its workers may still hold batches of this search: start afresh next time
        raise
