"""Bounds of a function over boxes, from the function's own code run on enclosures.

:func:`box_bounds` bounds any batched function of local states over boxes ``[lo, hi]``. The default
(``enclosure="mean-value"``) computes it in two ways and keeps the tighter: the plain interval bound, and the
mean-value form ``f(centre) + [grad f over the box] . (box - centre)`` (the gradient enclosure comes from dual
numbers; for the controller's clamp and the norms it is an enclosure of the Clarke generalised gradient, for
which the mean-value theorem still holds). ``enclosure="affine"`` runs the function on affine forms
(:class:`~drlyap.enclosures.Affine`, one noise symbol per box coordinate) instead of the mean-value form:
it keeps the dependence on the coordinates through every layer, and was measured 10-100x tighter on
4- and 6-state boxes (``benchmarks/enclosure_bench.py``) at about twice the cost per box.

:func:`condition_objective` is the function the verifier bounds for a decrease condition: the condition's
own ``components(terms(...))`` (:mod:`drlyap.conditions`), evaluated by the networks' and the system's own
code on enclosures.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from drlyap.conditions import Condition
from drlyap.enclosures import EPS, F64, REL1, Affine, Dual, Interval, _down, _up, is_enclosure
from drlyap.networks import Controller, Lyapunov
from drlyap.systems import UncertainSystem

Objective = Callable[[object], object]
"""``objective(z)``: ``z`` an enclosure of local states ``(B, n)`` -> an enclosure ``(B, Q)``."""


def condition_objective(condition: Condition, system: UncertainSystem, lyapunov: Lyapunov,
                        controller: Controller) -> Objective:
    """``z -> condition.components(condition.terms(system, lyapunov, controller, z))`` on enclosures."""

    def objective(z):
        out = condition.components(condition.terms(system, lyapunov, controller, z))
        if not is_enclosure(out):
            raise ValueError("the system's dynamics did not return an enclosure; write it with torch ops on its inputs")
        return out

    return objective


def value_objective(lyapunov: Lyapunov) -> Objective:
    """``z -> V(z)`` as ``(B, 1)``."""
    return lambda z: lyapunov(z).unsqueeze(-1)


def condition_and_value_objective(condition: Condition, system: UncertainSystem, lyapunov: Lyapunov,
                                  controller: Controller) -> Objective:
    """The condition's components followed by V as the last column, ``(B, Q + 1)``: what a proof restricted to a
    sublevel set of V bounds."""
    components, vobj = condition_objective(condition, system, lyapunov, controller), value_objective(lyapunov)

    def objective(z):
        return torch.cat([components(z), vobj(z)], -1)

    return objective


ENCLOSURES = ("mean-value", "affine")
"""The enclosures :func:`box_bounds` can use (the first is the default)."""


def default_enclosure(n: int) -> str:
    """The enclosure for an ``n``-state system: ``affine`` from 4 states on (9-16x tighter there,
    ``benchmarks/enclosure_bench.py``), else ``mean-value`` (cheaper per box, as tight in 2 states)."""
    return "affine" if n >= 4 else "mean-value"


def check_enclosure(enclosure: str) -> str:
    if enclosure not in ENCLOSURES:
        raise ValueError(f"unknown enclosure {enclosure!r}; valid: {', '.join(ENCLOSURES)}")
    return enclosure


def box_bounds(objective: Objective, lo: Tensor, hi: Tensor, enclosure: str = "mean-value",
               sensitivity: bool = False) -> tuple[Tensor, ...]:
    """Lower and upper bounds ``(B, Q)`` of ``objective`` over the boxes ``[lo, hi] (B, n)``.

    ``enclosure``: ``mean-value`` (the tighter of the plain interval bound and the mean-value form) or
    ``affine`` (the tighter of the plain interval bound and the affine-form bound). Also returns the enclosure
    of the objective at the box centres (an :class:`Interval` ``(B, Q)``). With ``sensitivity``, a fourth
    tensor ``(B, n)``: how much each coordinate's half-width adds to the first-order spread of the bounds, summed
    over the components (``|slope| * radius`` of the mean-value form, ``|coefficient|`` of the affine form):
    the coordinate worth splitting.
    """
    batch, n = lo.shape
    centre = (lo + hi) / 2
    at = objective(Interval(centre, centre))
    if check_enclosure(enclosure) == "affine":
        form = objective(Affine.box(lo, hi))
        over = form.to_interval()
        plain = objective(Interval(lo, hi))
        upper = torch.minimum(over.hi, plain.hi)
        lower = torch.maximum(over.lo, plain.lo)
        if sensitivity:
            sens = torch.zeros_like(lo) if form.g is None else form.g.abs().sum(1)
    else:
        rad = _up(torch.maximum(hi - centre, centre - lo), REL1)
        eye = torch.eye(n, dtype=F64).expand(batch, n, n)
        over = objective(Dual(Interval(lo, hi), Interval(eye, eye)))
        if over.d is None:
            spread = torch.zeros_like(at.lo)
            sens = torch.zeros_like(lo)
        else:
            contribution = torch.maximum(over.d.lo.abs(), over.d.hi.abs()) * rad.unsqueeze(1)  # (B, Q, n)
            spread = _up(contribution.sum(-1), 4 * (n + 2) * EPS)
            sens = contribution.sum(1)
        upper = torch.minimum(over.v.hi, _up(at.hi + spread, REL1))
        lower = torch.maximum(over.v.lo, _down(at.lo - spread, REL1))
    upper = torch.where(torch.isnan(upper), torch.inf, upper)
    lower = torch.where(torch.isnan(lower), -torch.inf, lower)
    if sensitivity:
        return lower, upper, at, torch.nan_to_num(sens, nan=torch.inf, posinf=torch.inf)
    return lower, upper, at


def combine_upper(condition: Condition, upper: Tensor) -> Tensor:
    """An upper bound ``(B,)`` of the residual from upper bounds ``(B, Q)`` of its components (the combination
    is non-decreasing in each component; its float64 evaluation is padded outward)."""
    out = condition.combine(upper)
    return _up(out, 64 * EPS, upper.abs().amax(-1))


def combine_lower(condition: Condition, lower: Tensor) -> Tensor:
    """A lower bound ``(B,)`` of the residual from lower bounds ``(B, Q)`` of its components."""
    out = condition.combine(lower)
    return _down(out, 64 * EPS, lower.abs().amax(-1))
