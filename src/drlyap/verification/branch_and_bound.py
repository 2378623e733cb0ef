"""Branch and bound over boxes of X_delta: prove a decrease condition, or find where it fails; suprema.

:func:`verify_condition` proves ``residual(z) <= 0`` for every local state ``z`` of a region X_delta (the
state box minus the open delta-ball) for a per-state condition of :mod:`drlyap.conditions`, or finds a
state where it fails (re-checked by the ordinary torch code path). :func:`maximize` bounds suprema of
functions over a union of boxes; :func:`uniform_margin` uses it for the uniform DR condition.

The networks are the stored weights read as float64 numbers and evaluated in exact real arithmetic;
every bound is computed in float64 with outward rounding (:mod:`drlyap.enclosures`), so it encloses the
real value. Boxes whose upper bound is ``<= 0`` are verified, a box whose centre violates the condition
is a counterexample, the rest are bisected (on the side that adds most to the bound, among the sides at
least 1/16 of the widest normalised one) until a time limit, box budget or minimum box size is reached.

Limits: the claim is about the float64 reading of the weights in real arithmetic (training and simulation
run float32; counterexamples report the residual both ways). A box straddling the sphere ``||z|| = delta``
is bounded as a whole, so a violation just inside the ball keeps it unverified down to the minimum box
size (the verdict is then ``unknown``, never wrong). Costs grow exponentially with the state dimension.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition, DRUniform
from drlyap.enclosures import EPS, F64, Interval, round_down, round_up
from drlyap.kinds import Status
from drlyap.networks import QuadraticLyapunov
from drlyap.progress import progress as show_progress
from drlyap.proof_settings import Budget
from drlyap.regions import Domain, Region, box_grid, default_grid, inside_ball, split
from drlyap.verification.bounding import ConditionBounds, ConditionJob, run_batches
from drlyap.verification.bounds import box_bounds, condition_objective, vertex_max
from drlyap.verification.checkpoints import SAVE_SPACING, load_checkpoint, proof_key, save_checkpoint
from drlyap.verification.partition import INSIDE_CORE, OPEN, PROVED, Partition, PartitionRecorder
from drlyap.verification.results import ConditionProof, UniformMargin
from drlyap.verification.search import (
    Boxes,
    Checkpointing,
    DomainQueue,
    Stopping,
    Taking,
    branch_and_bound,
    in_process,
)


@dataclass(frozen=True)
class Exempt:
    """Parts of a sublevel set ``{V <= level}`` that a condition's proof need not cover (each needs the level).

    ``floor``: the proof is on the band ``{floor <= V <= level}``: a box on which V is provably below ``floor`` needs
    nothing more (``BELOW_LEVEL`` in the partition), and a counterexample must have ``V >= floor``. ``core``: ``(P (n,
    n), c)``, an ellipsoid ``{z^T P z <= c}`` around x* whose own proof carries the trajectories that reach it (a
    certified region of attraction): boxes inside it (every vertex, rounded up: the form is convex) need nothing more
    (``INSIDE_CORE``), and a violation inside it is none of the claim's. Neither goes with a :class:`StartFrom`."""

    floor: float | None = None
    core: tuple[Tensor, float] | None = None


@dataclass(frozen=True)
class StartFrom:
    """A proof that starts from the ``partition`` of a proof, on the same region, level, grid and enclosure, of another
    condition of the closed loop (e.g. the same condition at a smaller Wasserstein radius): its tree is kept, its leaves
    in the ball and above the level stand (they do not depend on the condition), and its proved and open leaves are the
    starting queue, bounded again for this condition (split further where they must be), but for those marked
    ``standing`` (``(N,)`` bool over its nodes): leaves already proved for this condition (e.g. by a proof of the same
    condition at a larger radius, which implies it), kept as proved."""

    partition: Partition
    standing: Tensor | None = None


