"""Training with proofs: the default way to train (:func:`train`), and counterexample-guided rounds (SPEC §6: "a
falsifier that searches for violating states and adds them").

:func:`train_cegis` alternates training and sound verification:

1. an ordinary :func:`~drlyap.training.trainer.fit` run;
2. per round, the branch-and-bound verifier of :mod:`drlyap.verification` checks the trained condition on
   the whole of X_delta (or on ``{V <= roa_level}`` of it; the networks read as float64). If it is proved, CEGIS
   stops;
3. otherwise new training states are collected, in local coordinates:

   * the verifier's counterexample and the centres of (at most ``keep_boxes``) unverified boxes,
   * a gradient falsifier (:func:`~drlyap.verification.falsifier.falsify`): a few steps of projected gradient
     ascent on the condition's residual (float64 networks) from random states of X_delta and from the unverified
     boxes' centres, projected back into X_delta after every step;

   the states with a positive residual (the *counterexamples*), with ``neighbours`` jittered copies each, and
   the unverified box centres are added (deduplicated, at most ``max_extra``, the newest kept) to the
   accumulated extra states that :func:`~drlyap.training.trainer.fit` appends to every batch (``replicate``
   times, to weigh them); and at most ``train_boxes`` of the unverified boxes themselves, on which the retraining
   also minimises the verifier's own bound of the residual (``box_weight``; :mod:`drlyap.training.boxes`);
4. training continues from the current networks (both, or with ``retrain="controller"`` the controller only, V kept
   as the first run left it) for ``iters_per_round`` iterations (default ``iters // 2``; the
   acceptance check may stop it earlier), with explicit xi samples (the same ones as the first run) and a
   per-round seed (fresh batches), and the result is verified again.

All of these settings are a :class:`~drlyap.verification.ProofConfig`. The pair returned is the best one seen
(verified first, then one that passes the acceptance check, then Hurwitz at x* and free of other equilibria, then
the largest verified fraction), so a round that makes things worse does not lose a better earlier pair.
``metrics["cegis"]`` records every round (the branch and bound's verdicts) and, as ``final``, the returned pair's
proof, an ``unknown`` one settled by the falsifier (:func:`~drlyap.verification.falsifier.settle_unknown`:
``violated`` where a violation is certain).

The DR uniform condition has no per-state residual to falsify; :func:`train` gives it proof rounds of the same
shape: each round bounds its margin over X_delta (:func:`~drlyap.verification.uniform_margin`), and a round that
does not prove it adds the states where the margin's suprema were found (``UniformMargin.attained_at``: the
largest ``||W^T grad V||`` and each sample's largest ``Vdot + decay``) with ``neighbours`` jittered copies each;
the best pair is the one with the smallest margin after a proof and the acceptance check.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition
from drlyap.config import TrainConfig
from drlyap.io import jsonable
from drlyap.networks import Controller, Lyapunov
from drlyap.proof_settings import ProofConfig
from drlyap.records import ProofRound
from drlyap.regions import Region
from drlyap.render import proof_round_line, unverified_warning
from drlyap.sections import TrainSections
from drlyap.systems import UncertainSystem, get_system
from drlyap.training.boxes import OpenBoxes
from drlyap.training.resume import FitStart, fit_or_resume
from drlyap.training.trainer import TrainResult, fit
from drlyap.verification import (
    Budget,
    Certificate,
    ConditionProof,
    ProofRules,
    UniformMargin,
    prove_trained,
    uniform_margin,
)
from drlyap.verification.falsifier import box_centres, falsifier_starts, falsify, local_boxes, settle_unknown

F64 = torch.float64


@dataclass(frozen=True)
class CounterexampleSearch:
    """How :func:`collect_counterexamples` searches: from ``n_random`` random states of X_delta (uniform, or with
    ``near`` half of them spread over the distance from x*) and the centres of at most ``max_boxes`` unverified
    boxes, ``steps`` steps of the falsifier's ascent; ``neighbours`` jittered copies of each counterexample.
    ``level``: the claim is about ``{V <= level}`` only (region-of-attraction training), so only states there count
    as counterexamples (None: all of X_delta). ``train_boxes``: at most so many unverified boxes are handed back
    whole, to train the verifier's bound on (0: none)."""

    n_random: int = 512
    max_boxes: int = 200
    steps: int = 30
    neighbours: int = 3
    level: float | None = None
    near: bool = False
    train_boxes: int = 0


