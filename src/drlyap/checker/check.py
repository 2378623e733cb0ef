"""Re-check a certificate file box by box (``drlyap check RUN``), with the checker's own arithmetic.

What the checker takes on trust (its trust base): the float64 arithmetic of the machine with round-to-nearest, the
library functions ``sin cos tanh exp sqrt`` to within 8 ulps, torch's elementwise operations and matrix products as
used in :mod:`drlyap.checker.arith` and :mod:`drlyap.checker.affine` (whose results it pads outward), the backward
error bound of a Cholesky factorisation (the dual bound's semidefiniteness), numpy's reading of the arrays file, and the
system's dynamics function (the user's code, run on the checker's intervals). What it re-derives: every box (from the
state box, the starting grid and the splits; the file stores no coordinates, so the boxes cover the box by
construction), that every leaf is proved, that leaves said to lie in the delta-ball do, the sha256 of the weights and
of the system's description, and the residual of the claimed condition from V's and pi's weights (its own forward and
gradient code, not the library's networks).

A proved leaf is re-proved by the checker's second-order forms (:class:`~drlyap.checker.affine.Af`; where the DR
norm's own form does not prove it, again with that norm as the interval norm of its vector's ranges), and where they
do not prove it, by the tighter of the interval bound and the mean-value form (that one first where the header says
the proof used it); where neither bound is ``<= 0``, the leaf is bisected along its widest side up to ``refine``
times and every piece must be proved. A leaf whose recorded
bound lies below the residual at its centre is a false record and fails the check.

A claim on a sublevel set ``{V <= level}`` of X_delta is checked the same way, a box (or piece) counting as proved
where V is ``> level`` on it or the residual is ``<= 0`` at its states with ``V <= level`` (the S-procedure on the
second-order forms of the residual and V: ``R - lam (V - level) <= 0`` for one of a fixed list of ``lam >= 0``);
and ``V > level`` on the state box's faces is established by the checker's own bisection of the faces (it is not in
the file); a claim whose ``faces`` is ``"inward"`` (a set cut by the box, on the true model) has instead, on each face
box, V above the level or the outward component of every model's flow below 0 established the same way.

A ``roa-ball`` certificate (V's decrease inside the delta-ball) is checked on the ball's box: its ring of boxes as
above, and its cube around x* by :mod:`drlyap.checker.ball` (Vdot's Hessian over the cube, negative definite). The
decrease outside the ball it rests on must be strict: by a decay ``gamma ||z||``, or by ``alpha V`` with V > 0 there,
by V's form (drlyap's V) or, for an imported V, by the checker's own bisection of the box outside the ball.
An ``ellipsoid`` certificate is checked by :mod:`drlyap.checker.ellipsoid`; a claim with a ``core`` (V's region resting on
that ellipsoid) has leaves inside it, each of whose vertices the checker places in the ellipsoid
(:func:`~drlyap.checker.ellipsoid.inside_core`).

A ``band`` claim (decrease on ``c1 <= V <= c2`` of the whole box) is checked as a claim on ``{V <= c2}`` with the flow
entering on the faces, its leaves below the band by :mod:`drlyap.checker.band` (V < c1 by the checker's bisection),
about V as the files give it; the claim must state what its conclusion needs (``c1 > 0``, ``alpha > 0``).

A DR uniform claim is one inequality over all the leaves together (:mod:`drlyap.checker.uniform`): each component's
supremum is bounded over every leaf, and the margin made of those bounds must be ``<= 0``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from drlyap.checker.affine import Af
from drlyap.checker.arith import EPS, F64, Iv
from drlyap.checker.ball import ball_failures
from drlyap.checker.band import band_floor, below_failures, statement_failures
from drlyap.checker.ellipsoid import QuadraticPair, ellipsoid_failures, inside_core, read_core
from drlyap.checker.graphs import GraphPair
from drlyap.checker.levels import ball_below, faces_above, faces_inward, grid_cells, widest_split
from drlyap.checker.model import Pair, Residual, centre_lower, form_upper, upper_bounds, value_lower
from drlyap.checker.uniform import uniform_margin_bound
from drlyap.claims import claim_sentence, faces_rule
from drlyap.compute import Compute
from drlyap.parallel import check_device, pool_for
from drlyap.progress import progress as show_progress

INTERNAL, PROVED, INSIDE_BALL, ABOVE_LEVEL, INSIDE_CORE, BELOW_LEVEL = 0, 1, 2, 3, 5, 6


@dataclass
class CheckResult:
    """The outcome of re-checking one certificate: ``ok`` when every box holds and the boxes cover the region."""

    name: str
    ok: bool
    claim: str
    failures: list[str] = field(default_factory=list)
    boxes: int = 0
    proved: int = 0
    inside_ball: int = 0
    inside_core: int = 0
    below_band: int = 0
    """For a band claim: its leaves below the band, ``V < c1`` by the checker's bisection (counted in ``proved``)."""
    ball_max: float | None = None
    ball_boxes: int = 0
    refined: int = 0
    pieces: int = 0
    faces_min: float | None = None
    faces_boxes: int = 0
    positive_min: float | None = None
    """Where the decrease outside the ball is strict only where V > 0 (an imported V with ``alpha V``): V's smallest
    lower bound on the box outside the ball by the checker's bisection, over ``positive_boxes`` boxes."""
    positive_boxes: int = 0
    cube_bound: float | None = None
    """For V's second-order decrease near x* (``roa-ball``): ``lambda_max`` of the Hessian enclosure's centre plus its
    spread, the largest over the samples (< 0 proves the cube); for an ``ellipsoid``, the same of its Jacobian test's
    scaled matrices."""
    time_s: float = 0.0

    def to_dict(self) -> dict:
        return dict(self.__dict__)


