"""Searching for counterexamples: where branch and bound runs out of time, a violating state may still be found.

* :func:`falsify` -- projected gradient ascent (:meth:`~drlyap.regions.Region.ascent_step`) on a per-state
  condition's residual from many starts, batched (CEGIS uses it for new training states, :func:`settle_unknown` for
  verdicts).
* :func:`falsifier_starts` -- half of the starts uniform in X_delta, half spread evenly over the distance from
  x* (:meth:`~drlyap.regions.Region.sample_near`): in 6 states a uniform draw almost never lands near x*, where
  violations of a V that rises along some direction live (measured on the quadrotor: 3 of 3 seeds found one with
  these starts, 0 of 3 with 4,096 uniform ones).
* :func:`confirmed_violations` -- the states where a violation is *certain*: the sound lower bound of the
  residual at the point (the condition's own code on a point interval, float64, outward rounded) is positive,
  the point lies in X_delta and, on a sublevel set, V's sound upper bound there is at most the level. That is
  the standard of the branch and bound's own counterexamples (a box centre with a positive lower bound).
* :func:`settle_unknown` -- turns an ``unknown`` proof into ``violated`` when such a state is found, recording
  that the falsifier found it (``counterexample_source``); a proof is never changed otherwise.
"""

from __future__ import annotations

import time

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition
from drlyap.enclosures import Interval
from drlyap.kinds import Status
from drlyap.proof_settings import DEFAULT_SETTLE_STARTS
from drlyap.regions import Region
from drlyap.systems import UncertainSystem
from drlyap.verification.bounds import combine_lower, condition_and_value_objective, condition_objective
from drlyap.verification.results import ConditionProof

F64 = torch.float64


def falsify(loop: ClosedLoop, condition: Condition, region: Region, starts: Tensor, steps: int = 30,
            step_size: float = 0.02) -> tuple[Tensor, Tensor]:
    """Projected gradient ascent on the condition's residual from ``starts (B, n)`` (local states), batched.

    Each step moves every state by ``step_size`` (a fraction of the box width, shrinking over the steps) along
    its normalised gradient (per coordinate scaled by the box width), then projects into X_delta. Returns the
    best state found per start and its residual (float64). The controller's saturation has a straight-through
    gradient, so ascent in saturated regions is only a heuristic; the residuals returned are exact evaluations.
    """
    if not condition.per_state:
        raise ValueError("the falsifier needs a per-state condition (pointwise, nominal or plain decrease)")
    f64 = loop.f64
    z = region.project(starts.to(F64).clone())

    def evaluate(states: Tensor, grad: bool) -> tuple[Tensor, Tensor | None]:
        with torch.enable_grad():
            s = states.detach().requires_grad_(grad)
            res = f64.residual(condition, s)
            g = torch.autograd.grad(res.sum(), s)[0] if grad else None
        return res.detach(), g

    best_z, best_r = z.clone(), evaluate(z, False)[0]
    for k in range(steps):
        _, g = evaluate(z, True)
        z = region.ascent_step(z, g, step_size * (1 - k / max(steps, 1)) + 1e-3 * step_size)
        r, _ = evaluate(z, False)
        better = r > best_r
        best_z[better], best_r[better] = z[better], r[better]
    return best_z, best_r


def falsifier_starts(region: Region, count: int, generator: torch.Generator) -> Tensor:
    """``count`` local states ``(count, n)`` of X_delta: half uniform, half spread over the distance from x*."""
    near = count // 2
    return torch.cat([region.sample(count - near, generator), region.sample_near(near, generator)])


def box_centres(system: UncertainSystem, boxes: list[dict]) -> Tensor:
    """The centres ``(B, n)``, in local coordinates, of boxes ``{"lo": [...], "hi": [...]}`` given in user
    coordinates (a verification's ``unverified_boxes``; angles are not wrapped, so a box keeps its centre)."""
    lo, hi = local_boxes(system, boxes)
    return (lo + hi) / 2