def collect_counterexamples(loop: ClosedLoop, condition: Condition, region: Region, verification: ConditionProof,
                            generator: torch.Generator, search: CounterexampleSearch = CounterexampleSearch()) -> dict:
    """New training states from a failed verification: counterexamples (residual > 0) and unverified box centres.

    The falsifier starts from the verification's counterexample, the centres of its unverified boxes (user
    coordinates there) and the ``search``'s random states of X_delta (:class:`CounterexampleSearch`;
    :func:`~drlyap.verification.falsifier.falsifier_starts` where they are spread near x*). Returns local states:
    ``counterexamples`` (each re-evaluated, residual > 0), ``neighbours`` (jittered copies of them, in X_delta),
    ``box_centres`` (unverified boxes, in X_delta, any residual), ``open_boxes`` (the corners ``lo, hi (B, n)``,
    local, of at most ``search.train_boxes`` unverified boxes; None: none) and the counts.
    """
    n_random, max_boxes, steps, neighbours, level = (search.n_random, search.max_boxes, search.steps,
                                                     search.neighbours, search.level)
    system = loop.system
    scale = region.scale
    cand = []
    if verification.counterexample_local is not None:
        cand.append(torch.as_tensor([verification.counterexample_local], dtype=F64))
    unverified = verification.unverified_boxes or []
    centres = box_centres(system, unverified[:max_boxes])
    corners = local_boxes(system, unverified[:search.train_boxes]) if search.train_boxes and unverified else None
    centres = centres[region.in_region(centres)]
    if centres.shape[0]:
        cand.append(centres)
    if n_random:
        cand.append(falsifier_starts(region, n_random, generator) if search.near
                    else region.sample(n_random, generator))
    starts = torch.cat(cand) if cand else torch.empty(0, system.n, dtype=F64)
    if starts.shape[0] == 0:
        empty = torch.empty(0, system.n, dtype=F64)
        return {"counterexamples": empty, "neighbours": empty, "box_centres": centres, "open_boxes": corners,
                "max_residual": None, "falsifier_starts": 0, "falsifier_violations": 0, "falsify_time_s": 0.0}
    tic = time.perf_counter()
    found, values = falsify(loop, condition, region, starts, steps=steps)
    falsify_time = time.perf_counter() - tic
    pool = torch.cat([starts, found])
    res = loop.exact(condition, pool)
    if level is not None:
        v = loop.f64.value(pool)
        res = torch.where(v <= level, res, -torch.inf)
    cex = region.distinct(pool[res > 0])
    near = torch.empty(0, system.n, dtype=F64)
    if neighbours and cex.shape[0]:
        noise = 0.01 * scale * torch.randn(cex.shape[0] * neighbours, system.n, generator=generator, dtype=F64)
        near = region.project(cex.repeat(neighbours, 1) + noise)
    return {"counterexamples": cex, "neighbours": near, "box_centres": centres, "open_boxes": corners,
            "max_residual": float(res.max()),
            "falsifier_starts": int(starts.shape[0]), "falsifier_violations": int((values > 0).sum()),
            "falsify_time_s": falsify_time}


