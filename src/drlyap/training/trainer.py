"""Training a controller and its Lyapunov certificate (paper Sec. V, SPEC §3 and §5).

:func:`fit` samples the training states uniformly in X minus the delta-ball (and, for region-of-attraction
training, inside the sublevel set ``{V <= (1 + level_margin) roa_level}``: the claimed set and its margin), trains
both networks with Adam on the condition's loss (batched over states and xi samples), and runs the acceptance
check of :mod:`drlyap.training.acceptance` every ``check_every`` iterations. It stops as soon as the check passes
or at ``iters``, and returns the best checkpoint (passing first, then smallest validation violation); a growing
set (``grow_weight``) trains every iteration, the growth term on the first ``GROW_SHARE`` of them and the rest
repairing what it broke, and keeps the latest pair that passes. A diverging loss (NaN/inf) stops training with
the last good weights and says so.

:func:`fit` reads the config through its sections (:class:`~drlyap.sections.TrainSections`); the states it trains on
are drawn by :mod:`drlyap.training.states`, the LQR warm start is in :mod:`drlyap.training.warm_start`, and the
acceptance checks and the pair kept are :mod:`drlyap.training.acceptance`'s.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition, local_rates
from drlyap.config import TrainConfig
from drlyap.kernels import float_kernels
from drlyap.networks import Controller, Lyapunov
from drlyap.progress import progress as show_progress
from drlyap.records import AcceptanceCheck, TrainingRecord
from drlyap.regions import Region
from drlyap.sections import ConditionSection, NetworkSection, RegionGoal, Schedule, TrainSections
from drlyap.systems import UncertainSystem
from drlyap.training.acceptance import PairKeeper, restore, snapshot
from drlyap.training.boxes import OpenBoxes
from drlyap.training.reshape import GrowthTarget, grow_quadratic, quadratic_form, share
from drlyap.training.states import TrainingStates
from drlyap.training.warm_start import Regression, warm_start_pair
from drlyap.verification.results import ConditionProof, UniformMargin

LOCAL_EVERY = 4  # iterations between evaluations of the local term (second derivatives at x*: ~2x an iteration)
RESHAPE_BATCHES = 3  # states per convex program of the V step, in training batches
RESHAPE_MIX = (1.0, 0.75, 0.5, 0.25)  # the grown V's matrix mixed back towards the trained one until a check passes
GROW_SHARE = 2 / 3  # growing sets: the growth term acts on this share of the iterations, the rest repairs


@dataclass
class TrainResult:
    """What :func:`train` returns: the networks, the data, and the record of the run."""

    config: TrainConfig
    system: UncertainSystem
    lyapunov: Lyapunov
    controller: Controller
    xi_samples: Tensor  # (N, k) float64
    condition: Condition
    history: list[dict]
    metrics: dict
    trained_proof: ConditionProof | UniformMargin | None = None  # the trained condition's verified proof, with its partition

    @cached_property
    def loop(self) -> ClosedLoop:
        """The trained closed loop (what is proved)."""
        return ClosedLoop(self.system, self.lyapunov, self.controller)

    @property
    def record(self) -> TrainingRecord:
        """What the training recorded (the summary ``metrics.json`` is written from), typed."""
        return TrainingRecord.from_metrics(self.metrics)

    @property
    def acceptance(self) -> AcceptanceCheck:
        """The acceptance check of the pair kept (:attr:`record`'s, without reading the rest of the record)."""
        return AcceptanceCheck.from_dict(self.metrics["acceptance"])


def growth_words(grown: int, iterations: int) -> str:
    """How a growing set was trained: ``grown`` of its ``iterations`` with the growth term, the rest repairing the
    condition on the set grown."""
    if grown >= iterations:
        return f"grew the set for all {iterations} iterations"
    return f"grew the set for {grown} of {iterations} iterations, then repaired the condition on it"


def fit(cfg: TrainConfig, system: UncertainSystem, progress: bool = True, init: tuple[Lyapunov, Controller] | None = None,
        extra_states: Tensor | None = None, grow: bool = True, boxes: OpenBoxes | None = None,
        train_lyapunov: bool = True) -> TrainResult:
    """Train a pair for the resolved config ``cfg`` (:meth:`TrainConfig.resolved` for ``system``), without proving
    it (:func:`drlyap.training.train` trains and proves).

    ``init`` warm-starts from given networks (copied, not modified). ``extra_states`` ``(E, n)`` are
    local states (e.g. counterexamples found by the verifier) added to every training batch. ``grow=False`` leaves
    out the growth term (``grow_weight``; the faces keep its margin): the retraining rounds repair what a proof
    found instead of pulling the set further out. ``boxes``: boxes a proof left open, whose verifier bound is trained
    on beside the states (:class:`~drlyap.training.boxes.OpenBoxes`; certified training). ``train_lyapunov=False``
    keeps V as it starts (``init``'s) and trains the controller only: a retraining round that must not move V's sets.
    """
    if system.name != cfg.system:
        raise ValueError(f"TrainConfig(system={cfg.system!r}) names another system than the one passed "
                         f"({system.name!r}); set TrainConfig(system={system.name!r})")
    plan = TrainSections.of(cfg)
    schedule, sampling, goal = plan.schedule, plan.sampling, plan.goal
    device = schedule.torch_device()
    torch.manual_seed(schedule.seed)
    gen = torch.Generator().manual_seed(schedule.seed)
    xi_all = sampling.xi(system, schedule.seed)
    xi_train = plan.condition.training_samples(xi_all)
    condition = plan.condition.build(xi_train)
    region = sampling.region(system)
    lyapunov, controller = _networks(system, plan.networks, init, device)
    states = TrainingStates(sampling, goal, system, region, lyapunov, gen, device, _extra(extra_states, system, device))
    loop = ClosedLoop(system, lyapunov, controller)  # the live networks: no float64 copy is taken of this loop
    grid = region.grid()
    system.check_finite(xi_all, system.to_user(grid))
    growing = bool(goal.grow_weight) and grow and goal.level is not None  # trains every iteration: no early stop
    keeper = PairKeeper(loop, condition, xi_all.to(device), region, grid.float().to(device), states,
                        bool(plan.condition.local_rate), growing)
    warm = None
    if plan.networks.warm_start and not init:
        warm = warm_start_pair(loop, plan.networks, goal.level, region, gen, xi_train,
                               max(plan.condition.local_rate, plan.condition.exp_rate),
                               Regression(schedule.lr, n_states=min(4096, int(sampling.n_states))))
    run = _Iterations(schedule, plan.condition, goal, keeper,
                      None if boxes is None or not len(boxes) else (boxes.to(device), gen))
    lyapunov.requires_grad_(train_lyapunov)
    try:
        run.go(show_progress(schedule.iters, f"{cfg.system} {cfg.method}", progress))
    finally:
        lyapunov.requires_grad_(True)
    reshaped = None
    if growing and goal.reshape_steps:
        bar = show_progress(goal.reshape_steps, f"{cfg.system}: growing V's set", progress)
        reshaped = run.reshape(region, gen, RESHAPE_BATCHES * sampling.n_states, bar)
        bar.close()
    metrics = run.metrics() | {"condition": condition.describe(), "xi_samples": xi_all.tolist(),
                               "xi_train": xi_train.tolist(), "warm_start": warm, "reshape": reshaped,
                               "float_kernels": float_kernels(device)}
    return TrainResult(cfg, system, lyapunov.cpu(), controller.cpu(), xi_all, condition, run.history, metrics)


class _Iterations:
    """A fit's iterations: Adam on the loss of :func:`_loss` until the acceptance check passes (not while the set
    grows) or ``schedule.iters``; a diverging loss restores the last good weights (a snapshot every 50 iterations).
    The loop trained, its condition and states are the ``keeper``'s; afterwards its networks hold the pair the
    ``keeper`` ranked best."""

    def __init__(self, schedule: Schedule, section: ConditionSection, goal: RegionGoal, keeper: PairKeeper,
                 boxes: tuple[OpenBoxes, torch.Generator] | None = None) -> None:
        self.schedule, self.section, self.goal, self.keeper, self.boxes = schedule, section, goal, keeper, boxes
        # the loop trained, its condition, its states and whether its set grows: the keeper's
        self.loop, self.condition, self.states, self.growing = keeper.loop, keeper.condition, keeper.states, keeper.growing
        self.grow_until = math.floor(GROW_SHARE * schedule.iters)  # the last iteration with the growth term
        self.history: list[dict] = []
        self.status = "iteration cap reached without passing the acceptance check"
        self.iteration = 0
        self.seconds = 0.0
        self.check: AcceptanceCheck | None = None

    def go(self, bar) -> None:
        """Draw the states' start (:meth:`~drlyap.training.states.TrainingStates.start`: after the warm start, whose
        pair the states inside the set are drawn for), train, showing the iterations on ``bar``, and load the pair
        kept."""
        lyapunov, controller = self.loop.lyapunov, self.loop.controller
        self.states.start()
        trained = [p for p in (*lyapunov.parameters(), *controller.parameters()) if p.requires_grad]
        opt = torch.optim.Adam(trained, lr=self.schedule.lr, fused=True)
        last_good = snapshot(lyapunov, controller)
        start = time.perf_counter()
        try:
            for iteration in range(1, self.schedule.iters + 1):
                self.iteration = iteration
                loss = _loss(self.section, self.goal, self.loop, self.condition, self.states, iteration,
                             self.growing and iteration <= self.grow_until)
                if self.boxes is not None:
                    loss = loss + self.boxes[0].loss(self.loop, self.condition, self.boxes[1])
                if not torch.isfinite(loss):
                    restore(lyapunov, controller, last_good)
                    self.status = (f"diverged: loss became {float(loss.detach())} at iteration {iteration}; kept the "
                                   "last good weights")
                    break
                if iteration % 50 == 1:
                    last_good = snapshot(lyapunov, controller)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                if iteration % 10 == 0 or iteration == 1:
                    self.history.append({"iteration": iteration, "loss": float(loss.detach()),
                                         "time_s": time.perf_counter() - start})
                    bar.set_postfix(loss=f"{float(loss.detach()):.2e}")
                bar.update(1)
                if (iteration % self.schedule.check_every == 0 or iteration == self.schedule.iters) \
                        and self.keeper.check(iteration).passed and not self.growing:
                    self.status = f"passed the acceptance check at iteration {iteration}"
                    break
        finally:
            bar.close()
        self.check = self.keeper.restore(self.iteration)
        if self.growing and self.check.passed and not self.status.startswith("diverged"):
            self.status = (f"{growth_words(min(self.iteration, self.grow_until), self.iteration)}; kept the latest pair "
                           "passing the acceptance check")
        self.seconds = time.perf_counter() - start

    def reshape(self, region: Region, gen: torch.Generator, n_states: int, bar) -> dict:
        """After a growing fit that passed its check: grow a quadratic V's set with pi fixed
        (:func:`~drlyap.training.reshape.grow_quadratic`). The programs see only their states: where the grown V fails
        the acceptance check, V's matrix is moved back towards the trained one (``P_t = P0 + t (P1 - P0)``, ``t`` in
        :data:`RESHAPE_MIX`; the condition at a state is convex in P, so a mixture is no worse there than the two
        ends), and the first that passes is kept, else the trained pair. The record (``steps`` 0 and why where
        nothing ran; ``mix``: the ``t`` kept)."""
        if not self.check.passed:
            return {"steps": 0, "stopped": "the trained pair did not pass its acceptance check", "kept": False}
        tic = time.perf_counter()
        kept, before = snapshot(self.loop.lyapunov, self.loop.controller), quadratic_form(self.loop.lyapunov)
        target = GrowthTarget(self.goal.level, self.goal.faces_level, self.section.margin_rate, self.section.local_rate)
        record = grow_quadratic(self.loop, self.condition, region, target, self.goal.reshape_steps, gen, n_states, bar)
        if record is None:
            return {"steps": 0, "stopped": "V is not quadratic, or the condition is not the maximum over its samples",
                    "kept": False}
        grown, record["kept"], record["mix"] = quadratic_form(self.loop.lyapunov), False, None
        for mix in RESHAPE_MIX if record["steps"] else ():
            self.loop.lyapunov.set_quadratic(before + mix * (grown - before))
            check = self.keeper.check(self.iteration)
            if check.passed:
                self.check, record["kept"], record["mix"] = check, True, mix
                record["share_kept"] = share(quadratic_form(self.loop.lyapunov) / self.goal.level, region)
                break
        if not record["kept"]:
            restore(self.loop.lyapunov, self.loop.controller, kept)
        record["seconds"] = time.perf_counter() - tic
        return record

    def metrics(self) -> dict:
        """The run's record (the training part of ``metrics.json``)."""
        check, keeper, iteration = self.check, self.keeper, self.iteration
        return {"status": self.status, "passed": check.passed, "iterations": iteration,
                "best_iteration": check.iteration, "train_time_s": self.seconds, "check_time_s": keeper.seconds,
                "ms_per_iteration": 1000 * (self.seconds - keeper.seconds) / max(iteration, 1),
                "final_loss": self.history[-1]["loss"] if self.history else None, "acceptance": check.to_dict(),
                "checks": keeper.checks}


def _networks(system: UncertainSystem, section: NetworkSection, init: tuple[Lyapunov, Controller] | None,
              device: torch.device) -> tuple[Lyapunov, Controller]:
    """Fresh networks for the ``section`` (drawn from torch's global generator, seeded by the caller), or copies of
    ``init`` where it fits the section and is finite; on ``device``."""
    lyapunov, controller = section.build(system)
    if init:
        def shape(v: Lyapunov, pi: Controller) -> str:
            return (f"V {v.phi.sizes}, linear path {v.phi.skip is not None}, alpha_hat {v.alpha_hat}; pi "
                    f"{pi.varphi.sizes}, linear path {pi.varphi.skip is not None}")

        if shape(*init) != shape(lyapunov, controller):
            raise ValueError(f"warm-start networks ({shape(*init)}) do not match the config ({shape(lyapunov, controller)})")
        lyapunov, controller = copy.deepcopy(init[0]), copy.deepcopy(init[1])
        for name, net in (("V", lyapunov), ("pi", controller)):
            bad = [key for key, value in net.state_dict().items()
                   if value.is_floating_point() and not bool(torch.isfinite(value).all())]
            if bad:
                raise ValueError(f"warm-start network {name} holds NaN or inf in {', '.join(bad)}: it cannot be "
                                 "trained from")
    return lyapunov.to(device), controller.to(device)


def _extra(extra_states: Tensor | None, system: UncertainSystem, device: torch.device) -> Tensor | None:
    """``extra_states (E, n)`` checked, float32 on ``device`` (None stays None)."""
    if extra_states is None:
        return None
    extra_states = torch.as_tensor(extra_states, dtype=torch.float64)
    if extra_states.ndim != 2 or extra_states.shape[1] != system.n or not torch.isfinite(extra_states).all():
        raise ValueError(f"extra_states must be a finite (E, {system.n}) tensor of local states")
    return extra_states.float().to(device)


def _loss(section: ConditionSection, goal: RegionGoal, loop: ClosedLoop, condition: Condition, states: TrainingStates,
          iteration: int, grow_now: bool) -> Tensor:
    """The loss of one iteration: the condition's on this iteration's states, with a level V above it on the box's
    faces (and, while ``grow_now``, the growth term), and every ``LOCAL_EVERY`` iterations the local rate's term."""
    terms = condition.terms(loop, states.next(iteration, loop, condition))
    level = states.level
    loss = condition.loss(terms, section.margin, section.margin_rate, level, goal.outside_weight, goal.exclude_weight)
    if level is not None:  # V above the level on the faces of X: {V <= level} inside X
        loss = loss + states.faces_term(loop, condition.xi, iteration)
        if grow_now:  # the set pulled out towards the faces
            loss = loss + goal.grow_weight * (torch.relu(terms.value - level) / level).mean()
    if section.local_rate and (iteration - 1) % LOCAL_EVERY == 0:  # V a Lyapunov function of the linearisation
        loss = loss + torch.relu(local_rates(condition, loop) + section.local_rate).mean()
    return loss