class CertificateError(ValueError):
    """The certificate is inconsistent with itself or with the run (a structural failure, found before any bound)."""


def check_tree(arrays: dict[str, np.ndarray], cells: int, n: int, level: float | None, core: bool = False,
               band: bool = False) -> None:
    """Structural checks: roots are exactly the grid's cells, every other node names an earlier internal node as its
    parent, every internal node has exactly one lower and one upper half, every leaf has a verdict that proves it
    (above the level only with a ``level``, inside the core only with a ``core``, below the band only on a ``band``)."""
    parent, side = arrays["parent"].astype(np.int64), arrays["side"].astype(np.int64)
    axis, verdict = arrays["axis"].astype(np.int64), arrays["verdict"].astype(np.int64)
    size = parent.shape[0]
    if any(a.shape != (size,) for a in arrays.values()):
        raise CertificateError("the partition's arrays differ in length")
    if size < cells or (parent[:cells] != -1).any() or (parent[cells:] < 0).any():
        raise CertificateError(f"the partition does not start with the {cells} cells of its grid")
    ids = np.arange(size)
    if (parent[cells:] >= ids[cells:]).any():
        raise CertificateError("a node names a later node as its parent")
    internal = verdict == INTERNAL
    if (internal & ((axis < 0) | (axis >= n))).any() or (~internal & (axis != -1)).any():
        raise CertificateError("a split axis is missing or out of range")
    kids = parent[cells:]
    if not internal[kids].all():
        raise CertificateError("a node's parent is not a split node")
    if ((side[cells:] != 0) & (side[cells:] != 1)).any():
        raise CertificateError("a node is neither the lower nor the upper half of its parent")
    slots = np.bincount(kids * 2 + side[cells:], minlength=2 * size).reshape(size, 2)
    if (slots[internal] != 1).any() or (slots[~internal] != 0).any():
        raise CertificateError("a split node does not have exactly one lower and one upper half (a box is missing "
                               "or duplicated)")
    allowed = {PROVED, INSIDE_BALL} | ({ABOVE_LEVEL} if level is not None else set()) | (
        {INSIDE_CORE} if core else set()) | ({BELOW_LEVEL} if band and level is not None else set())
    leaves = verdict[~internal]
    bad = ~np.isin(leaves, sorted(allowed))
    if bad.any():
        raise CertificateError(f"{int(bad.sum())} leaves are not proved (verdict {int(leaves[bad][0])})")


