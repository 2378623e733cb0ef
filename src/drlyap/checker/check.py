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

import numpy as np
import torch
from torch import Tensor

from drlyap.checker.arith import EPS, F64, Iv
from drlyap.checker.ball import ball_failures
from drlyap.checker.band import band_floor, below_failures, statement_failures
from drlyap.checker.ellipsoid import QuadraticPair, ellipsoid_failures, inside_core, read_core
from drlyap.checker.graphs import GraphPair
from drlyap.checker.leaves import MIN_PIECES, REFINE, LeafJob, prove_leaves
from drlyap.checker.levels import ball_below, faces_above, faces_inward, grid_cells
from drlyap.checker.model import Pair, Residual, centre_lower
from drlyap.checker.uniform import uniform_margin_bound
from drlyap.claims import KINDS_OF, UNREADABLE, claim_kind, claim_sentence, faces_rule
from drlyap.compute import Compute

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
        if not (math.isfinite(ball) and ball > 0):
            raise CertificateError(f"the claim's ball (ball_of = {ball}) is not a finite radius > 0")
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


@dataclass
class _Reading:
    """A certificate as the checker reads it before any bound: its ``claim``, the region's box ``lo, hi`` (local
    coordinates), ``delta``, ``level`` (None: X_delta), a band's ``floor``, the ``pair`` the claim is about (V and pi,
    or W = z'Pz for an ``ellipsoid``), the claim's ``residual`` and a ``core`` ellipsoid ``(P, c)``."""

    claim: dict
    lo: Tensor
    hi: Tensor
    delta: float
    level: float | None
    floor: float | None
    pair: Pair | GraphPair | QuadraticPair
    residual: Residual
    core: tuple[Tensor, float] | None


def _read(out: CheckResult, header: dict, system, weights: dict, weights_sha256: str,
          system_sha256: str) -> _Reading:
    """The certificate's claim read against the run (its weights' and system's sha256, its box the system's), and what
    its statement alone must say (a band's premises, into ``out``); a CertificateError (or KeyError, TypeError,
    ValueError) where it cannot be read."""
    if header["networks"]["weights_sha256"] != weights_sha256:
        raise CertificateError("weights.pt is not the file the certificate was proved for (sha256 differs)")
    if header["system"]["description_sha256"] != system_sha256:
        raise CertificateError(f"the system {system.name!r} is not the one the certificate was proved for "
                               "(its description's sha256 differs)")
    claim = header.get("claim") or {}
    region = claim["region"]
    lo, hi = _claim_box(region, system)
    delta, level = float(region["delta"]), region.get("level")
    level = None if level is None else float(level)
    if not (math.isfinite(delta) and delta >= 0) or (level is not None and not math.isfinite(level)):
        raise CertificateError(f"the claim's delta ({delta}) or level ({level}) is not a finite number (delta >= 0)")
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
    return _Reading(claim, lo, hi, delta, level, floor, pair, residual, core)


def _practical(out: CheckResult, cert: _Reading, header: dict, system) -> bool:
    """A ``practical`` claim: V's bound on the delta-ball (the decrease outside it is its ``outer`` certificate's); no
    partition."""
    out.failures += _practical_failures(out, cert.claim, cert.pair, cert.lo, cert.hi)
    return False


def _near_x_star(out: CheckResult, cert: _Reading, header: dict, system) -> bool:
    """A decrease near x*: a ``roa-ball``'s cube by second order, an ``ellipsoid`` by its Jacobian; True where a ring of
    boxes around it (a partition) is to be checked too (a ``roa-ball`` resting on a core has its partition only)."""
    ring = header["partition"] is not None
    if cert.claim.get("cube") is None and cert.claim.get("ellipsoid") is None:
        return True
    if cert.claim.get("cube") is not None:
        failures, out.cube_bound = ball_failures(cert.claim, cert.pair, system, cert.lo, cert.hi, cert.delta, ring)
    else:
        failures, out.cube_bound = ellipsoid_failures(cert.claim, cert.residual, cert.lo, cert.hi, cert.delta, ring)
    out.failures += failures
    return ring  # without one the cube covers the ball, or the ellipsoid lies in its box


def _partition_only(out: CheckResult, cert: _Reading, header: dict, system) -> bool:
    """A claim proved on a partition alone (a condition on X_delta or a sublevel set, with a core, on a band; the DR
    uniform condition)."""
    return True


BEFORE_PARTITION = {"practical": _practical, "roa-ball": _near_x_star, "ellipsoid": _near_x_star}
"""Per kind of claim (:func:`~drlyap.claims.claim_kind`), what the checker establishes before (or instead of) the
partition's leaves, and whether a partition follows; the other kinds have only their partition."""


@dataclass(frozen=True)
class LeafSettings:
    """How the checker bounds a partition's leaves: bisected up to ``refine`` times where a bound does not prove one,
    at most ``pieces_per_leaf`` pieces a leaf on average, where ``compute`` says."""

    refine: int = REFINE
    compute: Compute = Compute()
    pieces_per_leaf: float = 1.0


