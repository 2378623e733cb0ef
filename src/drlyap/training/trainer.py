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
from drlyap.lqr import lqr_design
from drlyap.networks import Controller, Lyapunov
from drlyap.progress import progress as show_progress
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
    if system.name != cfg.system:
        raise ValueError(f"TrainConfig(system={cfg.system!r}) names another system than the one passed "
                         f"({system.name!r}); set TrainConfig(system={system.name!r})")
    if cfg.missing():
        raise ValueError(f"the training config leaves {cfg.missing()} open: resolve it first "
                         "(TrainConfig.resolved(system))")
    device = resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)

    xi_all = draw_xi_samples(system, cfg)
    xi_train = xi_all.mean(0, keepdim=True) if cfg.method == "baseline" else xi_all
    condition = run_condition(cfg, xi_train)
    region = Region.of(system, cfg.delta)
    grid = region.grid()
    system.check_finite(xi_all, system.to_user(grid))
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
    lyapunov.to(device)
    controller.to(device)
    loop = ClosedLoop(system, lyapunov, controller)  # the live networks: no float64 copy is taken of this loop
    if extra_states is not None:
        extra_states = torch.as_tensor(extra_states, dtype=torch.float64)
        if extra_states.ndim != 2 or extra_states.shape[1] != system.n or not torch.isfinite(extra_states).all():
            raise ValueError(f"extra_states must be a finite (E, {system.n}) tensor of local states")
        extra_states = extra_states.float().to(device)

    sampling = region if cfg.train_box is None else Region.of(training_region(system, cfg.train_box), cfg.delta)

    n_near = int(round(float(cfg.near_share) * int(cfg.n_states)))
    n_adv = int(round(float(cfg.adversarial_share) * int(cfg.n_states)))
    level = training_level(cfg)  # the claimed level, or above it by the level margin
    warm = None
    if cfg.warm_start == "lqr" and not init:
        warm = warm_start_lqr(system, lyapunov, controller, cfg, region, gen, n_states=min(4096, int(cfg.n_states)))

    def batch() -> Tensor:
        n_uniform = int(cfg.n_states) - n_near - n_adv
        z = sampling.sample(n_uniform, gen)
        if level is not None:  # up to half of the uniform share from inside (or just outside) the sublevel set
            inside = inside_states(lyapunov, sampling, 1.25 * level, n_uniform // 2, device, gen, tries=1)
            z = torch.cat([inside.double().cpu(), z[: n_uniform - inside.shape[0]]])
        if n_near:
            z = torch.cat([z, sampling.sample_near(n_near, gen)])
        z = z.float().to(device)
        return z if extra_states is None else torch.cat([z, extra_states])

    growing = bool(cfg.grow_weight) and grow and level is not None  # trains every iteration: no early stop
    grow_until = math.floor(GROW_SHARE * cfg.iters)  # the last iteration with the growth term
    faces_val = None
    faces_level = None if level is None else level * (1 + GROW_FACES_MARGIN if cfg.grow_weight else 1.0)
    if level is not None:
        faces_val = region.sample_faces(20000, torch.Generator().manual_seed(12345)).float().to(device)

    z_train = batch()
    z_val = grid.float().to(device)
    adversaries = adversarial_starts(lyapunov, sampling, level, n_adv, gen).float().to(device) if n_adv else None
    refresh = max(1, int(ADVERSARIAL_REFRESH * n_adv))

    params = list(lyapunov.parameters()) + list(controller.parameters())
    opt = torch.optim.Adam(params, lr=cfg.lr, fused=True)
    history: list[dict] = []
    checks: list[dict] = []
    best: tuple | None = None
    last_good = (copy.deepcopy(lyapunov.state_dict()), copy.deepcopy(controller.state_dict()))
    status = "iteration cap reached without passing the acceptance check"
    start = time.perf_counter()

    check_time = 0.0

    def run_check(iteration: int) -> dict:
        nonlocal best, check_time
        tic = time.perf_counter()
        validation = z_val
        if level is not None:  # the set is a few % of the box: add 20,000 states drawn inside it (fixed seed)
            inside = inside_states(lyapunov, region, level, 20000, device, torch.Generator().manual_seed(12345))
            validation = torch.cat([z_val, inside])
        check = acceptance_check(loop, condition, xi_all.to(device), region, validation=validation, level=level,
                                 faces=faces_val, local=bool(cfg.local_rate))
        check["iteration"] = iteration
        checks.append({k: check[k] for k in ("iteration", "passed", "max_violation", "violating_fraction")}
                      | {"hurwitz": check["jacobian"]["hurwitz"], "n_other_equilibria": len(check["other_equilibria"]),
                         "local_rate_max": check["local_rate_max"]})
        score = (check["passed"], check["jacobian"]["hurwitz"], not check["other_equilibria"],
                 -check["violating_fraction"], -check["max_violation"])
        if growing and check["passed"]:  # a growing set: the latest pair that passes holds the largest set
            score = (True, check["jacobian"]["hurwitz"], not check["other_equilibria"], iteration)
        if best is None or score > best[0]:
            best = (score, copy.deepcopy(lyapunov.state_dict()), copy.deepcopy(controller.state_dict()), check)
        check_time += time.perf_counter() - tic
        return check

    bar = show_progress(cfg.iters, f"{cfg.system} {cfg.method}", progress)
    iteration = 0
    try:
        for iteration in range(1, cfg.iters + 1):
            if cfg.resample and iteration > 1:
                z_train = batch()
            z = z_train
            if adversaries is not None:
                row = (iteration * refresh) % n_adv
                adversaries[row:row + refresh] = adversarial_starts(lyapunov, sampling, level, refresh, gen)[
                    : n_adv - row].float().to(device)
                adversaries = ascend(loop, condition, adversaries, sampling, level)
                z = torch.cat([z_train, adversaries])
            terms = condition.terms(loop, z)
            loss = condition.loss(terms, cfg.margin, cfg.margin_rate, level, cfg.outside_weight, cfg.exclude_weight)
            if level is not None:  # V above the level on the faces of X: {V <= level} inside X
                loss = loss + torch.relu(faces_level - lyapunov(region.sample_faces(1024, gen).float().to(device))).mean()
                if growing and iteration <= grow_until:  # the set pulled out towards the faces
                    loss = loss + cfg.grow_weight * (torch.relu(terms.value - level) / level).mean()
            if cfg.local_rate and (iteration - 1) % LOCAL_EVERY == 0:  # V a Lyapunov function of the linearisation
                loss = loss + torch.relu(local_rates(condition, loop) + cfg.local_rate).mean()
            if not torch.isfinite(loss):
                lyapunov.load_state_dict(last_good[0])
                controller.load_state_dict(last_good[1])
                status = f"diverged: loss became {float(loss.detach())} at iteration {iteration}; kept the last good weights"
                break
            if iteration % 50 == 1:
                last_good = (copy.deepcopy(lyapunov.state_dict()), copy.deepcopy(controller.state_dict()))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if iteration % 10 == 0 or iteration == 1:
                history.append({"iteration": iteration, "loss": float(loss.detach()), "time_s": time.perf_counter() - start})
                bar.set_postfix(loss=f"{float(loss.detach()):.2e}")
            bar.update(1)
            if iteration % cfg.check_every == 0 or iteration == cfg.iters:
                if run_check(iteration)["passed"] and not growing:
                    status = f"passed the acceptance check at iteration {iteration}"
                    break
    finally:
        bar.close()
    if best is None or (checks and checks[-1]["iteration"] != iteration):
        run_check(iteration)
    _, v_state, c_state, check = best
    lyapunov.load_state_dict(v_state)
    controller.load_state_dict(c_state)
    if growing and check["passed"] and not status.startswith("diverged"):
        status = (f"{growth_words(min(iteration, grow_until), iteration)}; kept the latest pair passing the acceptance "
                  "check")
    elapsed = time.perf_counter() - start
    metrics = {
        "status": status,
        "passed": bool(check["passed"]),
        "iterations": iteration,
        "best_iteration": check["iteration"],
        "train_time_s": elapsed,
        "check_time_s": check_time,
        "ms_per_iteration": 1000 * (elapsed - check_time) / max(iteration, 1),
        "final_loss": history[-1]["loss"] if history else None,
        "acceptance": check,
        "checks": checks,
        "condition": condition.describe(),
        "xi_samples": xi_all.tolist(),
        "xi_train": xi_train.tolist(),
        "warm_start": warm,
    }
    return TrainResult(cfg, system, lyapunov.cpu(), controller.cpu(), xi_all, condition, history, metrics)