def rebuild_boxes(lo: Tensor, hi: Tensor, grid: list[int], arrays: dict[str, np.ndarray]) -> tuple[Tensor, Tensor]:
    """Every node's box ``(N, n)``: the grid's cells, then each half from its parent (halved at the midpoint of the
    parent's split axis), generation by generation."""
    parent = torch.as_tensor(arrays["parent"].astype(np.int64))
    side = torch.as_tensor(arrays["side"].astype(np.int64))
    axis = torch.as_tensor(arrays["axis"].astype(np.int64))
    size, n = parent.shape[0], lo.shape[0]
    glo, ghi = grid_cells(lo, hi, grid)
    blo = torch.full((size, n), math.nan, dtype=F64)
    bhi = torch.full((size, n), math.nan, dtype=F64)
    cells = glo.shape[0]
    blo[:cells], bhi[:cells] = glo, ghi
    done = torch.zeros(size, dtype=torch.bool)
    done[:cells] = True
    while not bool(done.all()):
        ready = ~done & done[parent.clamp(min=0)]
        if not bool(ready.any()):
            raise CertificateError("the partition's tree is not connected")
        ids = ready.nonzero().squeeze(-1)
        p, ax, upper = parent[ids], axis[parent[ids]], side[ids] == 1
        plo, phi = blo[p], bhi[p]
        rows = torch.arange(ids.shape[0])
        mid = (plo[rows, ax] + phi[rows, ax]) / 2
        clo, chi = plo.clone(), phi.clone()
        clo[rows[upper], ax[upper]] = mid[upper]
        chi[rows[~upper], ax[~upper]] = mid[~upper]
        blo[ids], bhi[ids] = clo, chi
        done |= ready
    return blo, bhi


def inside_open_ball(lo: Tensor, hi: Tensor, delta: float) -> Tensor:
    """``(B,)``: boxes whose every point has ``||z|| < delta`` (sound: the far corner's squared distance, rounded up,
    below ``delta^2`` rounded down)."""
    far = Iv(torch.maximum(lo.abs(), hi.abs()), torch.maximum(lo.abs(), hi.abs())).square().sum(-1).hi
    d2 = (Iv.point(delta) * Iv.point(delta)).lo
    return far < d2


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


def prove_boxes(residual: Residual, lo: Tensor, hi: Tensor, scale: Tensor, refine: int, level: float | None = None,
                batch: int = 4096, above: Tensor | None = None, cheap_first: bool = False,
                budget: int | None = None) -> tuple[Tensor, Tensor, int, int]:
    """Re-prove ``residual <= 0`` on boxes ``(B, n)`` (with ``level``: at the boxes' states where ``V <= level``):
    ``ok (B,)``, lower bounds of the residual at the centres ``(B,)``, and how many boxes needed bisection and into
    how many pieces in all. ``above (B,)``: boxes to try ``V > level`` on first (the certificate's word, a hint
    only: each box is proved one way or the other whatever it says); ``cheap_first``: try the mean-value bounds
    before the second-order forms (an order, not a shortcut: see :func:`_holds`).

    A box the checker's bounds do not prove is bisected, ``refine`` times at most, and at most as many pieces are
    bounded in all as there are boxes (at least :data:`MIN_PIECES`; ``budget``: that many instead): a true certificate
    whose few boxes the verifier's tighter bounds proved is confirmed, and a false one costs at most about twice its
    boxes."""
    above = torch.zeros(lo.shape[0], dtype=torch.bool, device=lo.device) if above is None else above
    order = torch.argsort(above.to(torch.int8), stable=True)  # the hinted boxes together, so that batches share a path
    ok, centre_low = torch.empty_like(above), torch.empty(lo.shape[0], dtype=F64, device=lo.device)
    ok[order], centre_low[order] = _holds(residual, lo[order], hi[order], level, batch, above[order],
                                          cheap_first)
    todo = (~ok).nonzero().squeeze(-1)
    refined, pieces = int(todo.numel()), 0
    owner, plo, phi = todo, lo[todo], hi[todo]
    budget = max(MIN_PIECES, int(lo.shape[0])) if budget is None else budget
    for _ in range(refine if todo.numel() else 0):
        if pieces + 2 * plo.shape[0] > budget:
            break
        plo, phi = widest_split(plo, phi, scale)
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
        ok, low, refined, pieces = prove_boxes(self.residual, lo.to(device), hi.to(device), self.scale, self.refine,
                                               self.level, above=above.to(device), cheap_first=self.cheap_first,
                                               budget=budget)
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
    pool = pool_for(compute)
    starts = list(range(0, lo.shape[0], LEAF_CHUNK))
    bar = show_progress(int(lo.shape[0]), desc, compute.progress)
    parts, flight = [], []
    local = job.on(compute.device) if pool is None else None
    for i in starts:
        part = (lo[i:i + LEAF_CHUNK], hi[i:i + LEAF_CHUNK], above[i:i + LEAF_CHUNK], allowance[i:i + LEAF_CHUNK])
        if pool is None:
            parts.append(local(*part))
            bar.update(int(part[0].shape[0]))
            continue
        flight.append((pool.submit(job, *part, chunk=LEAF_CHUNK), int(part[0].shape[0])))  # whole, as here
        if len(flight) > 2 * pool.workers:
            future, count = flight.pop(0)
            parts.append(future.result())
            bar.update(count)
    for future, count in flight:
        parts.append(future.result())
        bar.update(count)
    bar.close()
    if not parts:
        return torch.zeros(0, dtype=torch.bool), torch.zeros(0, dtype=F64), 0, 0
    out = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
    return out["ok"], out["centre_low"], int(out["refined"].sum()), int(out["pieces"].sum())


