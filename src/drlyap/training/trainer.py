"""Training a controller and its Lyapunov certificate (paper Sec. V, SPEC §3 and §5).

:func:`fit` samples the training states uniformly in X minus the delta-ball (and, for region-of-attraction
training, inside the sublevel set ``{V <= (1 + level_margin) roa_level}``: the claimed set and its margin), trains
both networks with Adam on the condition's loss (batched over states and xi samples), and runs the acceptance
check of :mod:`drlyap.training.acceptance` every ``check_every`` iterations. It stops as soon as the check passes
or at ``iters``, and returns the best checkpoint (passing first, then smallest validation violation); a growing
set (``grow_weight``) trains every iteration, the growth term on the first ``GROW_SHARE`` of them and the rest
repairing what it broke, and keeps the latest pair that passes. A diverging loss (NaN/inf) stops training with
the last good weights and says so.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

from drlyap.assembly import (
    build_networks,
    draw_xi_samples,
    resolve_device,
    run_condition,
    training_level,
    training_region,
)
from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition, local_rates
from drlyap.config import TrainConfig
from drlyap.kinds import Method
from drlyap.lqr import lqr_design
from drlyap.networks import Controller, Lyapunov
from drlyap.progress import progress as show_progress
from drlyap.records import AcceptanceCheck, TrainingRecord
from drlyap.regions import Region
from drlyap.systems import UncertainSystem
from drlyap.training.acceptance import acceptance_check
from drlyap.verification.falsifier import ascent_step
from drlyap.verification.results import ConditionProof

ADVERSARIAL_STEP = 0.01  # one ascent step of the adversarial states, as a share of the box's width per coordinate
ADVERSARIAL_REFRESH = 0.02  # share of the adversarial states redrawn every iteration
LOCAL_EVERY = 4  # iterations between evaluations of the local term (second derivatives at x*: ~2x an iteration)
GROW_FACES_MARGIN = 0.05  # growing sets: V asked above (1 + this) level on the faces, room for the proof of V > level
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
    trained_proof: ConditionProof | None = None  # the verified proof of the trained condition, with its partition

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


def warm_start_lqr(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, cfg: TrainConfig,
                   region: Region, generator: torch.Generator, iters: int = 500, n_states: int = 4096) -> dict:
    """Fit the networks to an LQR pair (in place): ``V ~ s z^T P z`` and ``varphi(z) - varphi(0) ~ -K z``, exactly for
    a network without hidden layers (:func:`_linear_fit`), by regression for the others.

    ``P``, ``K``: the LQR design for ``cfg.lqr_weights`` (``[Q diagonal, R diagonal]``; None: Bryson's rule) on the
    nominal linearisation; ``s`` puts the quadratic's minimum over the faces of the box at 1.2 times the training
    level (:func:`~drlyap.assembly.training_level`; 1.2 without a level). States: half uniform in X_delta,
    half spread over the distance from x*. Returns the design's gain, the scale and the final relative errors.
    """
    q, r = cfg.lqr_weights if cfg.lqr_weights is not None else (None, None)
    try:
        design = lqr_design(system, q, r)
    except ValueError as err:
        raise ValueError(f"{err}; the LQR warm start needs one (TrainConfig.warm_start = 'lqr', the default for a "
                         "system of one's own): declare warm_start=None in the system's defaults, or "
                         "drlyap.config.PAPER_CONDITION for the paper's condition") from None
    half = torch.maximum(-region.lo, region.hi)
    scale = 1.2 * (training_level(cfg) or 1.0) / float((half.square() / torch.linalg.inv(design.P).diagonal()).min())
    ref = next(lyapunov.parameters())
    p_mat, k_mat = (design.P * scale).to(ref), design.K.to(ref)
    exact = _linear_fit(lyapunov, controller, design.P * scale, design.K)
    params = [p for net in (lyapunov, controller) if net not in exact for p in net.parameters()]
    opt = torch.optim.Adam(params, lr=cfg.lr) if params else None

    def errors() -> tuple[Tensor, Tensor]:
        z = torch.cat([region.sample(n_states // 2, generator), region.sample_near(n_states - n_states // 2, generator)])
        z = z.to(ref)
        v_target, u_target = ((z @ p_mat) * z).sum(-1), -(z @ k_mat.T)
        v_err = (lyapunov(z) - v_target).square().mean() / v_target.square().mean()
        u_err = (controller.raw(z) - u_target).square().mean() / u_target.square().mean().clamp_min(1e-12)
        return v_err, u_err

    if opt is None:  # nothing left to fit: the errors of the exact pair
        with torch.no_grad():
            v_err, u_err = errors()
    else:
        for _ in range(iters):
            v_err, u_err = errors()
            opt.zero_grad(set_to_none=True)
            (v_err + u_err).backward()
            opt.step()
    return {"method": "lqr", "K": design.K.tolist(), "P_scale": scale, "v_relative_error": float(v_err.detach()),
            "u_relative_error": float(u_err.detach()), "iterations": iters if opt else 0}


def _linear_fit(lyapunov: Lyapunov, controller: Controller, p: Tensor, k: Tensor) -> list:
    """Set the networks without hidden layers to ``V = z^T p z`` and ``varphi(z) - varphi(0) = -k z`` exactly (in
    place; ``p (n, n)``, ``k (m, n)`` float64); returns those set. A linear V is ``||A z/s||^2 + alpha_hat ||z/s||^2``:
    ``A^T A`` is ``s p s - alpha_hat I`` with negative eigenvalues clipped to 0 (V then lies above the target
    there), its leading ``out`` directions when the output has fewer rows than states."""
    done = []
    s = lyapunov.phi.input_scale.to(p)
    if len(lyapunov.phi.layers) == 1:
        layer = lyapunov.phi.layers[0]
        m = s[:, None] * p * s[None, :] - lyapunov.alpha_hat * torch.eye(p.shape[0], dtype=p.dtype)
        eig, vec = torch.linalg.eigh((m + m.T) / 2)
        rows = (eig.clamp_min(0).sqrt()[:, None] * vec.T).flip(0)  # largest first
        weight = torch.zeros(layer.weight.shape, dtype=p.dtype)
        count = min(weight.shape[0], rows.shape[0])
        weight[:count] = rows[:count]
        with torch.no_grad():
            layer.weight.copy_(weight)
            layer.bias.zero_()
        done.append(lyapunov)
    if len(controller.varphi.layers) == 1:
        layer = controller.varphi.layers[0]
        with torch.no_grad():
            layer.weight.copy_(-k.to(p) * controller.varphi.input_scale.to(p)[None, :])
            layer.bias.zero_()
        done.append(controller)
    return done


def radial_states(lyapunov: Lyapunov, region: Region, level: float, count: int, generator: torch.Generator) -> Tensor:
    """Up to ``count`` states ``(C, n)`` (float64) of X_delta with ``V <= level``, drawn without rejection: a direction
    uniform on the sphere in box-scaled coordinates, moved out to the set's boundary along its ray (by
    ``sqrt(level / V)``, exact where V is quadratic) and then back in by a uniform share ``U^(1/n)``. In 6 states a
    sublevel set of 1e-3 of the box holds about 4 of 4,096 uniform draws; these states spread over all of it (uniform
    draws in the box, moved in the same way, would crowd the box's diagonals)."""
    direction = torch.randn(count, region.n, generator=generator, dtype=region.lo.dtype)
    z = direction / direction.norm(dim=-1, keepdim=True).clamp_min(1e-30) * region.hi.maximum(-region.lo)
    z = z * (_to_boundary(lyapunov, z, level) * torch.rand(count, generator=generator, dtype=z.dtype)
             ** (1.0 / region.n))[:, None]
    with torch.no_grad():
        keep = region.contains(z) & (lyapunov(z.to(next(lyapunov.parameters()))).double().cpu() <= level)
    return z[keep]


def _to_boundary(lyapunov: Lyapunov, z: Tensor, level: float) -> Tensor:
    """``(B,)`` float64: the factor ``sqrt(level / V(z))`` that moves each state of ``z (B, n)`` (float64, CPU) along
    its ray from x* onto ``{V = level}`` (exactly where V is quadratic)."""
    with torch.no_grad():
        value = lyapunov(z.to(next(lyapunov.parameters()))).double().cpu()
    return torch.sqrt(level / value.clamp_min(1e-30))


def adversarial_starts(lyapunov: Lyapunov, region: Region, level: float | None, count: int,
                       generator: torch.Generator) -> Tensor:
    """``(count, n)`` float64 starts of adversarial states: :func:`radial_states` in ``{V <= level}``, topped up with
    uniform states of X_delta (all uniform without a level)."""
    if level is None:
        return region.sample(count, generator)
    z = radial_states(lyapunov, region, level, 2 * count, generator)[:count]
    return torch.cat([z, region.sample(count - z.shape[0], generator)]) if z.shape[0] < count else z


def ascend(loop: ClosedLoop, condition: Condition, z: Tensor, region: Region, level: float | None) -> Tensor:
    """One step of projected ascent on the residual from states ``z (B, n)`` (float32 or the networks' dtype):
    ``ADVERSARIAL_STEP`` of the box's width along the width-scaled, normalised gradient, then back into X_delta and,
    with a level, onto ``{V <= level}`` by moving towards x* (exact for a quadratic V). No gradient reaches the
    weights."""
    with torch.enable_grad():
        x = z.detach().requires_grad_(True)
        grad = torch.autograd.grad(condition.residual(condition.terms(loop, x)).sum(), x)[0]
    moved = ascent_step(region, z.detach(), grad, ADVERSARIAL_STEP)
    if level is not None:
        moved = region.project(moved * _to_boundary(loop.lyapunov, moved, level).clamp(max=1.0)[:, None])
    return moved.to(z)


def inside_states(lyapunov: Lyapunov, region: Region, level: float, count: int, device: torch.device,
                  generator: torch.Generator, tries: int = 20) -> Tensor:
    """Up to ``count`` states ``(C, n)`` of X_delta with ``V <= level``: uniform draws kept by rejection, at most
    ``tries`` rounds of ``4 count`` draws; float32 on ``device``."""
    kept = []
    found = 0
    with torch.no_grad():
        for _ in range(tries):
            z = region.sample(4 * count, generator).float().to(device)
            z = z[lyapunov(z) <= level]
            kept.append(z)
            found += z.shape[0]
            if found >= count:
                break
    return torch.cat(kept)[:count]


def fit(cfg: TrainConfig, system: UncertainSystem, progress: bool = True, init: tuple[Lyapunov, Controller] | None = None,
        extra_states: Tensor | None = None, grow: bool = True) -> TrainResult:
    """Train a pair for the resolved config ``cfg`` (:meth:`TrainConfig.resolved` for ``system``), without proving
    it (:func:`drlyap.training.train` trains and proves).

    ``init`` warm-starts from given networks (copied, not modified). ``extra_states`` ``(E, n)`` are
    local states (e.g. counterexamples found by the verifier) added to every training batch. ``grow=False`` leaves
    out the growth term (``grow_weight``; the faces keep its margin): the retraining rounds repair what a proof
    found instead of pulling the set further out.
    """
    _check_fit(cfg, system)
    device = resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    xi_all = draw_xi_samples(system, cfg)
    xi_train = xi_all.mean(0, keepdim=True) if cfg.method == Method.BASELINE else xi_all
    condition = run_condition(cfg, xi_train)
    region = Region.of(system, cfg.delta)
    grid = region.grid()
    system.check_finite(xi_all, system.to_user(grid))
    lyapunov, controller = _networks(system, cfg, init, device)
    loop = ClosedLoop(system, lyapunov, controller)  # the live networks: no float64 copy is taken of this loop
    states = TrainingStates(cfg, system, region, lyapunov, gen, device, _extra(extra_states, system, device))
    warm = None
    if cfg.warm_start == "lqr" and not init:
        warm = warm_start_lqr(system, lyapunov, controller, cfg, region, gen, n_states=min(4096, int(cfg.n_states)))
    growing = bool(cfg.grow_weight) and grow and states.level is not None  # trains every iteration: no early stop
    grow_until = math.floor(GROW_SHARE * cfg.iters)  # the last iteration with the growth term
    keeper = PairKeeper(loop, condition, xi_all.to(device), region, grid.float().to(device), states, bool(cfg.local_rate),
                        growing)
    states.start()
    opt = torch.optim.Adam(list(lyapunov.parameters()) + list(controller.parameters()), lr=cfg.lr, fused=True)
    history: list[dict] = []
    last_good = _snapshot(lyapunov, controller)
    status = "iteration cap reached without passing the acceptance check"
    start = time.perf_counter()
    bar = show_progress(cfg.iters, f"{cfg.system} {cfg.method}", progress)
    iteration = 0
    try:
        for iteration in range(1, cfg.iters + 1):
            loss = _loss(cfg, loop, condition, states, iteration, growing and iteration <= grow_until)
            if not torch.isfinite(loss):
                _restore(lyapunov, controller, last_good)
                status = f"diverged: loss became {float(loss.detach())} at iteration {iteration}; kept the last good weights"
                break
            if iteration % 50 == 1:
                last_good = _snapshot(lyapunov, controller)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if iteration % 10 == 0 or iteration == 1:
                history.append({"iteration": iteration, "loss": float(loss.detach()), "time_s": time.perf_counter() - start})
                bar.set_postfix(loss=f"{float(loss.detach()):.2e}")
            bar.update(1)
            if (iteration % cfg.check_every == 0 or iteration == cfg.iters) and keeper.check(iteration).passed \
                    and not growing:
                status = f"passed the acceptance check at iteration {iteration}"
                break
    finally:
        bar.close()
    check = keeper.restore(iteration)
    if growing and check.passed and not status.startswith("diverged"):
        status = (f"{growth_words(min(iteration, grow_until), iteration)}; kept the latest pair passing the acceptance "
                  "check")
    elapsed = time.perf_counter() - start
    metrics = {"status": status, "passed": check.passed, "iterations": iteration,
               "best_iteration": check.iteration, "train_time_s": elapsed, "check_time_s": keeper.seconds,
               "ms_per_iteration": 1000 * (elapsed - keeper.seconds) / max(iteration, 1),
               "final_loss": history[-1]["loss"] if history else None, "acceptance": check.to_dict(),
               "checks": keeper.checks,
               "condition": condition.describe(), "xi_samples": xi_all.tolist(), "xi_train": xi_train.tolist(),
               "warm_start": warm}
    return TrainResult(cfg, system, lyapunov.cpu(), controller.cpu(), xi_all, condition, history, metrics)


def _check_fit(cfg: TrainConfig, system: UncertainSystem) -> None:
    """A ValueError where ``cfg`` is not a resolved config of ``system``."""
    if system.name != cfg.system:
        raise ValueError(f"TrainConfig(system={cfg.system!r}) names another system than the one passed "
                         f"({system.name!r}); set TrainConfig(system={system.name!r})")
    if cfg.missing():
        raise ValueError(f"the training config leaves {cfg.missing()} open: resolve it first "
                         "(TrainConfig.resolved(system))")


def _networks(system: UncertainSystem, cfg: TrainConfig, init: tuple[Lyapunov, Controller] | None,
              device: torch.device) -> tuple[Lyapunov, Controller]:
    """Fresh networks for ``cfg`` (drawn from torch's global generator, seeded by the caller), or copies of ``init``
    where it fits the config and is finite; on ``device``."""
    lyapunov, controller = build_networks(system, cfg)
    if init:
        if (init[0].phi.sizes != lyapunov.phi.sizes or init[0].alpha_hat != lyapunov.alpha_hat
                or init[1].varphi.sizes != controller.varphi.sizes):
            raise ValueError(f"warm-start networks (V {init[0].phi.sizes}, alpha_hat {init[0].alpha_hat}; pi "
                             f"{init[1].varphi.sizes}) do not match the config (V {lyapunov.phi.sizes}, alpha_hat "
                             f"{lyapunov.alpha_hat}; pi {controller.varphi.sizes})")
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


def _snapshot(lyapunov: Lyapunov, controller: Controller) -> tuple[dict, dict]:
    return copy.deepcopy(lyapunov.state_dict()), copy.deepcopy(controller.state_dict())


def _restore(lyapunov: Lyapunov, controller: Controller, states: tuple[dict, dict]) -> None:
    lyapunov.load_state_dict(states[0])
    controller.load_state_dict(states[1])


def _loss(cfg: TrainConfig, loop: ClosedLoop, condition: Condition, states: TrainingStates, iteration: int,
          grow_now: bool) -> Tensor:
    """The loss of one iteration: the condition's on this iteration's states, with a level V above it on the box's
    faces (and, while ``grow_now``, the growth term), and every ``LOCAL_EVERY`` iterations the local rate's term."""
    terms = condition.terms(loop, states.next(iteration, loop, condition))
    level = states.level
    loss = condition.loss(terms, cfg.margin, cfg.margin_rate, level, cfg.outside_weight, cfg.exclude_weight)
    if level is not None:  # V above the level on the faces of X: {V <= level} inside X
        loss = loss + states.faces_term(loop.lyapunov)
        if grow_now:  # the set pulled out towards the faces
            loss = loss + cfg.grow_weight * (torch.relu(terms.value - level) / level).mean()
    if cfg.local_rate and (iteration - 1) % LOCAL_EVERY == 0:  # V a Lyapunov function of the linearisation
        loss = loss + torch.relu(local_rates(condition, loop) + cfg.local_rate).mean()
    return loss


class TrainingStates:
    """The states a fit trains on, drawn from ``gen`` (in this order: a batch, then the adversarial states, at the start;
    then each iteration a new batch where ``cfg.resample``, a share of the adversarial states redrawn and all of them
    moved one ascent step, and the faces' states of a level's term): uniform in X_delta (``cfg.train_box``: in that
    box), a share near x*, with a level up to half of the uniform share inside ``{V <= 1.25 level}``, adversarial
    states, and the ``extra`` states (E, n) in every batch. Float32 on ``device``."""

    def __init__(self, cfg: TrainConfig, system: UncertainSystem, region: Region, lyapunov: Lyapunov,
                 gen: torch.Generator, device: torch.device, extra: Tensor | None) -> None:
        self.cfg, self.region, self.lyapunov, self.gen, self.device, self.extra = cfg, region, lyapunov, gen, device, extra
        self.sampling = region if cfg.train_box is None else Region.of(training_region(system, cfg.train_box), cfg.delta)
        self.n_near = int(round(float(cfg.near_share) * int(cfg.n_states)))
        self.n_adv = int(round(float(cfg.adversarial_share) * int(cfg.n_states)))
        self.refresh = max(1, int(ADVERSARIAL_REFRESH * self.n_adv))
        self.level = training_level(cfg)  # the claimed level, or above it by the level margin
        self.faces_level = None if self.level is None else self.level * (1 + GROW_FACES_MARGIN if cfg.grow_weight else 1.0)
        self.faces = None  # fixed states on the box's faces for the acceptance check (own generator)
        if self.level is not None:
            self.faces = region.sample_faces(20000, torch.Generator().manual_seed(12345)).float().to(device)
        self.batch: Tensor | None = None
        self.adversaries: Tensor | None = None

    def start(self) -> None:
        """The first batch and the adversarial states."""
        self.batch = self.draw()
        if self.n_adv:
            self.adversaries = adversarial_starts(self.lyapunov, self.sampling, self.level, self.n_adv,
                                                  self.gen).float().to(self.device)

    def draw(self) -> Tensor:
        """A new batch ``(B, n)``: uniform (with a level, up to half of it inside the set), near x*, and the extra ones."""
        n_uniform = int(self.cfg.n_states) - self.n_near - self.n_adv
        z = self.sampling.sample(n_uniform, self.gen)
        if self.level is not None:  # up to half of the uniform share from inside (or just outside) the sublevel set
            inside = inside_states(self.lyapunov, self.sampling, 1.25 * self.level, n_uniform // 2, self.device,
                                   self.gen, tries=1)
            z = torch.cat([inside.double().cpu(), z[: n_uniform - inside.shape[0]]])
        if self.n_near:
            z = torch.cat([z, self.sampling.sample_near(self.n_near, self.gen)])
        z = z.float().to(self.device)
        return z if self.extra is None else torch.cat([z, self.extra])

    def next(self, iteration: int, loop: ClosedLoop, condition: Condition) -> Tensor:
        """The states of ``iteration`` (from 1): the batch (new where ``cfg.resample``) and the adversarial states,
        a share of them redrawn and all moved one ascent step on the residual."""
        if self.cfg.resample and iteration > 1:
            self.batch = self.draw()
        if self.adversaries is None:
            return self.batch
        row = (iteration * self.refresh) % self.n_adv
        fresh = adversarial_starts(self.lyapunov, self.sampling, self.level, self.refresh, self.gen)
        self.adversaries[row:row + self.refresh] = fresh[: self.n_adv - row].float().to(self.device)
        self.adversaries = ascend(loop, condition, self.adversaries, self.sampling, self.level)
        return torch.cat([self.batch, self.adversaries])

    def faces_term(self, lyapunov: Lyapunov) -> Tensor:
        """The mean shortfall of V below the faces' level at 1,024 new states of the box's faces."""
        faces = self.region.sample_faces(1024, self.gen).float().to(self.device)
        return torch.relu(self.faces_level - lyapunov(faces)).mean()


class PairKeeper:
    """A fit's acceptance checks (:func:`~drlyap.training.acceptance.acceptance_check` on the fixed ``validation``
    states, with a level also 20,000 states inside the set) and the best pair so far: a passing one first, then by
    :meth:`~drlyap.records.AcceptanceCheck.stability`, the violating share and the largest violation; while the set
    grows, the latest pair that passes."""

    def __init__(self, loop: ClosedLoop, condition: Condition, xi: Tensor, region: Region, validation: Tensor,
                 states: TrainingStates, local: bool, growing: bool) -> None:
        self.loop, self.condition, self.xi, self.region, self.validation = loop, condition, xi, region, validation
        self.states, self.local, self.growing = states, local, growing
        self.checks: list[dict] = []
        self.best: tuple | None = None
        self.seconds = 0.0

    def check(self, iteration: int) -> AcceptanceCheck:
        """Check the pair as it is now; keep it where it ranks above the best so far. Returns the check."""
        tic = time.perf_counter()
        level, lyapunov = self.states.level, self.loop.lyapunov
        validation = self.validation
        if level is not None:  # the set is a few % of the box: add 20,000 states drawn inside it (fixed seed)
            inside = inside_states(lyapunov, self.region, level, 20000, self.states.device,
                                   torch.Generator().manual_seed(12345))
            validation = torch.cat([validation, inside])
        check = acceptance_check(self.loop, self.condition, self.xi, self.region, validation=validation, level=level,
                                 faces=self.states.faces, local=self.local)
        check.iteration = iteration
        self.checks.append(check.summary())
        score = (*check.stability(), -check.violating_fraction, -check.max_violation)
        if self.growing and check.passed:  # a growing set: the latest pair that passes holds the largest set
            score = (*check.stability(), iteration)
        if self.best is None or score > self.best[0]:
            self.best = (score, *_snapshot(lyapunov, self.loop.controller), check)
        self.seconds += time.perf_counter() - tic
        return check

    def restore(self, iteration: int) -> AcceptanceCheck:
        """Load the best pair into the networks (checking the last one first where it was not); its check."""
        if self.best is None or (self.checks and self.checks[-1]["iteration"] != iteration):
            self.check(iteration)
        _, v_state, c_state, check = self.best
        _restore(self.loop.lyapunov, self.loop.controller, (v_state, c_state))
        return check
