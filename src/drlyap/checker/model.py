"""The checker's reading of a certificate's claim: the networks V and pi from their weights, and the residual of the
claimed condition, written with the checker's own arithmetic (:mod:`drlyap.checker.arith`), not with the library's
networks, conditions or enclosures. Only the system's dynamics are shared: they are the user's code, run here on the
checker's intervals and duals.

States are local coordinates ``z = x - x*`` (``(B, n)``). The formulas are the ones docs/method.md states:

* ``V(z) = ||phi(z) - phi(0)||^2 + alpha_hat ||z / s||^2`` with ``phi`` a tanh MLP on ``z / s`` plus, where the
  weights hold one (``phi.skip.weight``), a linear map of ``z / s``;
* ``pi(z) = u* + clamp(varphi(z) - varphi(0), U - u*)``, ``varphi`` the same kind of network (``varphi.skip.weight``);
* ``Vdot_j = grad V . (f + W xi_j)`` on the design model (``W = dF/dp`` at the nominal parameters, in the uncertain
  ones) or ``grad V . F(x, u, p0 + E xi_j)`` on the true model; ``decay = gamma ||z|| + alpha V``;
* components ``Vdot_j + decay`` (+ ``(r / eps) ||W^T grad V||`` for the DR pointwise condition), combined by the
  maximum or the sample CVaR (both non-decreasing in every component);
* for the DR uniform condition, components ``(||W^T grad V||, Vdot_j + decay)``, combined by
  ``(r / eps) L + CVaR_j h_j`` (non-decreasing too): at a state that is the uniform condition's margin with the
  suprema taken there alone, and over a set of boxes its margin from the suprema of the components over all of
  them (:mod:`drlyap.checker.uniform`).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable

import torch
from torch import Tensor

from drlyap.checker.affine import Af
from drlyap.checker.arith import EPS, F64, TINY, Du, Iv, lift
from drlyap.checker.quadratic import quad_max_minus

CONDITIONS = ("nominal", "pointwise", "uniform", "plain", "true")


class Mlp:
    """A tanh MLP from its state dict entries ``{prefix}layers.{i}.weight/bias`` and ``{prefix}input_scale``."""

    def __init__(self, state: dict[str, Tensor], prefix: str) -> None:
        head = prefix + "layers."
        count = len({k[len(head):].split(".")[0] for k in state if k.startswith(head)})
        self.weights = [state[f"{prefix}layers.{i}.weight"].to(F64) for i in range(count)]
        self.biases = [state[f"{prefix}layers.{i}.bias"].to(F64) for i in range(count)]
        self.scale = state[f"{prefix}input_scale"].to(F64)
        skip = state.get(f"{prefix}skip.weight")
        self.skip = None if skip is None else skip.to(F64)  # the linear path beside the hidden layers, if any
        if count < 1:
            raise ValueError(f"no layers under {prefix!r}")

    def forward(self, z) -> tuple[object, list]:
        h = zs = z / self.scale
        hidden = []
        for w, b in zip(self.weights[:-1], self.biases[:-1]):
            h = h.linear(w, b).tanh()
            hidden.append(h)
        out = h.linear(self.weights[-1], self.biases[-1])
        return (out if self.skip is None else out + zs.linear(self.skip)), hidden

    def at_origin(self, n: int) -> Iv:
        return self.forward(Iv.point(torch.zeros(1, n, dtype=F64, device=self.scale.device)))[0]

    def to(self, device: torch.device | str) -> Mlp:
        """The same network with its weights on ``device``."""
        out = copy.copy(self)
        out.weights = [w.to(device) for w in self.weights]
        out.biases = [b.to(device) for b in self.biases]
        out.scale = self.scale.to(device)
        out.skip = None if self.skip is None else self.skip.to(device)
        return out


class Pair:
    """V and pi of a run, read from ``weights.pt``'s state dicts (``lyapunov``, ``controller``)."""

    def __init__(self, weights: dict, alpha_hat: float, n: int) -> None:
        self.phi = Mlp(weights["lyapunov"], "phi.")
        self.varphi = Mlp(weights["controller"], "varphi.")
        ctrl = weights["controller"]
        self.u_star, self.low, self.high = (ctrl[k].to(F64) for k in ("u_star", "room_low", "room_high"))
        self.alpha_hat, self.n = float(alpha_hat), n
        self.phi0, self.varphi0 = self.phi.at_origin(n), self.varphi.at_origin(n)

    def to(self, device: torch.device | str) -> Pair:
        """The same pair with its weights and constants on ``device``."""
        out = copy.copy(self)
        out.phi, out.varphi = self.phi.to(device), self.varphi.to(device)
        out.u_star, out.low, out.high = (t.to(device) for t in (self.u_star, self.low, self.high))
        out.phi0, out.varphi0 = out.phi.at_origin(self.n), out.varphi.at_origin(self.n)
        return out

    def value(self, z):
        """V alone (no gradient): ``||phi(z) - phi(0)||^2 + alpha_hat ||z / s||^2``."""
        d = self.phi.forward(z)[0] - self.phi0
        zs = z / self.phi.scale
        return d.square().sum(-1) + zs.square().sum(-1) * self.alpha_hat

    def value_and_grad(self, z) -> tuple[object, object]:
        out, hidden = self.phi.forward(z)
        d = out - self.phi0
        zs = z / self.phi.scale
        value = d.square().sum(-1) + zs.square().sum(-1) * self.alpha_hat
        g = (d * 2.0).linear(self.phi.weights[-1].T)
        for i in range(len(hidden) - 1, -1, -1):
            g = (g * (1.0 - hidden[i].square())).linear(self.phi.weights[i].T)
        if self.phi.skip is not None:
            g = g + (d * 2.0).linear(self.phi.skip.T)
        return value, g / self.phi.scale + zs / self.phi.scale * (2.0 * self.alpha_hat)

    def controller(self, z):
        raw = self.varphi.forward(z)[0] - self.varphi0
        return raw.clamp(self.low, self.high) + self.u_star