def _pair(weights: dict, header: dict, n: int) -> Pair | GraphPair:
    """The checker's V and pi from the run's weights: an imported pair's graphs, or drlyap's networks (with the
    header's ``alpha_hat``)."""
    if "graphs" in weights:
        return GraphPair(weights["graphs"], weights["tensors"], n)
    return Pair(weights, float(header["networks"]["alpha_hat"]), n)


def _practical_failures(out: CheckResult, claim: dict, pair, lo: Tensor, hi: Tensor) -> list[str]:
    """What keeps a ``practical`` claim from following: its level ``c0`` (``claim["practical"]["level"]``) below the
    set's level ``c``, and ``V <= c0`` on the open delta-ball (``region.ball_of``; ``[lo, hi]`` its box) by the
    checker's bisection (:func:`~drlyap.checker.levels.ball_below`, recorded in ``out``)."""
    c0, c = float(claim["practical"]["level"]), float(claim["region"]["level"])
    if not (math.isfinite(c0) and c0 < c):
        return [f"the level trajectories end up in ({c0:g}) is not below the set's ({c:g})"]
    holds, out.ball_max, out.ball_boxes = ball_below(pair, lo, hi, float(claim["region"]["ball_of"]), c0)
    if holds:
        return []
    return [f"V <= {c0:g} is not established on the ball (V's upper bound there {out.ball_max:.6g}, {out.ball_boxes} "
            "boxes)"]


def _claim_box(region: dict, system) -> tuple[Tensor, Tensor]:
    """The claim's box ``(lo, hi)`` (local coordinates), which must be the system's state box, or with ``ball_of`` the
    delta-ball's box inside it; a CertificateError where it is not."""
    lo, hi = (torch.as_tensor(region[k], dtype=F64) for k in ("box_lo", "box_hi"))
    box_lo, box_hi = (torch.as_tensor(b, dtype=F64) - torch.as_tensor(system.equilibrium, dtype=F64)
                      for b in system.state_box)
    if region.get("ball_of") is not None:  # the box of the delta-ball inside the state box (roa-ball)
        ball = float(region["ball_of"])
        box_lo, box_hi = torch.maximum(box_lo, torch.full_like(box_lo, -ball)), \
            torch.minimum(box_hi, torch.full_like(box_hi, ball))
    if not (torch.equal(lo, box_lo) and torch.equal(hi, box_hi)):
        raise CertificateError("the certificate's state box is not the system's" + (
            "" if region.get("ball_of") is None else " inside the delta-ball's box"))
    return lo, hi


def _placed_leaves(out: CheckResult, verdict: Tensor, lo: Tensor, hi: Tensor, delta: float,
                   core: tuple[Tensor, float] | None) -> None:
    """Whether the leaves said to lie in the open delta-ball, and in the core ``(P, c)`` where there is one, do (boxes
    ``[lo, hi]`` of every node, ``verdict`` per node): counts and failures into ``out``."""
    ball = (verdict == INSIDE_BALL).nonzero().squeeze(-1)
    inside = inside_open_ball(lo[ball], hi[ball], delta)
    out.inside_ball = int(inside.sum())
    if not bool(inside.all()):
        out.failures.append(f"{int((~inside).sum())} boxes said to lie in the open ball ||z|| < {delta:g} do not")
    if core is not None:
        inner = (verdict == INSIDE_CORE).nonzero().squeeze(-1)
        held = inside_core(*core, lo[inner], hi[inner])
        out.inside_core = int(held.sum())
        if not bool(held.all()):
            out.failures.append(f"{int((~held).sum())} boxes said to lie in the core {{z'Pz <= {core[1]:g}}} do not")


