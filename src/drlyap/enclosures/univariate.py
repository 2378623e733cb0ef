"""Functions of one variable over intervals, for the affine forms' linearisations: secant slopes, the error bound
of a secant on a convex (or concave) stretch, and enclosures of the derivatives used there."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from drlyap.enclosures.interval import Interval
from drlyap.enclosures.rounding import REL1, round_down, round_up


def secant(f: Callable, df: Callable, a: Tensor, b: Tensor) -> Tensor:
    """The slope ``(f(b) - f(a)) / (b - a)`` in float64 (``df(a)`` where ``b == a``): any float is sound as the
    slope of a linearisation (its error bound is computed for the slope actually used)."""
    wide = b > a
    sec = (f(b) - f(a)) / torch.where(wide, b - a, torch.ones_like(a))
    return torch.where(wide, sec, df(a))


def convex_error(f: Callable, df: Callable, p: Tensor, q: Tensor, lam: Tensor, xt: Tensor,
                  convex: bool = True) -> Interval:
    """An interval containing ``e(x) = f(x) - lam x`` for every ``x`` in ``[p, q]`` where ``f`` is convex
    (``convex=False``: concave) on ``[p, q]``.

    ``f``, ``df``: the function and its derivative on :class:`Interval` (outward rounded). ``xt``: a point of
    ``[p, q]``, best where ``f' = lam``. A convex ``e`` is largest at an end of ``[p, q]`` and lies above its
    tangent at ``xt``: ``e(x) >= e(xt) + e'(xt) (x - xt)``, whose least value over ``[p, q]`` bounds ``e`` below
    (concave: mirrored). All of it in interval arithmetic, so rounding is covered.
    """
    lam_ = Interval.const(lam)
    pp, qq, xx = Interval.const(p), Interval.const(q), Interval.const(xt)
    ep, eq, ex = f(pp) - lam_ * pp, f(qq) - lam_ * qq, f(xx) - lam_ * xx
    tangent = ex + (df(xx) - lam_) * (Interval(p, q) - xx)
    if convex:
        return Interval(tangent.lo, torch.maximum(ep.hi, eq.hi))
    return Interval(torch.minimum(ep.lo, eq.lo), tangent.hi)


def dtanh(x: Interval) -> Interval:
    return 1.0 - x.tanh().square()


def dsqrt(x: Interval) -> Interval:
    s = x.sqrt()
    with torch.no_grad():
        return Interval(round_down(0.5 / s.hi, REL1), round_up(0.5 / s.lo, REL1))  # 0.5 / 0 = inf (then a fallback)


def drecip(x: Interval) -> Interval:
    return -x.reciprocal().square()