def train_cegis(cfg: TrainConfig, system: UncertainSystem, proof: ProofConfig, progress: bool = True,
                init: tuple[Lyapunov, Controller] | None = None, log=None) -> tuple[TrainResult, list[ProofRound]]:
    """Train with counterexample-guided rounds (see the module docstring), for a resolved ``cfg`` and resolved
    ``proof`` settings (:meth:`TrainConfig.resolved`, :meth:`ProofConfig.resolved`).

    Returns the best :class:`TrainResult` (its ``config`` is the first run's config, its ``history`` the training of
    every round up to it, iterations counted on, its ``metrics["cegis"]`` the record) and the rounds, each a
    :class:`~drlyap.records.ProofRound` (its proof, times, the states added and, when states were added, the
    ``counterexamples`` found, which the metrics do not keep). ``log(round)`` is called after each verification. No
    new retraining round starts once ``proof.total_time`` seconds (from the start) are spent.
    ``proof.falsifier_starts``: the falsifier's random starts per round; None: 512 uniform in X_delta, or, where
    training draws states near x* (``near_share > 0``: cart-pole, quadrotor), 2,048, half of them spread over the
    distance from x* (in 6 states uniform starts miss the violations near x*: docs/tuning.md).
    """
    if not proof.is_resolved:
        raise ValueError("resolve the proof settings for the system first (ProofConfig.resolved(system))")
    if TrainSections.of(cfg).condition.uniform:
        raise ValueError("CEGIS needs a per-state condition (method dr with loss pointwise, or baseline); "
                         "the uniform DR condition has no per-state residual to falsify")
    result, rounds, _ = _proof_rounds(cfg, system, proof, proof.round_budget(), progress, init, log)
    return result, rounds


class _Counterexamples:
    """Proof rounds of a per-state condition: the branch and bound on the trained condition, and for retraining the
    falsifier's counterexamples, their neighbours and the unproved boxes' centres (:func:`collect_counterexamples`)
    and at most ``train_boxes`` of the boxes it left open; the returned pair's verdict settled by the falsifier where
    the proof is ``unknown``. ``plan``: the first run's sections (the claimed level, the share of states drawn near x*,
    the seed, the hinge's margin)."""

    def __init__(self, condition: Condition, proof: ProofConfig, budget: Budget, region: Region,
                 plan: TrainSections) -> None:
        self.condition, self.proof, self.budget, self.region = condition, proof, budget, region
        self.level, self.seed = plan.goal.roa_level, plan.schedule.seed
        near = bool(plan.sampling.near_share)
        self.search = CounterexampleSearch(
            n_random=proof.falsifier_starts if proof.falsifier_starts is not None else (2048 if near else 512),
            max_boxes=proof.keep_boxes, steps=proof.falsifier_steps, neighbours=proof.neighbours, level=self.level,
            near=near, train_boxes=proof.train_boxes if proof.box_weight else 0)
        self.margin = float(plan.condition.margin)  # the open boxes' hinge margin, the states' own

    def prove(self, loop: ClosedLoop) -> ConditionProof:
        keep = max(self.proof.keep_boxes, self.proof.train_boxes if self.proof.box_weight else 0)
        return prove_trained(loop, self.condition, self.region, self.budget, self.level,
                             falsify_starts=0,  # its own falsifier below
                             rules=ProofRules(keep_boxes=keep,
                                              stop_at_counterexample=bool(self.proof.stop_at_counterexample)))

    def summary(self, verdict: ConditionProof) -> dict:
        return verdict.summary()

    def rank(self, verdict: ConditionProof) -> tuple:
        """After a proof and the acceptance check: a larger proved share, then a smaller counterexample."""
        return verdict.verified_fraction, -(verdict.counterexample_value or 0.0)

    def retraining(self, loop: ClosedLoop, verdict: ConditionProof, gen: torch.Generator,
                   entry: ProofRound) -> tuple[Tensor, OpenBoxes | None]:
        """New retraining states (box centres, neighbours, counterexamples: the counterexamples last), their counts
        put into ``entry``, and at most ``train_boxes`` boxes the proof left open, to train the verifier's bound on
        (None: none, or the term is off)."""
        found = collect_counterexamples(loop, self.condition, self.region, verdict, gen, self.search)
        entry.added = {"counterexamples_added": int(found["counterexamples"].shape[0]),
                       "neighbours_added": int(found["neighbours"].shape[0]),
                       "box_centres_added": int(found["box_centres"].shape[0]),
                       "falsifier_max_residual": found["max_residual"], "falsify_time_s": found["falsify_time_s"]}
        entry.counterexamples = found["counterexamples"]
        states = torch.cat([found["box_centres"], found["neighbours"], found["counterexamples"]])
        if found["open_boxes"] is None:
            return states, None
        return states, OpenBoxes(*found["open_boxes"], self.level, self.proof.enclosure,
                                 weight=float(self.proof.box_weight), margin=self.margin)

    def settle(self, entry: ProofRound, loop: ClosedLoop, verdict: ConditionProof) -> ConditionProof:
        """The returned pair's verdict: an unknown proof becomes violated where the falsifier finds a certain
        violation."""
        return settle_unknown(ConditionProof.from_dict(entry.verification), loop, self.condition, self.region,
                              self.level, starts=self.proof.settle_starts, seed=self.seed)