def local_boxes(system: UncertainSystem, boxes: list[dict]) -> tuple[Tensor, Tensor]:
    """The corners ``lo, hi (B, n)``, in local coordinates, of boxes given in user coordinates (see
    :func:`box_centres`)."""
    if not boxes:
        return torch.empty(0, system.n, dtype=F64), torch.empty(0, system.n, dtype=F64)
    x_star = torch.as_tensor(system.equilibrium, dtype=F64)
    lo = torch.as_tensor([b["lo"] for b in boxes], dtype=F64) - x_star
    hi = torch.as_tensor([b["hi"] for b in boxes], dtype=F64) - x_star
    return lo, hi


def confirmed_violations(loop: ClosedLoop, condition: Condition, region: Region, z: Tensor,
                         level: float | None = None, floor: float | None = None) -> Tensor:
    """``(B,)``: a sound lower bound of the residual at each local state of ``z (B, n)`` where a violation is
    certain (X_delta, and ``V <= level`` proved when a level is given, ``V >= floor`` too with a band's floor),
    ``-inf`` elsewhere."""
    z = torch.as_tensor(z, dtype=F64)
    if z.shape[0] == 0:
        return torch.empty(0, dtype=F64)
    f64 = loop.f64
    point = Interval(z, z)
    with torch.no_grad():
        if level is None:
            at = condition_objective(f64, condition)(point)
            inside = torch.ones(z.shape[0], dtype=torch.bool)
        else:
            at = condition_and_value_objective(f64, condition)(point)
            inside = at.hi[:, -1] <= level
            if floor is not None:
                inside = inside & (at.lo[:, -1] >= floor)
            at = at[:, :-1]
    lower = combine_lower(condition, at.lo)
    in_box = ((z >= region.lo) & (z <= region.hi)).all(-1)
    certain = inside & in_box & region.in_region(z) & (lower > 0)
    return torch.where(certain, lower, -torch.inf)


SETTLE_STEPS = 30
"""The ascent steps of the falsifier that settles an unknown proof (:func:`settle_unknown`)."""


def settle_unknown(result: ConditionProof, loop: ClosedLoop, condition: Condition, region: Region,
                   level: float | None = None, starts: int = DEFAULT_SETTLE_STARTS, seed: int = 0,
                   floor: float | None = None) -> ConditionProof:
    """Search for a counterexample where a proof ``result`` came back ``unknown`` (:data:`SETTLE_STEPS` ascent steps).

    Starts: :func:`falsifier_starts` (``starts`` states, generator seeded with ``seed``) plus the centres of the
    unverified boxes the result kept. When :func:`confirmed_violations` finds one, ``result`` becomes
    ``violated`` with the worst such state as its counterexample (``counterexample``, ``counterexample_local``,
    ``counterexample_value`` (float64 residual), ``counterexample_value_float32``, ``counterexample_source``
    ``"falsifier"``); ``verified_fraction`` (what the branch and bound proved) stays. ``result.falsifier``
    records the search (starts, seconds, largest residual, confirmed states). Returns ``result`` (updated in
    place); other statuses, non-per-state conditions and ``starts <= 0`` leave it as it was. ``floor``: a band's
    (with ``level``): a violation must have ``V >= floor`` too.
    """
    if result.status != Status.UNKNOWN or not condition.per_state or starts <= 0:
        return result
    system = loop.system
    tic = time.perf_counter()
    pool = [falsifier_starts(region, int(starts), torch.Generator().manual_seed(int(seed)))]
    pool.append(region.project(box_centres(system, result.unverified_boxes or [])))
    found, values = falsify(loop, condition, region, torch.cat(pool), steps=SETTLE_STEPS)
    lower = confirmed_violations(loop, condition, region, found, level, floor)
    record = {"starts": int(found.shape[0]), "time_s": time.perf_counter() - tic,
              "max_residual": float(values.max()), "confirmed": int(torch.isfinite(lower).sum())}
    result.falsifier = record
    if record["confirmed"]:
        best = found[int(lower.argmax())]
        result.status, result.counterexample_source = Status.VIOLATED, "falsifier"
        result.counterexample_local, result.counterexample = best.tolist(), system.to_user(best[None])[0].tolist()
        result.counterexample_value = float(loop.exact(condition, best[None])[0])
        result.counterexample_value_float32 = float(loop.exact(condition, best[None], torch.float32)[0])
        found_by = f"the falsifier found {record['confirmed']} violating states from {record['starts']} starts"
        result.stopped = f"{result.stopped}; {found_by}" if result.stopped else found_by
    return result
