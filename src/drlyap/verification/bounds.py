"""Bounds of a function over boxes, from the function's own code run on enclosures.

:func:`box_bounds` bounds any batched function of local states over boxes ``[lo, hi]``. The default
(``enclosure="mean-value"``) computes it in two ways and keeps the tighter: the plain interval bound, and the
mean-value form ``f(centre) + [grad f over the box] . (box - centre)`` (the gradient enclosure comes from dual
numbers; for the controller's clamp and the norms it is an enclosure of the Clarke generalised gradient, for
which the mean-value theorem still holds). ``enclosure="affine"`` runs the function on affine forms
(:class:`~drlyap.enclosures.Affine`, one noise symbol per box coordinate, with an exact quadratic part)
instead of both (the interval bound beside them saved 0.5% of the cart-pole's boxes for 9% more time): it
keeps the dependence on the coordinates through every layer to second order, and its result's linear and
quadratic parts are bounded jointly (over the cube's vertices and by a
dual bound, :func:`~drlyap.enclosures.quadratic_max`; :meth:`~drlyap.enclosures.Affine.tight_interval`);
``benchmarks/enclosure_bench.py`` compares the widths.

:func:`condition_objective` is the function the verifier bounds for a decrease condition: the condition's
own ``components(terms(...))`` (:mod:`drlyap.conditions`), evaluated by the networks' and the system's own
code on enclosures. On a sublevel set ``{V <= c}``, :func:`sublevel_upper` bounds the residual where
``V <= c`` only (an S-procedure on the affine form of the condition and V together).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from drlyap.conditions import Condition
from drlyap.enclosures import (
    EPS,
    F64,
    REL1,
    Affine,
    Dual,
    Interval,
    is_enclosure,
    max_lin_quad,
    quadratic_max,
    round_down,
    round_up,
    vertices,
)
from drlyap.kinds import Enclosure
from drlyap.networks import QuadraticLyapunov
from drlyap.proof_settings import check_enclosure

Objective = Callable[[object], object]
"""``objective(z)``: ``z`` an enclosure of local states ``(B, n)`` -> an enclosure ``(B, Q)``."""


def condition_objective(loop, condition: Condition) -> Objective:
    """``z -> condition.components(condition.terms(loop, z))`` on enclosures, for a closed loop
    (:class:`~drlyap.closed_loop.ClosedLoop`)."""

    def objective(z):
        out = condition.components(condition.terms(loop, z))
        if not is_enclosure(out):
            raise ValueError("the system's dynamics did not return an enclosure; write it with torch ops on its inputs")
        return out

    return objective


def value_objective(lyapunov) -> Objective:
    """``z -> V(z)`` as ``(B, 1)`` for a Lyapunov function V (a network or a quadratic form)."""
    return lambda z: lyapunov(z).unsqueeze(-1)


def condition_and_value_objective(loop, condition: Condition) -> Objective:
    """The condition's components followed by V as the last column, ``(B, Q + 1)``: what a proof restricted to a
    sublevel set of V bounds."""

    def objective(z):
        terms = condition.terms(loop, z)  # V once: its value comes with its gradient
        out = torch.cat([condition.components(terms), terms.value.unsqueeze(-1)], -1)
        if not is_enclosure(out):
            raise ValueError("the system's dynamics did not return an enclosure; write it with torch ops on its inputs")
        return out

    return objective


def box_bounds(objective: Objective, lo: Tensor, hi: Tensor, enclosure: Enclosure = Enclosure.MEAN_VALUE,
               sensitivity: bool = False, keep_form: bool = False, read_lower: slice | None = None) -> tuple:
    """Lower and upper bounds ``(B, Q)`` of ``objective`` over the boxes ``[lo, hi] (B, n)``.

    ``enclosure``: ``mean-value`` (the tighter of the plain interval bound and the mean-value form) or
    ``affine`` (the affine-form bound, its linear and quadratic parts bounded jointly). Also returns the enclosure
    of the objective at the box centres (an :class:`Interval` ``(B, Q)``). With ``sensitivity``, a fourth
    tensor ``(B, n)``: how much each coordinate's half-width adds to the spread of the bounds, summed over the
    components (``|slope| * radius`` of the mean-value form; ``|coefficient|`` of the affine form plus half of
    each ``|q_kl|`` of its quadratic part for each of the entry's two symbols): the coordinate worth splitting.
    With ``keep_form``, last: the objective's :class:`Affine` form ``(B, Q)`` over the boxes (``affine`` only;
    None for ``mean-value``), for :func:`sublevel_upper`. ``read_lower``: the components whose lower bounds
    the caller reads (None: all); the others' are the plain interval's, looser and cheaper (``affine``: the joint
    bound of the lower end is half of the bounding's last step), their upper bounds the same bits either way.
    """
    batch, n = lo.shape
    centre = (lo + hi) / 2
    at = objective(Interval(centre, centre))
    if check_enclosure(enclosure) == Enclosure.AFFINE:
        form = objective(Affine.box(lo, hi))
        over = form.tight_interval(lower=read_lower)
        upper, lower = over.hi, over.lo
        if sensitivity:
            sens = torch.zeros_like(lo) if form.g is None else form.g.abs().sum(1)
            if form.q is not None:  # a quadratic term q_kl e_k e_l shrinks with either side: count it on both
                sens = sens + (form.q.abs().sum(-1) + form.q.abs().sum(-2)).sum(1) / 2
    else:
        rad = round_up(torch.maximum(hi - centre, centre - lo), REL1)
        eye = torch.eye(n, dtype=F64, device=lo.device).expand(batch, n, n)
        over = objective(Dual(Interval(lo, hi), Interval(eye, eye)))
        if over.d is None:
            spread = torch.zeros_like(at.lo)
            sens = torch.zeros_like(lo)
        else:
            contribution = torch.maximum(over.d.lo.abs(), over.d.hi.abs()) * rad.unsqueeze(1)  # (B, Q, n)
            spread = round_up(contribution.sum(-1), 4 * (n + 2) * EPS)
            sens = contribution.sum(1)
        upper = torch.minimum(over.v.hi, round_up(at.hi + spread, REL1))
        lower = torch.maximum(over.v.lo, round_down(at.lo - spread, REL1))
    upper = torch.where(torch.isnan(upper), torch.inf, upper)
    lower = torch.where(torch.isnan(lower), -torch.inf, lower)
    out = (lower, upper, at)
    if sensitivity:
        out += (torch.nan_to_num(sens, nan=torch.inf, posinf=torch.inf),)
    if keep_form:
        out += (form if enclosure == Enclosure.AFFINE else None,)
    return out


def combine_upper(condition: Condition, upper: Tensor) -> Tensor:
    """An upper bound ``(B,)`` of the residual from upper bounds ``(B, Q)`` of its components (the combination
    is non-decreasing in each component; its float64 evaluation is padded outward)."""
    out = condition.combine(upper)
    return round_up(out, 64 * EPS, upper.abs().amax(-1))


def combine_lower(condition: Condition, lower: Tensor) -> Tensor:
    """A lower bound ``(B,)`` of the residual from lower bounds ``(B, Q)`` of its components."""
    out = condition.combine(lower)
    return round_down(out, 64 * EPS, lower.abs().amax(-1))


def sublevel_upper(condition: Condition, form: Affine, level: float) -> Tensor:
    """An upper bound ``(B,)`` of the residual over the part of each box where ``V <= level``, or ``-inf``-like
    values where that part is empty: ``min over lam >= 0 of max over the box of residual - lam (V - level)``
    (an S-procedure on the box: where ``V <= level`` the subtracted term is ``<= 0``).

    ``form``: the :class:`Affine` form ``(B, Q + 1)`` of :func:`condition_and_value_objective` over the boxes.
    The residual is ``condition.combine`` of its components, monotone and shifted by ``s`` when every component
    is (true of every per-state condition: a max, a CVaR or one entry), so ``residual - lam (V - level)`` is the
    combination of the components' ``comp_q - lam (V - level)``, each bounded on the shared noise symbols: the
    parts of the condition's linear and quadratic variation that follow V's cancel. ``lam`` is tried at 0 and at every kink
    ``g_qk / g_Vk > 0`` of the components' bounds (any ``lam >= 0`` is sound).
    """
    batch = form.shape[0]
    if form.g is None:
        return combine_upper(condition, round_up(form.c[:, :-1] + form._higher().hi[:, :-1], REL1))
    k = form.n_symbols
    cq, gq, rq = form.c[:, :-1], form.g[:, :-1], form.r.hi[:, :-1]  # (B, Q), (B, Q, K), (B, Q)
    cv, gv, rv = form.c[:, -1], form.g[:, -1], form.r.lo[:, -1]  # (B,), (B, K), (B,)
    kinks = (gq / gv[:, None]).flatten(1)
    lam = torch.cat([torch.zeros(batch, 1, dtype=F64, device=cq.device), kinks], 1)
    lam = torch.where(torch.isfinite(lam) & (lam > 0), lam, 0.0)
    best, best_lam = None, None
    for lo in range(0, lam.shape[1], 8):  # a few multipliers at a time: (B, 8, Q, K, K) at most
        lm = lam[:, lo:lo + 8, None]  # (B, C, 1)
        value = cq[:, None] - lm * (cv - level)[:, None, None] + rq[:, None] - lm * rv[:, None, None]
        lin = gq[:, None] - lm[..., None] * gv[:, None, None]  # (B, C, Q, K)
        mag = (cq.abs() + gq.abs().sum(-1) + rq.abs())[:, None] + lm * (
            cv.abs() + level + gv.abs().sum(-1) + rv.abs())[:, None, None]
        if form.q is None:
            value = value + lin.abs().sum(-1)
        else:  # sum_k max_e (lin_k e_k + m_kk e_k^2) + sum_{k != l} |m_kl|, m = q_q - lam q_V
            qq, qv = form.q[:, :-1], form.q[:, -1]
            m = qq[:, None] - lm[..., None, None] * qv[:, None, None]  # (B, C, Q, K, K)
            diag = torch.diagonal(m, dim1=-2, dim2=-1)
            value = value + max_lin_quad(lin, diag).sum(-1) + m.abs().sum((-2, -1)) - diag.abs().sum(-1)
            mag = mag + qq.abs().sum((-2, -1))[:, None] + lm * qv.abs().sum((-2, -1))[:, None, None]
        value = round_up(value, 8 * (k * k + k + 8) * EPS, mag)
        value = torch.where(torch.isnan(value), torch.inf, value)
        up, at = combine_upper(condition, value.flatten(0, 1)).reshape(batch, -1).min(-1)
        lam_at = lm[:, :, 0].gather(1, at[:, None])[:, 0]
        if best is None:
            best, best_lam = up, lam_at
        else:
            best_lam = torch.where(up < best, lam_at, best_lam)
            best = torch.minimum(best, up)
    if form.q is None or k > 8:
        return best
    # the chosen multiplier again, with the linear and quadratic parts bounded jointly (quadratic_max)
    lm = best_lam[:, None]
    qq, qv = form.q[:, :-1], form.q[:, -1]
    value = (cq - lm * (cv - level)[:, None] + rq - lm * rv[:, None]
             + quadratic_max(gq - lm[..., None] * gv[:, None], qq - lm[..., None, None] * qv[:, None]))
    mag = (cq.abs() + gq.abs().sum(-1) + rq.abs() + qq.abs().sum((-2, -1))) + lm * (
        cv.abs() + level + gv.abs().sum(-1) + rv.abs() + qv.abs().sum((-2, -1)))[:, None]
    value = round_up(value, 8 * (k * k + k + 8) * EPS, mag)
    value = torch.where(torch.isnan(value), torch.inf, value)
    return torch.minimum(best, combine_upper(condition, value))


def vertex_max(p: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """``max z^T P z`` over each box ``[lo, hi] (B, n)`` (at a vertex: the form is convex), rounded up."""
    n = lo.shape[-1]
    p = p.to(lo)
    if n > 8:  # 2^n vertices per box: beyond that, the interval bound
        return QuadraticLyapunov(p)(Interval(lo, hi)).hi
    corners = torch.where(vertices(n, lo.device)[None] > 0, hi[:, None, :], lo[:, None, :])  # (B, 2^n, n)
    values = (corners @ p * corners).sum(-1)
    mag = (corners.abs() @ p.abs() * corners.abs()).sum(-1)
    return round_up(values, 4 * (n + 2) * REL1, mag).amax(-1)