@dataclass(frozen=True)
class ProofRules:
    """How a condition's branch and bound runs and what it keeps.

    ``grid``: boxes per axis at the start (None: :func:`~drlyap.regions.default_grid`). ``stop_at_counterexample``:
    return at the first confirmed one (the fraction then counts every box not yet verified as unverified).
    ``give_up``: stop, ``unknown``, as soon as more boxes are queued than the budget has left (the proof cannot finish
    within it). ``violation_width``: a box whose centre is a confirmed counterexample is still split (to sharpen the
    verified fraction) until its widest relative side is below this. ``keep_boxes``: how many unverified boxes to
    list. ``keep_partition``: keep the partition of a proof that is not verified too (its leaves not proved ``OPEN``),
    for a proof that starts from it."""

    grid: Sequence[int] | None = None
    stop_at_counterexample: bool = False
    give_up: bool = False
    violation_width: float = 1e-2
    keep_boxes: int = 50
    keep_partition: bool = False


def verify_condition(loop: ClosedLoop, condition: Condition, region: Region, budget: Budget = Budget(), *,
                     level: float | None = None, exempt: Exempt = Exempt(), start: StartFrom | None = None,
                     rules: ProofRules = ProofRules()) -> ConditionProof:
    """Prove ``residual(z) <= 0`` for the closed loop on the region X_delta by branch and bound, or find where it
    fails, within ``budget`` (boxes, seconds, minimum box width, enclosure, and where to bound them).

    ``level``: prove it only on the sublevel set ``{V <= level}`` of X_delta (a box on which V provably exceeds
    the level needs nothing more; a counterexample must have ``V <= level``); the verified fraction is then
    the share of X_delta where the condition or ``V > level`` is proved. ``exempt``: parts of that set the proof need
    not cover (:class:`Exempt`: below a band's floor, inside a core ellipsoid). ``start``: a partition to start from
    (:class:`StartFrom`). ``rules``: how the search runs and what it keeps (:class:`ProofRules`).

    ``budget.min_width``: boxes whose widest side (relative to the state box) is below it are not split further.
    ``budget.boxes``: processed boxes at most. ``budget.enclosure``: how boxes are bounded
    (:func:`~drlyap.verification.bounds.box_bounds`: ``mean-value`` or ``affine``; None: by the dimension).
    ``budget.compute``: where (:class:`~drlyap.compute.Compute`): batches go to worker processes in the order a single
    process takes them, so the result, and the partition a verified proof keeps, are the same for any number of
    workers; with a ``checkpoint_dir`` the search is saved there every ``checkpoint_every`` seconds and when it ends,
    and the same proof (:func:`~drlyap.verification.checkpoints.proof_key`) started again continues from it.
    """
    if not condition.per_state:
        raise ValueError("use uniform_margin for the uniform condition")
    if exempt.core is not None and start is not None:
        raise ValueError("a proof with a core does not start from another proof's partition")
    floor = exempt.floor
    if floor is not None and (level is None or start is not None or not floor < level):
        raise ValueError(f"a band's floor goes with a level above it and no starting partition (floor {floor}, "
                         f"level {level})")
    search = _Search(loop, condition, region, budget, level, exempt, start, rules)
    if not (search.finished and (search.stopped == "counterexample" or not len(search.queue))):
        search.run()  # a finished search that ran out of budget goes on where a larger budget allows
    return search.result(rules.keep_boxes, rules.keep_partition)


def proof_label(condition: Condition, level: float | None = None) -> str:
    """What a proof's progress line calls it: the condition, its Wasserstein radius or the half-widths of its box of
    shifts (in the parameters' units), and the sublevel set it is proved on."""
    what = condition.label
    radius = getattr(condition, "r", None)
    if radius is not None:
        what += f", r = {radius:.4g}"
    if isinstance(condition.xi, Interval):
        what += ", xi within +-(" + ", ".join(f"{float(v):.4g}" for v in condition.xi.hi.reshape(-1)) + ")"
    return what + (f", on {{V <= {level:.6g}}}" if level is not None else "")


