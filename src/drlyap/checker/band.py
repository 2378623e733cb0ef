"""The checker's part of a band claim (the claim of :mod:`drlyap.verification.band_claim`, certificate ``band``):
whether the claim states what its conclusion needs (the whole state box, ``0 < c1 < c2``, decrease on the true model
at one shift with ``alpha > 0`` and no ``gamma ||z||``, the flow entering the box wherever ``V <= c2`` on its faces),
and ``V < c1`` on the leaves the proof left below the band, by the checker's own bisection. The decrease on the other
leaves and the flow on the faces are checked as for any claim on ``{V <= c2}`` (:mod:`drlyap.checker.check`)."""

from __future__ import annotations

import math

from torch import Tensor

from drlyap.checker.arith import EPS, Iv
from drlyap.checker.levels import boxes_below
from drlyap.wording import faces_rule


def band_floor(claim: dict) -> float | None:
    """``c1`` of a band claim (``claim["band"]["low"]``), None for a claim of another kind."""
    band = claim.get("band")
    return None if band is None else float(band["low"])


def statement_failures(claim: dict) -> list[str]:
    """What keeps a band claim's conclusion from following from what it states (see the module docstring)."""
    condition, region = claim["condition"], claim["region"]
    c1, c2 = band_floor(claim), region.get("level")
    problems = []
    if not (isinstance(c2, (int, float)) and math.isfinite(c1) and math.isfinite(c2) and 0 < c1 < c2):
        problems.append(f"its levels are not 0 < c1 < c2 (c1 = {c1!r}, c2 = {c2!r})")
    if condition.get("model") != "true" or len(condition.get("xi") or []) != 1:
        problems.append("it is not about the true model at one shift")
    if not float(condition.get("exp_rate") or 0.0) > 0 or float(condition.get("decay_rate") or 0.0) != 0:
        problems.append("its decrease is not Vdot + alpha V <= 0 with alpha > 0 (strict on the band only so)")
    if faces_rule(claim) != "inward":
        problems.append("it does not state the flow entering the box where V <= c2 on its faces")
    if region.get("delta") != 0 or region.get("ball_of") is not None:
        problems.append("its region is not the whole state box")
    return [f"the band claim does not follow: {p}" for p in problems]


def below_failures(pair, lo: Tensor, hi: Tensor, bound: Tensor, c1: float, scale: Tensor) -> tuple[list[str], int]:
    """Whether the leaves ``[lo, hi] (B, n)`` the proof left below the band have ``V < c1`` (bisected up to four times
    their number of boxes, at least 4,096), and whether each recorded upper bound of V (``bound (B,)``) lies at or
    above V at its centre; the failures and the boxes bounded."""
    if not lo.shape[0]:
        return [], 0
    holds, top, spent = boxes_below(pair, lo, hi, scale, c1, max(4096, 4 * int(lo.shape[0])))
    failures = [] if holds else [f"V < {c1:g} is not established on the leaves below the band (V's upper bound "
                                 f"there {top:.6g}, {spent} boxes)"]
    v_centre = pair.value_and_grad(Iv.point((lo + hi) / 2))[0].hi
    false = bound < v_centre - 4 * EPS * v_centre.abs()
    if bool(false.any()):
        failures.append(f"{int(false.sum())} recorded upper bounds of V lie below V at their box's centre")
    return failures, spent