class Residual:
    """The claimed condition's components ``(B, Q)`` at local states, and their combination.

    ``claim``: the certificate's ``claim.condition`` (name, model, xi, decay_rate, exp_rate, and for the DR condition
    wasserstein_radius, risk_level); ``system``: the run's :class:`~drlyap.systems.UncertainSystem` (its dynamics,
    nominal parameters, uncertain indices, equilibrium).
    """

    def __init__(self, claim: dict, pair: Pair, system) -> None:
        self.name = claim["name"]
        if self.name not in CONDITIONS:
            raise ValueError(f"the checker does not know the condition {self.name!r} (known: {', '.join(CONDITIONS)})")
        self.model = "true" if self.name == "true" else claim.get("model", "design")
        if self.model not in ("true", "design") or (self.model == "true" and self.name not in ("true", "plain")):
            raise ValueError(f"the {self.name!r} condition on the {self.model!r} model is not one drlyap states (the DR "
                             "and nominal conditions are on the design model)")
        k = len(system.uncertain_index)
        box = claim.get("xi_box")
        if box is not None:  # every shift in a box (the true model's condition only): each row a pair (low, high)
            if self.name != "true" or claim.get("xi") is not None:
                raise ValueError("a box of shifts is stated by the true model's condition alone, in place of xi")
            low, high = (torch.as_tensor(box[key], dtype=F64) for key in ("low", "high"))
            if low.shape != high.shape or low.ndim != 2 or low.shape[1] != k or not bool((low <= high).all()):
                raise ValueError(f"the claim's box of shifts is not (N, {k}) lows below highs")
            self.xi = torch.stack([low, high], 1)  # (N, 2, k)
        else:
            self.xi = torch.as_tensor(claim["xi"], dtype=F64)
            if self.xi.ndim != 2 or self.xi.shape[1] != k or self.xi.shape[0] < 1:
                raise ValueError(f"the claim's xi is not (N, {k}): one row of the {k} uncertain parameters per sample")
            if self.name == "nominal" and self.xi.shape[0] != 1:
                raise ValueError("the nominal condition takes exactly one xi (the sample mean)")
        if not bool(torch.isfinite(self.xi).all()):
            raise ValueError("the claim's shifts are not finite")
        self.xi_box = box is not None
        self.gamma, self.alpha = float(claim.get("decay_rate") or 0.0), float(claim.get("exp_rate") or 0.0)
        self.r = float(claim.get("wasserstein_radius") or 0.0)
        self.eps = 1.0 if claim.get("risk_level") is None else float(claim["risk_level"])  # 0 is stated, not absent
        if not all(math.isfinite(v) and v >= 0 for v in (self.gamma, self.alpha, self.r)) or not 0 < self.eps <= 1:
            raise ValueError("the claim's decay (gamma, alpha >= 0), Wasserstein radius (>= 0) or risk level (in (0, 1]) "
                             "is out of range")
        self.pair, self.system = pair, system
        self.x_star = torch.as_tensor(system.equilibrium, dtype=F64)
        self.p0 = torch.as_tensor(system.nominal_params, dtype=F64)
        self.uncertain = list(system.uncertain_index)

    def to(self, device: torch.device | str) -> Residual:
        """The same residual with the pair, the samples and the constants on ``device``."""
        out = copy.copy(self)
        out.pair = self.pair.to(device)
        out.xi, out.x_star, out.p0 = self.xi.to(device), self.x_star.to(device), self.p0.to(device)
        return out

    def _params(self, z, batch: int, xi: Tensor | None):
        """The parameters ``p0 + E xi`` (``xi (k,)``, or ``(2, k)``: every shift between its rows) at ``z``'s level."""
        p = self.p0.expand(batch, -1).clone()
        if xi is not None:
            shift = Iv(xi[0].expand(batch, -1), xi[1].expand(batch, -1)) if self.xi_box else \
                Iv.point(xi.expand(batch, -1))
            shifted = Iv.point(p[:, self.uncertain]) + shift
            lo, hi = p.clone(), p.clone()
            lo[:, self.uncertain], hi[:, self.uncertain] = shifted.lo, shifted.hi
            return lift(Iv(lo, hi), z.level, z if z.level > 0 else None)
        return lift(Iv.point(p), z.level, z if z.level > 0 else None)

    def components(self, z) -> object:
        """``(B, Q)``: one component per sample of xi, for ``z`` an :class:`Iv`, a :class:`Du` or an :class:`Af` of
        local states."""
        return self.terms(z)[0]

    @property
    def has_norm(self) -> bool:
        """Whether the components hold the DR condition's norm ``||W^T grad V||`` (scaled by ``r / eps`` in the
        pointwise condition's)."""
        return self.model != "true" and (self.name == "uniform" or (self.name == "pointwise" and self.r > 0))

    def terms(self, z, flat_norm: bool = False) -> tuple[object, object]:
        """The components ``(B, Q)`` and V ``(B,)`` at ``z``. ``flat_norm``: the DR norm as the constant form of the
        interval norm of its vector's ranges (second-order forms ``z`` only), instead of its own second-order form:
        narrower where the sum of squares reaches near 0, but without the dependence on the box's coordinates that
        the rest of the residual may cancel against."""
        value, grad = self.pair.value_and_grad(z)
        if self.model == "true":
            vdots = [(grad * f).sum(-1) for f in self.fields(z)]
            lip = None
        else:
            s = (grad * self._design(z)).sum(-1)
            vdots = [s.v + sum((s.d[i] * float(xi[i]) for i in range(len(self.uncertain))), start=s.v * 0.0)
                     for xi in self.xi]
            lip = None
            if self.name in ("pointwise", "uniform"):
                vector = torch.stack(s.d, -1)
                lip = vector.constant(vector.interval(dual=True).norm()) if flat_norm else vector.norm()
        decay = value * 0.0
        if self.gamma:
            decay = decay + z.norm() * self.gamma
        if self.alpha:
            decay = decay + value * self.alpha
        if self.name == "uniform":
            return torch.stack([lip, *[v + decay for v in vdots]], -1), value
        extra = decay if lip is None else decay + lip * (self.r / self.eps)
        return torch.stack([v + extra for v in vdots], -1), value

    def fields(self, z) -> list:
        """The closed loop's right-hand side ``F_j(z) (B, n)`` of each sample's model (the true model at the shift,
        or the design model ``f + W xi_j``)."""
        if self.model == "true":
            x, u = z + self.x_star, self.pair.controller(z)
            return [self.system.dynamics(x, u, self._params(z, z.shape[0], xi)) for xi in self.xi]
        out = self._design(z)
        return [out.v + sum((out.d[i] * float(xi[i]) for i in range(len(self.uncertain))), start=out.v * 0.0)
                for xi in self.xi]

    def _design(self, z):
        """The design model at nominal parameters with tangents in the uncertain ones: ``.v`` is ``f (B, n)``, ``.d[i]``
        the column ``dF/dp_i`` of W."""
        if getattr(self.system, "perturbation", None) is not None:
            raise ValueError("the checker does not take systems with a hand-written perturbation matrix W")
        batch = z.shape[0]
        x, u = z + self.x_star, self.pair.controller(z)
        tangents = []
        for i in self.uncertain:
            e = torch.zeros(batch, self.p0.shape[0], dtype=F64, device=self.p0.device)
            e[:, i] = 1.0
            tangents.append(lift(Iv.point(e), z.level, z if z.level > 0 else None))
        dynamics: Callable = self.system.dynamics
        return dynamics(x, u, Du(self._params(z, batch, None), tangents))

    def combine_upper(self, upper: Tensor) -> Tensor:
        """An upper bound ``(B,)`` of the residual from upper bounds ``(B, Q)`` of its components."""
        if self.name == "uniform":
            lip = Iv.point(upper[..., 0]) * (Iv.point(self.r) / Iv.point(self.eps))
            return (lip + Iv.point(self._cvar_upper(upper[..., 1:]))).hi
        if self.name == "nominal" or upper.shape[-1] == 1:
            return upper[..., 0]
        if self.name in ("plain", "true"):
            return upper.amax(-1)
        return self._cvar_upper(upper)

    def _cvar_upper(self, upper: Tensor) -> Tensor:
        """An upper bound ``(B,)`` of the sample CVaR at ``eps`` of values with upper bounds ``upper (B, N)``."""
        count = upper.shape[-1]
        j = max(1, math.ceil(self.eps * count - 1e-12))
        if j == 1:
            return upper.amax(-1)
        top = torch.topk(upper, j, dim=-1).values
        hj = Iv.point(top[..., -1])
        spread = (Iv.point(top[..., :-1]) - hj.unsqueeze(-1)).sum(-1)
        return (spread / (Iv.point(float(count)) * Iv.point(self.eps)) + hj).hi