class _Search:
    """The state of one branch and bound of :func:`verify_condition` (queue, tree, counters), which a checkpoint
    holds."""

    def __init__(self, loop: ClosedLoop, condition: Condition, region: Region, budget: Budget, level: float | None,
                 exempt: Exempt, start: StartFrom | None, rules: ProofRules) -> None:
        self.loop, self.condition, self.region, self.budget, self.level = loop, condition, region, budget, level
        floor, core = exempt.floor, exempt.core
        per_axis = list(rules.grid or default_grid(loop.system.n))
        stop_at_counterexample, violation_width, give_up = (rules.stop_at_counterexample, rules.violation_width,
                                                            rules.give_up)
        standing = None if start is None else start.standing
        start = None if start is None else start.partition
        self.floor = None if floor is None else float(floor)
        self.core = None if core is None else (torch.as_tensor(core[0], dtype=F64), float(core[1]))
        self.core_form = None if core is None else QuadraticLyapunov(self.core[0])
        self.stop_at_cex, self.violation_width, self.give_up = stop_at_counterexample, violation_width, give_up
        self.n = loop.system.n
        self.enclosure = budget.enclosure_for(self.n)
        self.compute = budget.compute
        self.volume = region.volume()
        self.tree = PartitionRecorder(per_axis, int(torch.tensor(per_axis).prod()), self.enclosure)
        self.processed = self.verified_count = self.n_cex_boxes = self.resumed = 0
        self.unverified_vol, self.elapsed = 0.0, 0.0
        self.leaves_lo: list[Tensor] = []
        self.leaves_hi: list[Tensor] = []
        self.sup_lo, self.sup_hi = -math.inf, -math.inf
        self.cex: tuple[float, Tensor] | None = None
        self.stopped, self.finished = "finished", False
        self.key = None
        if self.compute.checkpoint_dir is not None:
            self.key = proof_key(loop, condition, region, level=level,
                                 grid=per_axis, enclosure=self.enclosure, batch=int(budget.batch),
                                 min_width=float(budget.min_width), violation_width=float(violation_width),
                                 stop_at_counterexample=bool(stop_at_counterexample), give_up=bool(give_up),
                                 start=None if start is None else start.digest(standing),
                                 core=None if core is None else [self.core[0].tolist(), self.core[1]],
                                 **({} if floor is None else {"floor": self.floor}))
        saved = load_checkpoint(self.compute.checkpoint_dir, self.key) if self.key else None
        lo, hi = box_grid(region.lo, region.hi, per_axis)
        if saved is not None:
            self._restore(*saved)
        elif start is not None:
            if list(start.grid) != per_axis or start.enclosure != self.enclosure:
                raise ValueError(f"a proof can start from a partition of its own grid and enclosure only (this one: "
                                 f"{per_axis}, {self.enclosure}; the partition's: {start.grid}, {start.enclosure})")
            if standing is not None and tuple(standing.shape) != (start.size,):
                raise ValueError(f"standing must mark each of the partition's {start.size} nodes, got shape "
                                 f"{tuple(standing.shape)}")
            blo, bhi = start.boxes(lo, hi)
            self.tree.restore(start.state(standing))
            opened = (start.verdict == PROVED) | (start.verdict == OPEN) | (start.verdict == INSIDE_CORE)
            if standing is not None:
                opened = opened & ~standing.to(torch.bool)
            opened = opened.nonzero().squeeze(-1)
            self.queue = DomainQueue(Boxes(blo[opened], bhi[opened], opened))
        else:
            keep = region.meets(lo, hi)
            self.tree.inside_ball(self.tree.roots[~keep])
            self.queue = DomainQueue(self._outside_core(Boxes(lo[keep], hi[keep], self.tree.roots[keep])))

    def _outside_core(self, boxes: Boxes) -> Boxes:
        """The boxes not inside the core (those inside are recorded as such)."""
        if self.core is None or not len(boxes):
            return boxes
        top = vertex_max(self.core[0], boxes.lo, boxes.hi)
        inside = top <= self.core[1]
        self.tree.inside_core(boxes.ids[inside], top[inside])
        return boxes.select(~inside)

    # ------------------------------------------------------------------ checkpoints
    def _arrays(self) -> dict[str, Tensor]:
        leaves_lo = torch.cat(self.leaves_lo) if self.leaves_lo else torch.empty(0, self.n, dtype=F64)
        leaves_hi = torch.cat(self.leaves_hi) if self.leaves_hi else torch.empty(0, self.n, dtype=F64)
        cex = self.cex[1] if self.cex is not None else torch.empty(0, dtype=F64)
        queue = self.queue.everything()  # the batches in flight go first again, as taken
        return {"queue_lo": queue.lo, "queue_hi": queue.hi, "queue_ids": queue.ids, "leaves_lo": leaves_lo,
                "leaves_hi": leaves_hi, "cex": cex, **self.tree.state()}

    def _meta(self) -> dict:
        return {"processed": self.processed, "verified_count": self.verified_count, "n_cex_boxes": self.n_cex_boxes,
                "unverified_vol": self.unverified_vol, "elapsed": self.elapsed, "sup": [self.sup_lo, self.sup_hi],
                "cex_value": None if self.cex is None else self.cex[0], "stopped": self.stopped,
                "finished": self.finished}

    def _restore(self, arrays: dict[str, Tensor], meta: dict) -> None:
        self.queue = DomainQueue(Boxes(arrays["queue_lo"], arrays["queue_hi"], arrays["queue_ids"].to(torch.int64)))
        self.tree.restore(arrays)
        self.leaves_lo = [arrays["leaves_lo"]] if arrays["leaves_lo"].shape[0] else []
        self.leaves_hi = [arrays["leaves_hi"]] if arrays["leaves_hi"].shape[0] else []
        self.processed, self.verified_count = int(meta["processed"]), int(meta["verified_count"])
        self.n_cex_boxes, self.unverified_vol = int(meta["n_cex_boxes"]), float(meta["unverified_vol"])
        self.elapsed, (self.sup_lo, self.sup_hi) = float(meta["elapsed"]), (float(v) for v in meta["sup"])
        self.cex = None if meta["cex_value"] is None else (float(meta["cex_value"]), arrays["cex"])
        self.stopped, self.finished = str(meta["stopped"]), bool(meta["finished"])
        self.resumed = self.processed

    def _save(self) -> None:
        if self.key is None:
            return
        try:
            save_checkpoint(self.compute.checkpoint_dir, self.key, self._arrays(), self._meta())
        except OSError as err:  # a read-only or full folder: the proof goes on, it only cannot resume
            why = err.strerror or err
            warnings.warn(f"the proof's checkpoint cannot be written in {self.compute.checkpoint_dir} ({why}); it goes "
                          "on without one", stacklevel=2)
            self.key = None

    # ------------------------------------------------------------------ the search
    def run(self) -> None:
        budget, condition, level = self.budget, self.condition, self.level
        resumed = f" (resumed from its checkpoint after {self.resumed} boxes)" if self.resumed else ""
        bar = show_progress(int(budget.boxes), f"proof ({proof_label(condition, level)}){resumed}: boxes",
                            self.compute.progress)
        if self.resumed:
            bar.update(min(self.resumed, int(budget.boxes)))
        job = ConditionJob(self.loop, condition, level, self.enclosure, band=self.floor is not None)
        checkpoint = None if self.key is None else Checkpointing(self._save_at, self.compute.checkpoint_every,
                                                                  SAVE_SPACING)

        def sort(boxes: Boxes, found: dict[str, Tensor]) -> str | None:
            reason = self._sort(boxes, found)
            bar.set_postfix(queued=len(self.queue))
            return reason

        try:
            outcome = branch_and_bound(
                self.queue, lambda take, can_prefetch: run_batches(job, self.compute, take, can_prefetch), sort,
                Stopping(int(budget.boxes), budget.seconds, self.give_up, self.processed, self.elapsed),
                Taking(int(budget.batch)), bar=bar, checkpoint=checkpoint)
        finally:
            bar.close()
        self.elapsed, self.stopped, self.finished = outcome.seconds, outcome.stopped, True
        self._save()

    def _save_at(self, seconds: float) -> None:
        self.elapsed = seconds
        self._save()

    def _sort(self, boxes: Boxes, found: dict[str, Tensor]) -> str | None:
        """Take one batch's bounds: record proved boxes, confirm counterexamples, split the rest. A reason: stop."""
        region, condition, level, tree = self.region, self.condition, self.level, self.tree
        clo, chi, cids, scale, bounds = boxes.lo, boxes.hi, boxes.ids, region.scale, ConditionBounds(**found)
        self.processed += len(boxes)
        ub, centre_lb, sens = bounds.upper, bounds.centre_lower, bounds.sensitivity
        centre = (clo + chi) / 2
        in_region = region.in_region(centre)
        outside = below = torch.zeros(clo.shape[0], dtype=torch.bool)
        if level is not None:  # boxes above the level are done, centres must lie in the set
            outside = bounds.value_lower > level
            in_region = in_region & (bounds.centre_value_upper <= level)
        if self.floor is not None:  # and on a band, boxes below its floor
            below = (bounds.value_upper < self.floor) & ~outside
            in_region = in_region & (bounds.centre_value_lower >= self.floor)
        if in_region.any():
            self.sup_lo = max(self.sup_lo, float(centre_lb[in_region].max()))
        ub = torch.where(outside | below, -torch.inf, ub)
        ok = ub <= 0
        tree.proved(cids[ok & ~outside & ~below], ub[ok & ~outside & ~below])
        if level is not None:
            tree.above_level(cids[ok & outside], bounds.value_lower[ok & outside])
        if self.floor is not None:
            tree.below_level(cids[below], bounds.value_upper[below])
        self.verified_count += int(ok.sum())
        if (ok & ~outside & ~below).any():
            self.sup_hi = max(self.sup_hi, float(ub[ok & ~outside & ~below].max()))
        bad = ~ok & in_region & (centre_lb > 0)
        if self.core is not None:  # a violation inside the core is not one of the claim's
            bad = bad & (self.core_form(centre) > self.core[1])
        if bad.any():
            values = self.loop.exact(condition, centre[bad])
            confirmed = values > 0
            if confirmed.any():
                best = int(values.argmax())
                if self.cex is None or float(values[best]) > self.cex[0]:
                    self.cex = (float(values[best]), centre[bad][best])
                self.n_cex_boxes += int(confirmed.sum())
                idx = bad.nonzero().squeeze(-1)[confirmed]
                bad = torch.zeros_like(bad)
                bad[idx] = True
            else:
                bad = torch.zeros_like(bad)
        if bad.any() and self.stop_at_cex:
            self.unverified_vol += float((chi[~ok] - clo[~ok]).prod(-1).sum())
            self.leaves_lo.append(clo[~ok])
            self.leaves_hi.append(chi[~ok])
            self.sup_hi = math.inf
            return "counterexample"
        rel_width = ((chi - clo) / scale).amax(-1)
        bad = bad & (rel_width < self.violation_width)  # violating boxes still wide enough are split like the rest
        if bad.any():
            self.unverified_vol += float((chi[bad] - clo[bad]).prod(-1).sum())
            self.sup_hi = max(self.sup_hi, float(ub[bad].max()))
            self.leaves_lo.append(clo[bad])
            self.leaves_hi.append(chi[bad])
        rest = ~ok & ~bad
        small = rest & (rel_width < self.budget.min_width)
        if small.any():
            self.unverified_vol += float((chi[small] - clo[small]).prod(-1).sum())
            self.sup_hi = max(self.sup_hi, float(ub[small].max()))
            self.leaves_lo.append(clo[small])
            self.leaves_hi.append(chi[small])
        divide = rest & ~small
        if divide.any():
            nlo, nhi = split(clo[divide], chi[divide], scale, sens[divide])
            children = tree.split(cids[divide], chi[divide], nhi)
            keep = region.meets(nlo, nhi)
            tree.inside_ball(children[~keep])
            self.queue.push(self._outside_core(Boxes(nlo[keep], nhi[keep], children[keep])))
        return None

    def result(self, keep_boxes: int, keep_partition: bool = False) -> ConditionProof:
        system, n = self.loop.system, self.n
        leaves_lo, leaves_hi = list(self.leaves_lo), list(self.leaves_hi)
        unverified_vol, sup_hi, queued = self.unverified_vol, self.sup_hi, self.queue.queued
        if len(queued):
            unverified_vol += float((queued.hi - queued.lo).prod(-1).sum())
            leaves_lo.append(queued.lo)
            leaves_hi.append(queued.hi)
            sup_hi = math.inf
        left_lo = torch.cat(leaves_lo) if leaves_lo else torch.empty(0, n, dtype=F64)
        left_hi = torch.cat(leaves_hi) if leaves_hi else torch.empty(0, n, dtype=F64)
        partition = self.tree.finish() if left_lo.shape[0] == 0 or keep_partition else None
        stopped = self.stopped
        if left_lo.shape[0] == 0 and bool((partition.verdict == OPEN).any()):
            # nothing queued, yet a leaf of the tree was never decided: the state the search went on from was not
            # the one it left (never a verified proof)
            undecided = partition.verdict == OPEN
            blo, bhi = partition.boxes(*box_grid(self.region.lo, self.region.hi, self.tree.grid))
            left_lo, left_hi = blo[undecided], bhi[undecided]
            unverified_vol += float((left_hi - left_lo).prod(-1).sum())
            sup_hi, stopped = math.inf, "leaves of its tree were left undecided"
        if self.cex is not None:
            status = Status.VIOLATED
        elif left_lo.shape[0] == 0:
            status = Status.VERIFIED
        else:
            status = Status.UNKNOWN
        fraction = max(0.0, min(1.0, 1.0 - unverified_vol / self.volume)) if self.volume > 0 else 1.0
        if status == Status.VERIFIED:
            fraction = 1.0
        boxes = [{"lo": system.to_user(a[None])[0].tolist(), "hi": system.to_user(b[None])[0].tolist()}
                 for a, b in zip(left_lo[:keep_boxes], left_hi[:keep_boxes])]
        result = ConditionProof(
            condition=self.condition.label, status=status, verified_fraction=fraction, delta=float(self.region.delta),
            boxes_processed=self.processed, boxes_verified=self.verified_count, time_s=self.elapsed,
            n_unverified=int(left_lo.shape[0]), unverified_boxes=boxes, n_counterexample_boxes=self.n_cex_boxes,
            sup_bounds=[self.sup_lo, sup_hi], stopped=stopped, level=self.level,
            resumed_boxes=self.resumed or None)
        if status == Status.VERIFIED or keep_partition:
            result.partition = partition
        if self.cex is not None:
            z = self.cex[1]
            result.counterexample_value = self.cex[0]
            result.counterexample_value_float32 = float(self.loop.exact(self.condition, z[None], torch.float32)[0])
            result.counterexample_local = z.tolist()
            result.counterexample = system.to_user(z[None])[0].tolist()
        return result