def check_certificate(run_dir: str | Path, name: str, header: dict, arrays: dict[str, np.ndarray], system,
                      weights: dict, weights_sha256: str, system_sha256: str, refine: int = REFINE,
                      compute: Compute = Compute(), pieces_per_leaf: float = 1.0) -> CheckResult:
    """Re-check one certificate of ``run_dir`` against the run's own weights (``weights``, from the file with
    ``weights_sha256``) and system (``system_sha256``); leaves bounded as :func:`prove_leaves`, where ``compute`` says."""
    start = time.perf_counter()
    claim = header.get("claim") or {}
    out = CheckResult(name=name, ok=False, claim=claim_sentence(claim))
    try:
        if header["networks"]["weights_sha256"] != weights_sha256:
            raise CertificateError("weights.pt is not the file the certificate was proved for (sha256 differs)")
        if header["system"]["description_sha256"] != system_sha256:
            raise CertificateError(f"the system {system.name!r} is not the one the certificate was proved for "
                                   "(its description's sha256 differs)")
        region = claim["region"]
        lo, hi = _claim_box(region, system)
        delta, level = float(region["delta"]), region.get("level")
        level = None if level is None else float(level)
        pair = _pair(weights, header, system.n)
        floor = band_floor(claim)
        if floor is not None:  # about V as the files give it (an imported V is not pinned at x* for it)
            out.failures += statement_failures(claim)
            pair = pair.as_given() if isinstance(pair, GraphPair) else pair
        elif not getattr(pair, "pinned", True):
            raise CertificateError("V is not pinned at x* (graphs.json: imported as given): only a band claim is "
                                   "checked for it")
        if claim.get("ellipsoid") is not None:  # the closed loop's own W = z'Pz: its claims are about W, not V
            pair = QuadraticPair(pair, torch.as_tensor(claim["ellipsoid"]["P"], dtype=F64))
        residual = Residual(claim["condition"], pair, system)
        core = None if claim.get("core") is None else read_core(claim, system.n)
        if claim.get("practical") is not None:  # V's bound on the ball; the decrease outside it is outer's
            out.failures += _practical_failures(out, claim, pair, lo, hi)
            out.ok, out.time_s = not out.failures, time.perf_counter() - start
            return out
        if claim.get("cube") is not None or claim.get("ellipsoid") is not None:  # a decrease near x* (roa-ball, ellipsoid)
            ring = header["partition"] is not None
            failures, out.cube_bound = ball_failures(claim, pair, system, lo, hi, delta, ring) \
                if claim.get("cube") is not None else ellipsoid_failures(claim, residual, lo, hi, delta, ring)
            out.failures += failures
            if not ring:  # the cube covers the ball, or the ellipsoid lies in its box: no ring to prove
                out.ok, out.time_s = not out.failures, time.perf_counter() - start
                return out
        grid = [int(k) for k in header["partition"]["grid"]]
        if len(grid) != system.n or min(grid) < 1:
            raise CertificateError(f"the starting grid {grid} does not fit {system.n} states")
        check_tree(arrays, int(np.prod(grid)), system.n, level, core is not None, floor is not None)
    except (CertificateError, KeyError, TypeError, ValueError) as err:
        out.failures.append(str(err) if not isinstance(err, KeyError) else f"the header lacks {err}")
        out.time_s = time.perf_counter() - start
        return out
    blo, bhi = rebuild_boxes(lo, hi, grid, arrays)
    verdict = torch.as_tensor(arrays["verdict"].astype(np.int64))
    bound = torch.as_tensor(arrays["bound"].astype(np.float64))
    out.boxes = int((verdict != INTERNAL).sum())
    _placed_leaves(out, verdict, blo, bhi, delta, core)
    proved = ((verdict == PROVED) | (verdict == ABOVE_LEVEL)).nonzero().squeeze(-1)
    if residual.name == "uniform":
        _check_uniform(out, residual, blo[proved], bhi[proved], bound[proved], hi - lo, refine)
        out.ok, out.time_s = not out.failures, time.perf_counter() - start
        return out
    cheap_first = header["partition"].get("enclosure") in ("interval", "mean-value")  # an order, as for ``above``
    job = LeafJob(residual, hi - lo, refine, level, cheap_first)
    ok, centre_low, out.refined, out.pieces = prove_leaves(job, blo[proved], bhi[proved], verdict[proved] == ABOVE_LEVEL,
                                                           compute, f"check ({name}): leaves", pieces_per_leaf)
    out.proved = int(ok.sum())
    if not bool(ok.all()):
        first = proved[~ok][0]
        why = ("" if header["partition"].get("enclosure") != "affine" else
               "; the verifier bounded them with its own second-order forms, and this checker's do not reach its "
               "bounds there: the certificate is not confirmed, which does not show it false")
        out.failures.append(f"{int((~ok).sum())} of {proved.numel()} boxes are not proved by the checker's bounds "
                            f"(first: node {int(first)}, [{_fmt(blo[first])}] to [{_fmt(bhi[first])}]){why}")
    kind = verdict[proved]
    false = (kind == PROVED) & (bound[proved] < centre_low - 4 * EPS * centre_low.abs())
    if level is not None:  # V's recorded lower bound must not exceed V at the box's centre
        above = kind == ABOVE_LEVEL
        v_centre = pair.value_and_grad(Iv.point((blo[proved] + bhi[proved]) / 2))[0].lo
        false = false | (above & (bound[proved] > v_centre + 4 * EPS * v_centre.abs()))
        holds = True
        faces = faces_rule(claim)
        if faces not in ("above", "inward") or (faces == "inward" and (residual.model != "true"
                                                                       or claim.get("ellipsoid") is not None)):
            holds = False
            out.failures.append(f"the claim's rule for the box's faces {faces!r} is not one the checker takes "
                                "('above'; 'inward' for V's sets on the true model)")
        elif region.get("ball_of") is None and faces == "inward":
            holds, out.faces_min, out.faces_boxes = faces_inward(residual, lo, hi, level, max_boxes=1_000_000)
            if not holds:
                out.failures.append(f"the flow entering the box wherever V <= {level:g} on its faces is not established "
                                    f"({out.faces_boxes} face boxes)")
        elif region.get("ball_of") is None:  # inside the delta-ball the set's boundary is the outer proof's
            holds, out.faces_min, out.faces_boxes = faces_above(pair, lo, hi, level)
            if not holds:
                what = "W" if claim.get("ellipsoid") is not None else "V"
                out.failures.append(f"{what} > {level:g} is not established on the box's faces ({what}'s lower bound "
                                    f"there {out.faces_min:.6g}, {out.faces_boxes} face boxes)")
    if floor is not None:  # a band's leaves below it: V < c1 there, by the checker's bisection
        below = (verdict == BELOW_LEVEL).nonzero().squeeze(-1)
        failures, spent = below_failures(pair, blo[below], bhi[below], bound[below], floor, hi - lo)
        out.failures, out.pieces = out.failures + failures, out.pieces + spent
        out.below_band = int(below.numel()) if not failures else 0
        out.proved += out.below_band
    if bool(false.any()):
        first = proved[false][0]
        out.failures.append(f"{int(false.sum())} recorded bounds lie below the residual at their box's centre (first: "
                            f"node {int(first)}, recorded {float(bound[first]):.6g})")
    out.ok = not out.failures
    out.time_s = time.perf_counter() - start
    return out


