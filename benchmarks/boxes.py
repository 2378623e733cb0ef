"""Random boxes of a state box and the sampled range over them (shared by the enclosure benchmarks)."""

from __future__ import annotations

import torch
from torch import Tensor


def random_boxes(slo: Tensor, shi: Tensor, width: float, count: int, samples: int,
                 gen: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
    """``count`` boxes ``(lo, hi)`` (each ``(count, n)``) whose sides are ``width`` times the state box ``[slo, shi]``'s,
    centred uniformly in it, and ``samples`` uniform points of each plus its corners, ``(count, samples + 2^n, n)``."""
    n = slo.shape[0]
    corners = torch.cartesian_prod(*[torch.tensor([0.0, 1.0], dtype=slo.dtype)] * n).reshape(-1, n)
    centre = slo + (shi - slo) * torch.rand(count, n, generator=gen, dtype=slo.dtype)
    half = (shi - slo) * width / 2
    lo, hi = centre - half, centre + half
    unit = torch.cat([torch.rand(count, samples, n, generator=gen, dtype=slo.dtype), corners.expand(count, -1, -1)], 1)
    return lo, hi, lo[:, None] + (hi - lo)[:, None] * unit


def width_ratio(lower: Tensor, upper: Tensor, sampled_lo: Tensor, sampled_hi: Tensor) -> float:
    """Median over boxes and components of a bound's width / the sampled range (components with a non-zero range)."""
    enc = (upper - lower).reshape(-1)
    true = (sampled_hi - sampled_lo).reshape(-1)
    keep = true > 1e-12
    return float((enc[keep] / true[keep]).median()) if bool(keep.any()) else float("nan")
