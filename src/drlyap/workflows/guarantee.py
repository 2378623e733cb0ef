"""What the guarantees mean in numbers (SPEC §6): the probability behind the lemma, and the covering check.

:func:`guarantee` measures ``P(sup_{x in X_delta} Vdot(x, pi(x), xi) + gamma ||x - x*|| (+ alpha V) <= 0)`` on the
TRUE model ``F(x, u, p0 + xi)`` for ``xi`` drawn from a distribution (:func:`parse_distribution`), with an exact
(Clopper-Pearson) and a Wilson 95% interval, next to the bound ``(1 - eps)(1 - eps_bar)`` of
``lemma: dr_controller_guarantee``. Two ways to decide one draw:

* ``sampling``: the condition at every state of a dense grid of X_delta (:meth:`drlyap.regions.Region.grid`),
  batched over draws. A draw can pass the grid and still fail between grid points, so this fraction is an
  optimistic estimate;
* ``verifier``: the branch and bound of :mod:`drlyap.verification` for each distinct draw (time-limited).
  ``verified`` counts as holding, ``violated`` and ``unknown`` (time out) as not: a conservative estimate.

The bound assumes what the lemma assumes: a light-tailed true distribution, a radius ``r = r_N(eps_bar)`` of
``eq: wasserstein_r_guarantee`` (which needs the constants c1, c2, rho of Esfahani & Kuhn; pass them to get
``r_N`` and compare it with the run's radius), and a pair that satisfies the DR constraint (a DR run).

The covering argument of ``lemma: nominal_nn_lf`` lives in :mod:`drlyap.verification.covering`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import wasserstein_radius_guarantee
from drlyap.io import jsonable
from drlyap.kinds import Enclosure, Method, Status
from drlyap.regions import Region
from drlyap.runs import Run
from drlyap.sections import ConditionSection
from drlyap.systems import UncertainSystem
from drlyap.verification import Budget, ProofRules, verify_condition

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
def true_model_sup(loop: ClosedLoop, section: ConditionSection, xi: Tensor, z: Tensor,
                   draws_per_chunk: int = 128) -> Tensor:
    """``max_z Vdot(z, xi_d) + decay(z)`` on the true model for each draw ``xi (D, k)`` over states ``z (S, n)``
    (float64 networks, the decay terms of the run's condition ``section``): the components of plain decrease on the true
    model, maximised over the states. Returns ``(D,)``."""
    f64 = loop.f64
    out = []
    with torch.no_grad():
        for i in range(0, xi.shape[0], draws_per_chunk):
            condition = section.build(xi[i:i + draws_per_chunk].to(F64), "true")
            out.append(condition.components(condition.terms(f64, z.to(F64))).amax(0))
    return torch.cat(out)


@dataclass(frozen=True)
class Draws:
    """``n`` draws of xi from the distribution ``dist`` (a :func:`parse_distribution` spec), with ``seed``."""

    dist: str
    n: int
    seed: int = 0


def guarantee(run: Run, draws: Draws, method: str = "sampling", *, time_limit: float = 5.0, eps_bar: float = 0.05,
              radius_constants: Sequence[float] | None = None, confidence: float = 0.95) -> dict:
    """Fraction of the ``draws`` of xi (:class:`Draws`) for which plain decrease holds on the true model over X_delta.

    ``method``: ``sampling`` (dense grid, optimistic) or ``verifier`` (branch and bound per distinct draw with
    ``time_limit`` seconds each; unknown counts as failing). ``worst_sup_residual`` is the largest residual found
    over all draws (sampling: on the grid; verifier: at evaluated box centres), a lower estimate of the worst sup.
    ``radius_constants = (c1, c2, rho)`` adds ``r_N(eps_bar)``
    (:func:`drlyap.conditions.wasserstein_radius_guarantee`) for the run's k and N. Returns a JSON-friendly dict.
    """
    dist, n, seed = draws.dist, draws.n, draws.seed
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
    radius_guarantee = None if radius_constants is None else _radius_guarantee(run, radius_constants, eps_bar)
    sampler, description = parse_distribution(dist, system.k, system)
    xi = sampler(n, torch.Generator().manual_seed(seed)).to(F64).reshape(n, system.k)
    distinct, inverse = torch.unique(xi, dim=0, return_inverse=True)
    delta = float(cfg.delta)
    sup, holds_distinct, states, unknown = _decide(run, Region.of(system, delta), distinct, method, time_limit)
    holds = holds_distinct[inverse]
    k_ok = int(holds.sum())
    eps = float(cfg.risk_level)
    per_draw = sup[inverse]
    finite = per_draw[torch.isfinite(per_draw)]
    out = {
        "run_dir": str(getattr(run, "path", "")), "system": system.name, "method": cfg.method,
        "distribution": dist, "distribution_parsed": description, "n": n, "n_distinct": int(distinct.shape[0]),
        "check": method, "holds": k_ok, "fraction": k_ok / n, "confidence": confidence,
        "interval_clopper_pearson": list(clopper_pearson(k_ok, n, confidence)),
        "interval_wilson": list(wilson(k_ok, n, confidence)),
        **_lemma(run, eps, eps_bar),
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


def _radius_guarantee(run: Run, constants: Sequence[float], eps_bar: float) -> dict:
    """``r_N(eps_bar)`` of the constants ``(c1, c2, rho)`` for the run's k and N."""
    if len(constants) != 3:
        raise ValueError("radius constants are c1, c2, rho")
    c1, c2, rho = (float(v) for v in constants)
    n_xi, k = int(run.xi_samples.shape[0]), run.system.k
    return {"c1": c1, "c2": c2, "rho": rho, "k": k, "N": n_xi, "eps_bar": eps_bar,
            "r_N": wasserstein_radius_guarantee(c1, c2, rho, k, n_xi, eps_bar)}


def _decide(run: Run, region: Region, distinct: Tensor, method: str, time_limit: float) -> tuple:
    """For each distinct draw ``(D, k)``: the sup of the residual found ``(D,)``, whether decrease holds ``(D,)``
    bool, the grid's state count (sampling; None for the verifier) and the draws left unknown (verifier)."""
    if method == "sampling":
        z = region.grid()
        sup = true_model_sup(run.loop, run.sections.condition, distinct, z)
        return sup, sup <= 0, int(z.shape[0]), 0
    sups, flags, unknown = [], [], 0
    for d in distinct:
        res = verify_condition(run.loop, run.true_condition(d), region,
                               Budget(seconds=time_limit, enclosure=Enclosure.MEAN_VALUE),
                               rules=ProofRules(stop_at_counterexample=True))
        flags.append(res.status == Status.VERIFIED)
        unknown += res.status == Status.UNKNOWN
        sups.append(res.sup_bounds[0] if res.sup_bounds else math.nan)
    return torch.tensor(sups, dtype=F64), torch.tensor(flags, dtype=torch.bool), None, unknown


def _lemma(run: Run, eps: float, eps_bar: float) -> dict:
    """The lemma's bound ``(1 - eps)(1 - eps_bar)`` and whether it applies to the run."""
    uniform = run.sections.condition.uniform
    why = "baseline" if run.config.method == Method.BASELINE else "pointwise DR (a per-state condition)"
    return {"eps": eps, "eps_bar": eps_bar, "bound": (1 - eps) * (1 - eps_bar), "bound_applies": uniform,
            "bound_note": ("(1 - eps)(1 - eps_bar) of lemma dr_controller_guarantee; it assumes a light-tailed true "
                           "distribution, the Wasserstein radius r = r_N(eps_bar) of eq. wasserstein_r_guarantee and a "
                           "pair that satisfies the uniform DR constraint (sup over x inside the probability)" + (
                               "" if uniform else f"; this is a {why} run, so the lemma does not apply"))}
