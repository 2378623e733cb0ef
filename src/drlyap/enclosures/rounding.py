"""Outward rounding of float64 results: the pads every enclosure adds so that it contains the real value."""

from __future__ import annotations

import torch
from torch import Tensor

F64 = torch.float64
EPS = 2.0 ** -52  # float64 machine epsilon (unit roundoff is EPS / 2)
TINY = 1e-290  # absolute pad: covers underflow of any single operation
REL1 = 4 * EPS  # relative pad of one correctly rounded operation (generous)
RELT = 16 * EPS  # relative pad of a library transcendental (sin, cos, tanh, exp, sqrt: a few ulps at most)


def as_f64(x, device: torch.device | str | None = None) -> Tensor:
    """``x`` (a tensor, number or sequence) as a float64 tensor, on ``device`` (None: a tensor's own, else the CPU)."""
    return torch.as_tensor(x, dtype=F64, device=device)


def round_down(x: Tensor, rel: float, mag: Tensor | None = None) -> Tensor:
    """``x`` lowered by ``rel`` times its magnitude (or ``mag``) and an absolute pad: below the real value of a
    float64 result whose relative error is at most ``rel``."""
    if mag is None:  # one new tensor, changed in place (a hot path; autograd needs none of the intermediates)
        return x.abs().mul_(-rel).add_(x).sub_(TINY)
    return torch.sub(x, rel * mag).sub_(TINY)


def round_up(x: Tensor, rel: float, mag: Tensor | None = None) -> Tensor:
    """``x`` raised by ``rel`` times its magnitude (or ``mag``) and an absolute pad (see :func:`round_down`)."""
    if mag is None:
        return x.abs().mul_(rel).add_(x).add_(TINY)
    return torch.add(x, rel * mag).add_(TINY)


def sum_up(t: Tensor, dim: int = -1) -> Tensor:
    """An upper bound of the real sum of the non-negative ``t`` along ``dim``."""
    return round_up(t.sum(dim), 2 * (t.shape[dim] + 2) * EPS)
