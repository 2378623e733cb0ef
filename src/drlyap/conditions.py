"""Lyapunov decrease conditions: one object each, for training, checks, CEGIS and the verifier (SPEC §3).

A condition knows its samples of xi, its decay term and, for the DR conditions, the Wasserstein radius
r and risk level eps. It computes, from a batch of local states ``z (B, n)``:

* ``terms(loop, z)`` -> :class:`DecreaseTerms` (the per-state ingredients) for a closed loop
  (:class:`~drlyap.closed_loop.ClosedLoop`: the system, V and pi);
* ``components(terms) -> (B, Q)`` and ``combine(components) -> (B,)``: the residual is
  ``combine(components(terms))``; ``combine`` is non-decreasing in every component, so upper bounds of
  the components give an upper bound of the residual. The condition holds at the states of the batch
  if and only if every entry of the residual is ``<= 0``;
* ``loss(terms, margin)``: the training loss, the mean of ``(residual + margin)_+`` (zero exactly when the
  condition holds at every state of the batch for ``margin = 0``).

All of it is written with torch operations that also run on the enclosure types of
:mod:`drlyap.enclosures`: the verifier calls ``terms`` and ``components`` of the *same object* on boxes,
so what is proved is exactly what training minimised (no second encoding of any formula).

Per-state ingredients (:func:`decrease_terms`):

* ``vdot[i, j] = grad V(x_i) . xdot(x_i, pi(x_i), xi_j)`` on the design model ``f + W xi_j``
  (``eq: V_dot_uncertain``) or, for :class:`TrueDecrease`, on the true model ``F(x, u, p0 + xi_j)``;
* ``lip[i] = || W(x_i, pi(x_i))^T grad V(x_i) ||`` (the Lipschitz constant of Vdot in xi; design model only);
* ``decay[i] = gamma ||z_i|| + alpha V(z_i)`` (``alpha > 0``: the exponential variant).

:func:`local_rates` gives V's second-order decay rate at x* on each sample's model, from the same ``vdot``
(what the training's local term and the acceptance check ask to be negative).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor

from drlyap.enclosures import is_enclosure, norm
from drlyap.kinds import Loss, Method, Model


@dataclass
class DecreaseTerms:
    """Per-state terms of the decrease conditions for a batch of B states and N samples of xi."""

    vdot: Tensor  # (B, N) Lyapunov derivative under each sample
    lip: Tensor | None  # (B,) ||W^T grad V|| (design model; None on the true model)
    decay: Tensor  # (B,) gamma ||z|| + alpha V
    value: Tensor | None = None  # (B,) V(z) itself (what a sublevel-set condition restricts by)


def euclidean_norm(x: Tensor) -> Tensor:
    """``||x||`` along the last axis. Smoothed at 0 (``sqrt(|x|^2 + 1e-30)``) only where gradients flow in
    training; exact on plain tensors and on enclosures (with a Clarke-gradient enclosure at 0)."""
    if is_enclosure(x):
        return norm(x, -1)
    if x.requires_grad:
        return torch.sqrt(x.square().sum(-1) + 1e-30)
    return torch.linalg.vector_norm(x, dim=-1)


def decrease_terms(loop, z: Tensor, xi_samples: Tensor, decay_rate: float, exp_rate: float = 0.0,
                   model: Model = Model.DESIGN, with_lip: bool = True) -> DecreaseTerms:
    """Evaluate :class:`DecreaseTerms` of a closed loop (:class:`~drlyap.closed_loop.ClosedLoop`) at local states
    ``z (B, n)`` for ``xi_samples (N, k)``.

    ``model``: ``design`` (``f + W xi``, the training model) or ``true`` (``F(x, u, p0 + xi)``). ``z`` may be a
    tensor or an enclosure (then ``xi_samples`` may also be an interval ``(N, k)`` on the true model).
    ``with_lip=False`` skips ``lip`` (None). Zero decay rates add no norm term.
    """
    system = loop.system
    value, grad_v = loop.lyapunov.value_and_grad(z)
    x = system.to_user(z)
    u = loop.controller(z)
    if model == Model.DESIGN:
        gf, gw = system.weighted_design(x, u, grad_v)
        vdot = gf.unsqueeze(-1) + F.linear(gw, xi_samples)
        lip = euclidean_norm(gw) if with_lip else None
    elif model == Model.TRUE:
        vdot = torch.stack([(grad_v * system.true_dynamics(x, u, xi)).sum(-1) for xi in xi_samples], -1)
        lip = None
    else:
        raise ValueError(f"unknown model {model!r}; valid: design, true")
    decay = euclidean_norm(z) * decay_rate if decay_rate else value * 0.0
    if exp_rate:
        decay = decay + value * exp_rate
    return DecreaseTerms(vdot=vdot, lip=lip, decay=decay, value=value)


def local_rates(condition: Condition, loop) -> Tensor:
    """``(N,)``: V's second-order decay rate at x* of a closed loop on each sample's model of ``condition`` (its
    samples, its model).

    With ``H_V`` V's Hessian at x* and ``H_j`` the Hessian there of sample j's ``Vdot`` (the condition's own
    ``vdot``, so the very formula training and the verifier use), both ``V`` and ``Vdot`` are quadratic to second
    order (``V(0) = 0``, ``grad V(0) = 0``, x* an equilibrium), and ``Vdot <= lambda_j V + o(||z||^2)`` with
    ``lambda_j`` the largest generalised eigenvalue of ``(H_j, H_V)``. ``lambda_j < 0``: V is a strict Lyapunov
    function of that model's linearisation (``-lambda_j`` its local exponential rate); ``lambda_j > 0``: V rises
    along some direction arbitrarily close to x*, so no sublevel set of V is shown invariant by V's own decrease.
    Differentiable in the networks' weights (second derivatives by batched double backward passes); ``H_V`` is
    positive definite by V's construction (``alpha_hat > 0``); NaN where it cannot be factored (non-finite weights).
    """
    ref = next(iter([*loop.lyapunov.parameters(), *loop.lyapunov.buffers()]))
    n = loop.system.n
    z = torch.zeros(1, n, dtype=ref.dtype, device=ref.device, requires_grad=True)
    terms = decrease_terms(loop, z, condition._xi_for(z.detach()), 0.0, 0.0, condition.model, with_lip=False)
    f = torch.cat([terms.value, terms.vdot[0]])  # (1 + N,): V and every sample's Vdot
    k = f.shape[0]
    eye = torch.eye(k, dtype=f.dtype, device=f.device)
    grad = torch.autograd.grad(f, z, eye, create_graph=True, is_grads_batched=True)[0][:, 0]  # (1 + N, n)
    eye = torch.eye(k * n, dtype=f.dtype, device=f.device)
    hess = torch.autograd.grad(grad.flatten(), z, eye, create_graph=True, is_grads_batched=True)[0].reshape(k, n, n)
    hess = hess.double()  # V's Hessian may be conditioned 1e5 (the mountain car's): factor it in float64
    chol, info = torch.linalg.cholesky_ex((hess[0] + hess[0].mT) / 2)
    if int(info):  # not finite (diverged weights): no rate, and a loss built on it reads as diverged
        return torch.full((k - 1,), math.nan, dtype=ref.dtype, device=ref.device)
    m = torch.linalg.solve_triangular(chol, hess[1:], upper=False)  # L^-1 H_j, then L^-1 (L^-1 H_j)^T
    m = torch.linalg.solve_triangular(chol, m.mT, upper=False)
    return torch.linalg.eigvalsh((m + m.mT) / 2)[:, -1].to(ref.dtype)


def cvar_bound(h: Tensor, risk_level: float) -> Tensor:
    """The sample CVaR term of Proposition 1 (``eq: dr_clf_constraint_relaxed``) along the last axis.

    With ``h`` sorted decreasingly and ``j = ceil(eps N)``:
    ``(1 / (N eps)) sum_{i < j} (h_i - h_j) + h_j``, which equals
    ``(1/eps) inf_t [ mean_i (h_i + t)_+ - t eps ]`` (``eq: prop_1_eq2``) and reduces to ``max_i h_i``
    when ``eps <= 1/N``. ``h`` is ``(..., N)``; returns ``(...)``. Non-decreasing in every entry of ``h``.
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
    """Base class: a decrease condition over a batch of states (see the module docstring).

    ``xi_samples (N, k)``: the samples of xi the condition uses; ``decay_rate`` gamma and ``exp_rate`` alpha of
    the decay term. ``per_state``: whether ``residual`` has one entry per state (all but the uniform DR
    condition). ``model``: ``design`` or ``true``.
    """

    name = "condition"
    label = "condition"
    model = Model.DESIGN
    per_state = True
    uses_lip = False  # whether the components need ||W^T grad V|| (the DR conditions)

    def __init__(self, xi_samples: Tensor | None = None, decay_rate: float = 0.0, exp_rate: float = 0.0) -> None:
        if xi_samples is not None and not is_enclosure(xi_samples):
            xi_samples = torch.as_tensor(xi_samples, dtype=torch.float64)
            if xi_samples.ndim <= 1:
                xi_samples = xi_samples.reshape(1, -1)
            if xi_samples.ndim != 2 or xi_samples.numel() == 0 or not bool(torch.isfinite(xi_samples).all()):
                raise ValueError(f"xi samples must be a finite (N, k) array, got shape {tuple(xi_samples.shape)}")
        decay_rate, exp_rate = decay_rate or 0.0, exp_rate or 0.0  # None (an unresolved config's field): none
        for what, value in (("decay rate", decay_rate), ("exp rate", exp_rate)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{what} must be finite and >= 0, got {value}")
        self.xi = xi_samples
        self.decay_rate, self.exp_rate = float(decay_rate), float(exp_rate)
        self._xi_cache: dict = {}

    def _xi_for(self, z) -> Tensor:
        if self.xi is None:
            raise ValueError(f"the {self.label} condition was built without xi samples")
        if is_enclosure(z):
            return self.xi
        if is_enclosure(self.xi):
            return self._xi_box_on_points(z)
        key = (z.dtype, z.device)
        if key not in self._xi_cache:
            self._xi_cache[key] = self.xi.to(dtype=z.dtype, device=z.device)
        return self._xi_cache[key]

    def _xi_box_on_points(self, z: Tensor) -> Tensor:
        raise ValueError(f"the {self.label} condition takes an interval box of xi on enclosures only; "
                         "on plain states use PlainDecrease / TrueDecrease (evaluated at the box's corners)")

    def terms(self, loop, z: Tensor) -> DecreaseTerms:
        """:func:`decrease_terms` of a closed loop at local states ``z (B, n)`` (a tensor or an enclosure)."""
        return decrease_terms(loop, z, self._xi_for(z), self.decay_rate, self.exp_rate, self.model,
                              with_lip=self.uses_lip)

    def components(self, terms: DecreaseTerms) -> Tensor:
        raise NotImplementedError

    def combine(self, components: Tensor) -> Tensor:
        raise NotImplementedError

    def residual(self, terms: DecreaseTerms) -> Tensor:
        """The residual ``(B,)``: the condition holds at a state iff its entry is ``<= 0``."""
        return self.combine(self.components(terms))

    def loss(self, terms: DecreaseTerms, margin: float = 0.0, margin_rate: float = 0.0,
             level: float | None = None, outside: float = 0.0, exclude: float = 0.0) -> Tensor:
        """Mean of ``(residual + margin + margin_rate V)_+`` over the batch; with both margins 0 it is zero iff
        the condition holds at every state.

        ``level``: the condition is asked of the sublevel set ``{V <= level}`` (a region of attraction): the states
        with ``V > level`` count with the weight ``outside`` (0: not at all), and each state inside the set whose
        residual is positive adds ``exclude (level - V) / level``, which raises V there: a violation the
        controller cannot remove is left out of the set instead of being traded against the rest."""
        residual = self.residual(terms)
        hinge = residual + margin
        if margin_rate:
            hinge = hinge + terms.value * margin_rate
        hinge = torch.relu(hinge)
        if level is not None:
            inside = (terms.value <= level).detach().to(hinge.dtype)
            hinge = hinge * (inside + (1 - inside) * outside if outside else inside)
            if exclude:
                violating = (inside * (residual > 0).to(hinge.dtype)).detach()
                hinge = hinge + violating * torch.relu(level - terms.value) * (exclude / level)
        return hinge.mean()

    def per_sample(self, decay_rate: float = 0.0, exp_rate: float = 0.0) -> PlainDecrease | None:
        """The plain decrease condition, on the same model and samples, that this condition implies for every
        sample separately (with the given decay), or None when it implies none (a CVaR over several samples):
        what a trajectory statement ("V decreases along the flow of each sample's model") can rest on."""
        return None

    def describe(self) -> dict:
        return {"name": self.name, "decay_rate": self.decay_rate, "exp_rate": self.exp_rate}


class Nominal(Condition):
    """``Vdot(x, xi_bar) + gamma ||x|| <= 0`` at the mean sample (``eq: clf_loss``): the baseline.

    ``xi_samples`` is the single sample ``xi_bar`` (shape ``(1, k)``).
    """

    name = "nominal"
    label = "nominal (baseline)"

    def __init__(self, xi_samples: Tensor | None = None, decay_rate: float = 0.0, exp_rate: float = 0.0) -> None:
        super().__init__(xi_samples, decay_rate, exp_rate)
        if self.xi is not None and self.xi.shape[0] != 1:
            raise ValueError(f"the nominal condition takes exactly one xi (the sample mean), got {self.xi.shape[0]}")

    def components(self, terms: DecreaseTerms) -> Tensor:
        if terms.vdot.shape[1] != 1:
            raise ValueError("the nominal condition takes exactly one xi (the sample mean)")
        return terms.vdot + terms.decay.unsqueeze(-1)

    def combine(self, components: Tensor) -> Tensor:
        return components[..., 0]

    def per_sample(self, decay_rate: float = 0.0, exp_rate: float = 0.0) -> PlainDecrease | None:
        return PlainDecrease(self.xi, decay_rate, exp_rate, self.model)


class PlainDecrease(Condition):
    """Plain decrease ``Vdot(x, xi_j) + decay(x) <= 0`` for every sample j, on the ``model`` given
    (``design``: ``f + W xi``; ``true``: ``F(x, u, p0 + xi)``).

    ``xi_samples`` ``(N, k)`` may be an :class:`~drlyap.enclosures.Interval` box: on enclosures the condition is
    then proved for every shift in the box; on plain states it is evaluated at the box's corners (a real
    evaluation at real shifts, so a positive residual is a genuine violation).
    """

    name = "plain"

    def __init__(self, xi_samples: Tensor | None = None, decay_rate: float = 0.0, exp_rate: float = 0.0,
                 model: Model = Model.DESIGN) -> None:
        super().__init__(xi_samples, decay_rate, exp_rate)
        if model not in tuple(Model):
            raise ValueError(f"unknown model {model!r}; valid: design, true")
        self.model = model
        self.label = "true model at xi" if model == Model.TRUE else "design model at the samples"

    def _xi_box_on_points(self, z: Tensor) -> Tensor:
        """On plain states, an interval box of xi ``(N, k)`` is evaluated at its ``N 2^k`` corners ``(N 2^k, k)``:
        the residual (the max over them) is then a real value at real shifts, a lower bound of the maximum
        over the box (what the verifier's counterexample check needs)."""
        lo, hi = self.xi.lo.to(dtype=z.dtype, device=z.device), self.xi.hi.to(dtype=z.dtype, device=z.device)
        k = lo.shape[-1]
        pick = torch.cartesian_prod(*[torch.tensor([False, True], device=z.device)] * k).reshape(-1, k)
        return torch.where(pick[None], hi[:, None], lo[:, None]).reshape(-1, k)

    def components(self, terms: DecreaseTerms) -> Tensor:
        return terms.vdot + terms.decay.unsqueeze(-1)

    def combine(self, components: Tensor) -> Tensor:
        return components.max(dim=-1).values if components.shape[-1] > 1 else components[..., 0]

    def per_sample(self, decay_rate: float = 0.0, exp_rate: float = 0.0) -> PlainDecrease | None:
        return PlainDecrease(self.xi, decay_rate, exp_rate, self.model)

    def describe(self) -> dict:
        return super().describe() | {"model": self.model}


def decay_at_shift(decay_rate: float, exp_rate: float, rate: float | None = None) -> tuple[float, float]:
    """``(gamma, alpha)`` of the decrease asked of the true model at a shift: a pair's own decay terms, or with
    ``rate`` the decay ``rate V`` alone in their place (``Vdot + rate V <= 0``, ``verify --roa-rate``)."""
    return (float(decay_rate), float(exp_rate)) if rate is None else (0.0, float(rate))


class TrueDecrease(PlainDecrease):
    """Plain decrease on the TRUE model at given shifts ``xi (N, k)`` (usually one): the condition that
    simulation tests, proved over the whole region."""

    name = "true"

    def __init__(self, xi_samples: Tensor | None = None, decay_rate: float = 0.0, exp_rate: float = 0.0) -> None:
        super().__init__(xi_samples, decay_rate, exp_rate, model="true")


class _DR(Condition):
    uses_lip = True

    def __init__(self, wasserstein_radius: float, risk_level: float, xi_samples: Tensor | None = None,
                 decay_rate: float = 0.0, exp_rate: float = 0.0) -> None:
        super().__init__(xi_samples, decay_rate, exp_rate)
        if not (math.isfinite(wasserstein_radius) and wasserstein_radius >= 0):
            raise ValueError(f"Wasserstein radius must be finite and >= 0, got {wasserstein_radius}")
        if not 0 < risk_level < 1:
            raise ValueError(f"risk level eps must be in (0, 1), got {risk_level}")
        self.r, self.eps = float(wasserstein_radius), float(risk_level)

    def with_radius(self, wasserstein_radius: float):
        """The same condition at another Wasserstein radius."""
        return type(self)(wasserstein_radius, self.eps, self.xi, self.decay_rate, self.exp_rate)

    def describe(self) -> dict:
        return super().describe() | {"wasserstein_radius": self.r, "risk_level": self.eps}

    def per_sample(self, decay_rate: float = 0.0, exp_rate: float = 0.0) -> PlainDecrease | None:
        """Plain decrease at every sample: implied where the CVaR is the maximum over the samples (``eps N <= 1``;
        the uniform condition's margin then bounds every sample's ``sup (Vdot + decay)`` by ``-(r/eps) L <= 0``)."""
        if self.xi is None or self.eps * self.xi.shape[0] > 1:  # the CVaR is then not the max over samples
            return None
        return PlainDecrease(self.xi, decay_rate, exp_rate, self.model)


class DRPointwise(_DR):
    """Pointwise DR condition (``eq: point_ccp`` / ``eq: point_dr_lf_loss``) at every state x::

        (r/eps) ||W^T grad V(x)|| + CVaR_eps_j( Vdot(x, xi_j) ) + decay(x) <= 0

    (``CVaR`` is :func:`cvar_bound`: ``max_j`` when ``eps <= 1/N``). Components: ``Vdot_j + decay + (r/eps) lip``.
    """

    name = "pointwise"
    label = "DR pointwise"

    def components(self, terms: DecreaseTerms) -> Tensor:
        return terms.vdot + (terms.decay + terms.lip * self.r / self.eps).unsqueeze(-1)

    def combine(self, components: Tensor) -> Tensor:
        return cvar_bound(components, self.eps)



class DRUniform(_DR):
    """Uniform DR condition (``eq: dr_clf_constraint_relaxed``) over the states of the batch::

        (r/eps) max_x ||W^T grad V(x)|| + CVaR_eps_j( h(xi_j) ) <= 0,  h(xi) = max_x (Vdot(x, xi) + decay(x))

    Components per state: ``(lip, Vdot_j + decay)``; :meth:`margin` combines their suprema over a set of
    states. For ``eps <= 1/N`` the per-state residual ``(r/eps) L_h + max_j Vdot(x, xi_j) + decay(x)`` (with
    ``L_h`` the batch maximum) has all entries <= 0 exactly when the condition holds, and its hinge mean is
    the training loss (the paper's ``eq: dr_lf_loss`` with the sum over states moved outside the max, so
    that a zero loss means the condition holds at every training state). For ``eps > 1/N`` the CVaR of the
    per-sample suprema does not split over states, so the residual is the single margin (shape ``(1,)``).
    """

    name = "uniform"
    label = "DR uniform"
    per_state = False

    def components(self, terms: DecreaseTerms) -> Tensor:
        return torch.cat([terms.lip.unsqueeze(-1), terms.vdot + terms.decay.unsqueeze(-1)], -1)

    def margin(self, suprema: Tensor) -> Tensor:
        """The condition's left side from the suprema ``(..., 1 + N)`` of the components over the states."""
        return suprema[..., 0] * self.r / self.eps + cvar_bound(suprema[..., 1:], self.eps)

    def combine(self, components: Tensor) -> Tensor:
        lip_term = components[:, 0].max() * self.r / self.eps
        shifted = components[:, 1:]
        if self.eps <= 1.0 / shifted.shape[1]:
            return lip_term + shifted.max(dim=1).values
        return self.margin(components.amax(0)).reshape(1)


def make_condition(method: str, loss: str, wasserstein_radius: float, risk_level: float,
                   xi_samples: Tensor | None = None, decay_rate: float = 0.0, exp_rate: float = 0.0) -> Condition:
    """The condition for a training method (``baseline`` or ``dr``) and DR loss (``pointwise``/``uniform``).

    ``xi_samples``: the samples the condition uses (for the baseline: their mean, shape ``(1, k)``).
    """
    if method == Method.BASELINE:
        return Nominal(xi_samples, decay_rate, exp_rate)
    if method != Method.DR:
        raise ValueError(f"unknown method {method!r}; valid: baseline, dr")
    if loss == Loss.POINTWISE:
        return DRPointwise(wasserstein_radius, risk_level, xi_samples, decay_rate, exp_rate)
    if loss == Loss.UNIFORM:
        return DRUniform(wasserstein_radius, risk_level, xi_samples, decay_rate, exp_rate)
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