def check_certificate(name: str, header: dict, arrays: dict[str, np.ndarray], system, weights: dict,
                      weights_sha256: str, system_sha256: str, leaves: LeafSettings = LeafSettings()) -> CheckResult:
    """Re-check the certificate ``name`` of a run (its ``header`` and partition ``arrays``) against the run's own weights
    (``weights``, from the file with ``weights_sha256``) and system (``system_sha256``); leaves bounded as
    :func:`~drlyap.checker.leaves.prove_leaves`, as ``leaves`` says (refinement, pieces, where)."""
    start = time.perf_counter()
    claim = header.get("claim") or {}
    out = CheckResult(name=name, ok=False, claim=claim_sentence(claim))
    try:
        kind = claim_kind(claim)  # a claim of no kind is checked on nothing
        if kind not in KINDS_OF.get(name, ()):
            raise CertificateError(f"a {name!r} certificate does not state a {kind} claim")
        if out.claim == UNREADABLE:
            raise CertificateError("its claim cannot be put in words: nothing is confirmed of it")
        cert = _read(out, header, system, weights, weights_sha256, system_sha256)
        partition = BEFORE_PARTITION.get(kind, _partition_only)(out, cert, header, system)
        if partition:
            grid = [int(k) for k in header["partition"]["grid"]]
            if len(grid) != system.n or min(grid) < 1:
                raise CertificateError(f"the starting grid {grid} does not fit {system.n} states")
            check_tree(arrays, int(np.prod(grid)), system.n, cert.level, cert.core is not None,
                       cert.floor is not None)
    except (CertificateError, KeyError, TypeError, ValueError) as err:
        out.failures.append(str(err) if not isinstance(err, KeyError) else f"the header lacks {err}")
        out.time_s = time.perf_counter() - start
        return out
    if partition:
        _check_partition(out, cert, header, arrays, grid, leaves)
    out.ok, out.time_s = not out.failures, time.perf_counter() - start
    return out


def _check_partition(out: CheckResult, cert: _Reading, header: dict, arrays: dict[str, np.ndarray], grid: list[int],
                     settings: LeafSettings) -> None:
    """The partition's leaves: placed where they say (in the ball, in the core), proved by the checker's bounds (the
    DR uniform condition: one margin over them all), V above the level on the box's faces (or the flow entering it),
    a band's leaves below it, and no recorded bound below the value at its box's centre; into ``out``."""
    residual, pair, lo, hi, level = cert.residual, cert.pair, cert.lo, cert.hi, cert.level
    blo, bhi = rebuild_boxes(lo, hi, grid, arrays)
    verdict = torch.as_tensor(arrays["verdict"].astype(np.int64))
    bound = torch.as_tensor(arrays["bound"].astype(np.float64))
    out.boxes = int((verdict != INTERNAL).sum())
    _placed_leaves(out, verdict, blo, bhi, cert.delta, cert.core)
    proved = ((verdict == PROVED) | (verdict == ABOVE_LEVEL)).nonzero().squeeze(-1)
    if residual.name == "uniform":
        _check_uniform(out, residual, blo[proved], bhi[proved], bound[proved], hi - lo, settings.refine)
        return
    cheap_first = header["partition"].get("enclosure") in ("interval", "mean-value")  # an order, as for ``above``
    job = LeafJob(residual, hi - lo, settings.refine, level, cheap_first)
    ok, centre_low, out.refined, out.pieces = prove_leaves(job, blo[proved], bhi[proved], verdict[proved] == ABOVE_LEVEL,
                                                           settings.compute, f"check ({out.name}): leaves",
                                                           settings.pieces_per_leaf)
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
        _check_faces(out, cert)
    if cert.floor is not None:  # a band's leaves below it: V < c1 there, by the checker's bisection
        below = (verdict == BELOW_LEVEL).nonzero().squeeze(-1)
        failures, spent = below_failures(pair, blo[below], bhi[below], bound[below], cert.floor, hi - lo)
        out.failures, out.pieces = out.failures + failures, out.pieces + spent
        out.below_band = int(below.numel()) if not failures else 0
        out.proved += out.below_band
    if bool(false.any()):
        first = proved[false][0]
        out.failures.append(f"{int(false.sum())} recorded bounds lie below the residual at their box's centre (first: "
                            f"node {int(first)}, recorded {float(bound[first]):.6g})")


def _check_faces(out: CheckResult, cert: _Reading) -> None:
    """A sublevel set's rule on the box's faces (:func:`~drlyap.claims.faces_rule`): V (W) above the level there, or the
    flow entering the box wherever the set meets a face; inside the delta-ball the set's boundary is the outer proof's.
    Its failures and counts into ``out``."""
    claim, residual, level = cert.claim, cert.residual, cert.level
    faces = faces_rule(claim)
    if faces not in ("above", "inward") or (faces == "inward" and (residual.model != "true"
                                                                   or claim.get("ellipsoid") is not None)):
        out.failures.append(f"the claim's rule for the box's faces {faces!r} is not one the checker takes "
                            "('above'; 'inward' for V's sets on the true model)")
    elif claim["region"].get("ball_of") is None and faces == "inward":
        holds, out.faces_min, out.faces_boxes = faces_inward(residual, cert.lo, cert.hi, level, max_boxes=1_000_000)
        if not holds:
            out.failures.append(f"the flow entering the box wherever V <= {level:g} on its faces is not established "
                                f"({out.faces_boxes} face boxes)")
    elif claim["region"].get("ball_of") is None:
        holds, out.faces_min, out.faces_boxes = faces_above(cert.pair, cert.lo, cert.hi, level)
        if not holds:
            what = "W" if claim.get("ellipsoid") is not None else "V"
            out.failures.append(f"{what} > {level:g} is not established on the box's faces ({what}'s lower bound "
                                f"there {out.faces_min:.6g}, {out.faces_boxes} face boxes)")


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
