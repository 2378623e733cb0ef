"""Certified training on the boxes a proof left open (:class:`OpenBoxes`): the verifier's own sound bound of the
residual over each box, differentiated in the networks' weights, and a hinge on it.

A retraining round's sampled loss can be 0 on every state it draws while the proof still fails: the states satisfy
the condition with their margin, but the verifier's bound over the boxes around them does not (measured on the
quadrotor: a round that returned its starting pair bitwise). The hinge ``(upper + margin)_+`` on those boxes acts
exactly there: it lowers the bound the branch and bound needs below 0, by making the residual more negative and the
networks flatter over the box. The bound is :func:`~drlyap.verification.bounding.bound_condition`'s, the verifier's
code run on the live networks within :func:`~drlyap.enclosures.weight_gradients` (the number the verifier computes for
the same weights, up to the order of its float64 sums: 1e-15 apart on the quadrotor, each outward rounded); boxes
where it is undefined (+inf) are left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from drlyap.enclosures import F64, weight_gradients
from drlyap.kinds import Enclosure
from drlyap.verification.bounding import bound_condition


@dataclass
class OpenBoxes:
    """Boxes ``[lo, hi] (B, n)`` (local coordinates, float64) a proof of the condition on ``{V <= level}`` (None: on
    X_delta) left unproved, and how to train on them: ``weight`` of the hinge, its ``margin``, ``batch`` boxes drawn
    per iteration, bounded with ``enclosure`` (the proof's)."""

    lo: Tensor
    hi: Tensor
    level: float | None
    enclosure: Enclosure
    weight: float = 1.0
    margin: float = 0.0
    batch: int = 256

    def __post_init__(self) -> None:
        lo, hi = torch.as_tensor(self.lo, dtype=F64), torch.as_tensor(self.hi, dtype=F64)
        if lo.ndim != 2 or lo.shape != hi.shape or not (torch.isfinite(lo).all() and torch.isfinite(hi).all()):
            raise ValueError(f"open boxes need finite (B, n) corners of one shape, got {tuple(lo.shape)} and "
                             f"{tuple(hi.shape)}")
        if bool((lo > hi).any()):
            raise ValueError("open boxes need lo <= hi in every coordinate")
        if not (self.weight >= 0 and self.batch >= 1):
            raise ValueError(f"open boxes need weight >= 0 and batch >= 1, got {self.weight} and {self.batch}")
        self.lo, self.hi = lo, hi

    def __len__(self) -> int:
        return int(self.lo.shape[0])

    def to(self, device: torch.device) -> OpenBoxes:
        """The same boxes on ``device``."""
        return OpenBoxes(self.lo.to(device), self.hi.to(device), self.level, self.enclosure, self.weight, self.margin,
                         self.batch)

    def upper(self, loop, condition, index: Tensor | None = None) -> Tensor:
        """The verifier's upper bound ``(B,)`` of the residual over the boxes (those of ``index``), differentiable in
        the weights of ``loop``'s networks."""
        lo, hi = (self.lo, self.hi) if index is None else (self.lo[index], self.hi[index])
        with weight_gradients():
            return bound_condition(loop, condition, self.level, self.enclosure, lo, hi).upper

    def loss(self, loop, condition, generator: torch.Generator) -> Tensor:
        """``weight`` times the mean of ``(upper + margin)_+`` over ``batch`` boxes drawn without replacement."""
        count = len(self)
        index = torch.randperm(count, generator=generator)[:self.batch].to(self.lo.device)
        upper = self.upper(loop, condition, index)
        upper = torch.where(torch.isfinite(upper), upper, -torch.inf)  # undefined bounds (+inf) add nothing
        return self.weight * torch.relu(upper + self.margin).mean()
