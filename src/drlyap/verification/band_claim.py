"""The band claim, the form of practical stability the field's continuous-time verifiers state: on the true model at
a shift, V decreases strictly on the band ``{c1 <= V <= c2}`` of the state box (``Vdot + alpha V <= 0`` there, with
``alpha > 0`` and ``c1 > 0``, so ``Vdot <= -alpha c1``), and wherever ``V <= c2`` on the box's faces the flow points
into the box. Then every trajectory that starts in ``{V <= c2}`` (in the box) stays there, reaches ``{V <= c1}``
within ``(c2 - c1) / (alpha c1)`` time units and stays in it: convergence to ``{V <= c1}``, not to x*.

It asks nothing of V below ``c1``: V need not be least at x* nor zero there (a sigmoid V, whose value at x* is about
0.02, is proved as it is). :func:`prove_band` proves it by the branch and bound with a floor
(:func:`~drlyap.verification.branch_and_bound.verify_condition`: boxes where V is provably below ``c1`` are leaves of
their own) and :func:`~drlyap.verification.sublevel.exit_minimum` on the faces; the certificate file is ``band``,
re-proved by :mod:`drlyap.checker.band`.
"""

from __future__ import annotations

import math
import time

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition
from drlyap.kinds import Model, Status
from drlyap.proof_settings import DEFAULT_SETTLE_STARTS, Budget
from drlyap.regions import Region
from drlyap.verification.branch_and_bound import Exempt, verify_condition
from drlyap.verification.falsifier import settle_unknown
from drlyap.verification.results import BandProof
from drlyap.verification.sublevel import budget_left, exit_minimum, faces_budget


def band_levels(low: float, high: float) -> tuple[float, float]:
    """``(c1, c2)`` as floats, or a ValueError naming what is wrong: both finite, ``0 < c1 < c2`` (``c1 > 0`` is what
    makes ``Vdot + alpha V <= 0`` a strict decrease on the band)."""
    c1, c2 = float(low), float(high)
    if not (math.isfinite(c1) and math.isfinite(c2) and 0 < c1 < c2):
        raise ValueError(f"a band needs 0 < C1 < C2, both finite, got {low!r}, {high!r}")
    return c1, c2


def band_request(band: tuple[float, float] | None, roa: bool) -> tuple[float, float] | None:
    """A band claim asked for (``band``: ``(c1, c2)``, None: none) beside a region of attraction (``roa``): its levels
    (:func:`band_levels`), or a ValueError where they are wrong or a region is asked too (they are proved apart: the
    band claim is convergence to ``{V <= c1}``, a region of attraction convergence to x*)."""
    if band is None:
        return None
    levels = band_levels(*band)
    if roa:
        raise ValueError("a band claim and a region of attraction are proved apart: the band claim is convergence to "
                         "{V <= C1}, a region of attraction convergence to x*")
    return levels


def band_region(region: Region) -> Region:
    """The band claim's region: the whole state box (no ball around x* is left out; what lies below ``c1`` is)."""
    return region.with_delta(0.0)


def prove_band(loop: ClosedLoop, condition: Condition, region: Region, low: float, high: float,
               budget: Budget = Budget(), falsify_starts: int = DEFAULT_SETTLE_STARTS) -> BandProof:
    """Prove the band claim (module docstring) for ``condition`` (decrease on the true model at one shift, with
    ``alpha > 0`` and no ``gamma ||z||``) on the state box of ``region`` between the levels ``low < high``, within
    ``budget`` (a quarter of its seconds, and up to a million boxes, for the faces). Where the decrease's proof runs
    out, a falsifier from ``falsify_starts`` states looks for a certain rise on the band (0: none)."""
    c1, c2 = band_levels(low, high)
    if condition.model != Model.TRUE or not float(condition.exp_rate or 0.0) > 0 or float(condition.decay_rate or 0.0):
        raise ValueError("a band is proved for decrease Vdot + alpha V <= 0 on the true model, alpha > 0 (no gamma)")
    start = time.perf_counter()
    box = band_region(region)
    exits = exit_minimum(loop, condition, box, faces_budget(budget, loop.n), rel_tol=0.02)
    exit_low, exit_high = exits.lower, exits.upper
    decrease = verify_condition(loop, condition, box, budget_left(budget, loop.n, start), level=c2, exempt=Exempt(floor=c1))
    decrease = settle_unknown(decrease, loop, condition, box, c2, starts=falsify_starts, floor=c1)
    status, reason = decrease.status, decrease.stopped if decrease.status != Status.VERIFIED else ""
    if exit_high <= c2:
        status, reason = Status.VIOLATED, (f"the flow leaves the box (or runs along its face) at a face point with "
                                           f"V = {exit_high:.6g} <= {c2:g}")
    elif exit_low <= c2 and status == Status.VERIFIED:
        status, reason = Status.UNKNOWN, (f"the flow entering the box where V <= {c2:g} on its faces is not proved "
                                          f"(V's bound there {exit_low:.6g})")
    elif status == Status.VIOLATED:
        reason = f"V rises at a state of the band (residual {decrease.counterexample_value:.4g})"
    xi = condition.xi[0].tolist() if condition.xi is not None else None
    return BandProof(low=c1, high=c2, status=status, exp_rate=float(condition.exp_rate), decrease=decrease,
                     exit_min_lower=exit_low, exit_min_upper=exit_high, time_s=time.perf_counter() - start,
                     reason=reason, xi=xi, asked=condition)