def radius(lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """Centres ``(B, n)`` of boxes and half-widths rounded up so that ``[c - r, c + r]`` holds each box."""
    centre = (lo + hi) / 2
    rad = torch.maximum(hi - centre, centre - lo)
    return centre, torch.nextafter(rad + EPS * rad, torch.full_like(rad, math.inf))


MULTIPLIERS = [0.0] + [2.0 ** j for j in range(-6, 11)]
"""The S-procedure's multipliers: powers of two, so that multiplying a form by one is exact."""
DUAL_TRIES = 4
"""How many of the multipliers (those with the least corner bound) are tried again with the dual bound."""


def affine_upper(residual: Residual, lo: Tensor, hi: Tensor, level: float | None = None) -> Tensor:
    """Upper bounds ``(B,)`` of the residual over the boxes ``[lo, hi] (B, n)`` from its components as second-order
    forms over each box (:class:`~drlyap.checker.affine.Af`). With ``level``: over the boxes' states where
    ``V <= level`` only, by the S-procedure: for any ``lam >= 0``, ``R <= R - lam (V - level)`` there, and the
    right side is again a form of the box's coordinates, bounded as one; the least bound over
    :data:`MULTIPLIERS`, for each component."""
    return form_upper(residual, *residual.terms(Af.seed(lo, hi)), level)


def form_upper(residual: Residual, comps: Af, value: Af, level: float | None) -> Tensor:
    """:func:`affine_upper` from the forms of the components ``(B, Q)`` and of V ``(B,)``: first with the corner
    bound of the quadratic parts, then, for the boxes that leaves above 0, with the dual bound too. With a level, the
    multiplier 0 alone first (most boxes of a sublevel-set proof need no other), then every one for the rest."""
    if level is not None:
        lam = torch.zeros(*comps.shape, 1, dtype=F64, device=comps.c.device)
        upper = residual.combine_upper(_s_procedure(comps, value, level, lam, dual=False)[..., 0])
        rest = (upper > 0).nonzero().squeeze(-1)
        if rest.numel():
            upper[rest] = torch.minimum(upper[rest], _searched_upper(residual, comps[rest], value[rest], level))
        return upper
    return _searched_upper(residual, comps, value, level)


def _searched_upper(residual: Residual, comps: Af, value: Af, level: float | None) -> Tensor:
    """:func:`form_upper` over every multiplier (with a level), the corner bound first, the dual one where needed."""
    def bound(c: Af, v: Af, dual: bool) -> Tensor:
        if level is None:
            upper = c.interval(dual=dual).hi
        else:
            upper = sublevel_form_upper(c, v, level, dual)
        return residual.combine_upper(torch.where(torch.isnan(upper), math.inf, upper))

    upper = bound(comps, value, False)
    again = (upper > 0).nonzero().squeeze(-1)
    if again.numel():
        upper[again] = torch.minimum(upper[again], bound(comps[again], value[again], True))
    return upper


def sublevel_form_upper(comps: Af, value: Af, level: float, dual: bool = True) -> Tensor:
    """``min over lam`` of an upper bound of ``comps - lam (value - level)`` (``comps (B, Q)``, ``value (B,)``
    forms of the same boxes) over the boxes: ``(B, Q)``, each multiplier's quadratic part bounded by the smaller of
    the corner and (``dual``) the dual bound (:func:`~drlyap.checker.affine.quad_max`)."""
    lam = torch.tensor(MULTIPLIERS, dtype=F64, device=comps.c.device).expand(*comps.shape, -1)  # (B, Q, L)
    corner = _s_procedure(comps, value, level, lam, dual=False)
    if not dual:
        return corner.amin(-1)
    best = lam.gather(-1, corner.topk(DUAL_TRIES, -1, largest=False).indices)  # the dual bound at the best few
    return torch.minimum(corner.amin(-1), _s_procedure(comps, value, level, best, dual=True).amin(-1))


def _s_procedure(comps: Af, value: Af, level: float, lam: Tensor, dual: bool) -> Tensor:
    """Upper bounds ``(B, Q, L)`` of ``comps - lam (value - level)`` for multipliers ``lam (B, Q, L)`` (powers of
    two: the products with them are exact)."""
    shift = value.c - level  # (B,)
    c = comps.c[..., None] - lam * shift[:, None, None]  # (B, Q, L)
    cmag, vmag = comps._lmag() + comps._qmag(), value._lmag() + value._qmag()  # |l|_1 + |q|_1, kept by the forms
    mag = c.abs() + lam * shift.abs()[:, None, None] + 2 * lam * vmag[:, None, None] + 2 * cmag[..., None]
    rest = comps.r.hi[..., None] - lam * value.r.lo[:, None, None]
    top = c + quad_max_minus(comps.l, comps.q, value.l, value.q, lam, dual, (cmag, vmag)) + rest
    upper = top + 8 * EPS * (mag + rest.abs() + top.abs()) + TINY
    upper = torch.nextafter(upper, torch.full_like(upper, math.inf))
    return torch.where(torch.isnan(upper), math.inf, upper)


def upper_bounds(residual: Residual, lo: Tensor, hi: Tensor) -> Tensor:
    """Upper bounds ``(B,)`` of the residual over the boxes ``[lo, hi] (B, n)``: of its components'
    :func:`component_upper`, combined."""
    return residual.combine_upper(component_upper(residual, lo, hi))


def component_upper(residual: Residual, lo: Tensor, hi: Tensor) -> Tensor:
    """Upper bounds ``(B, Q)`` of the residual's components over the boxes ``[lo, hi] (B, n)``: the tighter of the
    interval bound and the mean-value form ``f(c) + sum_i |df/dz_i over the box| r_i`` (``inf`` where NaN)."""
    n = lo.shape[1]
    centre, rad = radius(lo, hi)
    at_centre = residual.components(Iv.point(centre))
    form = residual.components(Du.seed(Iv(lo, hi), n, list(range(n))))
    spread = Iv.point(torch.zeros_like(at_centre.hi))
    for i, t in enumerate(form.d):
        spread = spread + Iv.point(t.mag()) * Iv.point(rad[:, i:i + 1])
    mean_value = (Iv.point(at_centre.hi) + spread).hi
    upper = torch.minimum(form.v.hi, mean_value)
    return torch.where(torch.isnan(upper), math.inf, upper)


def centre_lower(residual: Residual, lo: Tensor, hi: Tensor) -> Tensor:
    """Lower bounds ``(B,)`` of the residual at the boxes' centres."""
    return _combine_lower(residual, residual.components(Iv.point(radius(lo, hi)[0])).lo)


def _combine_lower(residual: Residual, lower: Tensor) -> Tensor:
    """A lower bound of the residual from lower bounds of its components (the combination is monotone): the
    negated upper bound of the negated components is not the same formula, so the maximum/CVaR is computed and
    lowered by its rounding pad."""
    values = lower[..., 1:] if residual.name == "uniform" else lower
    if residual.name == "nominal" or values.shape[-1] == 1:
        out = values[..., 0]
    elif residual.name in ("plain", "true"):
        out = values.amax(-1)
    else:
        count = values.shape[-1]
        j = max(1, math.ceil(residual.eps * count - 1e-12))
        top = torch.topk(values, j, dim=-1).values
        hj = top[..., -1]
        out = (top[..., :-1] - hj[..., None]).sum(-1) / (count * residual.eps) + hj if j > 1 else top[..., 0]
    scale = 1.0
    if residual.name == "uniform":
        out = out + lower[..., 0] * (residual.r / residual.eps)
        scale = 1.0 + residual.r / residual.eps
    pad = 64 * EPS * lower.abs().amax(-1) * scale + 1e-300
    return torch.where(torch.isnan(out), -math.inf, out - pad)


def value_bounds(pair: Pair, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """Lower and upper bounds ``(B,)`` each of V over the boxes ``[lo, hi] (B, n)``: the tightest of the affine form,
    the interval bound and the mean-value form ``V(c) -+ sum_i |dV/dz_i over the box| r_i`` (a NaN bound is
    ``-inf`` / ``inf``)."""
    n = lo.shape[1]
    centre, rad = radius(lo, hi)
    at_centre = pair.value_and_grad(Iv.point(centre))[0]
    form = pair.value_and_grad(Du.seed(Iv(lo, hi), n, list(range(n))))[0]
    spread = Iv.point(torch.zeros_like(at_centre.lo))
    for i, t in enumerate(form.d):
        spread = spread + Iv.point(t.mag()) * Iv.point(rad[:, i])
    affine = pair.value_and_grad(Af.seed(lo, hi))[0].interval(dual=True)
    lower = torch.maximum(torch.maximum(form.v.lo, (Iv.point(at_centre.lo) - spread).lo), affine.lo)
    upper = torch.minimum(torch.minimum(form.v.hi, (Iv.point(at_centre.hi) + spread).hi), affine.hi)
    return torch.where(torch.isnan(lower), -math.inf, lower), torch.where(torch.isnan(upper), math.inf, upper)


def value_lower(pair: Pair, lo: Tensor, hi: Tensor) -> Tensor:
    """Lower bounds ``(B,)`` of V over the boxes ``[lo, hi] (B, n)`` (:func:`value_bounds`)."""
    return value_bounds(pair, lo, hi)[0]