# =========================================================================== suprema
@dataclass
class SearchInfo:
    """How a :func:`maximize` search went: boxes bounded, seconds, why it stopped (``finished``, ``time limit`` or
    ``box budget``) and ``attained_at (Q, n)``, where each component's lower bound was found (None: no centre
    accepted)."""

    boxes_processed: int
    time_s: float
    stopped: str
    attained_at: Tensor | None


def maximize(objective: Callable, domain: Domain, budget: Budget, *, rel_tol: float = 1e-3, abs_tol: float = 1e-9,
             tree: PartitionRecorder | None = None, leaf_bound: Callable | None = None,
             label: str | None = None) -> tuple[Tensor, Tensor, SearchInfo]:
    """Bounds ``lower <= sup <= upper`` (each ``(Q,)``) of every component of ``objective`` over the set ``domain``
    (its starting boxes, and the parts of them it ``meets``).

    The upper bound is sound over the boxes (kept by ``domain.meets``); the lower bound comes from box centres
    the domain ``contains`` (points of the set). Boxes that may still raise some component's supremum
    by more than the tolerance are split, widest side first, until the budget's time or boxes or minimum size.
    ``budget.enclosure``: as for :func:`verify_condition` (None: by the boxes' dimension). ``tree``: records the
    boxes (the domain's starting boxes are then its grid's cells, in order): those ``meets`` drops as inside the ball,
    the splits, and every other leaf as proved with ``leaf_bound(upper (L, Q)) -> (L,)`` of its components' upper
    bounds. The third result (:class:`SearchInfo`) says how the search went and holds ``attained_at`` ``(Q, n)``: the
    centre at which each component's lower bound was found (None where no centre was accepted). ``label``: what a
    progress line of its boxes calls the search (where ``budget.compute.progress``; None: none).
    """
    enclosure = budget.enclosure_for(domain.lo.shape[-1])
    start = time.perf_counter()
    rule = _Suprema(domain, budget.min_width, rel_tol, abs_tol, tree, leaf_bound)
    bar = show_progress(int(budget.boxes), f"{label}: boxes", budget.compute.progress and label is not None)
    try:
        outcome = branch_and_bound(rule.queue, in_process(lambda b: box_bounds(objective, b.lo, b.hi, enclosure)),
                                   rule.sort, Stopping(int(budget.boxes), budget.seconds), Taking(int(budget.batch)),
                                   bar=bar)
    finally:
        bar.close()
    closed, best, left = rule.closed, rule.best, rule.queue.queued
    if len(left):
        if len(left) <= 4 * budget.batch:
            leftover = box_bounds(objective, left.lo, left.hi, enclosure)[1]
        else:  # too many to bound again in time: their parents' bounds hold for them (None: never split, none known)
            leftover = left.known
        rest = leftover.amax(0) if leftover is not None else \
            torch.full_like(closed if closed is not None else best, torch.inf)
        if tree is not None and leftover is not None:
            tree.proved(left.ids, leaf_bound(leftover))
        closed = rest if closed is None else torch.maximum(closed, rest)
    if closed is None:
        raise ValueError("the set to maximise over is empty")
    if best is None:
        best = torch.full_like(closed, -torch.inf)
    return best, closed, SearchInfo(outcome.taken, time.perf_counter() - start, outcome.stopped, rule.best_at)