def _check_uniform(out: CheckResult, residual: Residual, lo: Tensor, hi: Tensor, bound: Tensor, scale: Tensor,
                   refine: int) -> None:
    """The DR uniform claim on the leaves ``[lo, hi] (B, n)`` (recorded bounds ``bound (B,)``: each leaf's own
    margin, which may not lie below the margin at its centre): the margin's bound from every leaf's components
    (:func:`~drlyap.checker.uniform.uniform_margin_bound`) must be ``<= 0``; its outcome goes into ``out``."""
    margin, suprema, out.refined, out.pieces = uniform_margin_bound(residual, lo, hi, scale, refine,
                                                                    max(MIN_PIECES, int(lo.shape[0])))
    out.proved = int(lo.shape[0]) if margin <= 0 else 0
    if margin > 0:
        out.failures.append(f"the checker's bound of the uniform margin over the {lo.shape[0]} leaves is {margin:.6g} "
                            f"> 0 (suprema of ||W^T grad V||, Vdot_j + decay: {_fmt(suprema)})")
    centre_low = centre_lower(residual, lo, hi)
    false = bound < centre_low - 4 * EPS * centre_low.abs()
    if bool(false.any()):
        out.failures.append(f"{int(false.sum())} recorded bounds lie below the margin at their box's centre")


def _fmt(v: Tensor) -> str:
    return ", ".join(f"{float(a):.6g}" for a in v)
