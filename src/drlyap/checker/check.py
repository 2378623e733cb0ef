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
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from drlyap.checker.arith import EPS, F64, Iv
from drlyap.checker.ellipsoid import inside_core
from drlyap.checker.leaves import REFINE, LeafJob, prove_leaves
from drlyap.checker.levels import faces_above, faces_inward, grid_cells
from drlyap.checker.reading import (
    ABOVE_LEVEL,
    BELOW_LEVEL,
    INSIDE_BALL,
    INSIDE_CORE,
    INTERNAL,
    PROVED,
    CertificateError,
    CheckResult,
    Leaves,
    Reading,
    RunFiles,
    read,
    vector_text,
)
from drlyap.claims.kind import ClaimKind
from drlyap.claims.registry import KINDS_OF, claim_sentence, kind_of
from drlyap.compute import Compute
from drlyap.wording import UNREADABLE, faces_rule


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
    (``weights``, from the file with ``weights_sha256``) and system (``system_sha256``), as its kind of claim
    (:mod:`drlyap.claims`) says; leaves bounded as :func:`~drlyap.checker.leaves.prove_leaves`, as ``leaves`` says
    (refinement, pieces, where)."""
    start = time.perf_counter()
    run = RunFiles(system, weights, weights_sha256, system_sha256)
    claim = header.get("claim") or {}
    out = CheckResult(name=name, ok=False, claim=claim_sentence(claim))
    try:
        kind = kind_of(claim)  # a claim of no kind is checked on nothing
        if kind.name not in KINDS_OF.get(name, ()):
            raise CertificateError(f"a {name!r} certificate does not state a {kind.name} claim")
        if out.claim == UNREADABLE:
            raise CertificateError("its claim cannot be put in words: nothing is confirmed of it")
        cert = read(out, header, kind, run)
        partition = kind.before_partition(out, cert, header, run.system)
        if partition:
            grid = [int(k) for k in header["partition"]["grid"]]
            if len(grid) != run.system.n or min(grid) < 1:
                raise CertificateError(f"the starting grid {grid} does not fit {run.system.n} states")
            check_tree(arrays, int(np.prod(grid)), run.system.n, cert.level, cert.core is not None,
                       cert.floor is not None)
    except (CertificateError, KeyError, TypeError, ValueError) as err:
        out.failures.append(str(err) if not isinstance(err, KeyError) else f"the header lacks {err}")
        out.time_s = time.perf_counter() - start
        return out
    if partition:
        _check_partition(out, cert, kind, header, arrays, grid, leaves)
    out.ok, out.time_s = not out.failures, time.perf_counter() - start
    return out


def _check_partition(out: CheckResult, cert: Reading, kind: ClaimKind, header: dict, arrays: dict[str, np.ndarray],
                     grid: list[int], settings: LeafSettings) -> None:
    """The partition's leaves: placed where they say (in the ball, in the core), then proved as the claim's kind says
    (:meth:`~drlyap.claims.kind.ClaimKind.leaves`); into ``out``."""
    blo, bhi = rebuild_boxes(cert.lo, cert.hi, grid, arrays)
    verdict = torch.as_tensor(arrays["verdict"].astype(np.int64))
    bound = torch.as_tensor(arrays["bound"].astype(np.float64))
    out.boxes = int((verdict != INTERNAL).sum())
    _placed_leaves(out, verdict, blo, bhi, cert.delta, cert.core)
    proved = ((verdict == PROVED) | (verdict == ABOVE_LEVEL)).nonzero().squeeze(-1)
    leaves = Leaves(blo, bhi, verdict, bound, proved, settings.refine)
    kind.leaves(out, cert, leaves, lambda: _prove_leaves(out, cert, kind, header, leaves, settings))


def _prove_leaves(out: CheckResult, cert: Reading, kind: ClaimKind, header: dict, leaves: Leaves,
                  settings: LeafSettings) -> None:
    """The proved leaves by the checker's bounds, V above the level on the box's faces (or the flow entering it), what
    the kind establishes beside them (a band's leaves below it), and no recorded bound below the value at its box's
    centre; into ``out``."""
    pair, level, proved = cert.pair, cert.level, leaves.proved
    blo, bhi, bound = leaves.lo, leaves.hi, leaves.bound
    cheap_first = header["partition"].get("enclosure") in ("interval", "mean-value")  # an order, as for ``above``
    job = LeafJob(cert.residual, cert.hi - cert.lo, settings.refine, level, cheap_first)
    ok, centre_low, out.refined, out.pieces = prove_leaves(job, blo[proved], bhi[proved],
                                                           leaves.verdict[proved] == ABOVE_LEVEL, settings.compute,
                                                           f"check ({out.name}): leaves", settings.pieces_per_leaf)
    out.proved = int(ok.sum())
    if not bool(ok.all()):
        first = proved[~ok][0]
        why = ("" if header["partition"].get("enclosure") != "affine" else
               "; the verifier bounded them with its own second-order forms, and this checker's do not reach its "
               "bounds there: the certificate is not confirmed, which does not show it false")
        out.failures.append(f"{int((~ok).sum())} of {proved.numel()} boxes are not proved by the checker's bounds "
                            f"(first: node {int(first)}, [{vector_text(blo[first])}] to [{vector_text(bhi[first])}])"
                            f"{why}")
    verdict = leaves.verdict[proved]
    false = (verdict == PROVED) & (bound[proved] < centre_low - 4 * EPS * centre_low.abs())
    if level is not None:  # V's recorded lower bound must not exceed V at the box's centre
        above = verdict == ABOVE_LEVEL
        v_centre = pair.value_and_grad(Iv.point((blo[proved] + bhi[proved]) / 2))[0].lo
        false = false | (above & (bound[proved] > v_centre + 4 * EPS * v_centre.abs()))
        _check_faces(out, cert)
    kind.after_leaves(out, cert, leaves)
    if bool(false.any()):
        first = proved[false][0]
        out.failures.append(f"{int(false.sum())} recorded bounds lie below the residual at their box's centre (first: "
                            f"node {int(first)}, recorded {float(bound[first]):.6g})")


def _check_faces(out: CheckResult, cert: Reading) -> None:
    """A sublevel set's rule on the box's faces (:func:`~drlyap.wording.faces_rule`): V (W) above the level
    there, or the flow entering the box wherever the set meets a face; inside the delta-ball the set's boundary is the
    outer proof's. Its failures and counts into ``out``."""
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
