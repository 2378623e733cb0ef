"""Verification of a run directory: its trained condition, the uniform DR margin, the true model, the ROA."""

from __future__ import annotations

import math
from collections.abc import Sequence

from torch import Tensor

from drlyap.conditions import Condition, DRUniform, TrueDecrease, make_condition
from drlyap.io import jsonable
from drlyap.regions import Region
from drlyap.verification.bounds import check_enclosure, default_enclosure
from drlyap.verification.branch_and_bound import uniform_margin
from drlyap.verification.roa import certified_roa, prove_trained


def run_condition(run, xi: Sequence[float] | Tensor | None = None) -> Condition:
    """The condition a run was trained on (``xi is None``), or plain decrease on the true model at ``xi``
    (with the run's decay terms). ``run`` has ``config`` (a TrainConfig), ``system`` and ``xi_train``."""
    cfg = run.config
    if xi is not None:
        return TrueDecrease(run.system.check_xi(xi)[None], cfg.decay_rate, cfg.exp_rate)
    return make_condition(cfg.method, cfg.loss, cfg.wasserstein_radius, cfg.risk_level, run.xi_train,
                          cfg.decay_rate, cfg.exp_rate)


def verify_run(run, delta: float | None = None, xi: Sequence[float] | Tensor | None = None, time_limit: float = 30.0,
               roa: bool = False, min_width: float = 1e-4, uniform_time: float = 3.0,
               enclosure: str | None = None, roa_time: float | None = None) -> dict:
    """Verify a loaded run (:func:`drlyap.rundir.load_run`) on X_delta.

    Returns a JSON-friendly dict: ``trained`` (the run's own condition: pointwise / nominal through
    :func:`verify_condition`, uniform through :func:`uniform_margin`), ``uniform`` (always: the uniform DR
    margin bounds at the run's radius, risk level and samples), ``true_model`` (with ``xi``: plain decrease
    on the true model at that shift) and ``roa`` (with ``roa=True``: :func:`certified_roa` for the main
    condition, ``roa_time`` seconds, None: 3x ``time_limit``, as it proves the condition on a sublevel set and
    then the decrease inside the ball; for a run trained for a region of attraction, up to the level trained
    for). The top-level ``status``, ``verified_fraction``, ``counterexample`` and ``time_s`` are those
    of the main check: the true model when ``xi`` is given, else the trained condition. Non-finite bounds
    are reported as None (strict JSON). ``enclosure`` bounds the boxes of the trained, uniform and true-model
    checks and of the region-of-attraction search (:data:`~drlyap.verification.bounds.ENCLOSURES`; None:
    :func:`default_enclosure`, ``"affine"`` from 4 states on). A run trained for a region of
    attraction (``config.roa_level``) has its trained and true-model conditions proved on ``{V <= roa_level}``
    with V above the level on the box's faces (:func:`verify_sublevel`).
    """
    cfg = run.config
    enclosure = check_enclosure(enclosure or default_enclosure(run.system.n))
    level = cfg.roa_level
    delta = float(cfg.delta if delta is None else delta)
    if not (delta == delta and delta >= 0 and delta != float("inf")):
        raise ValueError(f"delta must be finite and >= 0, got {delta}")
    system, lyap, ctrl = run.system, run.lyapunov_net, run.controller_net
    region = Region.of(system, delta)
    trained_condition = run_condition(run)
    out: dict = {"run_dir": str(run.path), "system": system.name, "method": cfg.method,
                 "loss": cfg.loss if cfg.method == "dr" else None, "delta": delta, "enclosure": enclosure}
    uniform_condition = DRUniform(cfg.wasserstein_radius, cfg.risk_level, run.xi_samples, cfg.decay_rate, cfg.exp_rate)
    if isinstance(trained_condition, DRUniform):
        trained = uniform_margin(system, lyap, ctrl, trained_condition, region, time_limit=time_limit, min_width=min_width,
                                 enclosure=enclosure)
        uniform = trained
    else:
        trained = prove_trained(system, lyap, ctrl, trained_condition, region, level, time_limit=time_limit,
                                min_width=min_width, enclosure=enclosure)
        uniform = uniform_margin(system, lyap, ctrl, uniform_condition, region, time_limit=uniform_time,
                                 min_width=min_width, enclosure=enclosure)
    out["trained"] = trained
    out["uniform"] = uniform
    main, main_condition = trained, trained_condition
    if xi is not None:
        main_condition = run_condition(run, xi)
        main = prove_trained(system, lyap, ctrl, main_condition, region, level, time_limit=time_limit,
                             min_width=min_width, enclosure=enclosure)
        main["xi"] = main_condition.xi[0].tolist()
        out["true_model"] = main
    out["roa"] = None
    if roa:
        if not main_condition.per_state:
            out["roa"] = {"error": "no per-state residual for the uniform condition; no sublevel-set certificate"}
        else:
            out["roa"] = certified_roa(system, lyap, ctrl, main_condition, region,
                                       time_limit=3 * time_limit if roa_time is None else roa_time,
                                       min_width=min_width, enclosure=enclosure,
                                       max_level=math.inf if level is None else float(level))
    out["status"] = main["status"]
    out["condition"] = main["condition"]
    out["verified_fraction"] = main.get("verified_fraction")
    out["counterexample"] = main.get("counterexample")
    out["counterexample_value"] = main.get("counterexample_value")
    out["time_s"] = main["time_s"]
    return jsonable(out)