class _Suprema:
    """The rule of :func:`maximize` for a batch's bounds: the best lower bounds at the centres the domain contains, the
    upper bounds of the boxes closed (no longer able to raise a supremum by more than the tolerance), the rest split
    with their bound inherited (``known``)."""

    def __init__(self, domain: Domain, min_width: float, rel_tol: float, abs_tol: float,
                 tree: PartitionRecorder | None, leaf_bound: Callable | None) -> None:
        self.domain, self.min_width, self.rel_tol, self.abs_tol = domain, min_width, rel_tol, abs_tol
        self.tree, self.leaf_bound = tree, leaf_bound
        self.closed: Tensor | None = None
        self.best: Tensor | None = None
        self.best_at: Tensor | None = None
        ids = tree.roots if tree is not None else torch.zeros(domain.lo.shape[0], dtype=torch.int64)
        self.queue = DomainQueue(self._kept(Boxes(domain.lo, domain.hi, ids)))  # known (B, Q), once one is split

    def _kept(self, boxes: Boxes) -> Boxes:
        """The boxes that meet the domain (those that do not are recorded as inside the ball)."""
        if self.domain.meets is None:
            return boxes
        keep = self.domain.meets(boxes.lo, boxes.hi)
        if self.tree is not None:
            self.tree.inside_ball(boxes.ids[~keep])
        return boxes.select(keep)

    def sort(self, taken: Boxes, bounds: tuple) -> None:
        clo, chi, cids, scale = taken.lo, taken.hi, taken.ids, self.domain.scale
        _, ub, at = bounds
        centre = (clo + chi) / 2
        good = self.domain.points_in(centre)
        if good.any():
            cand, where = at.lo[good].max(0)
            found = centre[good][where]  # (Q, n): where each component's new value was attained
            better = torch.ones_like(cand, dtype=torch.bool) if self.best is None else cand > self.best
            self.best_at = found if self.best_at is None else torch.where(better[:, None], found, self.best_at)
            self.best = cand if self.best is None else torch.maximum(self.best, cand)
        ref = self.best if self.best is not None else torch.full_like(ub[0], -torch.inf)
        # no centre accepted yet (ref = -inf): every box that may hold one is split, not closed at its first bound
        tol = torch.where(ref.isfinite(), torch.clamp(self.rel_tol * ref.abs(), min=self.abs_tol), self.abs_tol)
        refine = (ub > ref + tol).any(-1) & (((chi - clo) / scale).amax(-1) >= self.min_width)
        done = ~refine
        if done.any():
            cand = ub[done].amax(0)
            self.closed = cand if self.closed is None else torch.maximum(self.closed, cand)
            if self.tree is not None:
                self.tree.proved(cids[done], self.leaf_bound(ub[done]))
        if refine.any():
            nlo, nhi = split(clo[refine], chi[refine], scale)
            inherited = ub[refine].repeat(2, 1)  # split() returns the lower halves, then the upper halves
            nids = (self.tree.split(cids[refine], chi[refine], nhi) if self.tree is not None else
                    nlo.new_zeros(nlo.shape[0], dtype=torch.int64))
            self.queue.push(self._kept(Boxes(nlo, nhi, nids, inherited)))
        return None


