"""What the guarantees mean in numbers (SPEC §6): the probability behind the lemma, and the covering check.

:func:`guarantee` measures ``P(sup_{x in X_delta} Vdot(x, pi(x), xi) + gamma ||x - x*|| (+ alpha V) <= 0)`` on the
TRUE model ``F(x, u, p0 + xi)`` for ``xi`` drawn from a distribution (:func:`parse_distribution`), with an exact
(Clopper-Pearson) and a Wilson 95% interval, next to the bound ``(1 - eps)(1 - eps_bar)`` of
``lemma: dr_controller_guarantee``. Two ways to decide one draw:

* ``sampling``: the condition at every state of a dense grid of X_delta (:func:`drlyap.checks.validation_states`),
  batched over draws. A draw can pass the grid and still fail between grid points, so this fraction is an
  optimistic estimate;
* ``verifier``: the branch and bound of :mod:`drlyap.verification` for each distinct draw (time-limited).
  ``verified`` counts as holding, ``violated`` and ``unknown`` (time out) as not: a conservative estimate.

The bound assumes what the lemma assumes: a light-tailed true distribution, a radius ``r = r_N(eps_bar)`` of
``eq: wasserstein_r_guarantee`` (which needs the constants c1, c2, rho of Esfahani & Kuhn; pass them to get
``r_N`` and compare it with the run's radius), and a pair that satisfies the DR constraint (a DR run).

:func:`lipschitz_covering` is the covering argument of ``lemma: nominal_nn_lf`` / ``proposition: dr_controller_LF``
made concrete on a grid: if the residual ``c`` is ``L``-Lipschitz and every cell of a grid that meets X_delta has
``c(centre) <= -L rho`` (``rho`` = half the cell diagonal), then ``c <= 0`` on all of X_delta.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from drlyap.checks import validation_states
from drlyap.conditions import wasserstein_radius_guarantee
from drlyap.systems import UncertainSystem
from drlyap.verification import (
    ConditionSpec,
    Dual,
    Interval,
    PairBounds,
    box_grid,
    inside_ball,
    jsonable,
    run_condition,
    verify_condition,
)

F64 = torch.float64
Sampler = Callable[[int, torch.Generator], Tensor]


# =========================================================================== distributions
def _vector(text: str, k: int, what: str) -> Tensor:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"{what} must be comma-separated numbers, got {text!r}") from None
    if len(values) != k:
        raise ValueError(f"{what} needs {k} value(s) (one per uncertain parameter), got {len(values)} in {text!r}")
    t = torch.tensor(values, dtype=F64)
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{what} must be finite, got {text!r}")
    return t


def parse_distribution(spec: str, k: int, system: UncertainSystem | None = None) -> tuple[Sampler, dict]:
    """A sampler ``(count, generator) -> (count, k)`` float64 and a description, from a spec string:

    ``train`` (the system's own training distribution, ``system.sample_xi``), ``normal:M1,M2;S1,S2``
    (independent normals, std >= 0), ``uniform:L1,L2;H1,H2`` (independent uniforms, L <= H) or ``point:V1,V2``.
    """
    spec = spec.strip()
    kind, _, rest = spec.partition(":")
    kind = kind.strip().lower()
    if kind == "train":
        if rest.strip():
            raise ValueError(f"'train' takes no parameters, got {spec!r}")
        if system is None or system.xi_sampler is None:
            raise ValueError("'train' needs a system that declares its xi distribution")
        return system.sample_xi, {"kind": "train", "system": system.name}
    if kind not in ("normal", "uniform", "point"):
        raise ValueError(f"unknown distribution {spec!r}; valid: train, normal:MEANS;STDS, uniform:LOWS;HIGHS, point:VALUES")
    parts = rest.split(";")
    if kind == "point":
        if len(parts) != 1:
            raise ValueError(f"point takes one vector 'point:V1,V2', got {spec!r}")
        value = _vector(parts[0], k, "point")
        return (lambda count, gen: value.expand(count, k).clone()), {"kind": "point", "value": value.tolist()}
    if len(parts) != 2:
        raise ValueError(f"{kind} takes two vectors separated by ';' ({kind}:A1,A2;B1,B2), got {spec!r}")
    a, b = _vector(parts[0], k, f"{kind} first vector"), _vector(parts[1], k, f"{kind} second vector")
    if kind == "normal":
        if bool((b < 0).any()):
            raise ValueError(f"normal standard deviations must be >= 0, got {b.tolist()}")
        return (lambda count, gen: a + b * torch.randn(count, k, generator=gen, dtype=F64)), \
            {"kind": "normal", "mean": a.tolist(), "std": b.tolist()}
    if bool((a > b).any()):
        raise ValueError(f"uniform needs low <= high, got low {a.tolist()} and high {b.tolist()}")
    return (lambda count, gen: a + (b - a) * torch.rand(count, k, generator=gen, dtype=F64)), \
        {"kind": "uniform", "low": a.tolist(), "high": b.tolist()}


# =========================================================================== intervals
def clopper_pearson(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Exact two-sided binomial interval."""
    from scipy.stats import beta

    if n < 1 or not 0 <= successes <= n:
        raise ValueError(f"need 0 <= successes <= n, n >= 1, got {successes}/{n}")
    alpha = 1 - confidence
    lo = 0.0 if successes == 0 else float(beta.ppf(alpha / 2, successes, n - successes + 1))
    hi = 1.0 if successes == n else float(beta.ppf(1 - alpha / 2, successes + 1, n - successes))
    return lo, hi


def wilson(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval."""
    from scipy.stats import norm

    if n < 1 or not 0 <= successes <= n:
        raise ValueError(f"need 0 <= successes <= n, n >= 1, got {successes}/{n}")
    z = float(norm.ppf(1 - (1 - confidence) / 2))
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    lo = 0.0 if successes == 0 else max(0.0, min(p, centre - half))
    hi = 1.0 if successes == n else min(1.0, max(p, centre + half))
    return lo, hi


# =========================================================================== the probability
def true_model_sup(system: UncertainSystem, lyapunov, controller, xi: Tensor, z: Tensor, decay_rate: float,
                   exp_rate: float = 0.0, budget: int = 2_000_000) -> Tensor:
    """``max_z Vdot(z, xi_d) + decay(z)`` on the true model for each draw ``xi (D, k)`` over states ``z (S, n)``
    (float64 networks), batched over draws. Returns ``(D,)``."""
    lyap, ctrl = copy.deepcopy(lyapunov).to(F64), copy.deepcopy(controller).to(F64)
    z = z.to(F64)
    with torch.no_grad():
        value, grad = lyap.value_and_grad(z)
        u = ctrl(z)
        x = system.to_user(z)
        decay = decay_rate * z.norm(dim=-1) + (exp_rate * value if exp_rate else 0.0)
        s = z.shape[0]
        step = max(1, budget // max(s, 1))
        out = []
        for i in range(0, xi.shape[0], step):
            chunk = xi[i:i + step].to(F64)
            d = chunk.shape[0]
            f = system.true_dynamics(x.repeat(d, 1), u.repeat(d, 1), chunk.repeat_interleave(s, dim=0))
            vdot = (grad.repeat(d, 1) * f).sum(-1).reshape(d, s)
            out.append((vdot + decay).amax(-1))
    return torch.cat(out)


def guarantee(run, dist: str, n: int, method: str = "sampling", seed: int = 0, eps_bar: float = 0.05,
              time_limit: float = 5.0, radius_constants: Sequence[float] | None = None,
              confidence: float = 0.95) -> dict:
    """Fraction of ``n`` draws of xi from ``dist`` for which plain decrease holds on the true model over X_delta.

    ``method``: ``sampling`` (dense grid, optimistic) or ``verifier`` (branch and bound per distinct draw with
    ``time_limit`` seconds each; unknown counts as failing). ``worst_sup_residual`` is the largest residual found
    over all draws (sampling: on the grid; verifier: at evaluated box centres), a lower estimate of the worst sup.
    ``radius_constants = (c1, c2, rho)`` adds ``r_N(eps_bar)``
    (:func:`drlyap.conditions.wasserstein_radius_guarantee`) for the run's k and N. Returns a JSON-friendly dict.
    """
    if method not in ("sampling", "verifier"):
        raise ValueError(f"unknown method {method!r}; valid: sampling, verifier")
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if not 0 < eps_bar < 1:
        raise ValueError(f"eps_bar must be in (0, 1), got {eps_bar}")
    if not time_limit > 0:
        raise ValueError(f"time limit must be > 0, got {time_limit}")
    start = time.perf_counter()
    cfg, system = run.config, run.system
    radius_guarantee = None
    if radius_constants is not None:
        if len(radius_constants) != 3:
            raise ValueError("radius constants are c1, c2, rho")
        c1, c2, rho = (float(v) for v in radius_constants)
        n_xi = int(run.xi_samples.shape[0])
        radius_guarantee = {"c1": c1, "c2": c2, "rho": rho, "k": system.k, "N": n_xi, "eps_bar": eps_bar,
                            "r_N": wasserstein_radius_guarantee(c1, c2, rho, system.k, n_xi, eps_bar)}
    sampler, description = parse_distribution(dist, system.k, system)
    xi = sampler(n, torch.Generator().manual_seed(seed)).to(F64).reshape(n, system.k)
    distinct, inverse = torch.unique(xi, dim=0, return_inverse=True)
    delta = float(cfg.delta)
    unknown = 0
    if method == "sampling":
        z = validation_states(system, delta)
        sup = true_model_sup(system, run.lyapunov_net, run.controller_net, distinct, z, cfg.decay_rate, cfg.exp_rate)
        holds_distinct = sup <= 0
        states = int(z.shape[0])
    else:
        sups, flags = [], []
        for d in distinct:
            spec = ConditionSpec("true", d[None], cfg.decay_rate, cfg.exp_rate)
            res = verify_condition(system, run.lyapunov_net, run.controller_net, spec, delta, time_limit=time_limit,
                                   stop_at_counterexample=True)
            flags.append(res.status == "verified")
            unknown += res.status == "unknown"
            sups.append(res.sup_bounds[0] if res.sup_bounds else math.nan)
        sup = torch.tensor(sups, dtype=F64)
        holds_distinct = torch.tensor(flags, dtype=torch.bool)
        states = None
    holds = holds_distinct[inverse]
    k_ok = int(holds.sum())
    eps = float(cfg.risk_level)
    bound = (1 - eps) * (1 - eps_bar)
    per_draw = sup[inverse]
    finite = per_draw[torch.isfinite(per_draw)]
    uniform = cfg.method == "dr" and cfg.loss == "uniform"
    why = "baseline" if cfg.method == "baseline" else "pointwise DR (a per-state condition)"
    out = {
        "run_dir": str(getattr(run, "path", "")), "system": system.name, "method": cfg.method,
        "distribution": dist, "distribution_parsed": description, "n": n, "n_distinct": int(distinct.shape[0]),
        "check": method, "holds": k_ok, "fraction": k_ok / n, "confidence": confidence,
        "interval_clopper_pearson": list(clopper_pearson(k_ok, n, confidence)),
        "interval_wilson": list(wilson(k_ok, n, confidence)),
        "eps": eps, "eps_bar": eps_bar, "bound": bound,
        "bound_applies": uniform,
        "bound_note": ("(1 - eps)(1 - eps_bar) of lemma dr_controller_guarantee; it assumes a light-tailed true "
                       "distribution, the Wasserstein radius r = r_N(eps_bar) of eq. wasserstein_r_guarantee and a pair "
                       "that satisfies the uniform DR constraint (sup over x inside the probability)" + (
                           "" if uniform else f"; this is a {why} run, so the lemma does not apply")),
        "radius": float(cfg.wasserstein_radius), "n_xi": int(run.xi_samples.shape[0]),
        "worst_sup_residual": float(finite.max()) if finite.numel() else None,
        "sup_residual_quantiles": ({q: float(finite.quantile(float(q))) for q in ("0.05", "0.5", "0.95")}
                                   if finite.numel() else None),
        "delta": delta, "grid_states": states, "unknown": unknown if method == "verifier" else None,
        "estimate_note": ("grid of X_delta: a draw may pass the grid and fail between its points (optimistic)"
                          if method == "sampling" else
                          "branch and bound per draw: unknown (time limit) counts as failing (conservative)"),
        "seed": seed, "time_s": 0.0,
    }
    if radius_guarantee is not None:
        radius_guarantee["run_radius"] = out["radius"]
        radius_guarantee["radius_sufficient"] = out["radius"] >= radius_guarantee["r_N"]
        out["radius_guarantee"] = radius_guarantee
    out["time_s"] = time.perf_counter() - start
    return jsonable(out)


# =========================================================================== Lipschitz covering
def lipschitz_covering(run, spacing: float | None = None, n_samples: int = 20000, xi: Sequence[float] | None = None,
                       safety: float = 1.5, verify_time: float = 0.0, batch: int = 2048) -> dict:
    """The covering certificate of ``lemma: nominal_nn_lf`` on a grid of X_delta, next to the branch and bound.

    The state box is cut into cells of side at most ``spacing`` (local units, the same on every axis; default:
    about ``n_samples`` cells); cells entirely inside the open delta-ball are dropped, the rest cover X_delta.
    With ``rho`` = the largest half cell diagonal and ``c`` the run's condition residual (or plain decrease on
    the true model at ``xi``):

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

    With ``verify_time > 0`` the branch and bound runs on the same condition for comparison.
    """
    start = time.perf_counter()
    cfg, system = run.config, run.system
    spec = run_condition(run) if xi is None else run_condition(run, xi)
    if spec.kind == "uniform":
        raise ValueError("the uniform DR condition has no per-state residual; the covering check needs one")
    delta = float(cfg.delta)
    lo, hi = system.local_box()
    width = hi - lo
    n = system.n
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
    glo, ghi = box_grid(lo, hi, per_axis)
    keep = ~inside_ball(glo, ghi, delta)
    glo, ghi = glo[keep], ghi[keep]
    rho = float(((ghi - glo) / 2).norm(dim=-1).max()) * (1 + 1e-12)
    pb = PairBounds(system, run.lyapunov_net, run.controller_net)
    max_res, l_sound = -math.inf, 0.0
    for i in range(0, glo.shape[0], batch):
        clo, chi = glo[i:i + batch], ghi[i:i + batch]
        b = clo.shape[0]
        eye = torch.eye(n, dtype=F64).expand(b, n, n)
        over = spec.components(pb, Dual(Interval(clo, chi), Interval(eye, eye)))
        if over.d is not None:
            slope = torch.maximum(over.d.lo.abs(), over.d.hi.abs())  # (B, Q, n)
            norms = torch.sqrt((slope * slope).sum(-1)) * (1 + 1e-12)
            l_sound = max(l_sound, float(torch.nan_to_num(norms, nan=math.inf).max()))
        centre = (clo + chi) / 2
        at = spec.components(pb, Interval(centre, centre))
        max_res = max(max_res, float(spec.combine(at.hi).max()))
    # sampled gradient norms at the centres (float64 autograd through the ordinary code path)
    centres = (glo + ghi) / 2
    lyap, ctrl = copy.deepcopy(run.lyapunov_net).to(F64), copy.deepcopy(run.controller_net).to(F64)
    for p in list(lyap.parameters()) + list(ctrl.parameters()):
        p.requires_grad_(False)
    l_sampled, exact_max, region_max = 0.0, -math.inf, -math.inf
    for i in range(0, centres.shape[0], 20000):
        zc = centres[i:i + 20000].clone().requires_grad_(True)
        with torch.enable_grad():
            res = spec.residual(system, lyap, ctrl, zc)
            (g,) = torch.autograd.grad(res.sum(), zc)
        l_sampled = max(l_sampled, float(g.norm(dim=-1).max()))
        exact_max = max(exact_max, float(res.detach().max()))
        inside = zc.detach().norm(dim=-1) >= delta
        if bool(inside.any()):
            region_max = max(region_max, float(res.detach()[inside].max()))
    needed = -l_sound * rho
    out = {
        "condition": spec.label, "delta": delta, "spacing": spacing, "per_axis": per_axis, "cells": int(glo.shape[0]),
        "covering_radius": rho, "max_residual": max_res, "max_residual_float64": exact_max,
        "max_residual_in_x_delta": region_max,
        "lipschitz_sound": l_sound, "lipschitz_sampled": l_sampled, "safety": safety,
        "required_max_residual": needed, "certified": bool(max_res <= needed),
        "certified_estimate": bool(max_res <= -safety * l_sampled * rho),
        "spacing_needed": None, "samples_needed": None,
        "lipschitz_note": ("lipschitz_sound: interval enclosure of the gradient over every cell (sound); "
                           "lipschitz_sampled: max gradient norm at the centres (an estimate from below)"),
    }
    if max_res < 0 and l_sound > 0:
        h_needed = 2 * (-max_res) / (l_sound * math.sqrt(n))  # rho = h sqrt(n) / 2 for equal sides
        out["spacing_needed"] = h_needed
        out["samples_needed"] = float(math.prod(math.ceil(float(w) / h_needed) for w in width))
    out["verifier"] = None
    if verify_time > 0:
        ver = verify_condition(system, run.lyapunov_net, run.controller_net, spec, delta, time_limit=verify_time)
        out["verifier"] = {"status": ver.status, "verified_fraction": ver.verified_fraction,
                           "boxes_processed": ver.boxes_processed, "time_s": ver.time_s,
                           "counterexample": ver.counterexample, "counterexample_value": ver.counterexample_value}
    out["time_s"] = time.perf_counter() - start
    return jsonable(out)


