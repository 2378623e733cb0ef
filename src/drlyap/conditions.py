"""Lyapunov decrease conditions and their training losses (paper Sec. IV-V, SPEC §3).

Every condition is a swappable piece with two methods:

* ``residual(terms) -> (B,)``: a per-state quantity; the condition holds at the states of the batch
  if and only if every entry is ``<= 0``. The verifier bounds exactly this quantity.
* ``loss(terms) -> scalar``: the training loss, zero exactly when the condition holds at every
  state of the batch (the mean of the positive parts of the residual, or of one scalar residual).

The per-state ingredients are collected once in :class:`DecreaseTerms` from the design model
``xdot = f(x, u) + W(x, u) xi``:

* ``vdot[i, j] = grad V(x_i) . (f(x_i, pi(x_i)) + W(x_i, pi(x_i)) xi_j)``   (``eq: V_dot_uncertain``)
* ``lip[i] = || W(x_i, pi(x_i))^T grad V(x_i) ||``                       (the Lipschitz constant of Vdot in xi)
* ``decay[i] = gamma ||z_i|| + alpha V(z_i)``                               (``alpha > 0``: the exponential variant)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from drlyap.networks import Controller, Lyapunov
from drlyap.systems import UncertainSystem


@dataclass
class DecreaseTerms:
    """Per-state terms of the decrease conditions for a batch of B states and N samples of xi."""

    vdot: Tensor  # (B, N) Lyapunov derivative under each sample
    lip: Tensor  # (B,) ||W^T grad V||
    decay: Tensor  # (B,) gamma ||z|| + alpha V


def decrease_terms(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, z: Tensor,
                   xi_samples: Tensor, decay_rate: float, exp_rate: float = 0.0) -> DecreaseTerms:
    """Evaluate :class:`DecreaseTerms` at local states ``z (B, n)`` for ``xi_samples (N, k)``."""
    value, grad_v = lyapunov.value_and_grad(z)
    x = system.to_user(z)
    u = controller(z)
    gf, gw = system.weighted_design(x, u, grad_v)
    vdot = gf[:, None] + gw @ xi_samples.T
    lip = torch.sqrt((gw * gw).sum(-1) + 1e-30)
    decay = decay_rate * torch.sqrt((z * z).sum(-1) + 1e-30)
    if exp_rate:
        decay = decay + exp_rate * value
    return DecreaseTerms(vdot=vdot, lip=lip, decay=decay)


def cvar_bound(h: Tensor, risk_level: float) -> Tensor:
    """The sample CVaR term of Proposition 1 (``eq: dr_clf_constraint_relaxed``) along the last axis.

    With ``h`` sorted decreasingly and ``j = ceil(eps N)``:
    ``(1 / (N eps)) sum_{i < j} (h_i - h_j) + h_j``, which equals
    ``(1/eps) inf_t [ mean_i (h_i + t)_+ - t eps ]`` (``eq: prop_1_eq2``) and reduces to ``max_i h_i``
    when ``eps <= 1/N``. ``h`` is ``(..., N)``; returns ``(...)``.
    """
    n = h.shape[-1]
    if not 0 < risk_level < 1:
        raise ValueError(f"risk level eps must be in (0, 1), got {risk_level}")
    j = max(1, math.ceil(risk_level * n - 1e-12))
    if j == 1:
        return h.max(dim=-1).values
    top, _ = torch.topk(h, j, dim=-1)
    hj = top[..., -1]
    return (top[..., :-1] - hj[..., None]).sum(-1) / (n * risk_level) + hj


class Condition:
    """Base class: a decrease condition over a batch of states."""

    name = "condition"

    def residual(self, terms: DecreaseTerms) -> Tensor:
        raise NotImplementedError

    def loss(self, terms: DecreaseTerms, margin: float = 0.0) -> Tensor:
        """Mean of ``(residual + margin)_+``; with ``margin = 0`` it is zero iff the condition holds."""
        return torch.relu(self.residual(terms) + margin).mean()

    def describe(self) -> dict:
        return {"name": self.name}


class Nominal(Condition):
    """``Vdot(x, xi_bar) + gamma ||x|| <= 0`` at the mean sample (``eq: clf_loss``): the baseline.

    ``terms`` must be built with the single sample ``xi_bar`` (shape ``(1, k)``).
    """

    name = "nominal"

    def residual(self, terms: DecreaseTerms) -> Tensor:
        if terms.vdot.shape[1] != 1:
            raise ValueError("the nominal condition takes exactly one xi (the sample mean)")
        return terms.vdot[:, 0] + terms.decay


class DRPointwise(Condition):
    """Pointwise DR condition (``eq: point_ccp`` / ``eq: point_dr_lf_loss``) at every state x::

        (r/eps) ||W^T grad V(x)|| + CVaR_eps_j( Vdot(x, xi_j) ) + decay(x) <= 0

    (``CVaR`` is :func:`cvar_bound`: ``max_j`` when ``eps <= 1/N``).
    """

    name = "pointwise"

    def __init__(self, wasserstein_radius: float, risk_level: float) -> None:
        self.r, self.eps = float(wasserstein_radius), float(risk_level)

    def residual(self, terms: DecreaseTerms) -> Tensor:
        return self.r / self.eps * terms.lip + cvar_bound(terms.vdot + terms.decay[:, None], self.eps)

    def describe(self) -> dict:
        return {"name": self.name, "wasserstein_radius": self.r, "risk_level": self.eps}


class DRUniform(Condition):
    """Uniform DR condition (``eq: dr_clf_constraint_relaxed``) over the states of the batch::

        (r/eps) max_x ||W^T grad V(x)|| + CVaR_eps_j( h(xi_j) ) <= 0,  h(xi) = max_x (Vdot(x, xi) + decay(x))

    For ``eps <= 1/N`` the per-state residual ``(r/eps) L_h + max_j Vdot(x, xi_j) + decay(x)`` has all
    entries <= 0 exactly when the condition holds, and its hinge mean is the training loss (the paper's
    ``eq: dr_lf_loss`` with the sum over states moved outside the max, so that a zero loss means the
    condition holds at every training state). For ``eps > 1/N`` the CVaR of the per-sample suprema does
    not split over states, so the residual is the single exact value (shape ``(1,)``) and the loss its
    positive part.
    """

    name = "uniform"

    def __init__(self, wasserstein_radius: float, risk_level: float) -> None:
        self.r, self.eps = float(wasserstein_radius), float(risk_level)

    def residual(self, terms: DecreaseTerms) -> Tensor:
        shifted = terms.vdot + terms.decay[:, None]
        lip_term = self.r / self.eps * terms.lip.max()
        n = shifted.shape[1]
        if self.eps <= 1.0 / n:
            return lip_term + shifted.max(dim=1).values
        return (lip_term + cvar_bound(shifted.max(dim=0).values, self.eps)).reshape(1)

    def describe(self) -> dict:
        return {"name": self.name, "wasserstein_radius": self.r, "risk_level": self.eps}


def make_condition(method: str, loss: str, wasserstein_radius: float, risk_level: float) -> Condition:
    """The condition for a training method (``baseline`` or ``dr``) and DR loss (``pointwise``/``uniform``)."""
    if method == "baseline":
        return Nominal()
    if method != "dr":
        raise ValueError(f"unknown method {method!r}; valid: baseline, dr")
    if wasserstein_radius < 0 or not math.isfinite(wasserstein_radius):
        raise ValueError(f"Wasserstein radius must be finite and >= 0, got {wasserstein_radius}")
    if loss == "pointwise":
        return DRPointwise(wasserstein_radius, risk_level)
    if loss == "uniform":
        return DRUniform(wasserstein_radius, risk_level)
    raise ValueError(f"unknown DR loss {loss!r}; valid: pointwise, uniform")


def wasserstein_radius_guarantee(c1: float, c2: float, rho: float, k: int, n_samples: int,
                                 confidence_slack: float) -> float:
    """The radius ``r_N(eps_bar)`` of ``eq: wasserstein_r_guarantee`` (Esfahani & Kuhn, Thm 3.4).

    With it, the Wasserstein ball around the N-sample empirical distribution contains the true
    (light-tailed) distribution with probability at least ``1 - eps_bar`` (``confidence_slack``).
    ``c1, c2`` are the constants of that theorem (they depend on ``rho``, the light-tail constant and ``k``).
    """
    if c1 <= 0 or c2 <= 0 or rho <= 0 or k < 1 or n_samples < 1:
        raise ValueError("need c1 > 0, c2 > 0, rho > 0, k >= 1, N >= 1")
    if not 0 < confidence_slack < 1:
        raise ValueError(f"eps_bar must be in (0, 1), got {confidence_slack}")
    a = math.log(c1 / confidence_slack) / c2
    if a <= 0:
        return 0.0
    exponent = 1.0 / max(k, 2) if n_samples >= a else 1.0 / rho
    return (a / n_samples) ** exponent
