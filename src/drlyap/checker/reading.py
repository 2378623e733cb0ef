"""A certificate as the checker reads it before any bound (:class:`Reading`): its claim checked against the run
(the weights' and the system's sha256, its box the system's, finite numbers), the pair the claim is about (as its
kind says, :mod:`drlyap.claims`) and the residual of its condition; what the checker found of it
(:class:`CheckResult`); and a partition's nodes with their verdicts (:class:`Leaves`). The kinds of claim read
these; :mod:`drlyap.checker.check` drives them."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from drlyap.checker.arith import F64
from drlyap.checker.ellipsoid import QuadraticPair, read_core
from drlyap.checker.graphs import GraphPair
from drlyap.checker.model import Pair, Residual

INTERNAL, PROVED, INSIDE_BALL, ABOVE_LEVEL, INSIDE_CORE, BELOW_LEVEL = 0, 1, 2, 3, 5, 6
"""A partition node's verdict: split, proved, inside the open delta-ball, V above the level, inside the core, V
below a band."""


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


@dataclass
class Reading:
    """A certificate as the checker reads it before any bound: its ``claim``, the region's box ``lo, hi`` (local
    coordinates), ``delta``, ``level`` (None: X_delta), a band's ``floor``, the ``pair`` the claim is about (V and pi,
    or W = z'Pz for an ``ellipsoid``), the claim's ``residual`` (None for a claim about no condition) and a ``core``
    ellipsoid ``(P, c)``."""

    claim: dict
    lo: Tensor
    hi: Tensor
    delta: float
    level: float | None
    floor: float | None
    pair: Pair | GraphPair | QuadraticPair
    residual: Residual | None
    core: tuple[Tensor, float] | None


@dataclass
class Leaves:
    """A partition's nodes: boxes ``lo, hi (N, n)``, ``verdict (N,)`` and recorded ``bound (N,)``; ``proved``: the
    nodes proved (or above the level); ``refine``: how often the checker may bisect a leaf its bounds do not prove."""

    lo: Tensor
    hi: Tensor
    verdict: Tensor
    bound: Tensor
    proved: Tensor
    refine: int

    def proved_boxes(self) -> tuple[Tensor, Tensor, Tensor]:
        """The proved leaves' boxes and recorded bounds."""
        return self.lo[self.proved], self.hi[self.proved], self.bound[self.proved]

    def with_verdict(self, verdict: int) -> tuple[Tensor, Tensor, Tensor]:
        """The boxes and recorded bounds of the leaves with ``verdict``."""
        ids = (self.verdict == verdict).nonzero().squeeze(-1)
        return self.lo[ids], self.hi[ids], self.bound[ids]


def pair_of(weights: dict, header: dict, n: int) -> Pair | GraphPair:
    """The checker's V and pi from the run's weights: an imported pair's graphs, or drlyap's networks (with the
    header's ``alpha_hat``)."""
    if "graphs" in weights:
        return GraphPair(weights["graphs"], weights["tensors"], n)
    return Pair(weights, float(header["networks"]["alpha_hat"]), n)


def claim_box(region: dict, system) -> tuple[Tensor, Tensor]:
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


@dataclass(frozen=True)
class RunFiles:
    """What a certificate is read against: the run's ``system``, its ``weights`` (from the file with
    ``weights_sha256``) and the sha256 of the system's description."""

    system: object
    weights: dict
    weights_sha256: str
    system_sha256: str


def read(out: CheckResult, header: dict, kind, run: RunFiles) -> Reading:
    """The certificate's claim read against the run (its weights' and system's sha256, its box the system's) and the
    pair it is about as its ``kind`` (:class:`~drlyap.claims.kind.ClaimKind`) says (what its statement alone must say
    into ``out``); a CertificateError (or KeyError, TypeError, ValueError) where it cannot be read."""
    system = run.system
    if header["networks"]["weights_sha256"] != run.weights_sha256:
        raise CertificateError("weights.pt is not the file the certificate was proved for (sha256 differs)")
    if header["system"]["description_sha256"] != run.system_sha256:
        raise CertificateError(f"the system {system.name!r} is not the one the certificate was proved for "
                               "(its description's sha256 differs)")
    claim = header.get("claim") or {}
    region = claim["region"]
    lo, hi = claim_box(region, system)
    delta, level = float(region["delta"]), region.get("level")
    level = None if level is None else float(level)
    if not (math.isfinite(delta) and delta >= 0) or (level is not None and not math.isfinite(level)):
        raise CertificateError(f"the claim's delta ({delta}) or level ({level}) is not a finite number (delta >= 0)")
    pair = kind.about(out, claim, pair_of(run.weights, header, system.n))
    residual = Residual(claim["condition"], pair, system) if kind.condition else None
    core = None if claim.get("core") is None else read_core(claim, system.n)
    return Reading(claim, lo, hi, delta, level, kind.floor(claim), pair, residual, core)


def vector_text(v: Tensor) -> str:
    """A vector's entries in 6 significant digits, comma separated."""
    return ", ".join(f"{float(a):.6g}" for a in v)
