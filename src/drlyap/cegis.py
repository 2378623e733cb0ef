"""Counterexample-guided training (SPEC §6: "a falsifier that searches for violating states and adds them").

:func:`train_cegis` alternates training and sound verification:

1. an ordinary :func:`drlyap.training.train` run;
2. per round, the branch-and-bound verifier of :mod:`drlyap.verification` checks the trained condition on
   the whole of X_delta (the networks read as float64, like :func:`drlyap.verification.verify_run`). If it is
   proved, CEGIS stops;
3. otherwise new training states are collected, in local coordinates:

   * the verifier's counterexample and the centres of (at most ``max_boxes``) unverified boxes,
   * a gradient falsifier (:func:`~drlyap.verification.falsifier.falsify`): a few steps of projected gradient
     ascent on the condition's residual (``condition.evaluate``, float64 networks) from random states of X_delta
     and from the unverified boxes' centres, projected back into X_delta after every step;

   the states with a positive residual (the *counterexamples*), with ``neighbours`` jittered copies each, and
   the unverified box centres are added (deduplicated, at most ``max_extra``, the newest kept) to the
   accumulated ``extra_states`` that :func:`train` appends to every batch (``replicate`` times, to weigh them);
4. training continues from the current networks (``init=``) for ``iters_per_round`` iterations (default
   ``cfg.iters // 2``; the acceptance check inside ``train`` may stop it earlier), with explicit xi samples
   (the same ones as the first run) and a per-round seed (fresh batches), and the result is verified again.

The pair returned is the best one seen (verified first, then one that passes the acceptance check, then
Hurwitz at x* and free of other equilibria, then the largest verified fraction), so a round that makes
things worse does not lose a better earlier pair. ``metrics["cegis"]`` records every round (the branch and
bound's verdicts) and, as ``final``, the returned pair's proof, an ``unknown`` one settled by the falsifier
(:func:`~drlyap.verification.falsifier.settle_unknown`: ``violated`` where a violation is certain).
Only per-state conditions are supported (DR pointwise and the baseline's nominal condition): the uniform
DR condition has no per-state residual to falsify.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time

import torch
from torch import Tensor

from drlyap.conditions import Condition
from drlyap.io import jsonable
from drlyap.networks import Controller, Lyapunov
from drlyap.regions import Region
from drlyap.systems import UncertainSystem, get_system
from drlyap.training import TrainConfig, TrainResult, train
from drlyap.verification import default_enclosure, prove_trained
from drlyap.verification.falsifier import box_centres, falsifier_starts, falsify, settle_unknown

F64 = torch.float64


def _dedupe(z: Tensor, scale: Tensor, resolution: float = 1e-6) -> Tensor:
    if z.shape[0] == 0:
        return z
    keys = torch.round(z / (scale * resolution)).to(torch.int64)
    _, idx = torch.unique(keys, dim=0, return_inverse=True)
    first = torch.full((int(idx.max()) + 1,), z.shape[0], dtype=torch.int64)
    first = first.scatter_reduce(0, idx, torch.arange(z.shape[0]), reduce="amin")
    return z[first.sort().values]


def collect_counterexamples(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, condition: Condition,
                            region: Region, verification: dict, generator: torch.Generator,
                            n_random: int = 512, max_boxes: int = 200, steps: int = 30,
                            neighbours: int = 3, level: float | None = None, near: bool = False) -> dict:
    """New training states from a failed verification: counterexamples (residual > 0) and unverified box centres.

    ``verification`` is :meth:`VerificationResult.to_dict` (states in user coordinates). The falsifier starts from
    its counterexample, the unverified boxes' centres and ``n_random`` random states of X_delta: uniform, or with
    ``near`` half of them spread over the distance from x* (:func:`~drlyap.verification.falsifier.falsifier_starts`).
    Returns local states:
    ``counterexamples`` (each re-evaluated, residual > 0), ``neighbours`` (jittered copies of them, in X_delta),
    ``box_centres`` (unverified boxes, in X_delta, any residual) and the counts. ``level``: the claim is about
    ``{V <= level}`` only (region-of-attraction training), so only states there count as counterexamples.
    """
    scale = region.scale
    cand = []
    if verification.get("counterexample_local") is not None:
        cand.append(torch.as_tensor([verification["counterexample_local"]], dtype=F64))
    centres = box_centres(system, (verification.get("unverified_boxes") or [])[:max_boxes])
    centres = centres[region.in_region(centres)]
    if centres.shape[0]:
        cand.append(centres)
    if n_random:
        cand.append(falsifier_starts(region, n_random, generator) if near else region.sample(n_random, generator))
    starts = torch.cat(cand) if cand else torch.empty(0, system.n, dtype=F64)
    if starts.shape[0] == 0:
        empty = torch.empty(0, system.n, dtype=F64)
        return {"counterexamples": empty, "neighbours": empty, "box_centres": centres, "max_residual": None,
                "falsifier_starts": 0, "falsifier_violations": 0, "falsify_time_s": 0.0}
    tic = time.perf_counter()
    found, values = falsify(system, lyapunov, controller, condition, region, starts, steps=steps)
    falsify_time = time.perf_counter() - tic
    pool = torch.cat([starts, found])
    res = condition.exact(system, lyapunov, controller, pool)
    if level is not None:
        with torch.no_grad():
            v = copy.deepcopy(lyapunov).to(F64)(pool)
        res = torch.where(v <= level, res, -torch.inf)
    cex = _dedupe(pool[res > 0], scale)
    near = torch.empty(0, system.n, dtype=F64)
    if neighbours and cex.shape[0]:
        noise = 0.01 * scale * torch.randn(cex.shape[0] * neighbours, system.n, generator=generator, dtype=F64)
        near = region.project(cex.repeat(neighbours, 1) + noise)
    return {"counterexamples": cex, "neighbours": near, "box_centres": centres,
            "max_residual": float(res.max()),
            "falsifier_starts": int(starts.shape[0]), "falsifier_violations": int((values > 0).sum()),
            "falsify_time_s": falsify_time}


def _summary(ver: dict) -> dict:
    keys = ("condition", "status", "verified_fraction", "boxes_processed", "time_s", "stopped", "counterexample",
            "counterexample_value", "counterexample_source", "n_unverified", "n_counterexample_boxes", "sup_bounds",
            "level", "boundary_min_lower")
    out = {k: ver.get(k) for k in keys}
    out["sup_bounds"] = [v if math.isfinite(v) else None for v in (out["sup_bounds"] or [])]
    return out


def train_cegis(cfg: TrainConfig, system: UncertainSystem | None = None, rounds: int = 5,
                verify_time_limit: float = 30.0, progress: bool = True,
                init: tuple[Lyapunov, Controller] | None = None, iters_per_round: int | None = None,
                max_extra: int = 2000, replicate: int = 2, max_boxes: int = 200, n_random: int | None = None,
                falsifier_steps: int = 30, neighbours: int = 3, min_width: float = 1e-4,
                log=None, time_budget: float | None = None) -> tuple[TrainResult, list[dict]]:
    """Train with counterexample-guided rounds (see the module docstring).

    Returns the best :class:`TrainResult` (its ``config`` is the first run's resolved config, its ``history``
    the training of every round up to it, iterations counted on, its ``metrics["cegis"]`` the record)
    and the list of rounds. Each round dict has ``round``, ``verification``
    (summary), ``verified``, ``verified_fraction``, times, counts of states added and, when states were added,
    ``counterexamples`` (a float64 ``(C, n)`` tensor of the violating local states found; not in the metrics).
    ``log(round_dict)`` is called after each verification. ``time_budget`` (seconds, from the start): no new
    retraining round starts once it is spent. ``n_random``: the falsifier's random starts per round; None: 512
    uniform in X_delta, or, where training draws states near x* (``near_share > 0``: cart-pole, quadrotor), 2,048,
    half of them spread over the distance from x* (in 6 states uniform starts miss the violations near x*:
    docs/defaults.md).
    """
    if time_budget is not None and not time_budget > 0:
        raise ValueError(f"time_budget must be > 0 seconds, got {time_budget}")
    if rounds < 0:
        raise ValueError(f"rounds must be >= 0, got {rounds}")
    if not (verify_time_limit > 0):
        raise ValueError(f"verify_time_limit must be > 0, got {verify_time_limit}")
    if max_extra < 1 or replicate < 1:
        raise ValueError("max_extra and replicate must be >= 1")
    if iters_per_round is not None and iters_per_round < 1:
        raise ValueError(f"iters_per_round must be >= 1, got {iters_per_round}")
    if cfg.method == "dr" and cfg.loss != "pointwise":
        raise ValueError("CEGIS needs a per-state condition (method dr with loss pointwise, or baseline); "
                         "the uniform DR condition has no per-state residual to falsify")
    system = system or get_system(cfg.system)
    start = time.perf_counter()
    result = train(cfg, system, progress=progress, init=init)
    base_cfg = result.config
    condition = result.condition
    iters_round = int(iters_per_round if iters_per_round is not None else max(1, base_cfg.iters // 2))
    region = Region.of(system, float(base_cfg.delta))
    near = bool(base_cfg.near_share)
    if n_random is None:
        n_random = 2048 if near else 512
    gen = torch.Generator().manual_seed(base_cfg.seed + 7919)
    extra = torch.empty(0, system.n, dtype=F64)
    record: list[dict] = []
    best: tuple | None = None
    total_iters = result.metrics["iterations"]
    history = list(result.history)  # all rounds' training, iterations and seconds counted from the first run
    train_time = time.perf_counter() - start
    for r in range(rounds + 1):
        tic = time.perf_counter()
        ver = prove_trained(system, result.lyapunov, result.controller, condition, region, base_cfg.roa_level,
                            time_limit=verify_time_limit, min_width=min_width, keep_boxes=max_boxes,
                            enclosure=default_enclosure(system.n), falsify_starts=0)  # its own falsifier below
        entry: dict = {"round": r, "verification": _summary(ver), "verified": ver["status"] == "verified",
                       "status": ver["status"], "verified_fraction": ver["verified_fraction"],
                       "verify_time_s": time.perf_counter() - tic, "train_time_s": train_time,
                       "train_iterations": result.metrics["iterations"], "acceptance_passed": result.metrics["passed"]}
        acc = result.metrics["acceptance"]
        # a proof first; among unproved pairs, one that passes the acceptance check (Hurwitz at x*, no other
        # equilibrium) before a larger proved share: retraining on counterexamples of an infeasible condition
        # can trade stability for area (measured on pendulum-u9: 0/200 stabilised instead of 170/200)
        score = (entry["verified"], bool(result.metrics["passed"]), bool(acc["jacobian"]["hurwitz"]),
                 not acc["other_equilibria"], ver["verified_fraction"], -(ver["counterexample_value"] or 0.0))
        if best is None or score > best[0]:
            best = (score, result, r, list(history))
        out_of_time = time_budget is not None and time.perf_counter() - start > time_budget
        if entry["verified"] or r == rounds or out_of_time:
            if out_of_time and not entry["verified"] and r < rounds:
                entry["stopped"] = "time budget"
            record.append(entry)
            if log is not None:
                log(entry)
            break
        found = collect_counterexamples(system, result.lyapunov, result.controller, condition, region, ver,
                                        gen, n_random=n_random, max_boxes=max_boxes, steps=falsifier_steps,
                                        neighbours=neighbours, level=base_cfg.roa_level, near=near)
        # newest last, the counterexamples at the very end: the cap keeps the tail
        new = torch.cat([found["box_centres"], found["neighbours"], found["counterexamples"]])
        extra = _dedupe(torch.cat([extra, new]), region.scale)[-max_extra:]
        entry.update({"counterexamples_added": int(found["counterexamples"].shape[0]),
                      "neighbours_added": int(found["neighbours"].shape[0]),
                      "box_centres_added": int(found["box_centres"].shape[0]),
                      "falsifier_max_residual": found["max_residual"], "falsify_time_s": found["falsify_time_s"],
                      "extra_states": int(extra.shape[0]), "counterexamples": found["counterexamples"]})
        record.append(entry)
        if log is not None:
            log(entry)
        round_cfg = dataclasses.replace(base_cfg, iters=iters_round, seed=base_cfg.seed + 1000 * (r + 1),
                                        xi_samples=result.xi_samples.tolist())
        tic = time.perf_counter()
        result = train(round_cfg, system, progress=progress, init=(result.lyapunov, result.controller),
                       extra_states=extra.repeat(replicate, 1))
        train_time = time.perf_counter() - tic
        offset_t = history[-1]["time_s"] if history else 0.0
        history += [{"iteration": h["iteration"] + total_iters, "loss": h["loss"], "time_s": h["time_s"] + offset_t}
                    for h in result.history]
        total_iters += result.metrics["iterations"]
    _, chosen, chosen_round, chosen_history = best
    metrics = dict(chosen.metrics)
    final = record[chosen_round] if chosen_round < len(record) else record[-1]
    # the returned pair's verdict: an unknown proof becomes violated where the falsifier finds a certain violation
    verdict = settle_unknown(dict(final["verification"]), system, chosen.lyapunov, chosen.controller, condition,
                             region, base_cfg.roa_level, seed=base_cfg.seed)
    metrics["cegis"] = jsonable({
        "rounds": [{k: v for k, v in e.items() if k != "counterexamples"} for e in record],
        "final": verdict, "verified": final["verified"], "returned_round": chosen_round,
        "retraining_rounds": len(record) - 1, "max_rounds": rounds, "iters_per_round": iters_round,
        "total_iterations": total_iters, "extra_states": int(extra.shape[0]), "replicate": replicate,
        "verify_time_limit_s": verify_time_limit, "total_time_s": time.perf_counter() - start,
    })
    out = dataclasses.replace(chosen, config=base_cfg, metrics=metrics, history=chosen_history)
    return out, record


def certificate_summary(verification: dict, condition_label: str, delta: float, rounds: int | None = None) -> dict:
    """``metrics["certificate"]``: what the verifier proved about a run's trained condition.

    ``status`` is ``verified`` (proved at every state of X_delta = the state box minus the open ball of radius
    ``delta`` around x*; with a ``level`` in the verification, at every state of X_delta with ``V <= level``,
    and ``V > level`` on the box's boundary), ``violated`` (a counterexample state, re-checked) or ``unknown``
    (time or box budget ran out); ``verified_fraction`` a lower bound of the share of X_delta proved.
    """
    level = verification.get("level")
    region = f"state box minus the open ball ||x - x*|| < {delta:g}"
    if level is not None:
        region = f"{{V <= {level:g}}} minus the open ball ||x - x*|| < {delta:g}, with V > {level:g} on the box's faces"
    return jsonable({
        "status": verification["status"], "condition": condition_label, "region": region, "level": level,
        "delta": delta, "verified_fraction": verification.get("verified_fraction"),
        "time_s": verification.get("time_s"), "boxes": verification.get("boxes_processed"),
        "counterexample": verification.get("counterexample"),
        "counterexample_source": verification.get("counterexample_source"), "rounds": rounds,
        "margin_upper": verification.get("margin_upper"),
    })


def train_certified(cfg: TrainConfig, system: UncertainSystem | None = None, progress: bool = True,
                    init: tuple[Lyapunov, Controller] | None = None, log=None, warn: bool = True) -> TrainResult:
    """Train a pair and, unless ``cfg.verify`` is False, prove its trained condition: the default way to train.

    Per-state conditions (baseline, DR pointwise) run :func:`train_cegis` with ``cfg.verify_rounds`` retraining
    rounds, ``cfg.verify_time`` seconds per proof and an optional total ``cfg.verify_budget``; the uniform DR
    condition is bounded once (:func:`drlyap.verification.uniform_margin`, no per-state residual to retrain on).
    ``metrics["certificate"]`` records the verdict (:func:`certificate_summary`); with ``warn`` a run that is
    not verified raises a :class:`UserWarning` saying so.
    """
    import warnings

    from drlyap.verification import uniform_margin

    system = system or get_system(cfg.system)
    cfg = cfg.resolved(system)  # the system's defaults (e.g. its seconds per proof)
    if not cfg.verify:
        result = train(cfg, system, progress=progress, init=init)
        result.metrics["certificate"] = {"status": "not checked", "condition": result.condition.label}
        return result
    if cfg.verify_rounds < 0 or not cfg.verify_time > 0:
        raise ValueError(f"verify_rounds must be >= 0 and verify_time > 0, got {cfg.verify_rounds} and {cfg.verify_time}")
    uniform = cfg.method == "dr" and cfg.loss == "uniform"
    if uniform:
        result = train(cfg, system, progress=progress, init=init)
        delta = float(result.config.delta)
        ver = uniform_margin(system, result.lyapunov, result.controller, result.condition, delta,
                             time_limit=cfg.verify_time)
        ver["boxes_processed"] = ver.get("boxes_processed")
        ver["verified_fraction"] = None
        result.metrics["certificate"] = certificate_summary(ver, result.condition.label, delta)
    else:
        result, rounds = train_cegis(cfg, system, rounds=int(cfg.verify_rounds), verify_time_limit=cfg.verify_time,
                                     progress=progress, init=init, log=log, time_budget=cfg.verify_budget)
        final = result.metrics["cegis"]["final"]
        result.metrics["certificate"] = certificate_summary(final, result.condition.label, float(result.config.delta),
                                                            rounds=result.metrics["cegis"]["retraining_rounds"])
    cert = result.metrics["certificate"]
    if warn and cert["status"] != "verified":
        share = cert.get("verified_fraction")
        detail = "" if share is None else f"; {100 * share:.4f}% of X_delta proved"
        warnings.warn(f"drlyap: the trained {cert['condition']} condition of this {cfg.system} {cfg.method} run is NOT "
                      f"verified ({cert['status']}{detail}){'' if uniform else '; raise verify_rounds'}",
                      stacklevel=2)
    return result
