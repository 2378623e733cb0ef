"""The DR uniform condition's certificate re-checked: one inequality over the whole region, not one per box.

The claim is ``(r / eps) sup ||W^T grad V|| + CVaR_eps_j sup (Vdot_j + decay) <= 0``, the suprema over X_delta. The
certificate's leaves cover X_delta (the checker rebuilds them from the grid and the splits, and re-proves the leaves
said to lie in the ball); the checker bounds each component on every leaf with its own arithmetic (the tighter of
the interval bound and the mean-value form, and where those leave the margin above 0 the second-order forms), takes
each component's largest bound over the leaves, and combines them outward rounded
(:meth:`~drlyap.checker.model.Residual.combine_upper`). The combination is non-decreasing in every component, so a
bound of each supremum gives a bound of the margin. Where that bound is not ``<= 0`` the leaves whose bound of some
component lies above the largest value it takes at a leaf's centre are bisected along their widest side (``refine``
rounds at most, and at most ``pieces`` pieces in all): the pieces' bounds replace their leaf's.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from drlyap.checker.affine import Af
from drlyap.checker.arith import EPS, Iv
from drlyap.checker.model import Residual, component_upper, radius


def leaf_bounds(residual: Residual, lo: Tensor, hi: Tensor, forms: bool = True,
                batch: int = 4096) -> tuple[Tensor, Tensor]:
    """Upper bounds ``(B, Q)`` of the components over the boxes ``[lo, hi] (B, n)`` (the tighter of the interval
    bound and the mean-value form; with ``forms`` also of the second-order forms, the DR norm's own and its interval
    norm) and lower bounds ``(B, Q)`` of their values at the boxes' centres, in batches."""
    uppers, centres = [], []
    for i in range(0, lo.shape[0], batch):
        a, b = lo[i:i + batch], hi[i:i + batch]
        upper = component_upper(residual, a, b)
        for flat in (False, True) if forms else ():
            form = residual.terms(Af.seed(a, b), flat_norm=flat)[0].interval(dual=False).hi
            upper = torch.minimum(upper, torch.where(torch.isnan(form), math.inf, form))
        uppers.append(upper)
        low = residual.components(Iv.point(radius(a, b)[0])).lo
        centres.append(torch.where(torch.isnan(low), -math.inf, low))
    width = residual.xi.shape[0] + 1
    if not uppers:
        empty = torch.zeros(0, width, dtype=lo.dtype, device=lo.device)
        return empty, empty
    return torch.cat(uppers), torch.cat(centres)


def uniform_margin_bound(residual: Residual, lo: Tensor, hi: Tensor, scale: Tensor, refine: int,
                         pieces: int) -> tuple[float, Tensor, int, int]:
    """An upper bound of the uniform condition's margin over the leaves ``[lo, hi] (B, n)`` (``scale (n,)``: the
    widths sides are measured against, for bisection; ``refine`` rounds of it, ``pieces`` pieces bounded at most),
    with the suprema's bounds ``(Q,)`` it is made of, how many leaves needed bisection and into how many pieces (see
    the module docstring)."""
    upper, centre_low = leaf_bounds(residual, lo, hi, forms=False)
    if upper.shape[0] == 0:
        raise ValueError("the certificate has no leaf outside the ball: there is nothing to bound")
    attained = centre_low.amax(0)
    if float(residual.combine_upper(upper.amax(0)[None])[0]) > 0:  # the second-order forms where they may matter
        loose = (upper > attained + 4 * EPS * attained.abs() + 1e-300).any(-1)
        upper[loose] = torch.minimum(upper[loose], leaf_bounds(residual, lo[loose], hi[loose])[0])
    owner = torch.arange(lo.shape[0], device=lo.device)
    plo, phi = lo, hi
    budget, pieces, refined = pieces, 0, set()
    margin = float(residual.combine_upper(upper.amax(0)[None])[0])
    for _ in range(refine):
        if margin <= 0:
            break
        slack = 4 * EPS * attained.abs() + 1e-300
        loose = (upper > attained + slack).any(-1)
        count = int(loose.sum())
        if not count or pieces + 2 * count > budget:
            break
        refined.update(owner[loose].tolist())
        widest = ((phi[loose] - plo[loose]) / scale).argmax(-1)
        rows = torch.arange(count, device=lo.device)
        a, b = plo[loose], phi[loose]
        mid = (a[rows, widest] + b[rows, widest]) / 2
        b1, a2 = b.clone(), a.clone()
        b1[rows, widest], a2[rows, widest] = mid, mid
        nlo, nhi = torch.cat([a, a2]), torch.cat([b1, b])
        nup, nlow = leaf_bounds(residual, nlo, nhi)
        pieces += 2 * count
        attained = torch.maximum(attained, nlow.amax(0))
        keep = ~loose
        plo, phi = torch.cat([plo[keep], nlo]), torch.cat([phi[keep], nhi])
        upper = torch.cat([upper[keep], nup])
        owner = torch.cat([owner[keep], owner[loose].repeat(2)])
        margin = float(residual.combine_upper(upper.amax(0)[None])[0])
    return margin, upper.amax(0), len(refined), pieces
