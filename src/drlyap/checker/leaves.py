"""The checker's proof of a partition's leaves (:mod:`drlyap.checker.check`): each leaf by the checker's second-order
forms (where the DR norm's own form does not prove it, again with that norm as the interval norm of its vector's
ranges), else by the tighter of the interval bound and the mean-value form; where neither bound is ``<= 0``, bisected
along its widest side up to ``refine`` times, every piece to be proved. Leaves go in chunks of :data:`LEAF_CHUNK`, here
or on workers (:mod:`drlyap.parallel`), with a budget of pieces shared between them.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from drlyap.checker.affine import Af
from drlyap.checker.arith import F64, Iv
from drlyap.checker.levels import widest_split
from drlyap.checker.model import Residual, centre_lower, form_upper, upper_bounds, value_lower
from drlyap.compute import Compute
from drlyap.parallel import check_device, map_chunks
from drlyap.progress import progress as show_progress


def _by_forms(residual: Residual, lo: Tensor, hi: Tensor, level: float | None) -> Tensor:
    """``(B,)``: boxes proved by the second-order forms of the residual and V, together; where the DR norm's own
    form does not prove a box, the interval norm is tried in its place (either is an enclosure)."""
    comps, value = residual.terms(Af.seed(lo, hi))
    good = form_upper(residual, comps, value, level) <= 0
    if level is not None:
        good = good | (value.interval(dual=True).lo > level)
    rest = (~good).nonzero().squeeze(-1)
    if rest.numel() and residual.has_norm:
        comps, value = residual.terms(Af.seed(lo[rest], hi[rest]), flat_norm=True)
        good[rest] = form_upper(residual, comps, value, level) <= 0
    return good


def _by_mean_value(residual: Residual, lo: Tensor, hi: Tensor, level: float | None) -> Tensor:
    """``(B,)``: boxes proved by the interval and mean-value bounds (with a level, V's lower bound is asked only of
    the boxes the residual's bound leaves)."""
    good = upper_bounds(residual, lo, hi) <= 0
    rest = (~good).nonzero().squeeze(-1)
    if level is not None and rest.numel():
        good[rest] = value_lower(residual.pair, lo[rest], hi[rest]) > level
    return good


def _holds(residual: Residual, lo: Tensor, hi: Tensor, level: float | None, batch: int,
           above: Tensor, cheap_first: bool = False) -> tuple[Tensor, Tensor]:
    """``(B,)``: boxes on which the residual is proved ``<= 0`` (or, with a level, V is proved ``> level``), and lower
    bounds of the residual at the centres ``(B,)`` (``-inf`` where V may exceed the level there). ``above (B,)``:
    where to try V alone first; ``cheap_first``: the mean-value bounds before the forms (the other order otherwise;
    each box not proved by the first is tried by the second)."""
    steps = (_by_mean_value, _by_forms) if cheap_first else (_by_forms, _by_mean_value)
    ok, low = [torch.zeros(0, dtype=torch.bool, device=lo.device)], [torch.zeros(0, dtype=F64, device=lo.device)]
    for i in range(0, lo.shape[0], batch):
        a, b = lo[i:i + batch], hi[i:i + batch]
        good = torch.zeros(a.shape[0], dtype=torch.bool, device=a.device)
        first = (above[i:i + batch] & (level is not None)).nonzero().squeeze(-1)
        if first.numel():  # V alone: above the level, nothing is claimed
            good[first] = residual.pair.value(Af.seed(a[first], b[first])).interval(dual=True).lo > level
        for step in steps:
            rest = (~good).nonzero().squeeze(-1)
            if rest.numel():
                good[rest] = step(residual, a[rest], b[rest], level)
        centre_low = centre_lower(residual, a, b)
        if level is not None:
            v_centre = residual.pair.value_and_grad(Iv.point((a + b) / 2))[0].hi
            centre_low = torch.where(v_centre <= level, centre_low, -math.inf)
        ok.append(good)
        low.append(centre_low)
    return torch.cat(ok), torch.cat(low)


MIN_PIECES = 4096  # pieces the refinement of prove_boxes may always bound, however few the boxes


def prove_boxes(job: LeafJob, lo: Tensor, hi: Tensor, above: Tensor | None = None, budget: int | None = None,
                batch: int = 4096) -> tuple[Tensor, Tensor, int, int]:
    """Re-prove ``job``'s residual ``<= 0`` on boxes ``(B, n)`` (with its ``level``: at the boxes' states where
    ``V <= level``): ``ok (B,)``, lower bounds of the residual at the centres ``(B,)``, and how many boxes needed
    bisection and into how many pieces in all. ``above (B,)``: boxes to try ``V > level`` on first (the certificate's
    word, a hint only: each box is proved one way or the other whatever it says); the job's ``cheap_first``: try the
    mean-value bounds before the second-order forms (an order, not a shortcut: see :func:`_holds`).

    A box the checker's bounds do not prove is bisected (along its widest side relative to the job's ``scale``), the
    job's ``refine`` times at most, and at most as many pieces are bounded in all as there are boxes (at least
    :data:`MIN_PIECES`; ``budget``: that many instead): a true certificate whose few boxes the verifier's tighter
    bounds proved is confirmed, and a false one costs at most about twice its boxes."""
    residual, level, cheap_first = job.residual, job.level, job.cheap_first
    above = torch.zeros(lo.shape[0], dtype=torch.bool, device=lo.device) if above is None else above
    order = torch.argsort(above.to(torch.int8), stable=True)  # the hinted boxes together, so that batches share a path
    ok, centre_low = torch.empty_like(above), torch.empty(lo.shape[0], dtype=F64, device=lo.device)
    ok[order], centre_low[order] = _holds(residual, lo[order], hi[order], level, batch, above[order],
                                          cheap_first)
    todo = (~ok).nonzero().squeeze(-1)
    refined, pieces = int(todo.numel()), 0
    owner, plo, phi = todo, lo[todo], hi[todo]
    budget = max(MIN_PIECES, int(lo.shape[0])) if budget is None else budget
    for _ in range(job.refine if todo.numel() else 0):
        if pieces + 2 * plo.shape[0] > budget:
            break
        plo, phi = widest_split(plo, phi, job.scale)
        owner = owner.repeat(2)
        pieces += int(plo.shape[0])
        failed = ~_holds(residual, plo, phi, level, batch, above[owner], cheap_first)[0]
        plo, phi, owner = plo[failed], phi[failed], owner[failed]
        if not owner.numel():
            break
    ok[todo] = True
    ok[owner.unique()] = False
    return ok, centre_low, refined, pieces


class LeafJob:
    """:func:`prove_boxes` as a job for workers (:mod:`drlyap.parallel`) or a device: on leaves ``lo, hi (B, n)``, ``above
    (B,)`` and the pieces allowed per leaf, ``ok``, ``centre_low`` ``(B,)``, ``refined``, ``pieces`` ``(1,)`` on the CPU."""

    def __init__(self, residual: Residual, scale: Tensor, refine: int, level: float | None, cheap_first: bool,
                 device: str = "cpu") -> None:
        self.residual, self.scale, self.refine, self.level, self.cheap_first = residual, scale, refine, level, cheap_first
        self.device = device

    def on(self, device: str) -> LeafJob:
        """The same job with the pair and the claim's constants on ``device`` (float64 there too)."""
        if device == self.device:
            return self
        check_device(device)
        return LeafJob(self.residual.to(device), self.scale.to(device), self.refine, self.level, self.cheap_first,
                       device)

    def __call__(self, lo: Tensor, hi: Tensor, above: Tensor, allowance: Tensor | None = None) -> dict:
        device = torch.device(self.device)
        budget = None if allowance is None else max(MIN_PIECES, int(allowance.sum()))
        ok, low, refined, pieces = prove_boxes(self, lo.to(device), hi.to(device), above.to(device), budget)
        return {"ok": ok.cpu(), "centre_low": low.cpu(), "refined": torch.tensor([refined]),
                "pieces": torch.tensor([pieces])}


REFINE = 30
"""Times the checker may bisect a leaf its own bounds do not prove, by default: in 6 states 12 halved each side only
twice, and the quadrotor's default region certificate at its test shift kept 2 of 302,883 leaves unproved at depth 12
(another pair's, 12 of 318,528 at depth 20) that depth 30 proves within the default pieces. The cost is capped by
the pieces a chunk may bound (:func:`prove_leaves`), not by the depth."""

LEAF_CHUNK = 16_384
"""Leaves bounded per job (each its own piece budget for bisection, :func:`prove_boxes`): the same chunks here and on
any number of workers, so the verdict never depends on where they are bounded."""


def prove_leaves(job: LeafJob, lo: Tensor, hi: Tensor, above: Tensor, compute: Compute = Compute(),
                 desc: str = "check: leaves", pieces_per_leaf: float = 1.0) -> tuple[Tensor, Tensor, int, int]:
    """:func:`prove_boxes` of ``job`` on every leaf in chunks of :data:`LEAF_CHUNK`, here or on ``compute``'s workers
    (two chunks each in flight); the same four results; progress as ``desc``. Each chunk may bound
    ``pieces_per_leaf`` pieces per leaf; the leaves a chunk's budget left unproved (hard leaves crowd into a few
    chunks) are tried once more with the pieces the first pass left, shared out by count: at most about ``1 +
    pieces_per_leaf`` times the leaves bounded in all, the same chunks on any number of workers."""
    if not (math.isfinite(pieces_per_leaf) and pieces_per_leaf >= 1):
        raise ValueError(f"pieces per leaf must be >= 1, got {pieces_per_leaf}")
    ok, low, refined, pieces = _prove_chunks(job, lo, hi, above, torch.full((len(lo),), pieces_per_leaf, dtype=F64),
                                             compute, desc)
    failed = (~ok).nonzero().squeeze(-1)
    spare = int(pieces_per_leaf * lo.shape[0]) - pieces
    if failed.numel() and spare > 2 * failed.numel():
        allowance = torch.full((failed.numel(),), spare / failed.numel(), dtype=F64)
        again, _, refined_again, pieces_again = _prove_chunks(job, lo[failed], hi[failed], above[failed], allowance,
                                                              compute, f"{desc} (again)")
        ok[failed[again]] = True
        refined, pieces = refined + refined_again, pieces + pieces_again
    return ok, low, refined, pieces


def _prove_chunks(job: LeafJob, lo: Tensor, hi: Tensor, above: Tensor, allowance: Tensor, compute: Compute,
                  desc: str) -> tuple[Tensor, Tensor, int, int]:
    """One pass of :func:`prove_leaves`, each chunk bisecting within the pieces its leaves are allowed."""
    if not lo.shape[0]:
        return torch.zeros(0, dtype=torch.bool), torch.zeros(0, dtype=F64), 0, 0
    chunks = list(zip(*(torch.split(a, LEAF_CHUNK) for a in (lo, hi, above, allowance))))
    bar = show_progress(int(lo.shape[0]), desc, compute.progress)
    parts = map_chunks(job, chunks, compute, bar.update)
    bar.close()
    out = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
    return out["ok"], out["centre_low"], int(out["refined"].sum()), int(out["pieces"].sum())