def uniform_margin(loop: ClosedLoop, condition: DRUniform, region: Region, budget: Budget = Budget(seconds=3.0), *,
                   rel_tol: float = 1e-3, keep_partition: bool = False) -> UniformMargin:
    """Bounds of the uniform DR condition's left side over X_delta (``eq: dr_clf_constraint_relaxed``), see
    :class:`~drlyap.verification.results.UniformMargin`. ``keep_partition``: a verified margin keeps the boxes it was
    bounded on (:class:`~drlyap.verification.partition.Partition`, each leaf's bound the margin of its own
    components' upper bounds: at most the whole margin), for a certificate that :mod:`drlyap.checker` re-checks."""
    delta, coef = region.delta, condition.r / condition.eps
    grid = default_grid(region.n)
    lo, hi = box_grid(region.lo, region.hi, grid)
    enclosure = budget.enclosure_for(region.n)
    tree = PartitionRecorder(grid, lo.shape[0], enclosure) if keep_partition else None

    def margin_up(suprema: Tensor) -> Tensor:
        return round_up(condition.margin(suprema), 64 * EPS, suprema.abs().amax(-1) * (1 + coef))

    lower, upper, info = maximize(
        condition_objective(loop, condition),
        Domain(lo, hi, region.scale, lambda a, b: ~inside_ball(a, b, delta), region.in_region), budget,
        rel_tol=rel_tol, tree=tree, leaf_bound=margin_up, label="proof of the uniform margin")
    m_up = float(margin_up(upper))
    m_lo = float(round_down(condition.margin(lower), 64 * EPS, lower.abs().amax() * (1 + coef)))
    status = Status.VERIFIED if m_up <= 0 else (Status.VIOLATED if m_lo > 0 else Status.UNKNOWN)
    return UniformMargin(condition="DR uniform", status=status, margin_upper=m_up, margin_lower=m_lo,
                         lipschitz_sup=[float(lower[0]), float(upper[0])],
                         h_sup=[[float(a), float(b)] for a, b in zip(lower[1:], upper[1:])],
                         lipschitz_term=[coef * float(lower[0]), coef * float(upper[0])], delta=float(delta),
                         boxes_processed=info.boxes_processed, time_s=info.time_s, stopped=info.stopped,
                         partition=tree.finish() if tree is not None and status == Status.VERIFIED else None,
                         attained_at=None if info.attained_at is None else info.attained_at.tolist())