class _MarginPeaks:
    """Proof rounds of the DR uniform condition: its margin over X_delta (:func:`~drlyap.verification.uniform_margin`,
    keeping its boxes), and for retraining the states where each component's supremum was found
    (``UniformMargin.attained_at``) with ``neighbours`` jittered copies each: the margin is made of those suprema."""

    def __init__(self, condition: Condition, proof: ProofConfig, budget: Budget, region: Region,
                 plan: TrainSections) -> None:
        self.condition, self.proof, self.budget, self.region = condition, proof, budget, region

    def prove(self, loop: ClosedLoop) -> UniformMargin:
        return uniform_margin(loop, self.condition, self.region, self.budget, keep_partition=True)

    def summary(self, verdict: UniformMargin) -> dict:
        return verdict.to_dict()

    def rank(self, verdict: UniformMargin) -> tuple:
        """After a proof and the acceptance check: a smaller margin."""
        return (-(verdict.margin_upper if verdict.margin_upper is not None else math.inf),)

    def retraining(self, loop: ClosedLoop, verdict: UniformMargin, gen: torch.Generator,
                   entry: ProofRound) -> tuple[Tensor, None]:
        """The states where the components' suprema were found, and ``neighbours`` jittered copies of each; no open
        boxes (None: the uniform margin is one number over X_delta, no per-box residual to train on)."""
        peaks = torch.as_tensor(verdict.attained_at or [], dtype=F64).reshape(-1, self.region.n)
        copies = int(self.proof.neighbours)
        noise = 0.01 * self.region.scale * torch.randn(peaks.shape[0] * copies, self.region.n, generator=gen,
                                                        dtype=F64)
        near = self.region.project(peaks.repeat(copies, 1) + noise)
        entry.added = {"peaks_added": int(peaks.shape[0]), "neighbours_added": int(near.shape[0])}
        return torch.cat([near, peaks]), None

    def settle(self, entry: ProofRound, loop: ClosedLoop, verdict: UniformMargin) -> UniformMargin:
        return verdict


