"""The paper's Lipschitz covering check (``lemma: nominal_nn_lf``), beside the branch and bound.

If the residual ``c`` is ``L``-Lipschitz and every cell of a grid that meets X_delta has
``c(centre) <= -L rho`` (``rho`` = half the cell diagonal), then ``c <= 0`` on all of X_delta.
"""

from __future__ import annotations

import math
import time

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition
from drlyap.enclosures import F64, Dual, Interval
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.verification.bounds import combine_upper, condition_objective
from drlyap.verification.branch_and_bound import verify_condition
from drlyap.verification.results import CoveringCheck


def lipschitz_covering(loop: ClosedLoop, condition: Condition, region: Region, spacing: float | None = None,
                       n_samples: int = 20000, safety: float = 1.5, compare: Budget | None = None,
                       batch: int = 2048) -> CoveringCheck:
    """The covering certificate of ``lemma: nominal_nn_lf`` for a closed loop's per-state ``condition`` on a grid of
    the region X_delta, next to the branch and bound.

    The state box is cut into cells of side at most ``spacing`` (local units, the same on every axis; default:
    about ``n_samples`` cells); cells entirely inside the open delta-ball are dropped, the rest cover X_delta.
    With ``rho`` = the largest half cell diagonal and ``c`` the condition's residual:

    * ``max_residual``: sound upper bound of ``max c`` at the cell centres (interval evaluation; centres of cells
      that straddle the sphere may lie inside the ball, where c is not required to be <= 0 but still counts);
      ``max_residual_in_x_delta`` the largest float64 value at centres in X_delta;
    * ``lipschitz_sound``: a sound Lipschitz constant of ``c`` on the union of the cells: the largest norm of the
      verifier's interval enclosure of the (Clarke) gradient of the residual's components over any cell (the
      residual is a max / CVaR of its components, so it is no steeper than the steepest one);
    * ``lipschitz_sampled``: the largest gradient norm at the cell centres (autograd), an estimate from below;
    * ``certified``: ``max_residual <= -lipschitz_sound * rho`` (sound: then ``c <= 0`` on X_delta);
      ``certified_estimate`` the same with ``safety * lipschitz_sampled`` (not sound);
    * ``spacing_needed``: the spacing at which the same test would pass with the same ``L`` and maximum
      (``None`` when the maximum is >= 0), and ``samples_needed`` the resulting number of cells.

    With a ``compare`` budget the branch and bound runs on the same condition for comparison.
    """
    start = time.perf_counter()
    if not condition.per_state:
        raise ValueError("the uniform DR condition has no per-state residual; the covering check needs one")
    n, width = loop.system.n, region.hi - region.lo
    spacing, per_axis = _cells_per_axis(width, n, spacing, n_samples)
    glo, ghi = Region(region.lo, region.hi, region.delta).boxes(per_axis)
    rho = float(((ghi - glo) / 2).norm(dim=-1).max()) * (1 + 1e-12)
    max_res, l_sound = _sound_bounds(loop, condition, glo, ghi, batch)
    l_sampled, exact_max, region_max = _sampled_bounds(loop, condition, (glo + ghi) / 2, region.delta)
    needed = -l_sound * rho
    out = {
        "condition": condition.label, "delta": region.delta, "spacing": spacing, "per_axis": per_axis,
        "cells": int(glo.shape[0]), "covering_radius": rho, "max_residual": max_res, "max_residual_float64": exact_max,
        "max_residual_in_x_delta": region_max,
        "lipschitz_sound": l_sound, "lipschitz_sampled": l_sampled, "safety": safety,
        "required_max_residual": needed, "certified": bool(max_res <= needed),
        "certified_estimate": bool(max_res <= -safety * l_sampled * rho),
    }
    if max_res < 0 and l_sound > 0:
        h_needed = 2 * (-max_res) / (l_sound * math.sqrt(n))  # rho = h sqrt(n) / 2 for equal sides
        out["spacing_needed"] = h_needed
        out["samples_needed"] = float(math.prod(math.ceil(float(w) / h_needed) for w in width))
    if compare is not None:
        out["verifier"] = verify_condition(loop, condition, region, compare)
    return CoveringCheck(**out, time_s=time.perf_counter() - start)


def _cells_per_axis(width: Tensor, n: int, spacing: float | None, n_samples: int) -> tuple[float, list[int]]:
    """The spacing (default: about ``n_samples`` cells over the box of side lengths ``width (n,)``) and the cells per
    axis it gives; a spacing that is not > 0 or gives over 2,000,000 cells is refused."""
    if spacing is None:
        if n_samples < 1:
            raise ValueError(f"n_samples must be >= 1, got {n_samples}")
        spacing = float((width.prod() / n_samples) ** (1.0 / n))
    if not (math.isfinite(spacing) and spacing > 0):
        raise ValueError(f"spacing must be > 0, got {spacing}")
    per_axis = [max(1, math.ceil(float(w) / spacing - 1e-9)) for w in width]
    cells = math.prod(per_axis)
    if cells > 2_000_000:
        raise ValueError(f"spacing {spacing} gives {cells} cells; choose a larger spacing")
    return spacing, per_axis


def _sound_bounds(loop: ClosedLoop, condition: Condition, glo: Tensor, ghi: Tensor, batch: int) -> tuple[float, float]:
    """Over the cells ``[glo, ghi] (C, n)``: a sound upper bound of the residual at their centres, and a sound
    Lipschitz constant of it (the largest norm of the interval enclosure of its components' gradients on a cell)."""
    n = glo.shape[1]
    objective = condition_objective(loop, condition)
    max_res, l_sound = -math.inf, 0.0
    for i in range(0, glo.shape[0], batch):
        clo, chi = glo[i:i + batch], ghi[i:i + batch]
        b = clo.shape[0]
        eye = torch.eye(n, dtype=F64).expand(b, n, n)
        over = objective(Dual(Interval(clo, chi), Interval(eye, eye)))
        if over.d is not None:
            slope = torch.maximum(over.d.lo.abs(), over.d.hi.abs())  # (B, Q, n)
            norms = torch.sqrt((slope * slope).sum(-1)) * (1 + 1e-12)
            l_sound = max(l_sound, float(torch.nan_to_num(norms, nan=math.inf).max()))
        centre = (clo + chi) / 2
        at = objective(Interval(centre, centre))
        max_res = max(max_res, float(combine_upper(condition, at.hi).max()))
    return max_res, l_sound


def _sampled_bounds(loop: ClosedLoop, condition: Condition, centres: Tensor, delta: float) -> tuple[float, float, float]:
    """At the cell ``centres (C, n)``, by float64 autograd through the ordinary code path: the largest gradient norm
    of the residual (an estimate of its Lipschitz constant from below), its largest value, and its largest value at
    centres in X_delta (``||z|| >= delta``; ``-inf`` where none is)."""
    f64 = loop.f64
    l_sampled, exact_max, region_max = 0.0, -math.inf, -math.inf
    for i in range(0, centres.shape[0], 20000):
        zc = centres[i:i + 20000].clone().requires_grad_(True)
        with torch.enable_grad():
            res = f64.residual(condition, zc)
            (g,) = torch.autograd.grad(res.sum(), zc)
        l_sampled = max(l_sampled, float(g.norm(dim=-1).max()))
        exact_max = max(exact_max, float(res.detach().max()))
        inside = zc.detach().norm(dim=-1) >= delta
        if bool(inside.any()):
            region_max = max(region_max, float(res.detach()[inside].max()))
    return l_sampled, exact_max, region_max