class _Rounds:
    """What the proof rounds for the resolved ``cfg`` and ``proof`` settle at the start and gather as they go: X_delta
    (``region``), at most ``rounds`` retraining rounds of ``iters_round`` iterations each, the generator of the
    retraining states (``gen``); every round's record (``done``), all rounds' training ``history`` (iterations and
    seconds counted on from the first run), the best pair so far (a proof first; among unproved pairs, one that passes
    the acceptance check, then the kind's rank), and the accumulated retraining states ``extra`` ``(E, n)``."""

    def __init__(self, cfg: TrainConfig, system: UncertainSystem, proof: ProofConfig, start: float) -> None:
        self.plan = TrainSections.of(cfg)
        schedule = self.plan.schedule
        self.region, self.start = Region.of(system, float(self.plan.sampling.delta)), start
        self.rounds = int(proof.rounds)
        self.iters_round = int(proof.iters_per_round if proof.iters_per_round is not None
                               else max(1, schedule.iters // 2))
        self.gen = torch.Generator().manual_seed(schedule.seed + 7919)
        self.done: list[ProofRound] = []
        self.history: list[dict] = []
        self.total_iters = 0
        self.best: tuple | None = None
        self.extra = torch.empty(0, system.n, dtype=F64)

    def judged(self, entry: ProofRound, result: TrainResult, verdict, rank: tuple) -> None:
        """Keep the round's pair where it ranks above the best so far."""
        # a proof first; among unproved pairs, one that passes the acceptance check (Hurwitz at x*, no other
        # equilibrium) before a larger proved share: retraining on counterexamples of an infeasible condition
        # can trade stability for area (measured on pendulum-u9: 0/200 stabilised instead of 170/200)
        score = (entry.verified, *result.record.acceptance.stability(), *rank)
        if self.best is None or score > self.best[0]:
            self.best = (score, result, entry.round, list(self.history), verdict)

    def out_of_time(self, budget: float | None) -> bool:
        return budget is not None and time.perf_counter() - self.start > budget


def _proof_rounds(cfg: TrainConfig, system: UncertainSystem, proof: ProofConfig, budget: Budget, progress: bool,
                  init: tuple[Lyapunov, Controller] | None,
                  log) -> tuple[TrainResult, list[ProofRound], Certificate]:
    """Rounds of :func:`~drlyap.training.trainer.fit` and a proof with the ``budget``, for the resolved ``cfg`` and
    ``proof``: round 0 is the first run (from ``init``), every later one continues from the pair
    before it on the states the proof left (per-state conditions by :class:`_Counterexamples`, the DR uniform
    condition by :class:`_MarginPeaks`). Returns the best pair, the rounds and the certificate of its trained condition
    (also its ``metrics["certificate"]``)."""
    gather = _Rounds(cfg, system, proof, time.perf_counter())
    rounds, done = gather.rounds, gather.done
    round_cfg, kind, result, boxes, first_reshape = cfg, None, None, None, None
    for r in range(rounds + 1):
        tic = time.perf_counter()
        warm = init if result is None else (result.lyapunov, result.controller)
        start = FitStart(warm, gather.extra.repeat(int(proof.replicate), 1) if r else None, not r, boxes,
                         not r or proof.retrain == "pair")
        result = fit_or_resume(proof.compute.checkpoint_dir, round_cfg, system, start, progress)
        train_time = time.perf_counter() - (tic if r else gather.start)
        if not r:
            first_reshape = result.metrics.get("reshape")  # the first fit's, which every later round starts from
            kind = (_Counterexamples if result.condition.per_state else _MarginPeaks)(
                result.condition, proof, budget, gather.region, gather.plan)
        gather.history += _continued(result.history, gather.total_iters,
                                     gather.history[-1]["time_s"] if gather.history else 0.0)
        gather.total_iters += result.record.iterations
        tic = time.perf_counter()
        ver = kind.prove(result.loop)
        trained = result.record
        entry = ProofRound(round=r, verification=kind.summary(ver), verified=ver.verified, status=ver.status,
                           verified_fraction=ver.verified_fraction, verify_time_s=time.perf_counter() - tic,
                           train_time_s=train_time, train_iterations=trained.iterations,
                           acceptance_passed=trained.passed, unchanged=bool(r) and _same_pair(warm, result))
        gather.judged(entry, result, ver, kind.rank(ver))
        out_of_time = gather.out_of_time(proof.total_time)
        if entry.verified or r == rounds or out_of_time:
            if not entry.verified:
                entry.stopped = ("its time budget (verify_budget) is spent" if out_of_time and r < rounds
                                 else f"its {rounds} retraining round(s) are spent")
            _logged(done, entry, log)
            break
        new, boxes = kind.retraining(result.loop, ver, gather.gen, entry)
        if boxes is not None:
            entry.added["open_boxes"] = len(boxes)
        gather.extra = gather.region.distinct(torch.cat([gather.extra, new]))[-int(proof.max_extra):]  # the newest
        entry.added.update(extra_states=int(gather.extra.shape[0]), next_iterations=gather.iters_round,
                           max_rounds=rounds)
        _logged(done, entry, log)
        round_cfg = dataclasses.replace(cfg, iters=gather.iters_round, seed=cfg.seed + 1000 * (r + 1),
                                        xi_samples=result.xi_samples.tolist())
    _, chosen, chosen_round, chosen_history, chosen_proof = gather.best
    final = done[chosen_round] if chosen_round < len(done) else done[-1]
    verdict = kind.settle(final, chosen.loop, chosen_proof)
    cert = Certificate.of(verdict, float(cfg.delta), rounds=len(done) - 1)
    metrics = dict(chosen.metrics) | {"reshape": first_reshape, "cegis": jsonable({
        "rounds": [e.to_dict() for e in done], "final": verdict.to_dict(), "verified": final.verified,
        "returned_round": chosen_round, "retraining_rounds": len(done) - 1, "max_rounds": rounds,
        "iters_per_round": gather.iters_round, "total_iterations": gather.total_iters,
        "extra_states": int(gather.extra.shape[0]), "replicate": int(proof.replicate),
        "verify_time_limit_s": budget.seconds, "verify_boxes": budget.boxes,
        "total_time_s": time.perf_counter() - gather.start})}
    metrics["certificate"] = jsonable(cert.to_dict())
    out = dataclasses.replace(chosen, config=cfg, metrics=metrics, history=chosen_history,
                              trained_proof=chosen_proof if chosen_proof.verified else None)
    return out, done, cert


def _logged(done: list[ProofRound], entry: ProofRound, log) -> None:
    """Add a round's record to ``done`` and hand it to ``log`` (where there is one)."""
    done.append(entry)
    if log is not None:
        log(entry)


def _same_pair(before: tuple[Lyapunov, Controller], after: TrainResult) -> bool:
    """Whether a retraining returned the very weights it started from (a loss of 0 on every state it drew)."""
    for old, new in ((before[0], after.lyapunov), (before[1], after.controller)):
        a, b = old.state_dict(), new.state_dict()
        if a.keys() != b.keys() or not all(torch.equal(a[k].cpu(), b[k].cpu()) for k in a):
            return False
    return True


def _continued(history: list[dict], iterations: int, seconds: float) -> list[dict]:
    """A retraining round's ``history`` with its iterations and seconds counted on from the rounds before it."""
    return [{"iteration": h["iteration"] + iterations, "loss": h["loss"], "time_s": h["time_s"] + seconds}
            for h in history]


def train(config: TrainConfig, system: UncertainSystem | None = None, proof: ProofConfig | None = ProofConfig(), *,
          progress: bool = True, init: tuple[Lyapunov, Controller] | None = None, log=None,
          warn: bool = True) -> TrainResult:
    """Train a pair for ``config`` and prove its trained condition: the default way to train.

    ``system``: the system object (default: the registered one ``config.system`` names). ``config`` and ``proof``
    are resolved for it here, once. ``proof``: the proof settings (:class:`~drlyap.verification.ProofConfig`);
    None trains without proving. Per-state conditions (baseline, DR pointwise) run the rounds of
    :func:`train_cegis`; the uniform DR condition runs rounds on its margin's suprema (module docstring).
    ``metrics["certificate"]`` records the verdict (:class:`~drlyap.verification.Certificate`); with ``warn``
    a run that is not verified raises a :class:`UserWarning` saying so. ``init``: networks to start from (copied);
    ``log(round)``: called after each proof round (None: with ``progress``, its line is printed on stderr).
    """
    system = system or get_system(config.system)
    cfg = config.resolved(system)
    proof = None if proof is None else proof.resolved(system)
    if log is None and progress:  # every phase named where progress is shown: a line per proof round on stderr
        def log(entry: ProofRound) -> None:
            print(proof_round_line(entry), file=sys.stderr, flush=True)
    settings, budget = (None, None) if proof is None else (proof.to_dict(), proof.round_budget())
    if proof is None:
        result = fit(cfg, system, progress=progress, init=init)
        result.metrics["certificate"] = Certificate(status="not checked", condition=result.condition.label).to_dict()
        return result
    result, _, cert = _proof_rounds(cfg, system, proof, budget, progress, init, log)
    result.metrics["proof"] = settings
    if warn and not cert.verified:
        warnings.warn(unverified_warning(cert, cfg.system, cfg.method), stacklevel=2)
    return result
