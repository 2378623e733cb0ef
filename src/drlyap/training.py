"""Training a controller and its Lyapunov certificate (paper Sec. V, SPEC §3 and §5).

One :class:`TrainConfig` describes a run. :func:`train` samples the training states uniformly in
X minus the delta-ball, trains both networks with Adam on the chosen condition's loss (batched over
states and xi samples), and runs the acceptance check of :mod:`drlyap.checks` every
``check_every`` iterations. It stops as soon as the check passes or at ``iters``, and returns the
best checkpoint (passing first, then smallest validation violation). A diverging loss (NaN/inf)
stops training with the last good weights and says so.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from dataclasses import dataclass

import torch
from torch import Tensor

from drlyap.checks import acceptance_check
from drlyap.conditions import Condition, local_rates, make_condition
from drlyap.io import from_fields
from drlyap.networks import Controller, Lyapunov
from drlyap.progress import progress as show_progress
from drlyap.regions import Region
from drlyap.systems import UncertainSystem, get_system

LOCAL_EVERY = 4  # iterations between evaluations of the local term (second derivatives at x*: ~2x an iteration)


@dataclass
class TrainConfig:
    """Everything a training run depends on (saved verbatim as ``config.json``).

    ``None`` fields take the system's paper defaults (``UncertainSystem.defaults``).
    """

    system: str = "pendulum"
    method: str = "dr"  # "baseline" (nominal condition at the sample mean) or "dr"
    loss: str = "pointwise"  # DR loss: "pointwise" or "uniform"
    wasserstein_radius: float | None = None  # r
    risk_level: float | None = None  # eps
    decay_rate: float | None = None  # gamma in Vdot + gamma ||x - x*|| <= 0
    exp_rate: float | None = None  # alpha of the exponential variant (adds alpha V inside the hinge)
    n_states: int | None = None  # M training states
    n_xi: int | None = None  # N samples of xi drawn from the system's distribution
    xi_samples: list[list[float]] | None = None  # explicit samples (N, k); overrides n_xi
    delta: float | None = None  # radius of the excluded ball around x* (local coordinates)
    lr: float | None = None  # Adam's step size (system default; 0.002)
    iters: int = 3000  # iteration cap
    check_every: int = 250  # acceptance check period (iterations)
    seed: int = 0
    device: str = "cpu"
    lyapunov_hidden: list[int] | None = None
    lyapunov_out: int = 8
    alpha_hat: float | None = None
    controller_hidden: list[int] | None = None
    init_gain: float = 10.0  # scale of the controller's output layer at initialisation
    margin: float | None = None  # training hinge is (residual + margin)_+: pushes the condition past zero
    resample: bool = True  # draw a fresh uniform batch of n_states every iteration (False: one fixed set)
    # share of each batch drawn evenly over the distance from x* (Region.sample_near) instead of uniformly:
    # with 4 or more states a uniform batch holds almost no states near x*, where local stability is decided
    near_share: float | None = None
    # proof after training (drlyap.cegis.train_certified; drlyap.training.train ignores these)
    verify: bool = True  # prove the trained condition, with counterexample-guided rounds until it is proved
    verify_rounds: int = 5  # retraining rounds at most
    verify_time: float | None = None  # seconds per proof (None: the system's; 30, 120 for cartpole and quadrotor2d)
    verify_budget: float | None = None  # total seconds for the rounds (None: no limit beyond the rounds)
    # Box ((low...), (high...)) in user coordinates the training states are drawn from; None: the
    # system's X. Only where training samples: the networks' input scaling, the acceptance check, the
    # verifier and the success criterion keep X.
    train_box: list[list[float]] | None = None
    # Region-of-attraction training: the condition is asked only of {V <= roa_level}, and a hinge keeps V above
    # roa_level on the faces of X (so the set lies inside X and is forward invariant once the condition holds
    # on it); half of each batch is drawn inside the set. None: the paper's condition on all of X_delta.
    roa_level: float | None = None
    margin_rate: float | None = None  # adds margin_rate * V to the hinge: a margin that scales with V (0 at x*)
    # V's local decay rate asked at x*: a hinge (lambda_j + local_rate)_+ on conditions.local_rates at every training
    # sample (every LOCAL_EVERY iterations), and the acceptance check then asks lambda_j < 0. 0: neither.
    local_rate: float | None = None
    # "lqr": before training, fit V to the LQR's z^T P z (scaled to 1.2 roa_level, or 1, on the faces) and pi to
    # its gain, by regression; lqr_weights = [Q diagonal, R diagonal] (None: Bryson's rule)
    warm_start: str | None = None
    lqr_weights: list[list[float]] | None = None

    def resolved(self, system: UncertainSystem) -> TrainConfig:
        """A copy with ``None`` fields filled from the system's defaults, validated."""
        cfg = copy.deepcopy(self)
        base = {"wasserstein_radius": 0.01, "risk_level": 0.1, "n_states": 3600, "n_xi": 5, "decay_rate": 1.0,
                "delta": 0.1, "alpha_hat": 1.0, "margin": 0.0, "lyapunov_hidden": [32, 32],
                "controller_hidden": [32, 32], "train_box": None, "near_share": 0.0, "margin_rate": 0.0, "exp_rate": 0.0,
                "local_rate": 0.0,
                "lr": 0.002, "verify_time": 30.0}
        base.update(system.defaults)
        for key, value in base.items():
            if getattr(cfg, key) is None:
                setattr(cfg, key, value)
        cfg.validate(system)
        return cfg

    def validate(self, system: UncertainSystem) -> None:
        problems = []
        if self.method not in ("baseline", "dr"):
            problems.append(f"method {self.method!r} (valid: baseline, dr)")
        if self.loss not in ("pointwise", "uniform"):
            problems.append(f"loss {self.loss!r} (valid: pointwise, uniform)")
        for name in ("wasserstein_radius", "decay_rate", "exp_rate", "margin", "alpha_hat", "margin_rate", "local_rate"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                problems.append(f"{name} = {value} (must be finite and >= 0)")
        if not 0 < self.risk_level < 1:
            problems.append(f"risk_level = {self.risk_level} (must be in (0, 1))")
        if int(self.verify_rounds) < 0 or not (math.isfinite(self.verify_time) and self.verify_time > 0):
            problems.append(f"verify_rounds = {self.verify_rounds} (>= 0) / verify_time = {self.verify_time} (> 0)")
        if self.verify_budget is not None and not (math.isfinite(self.verify_budget) and self.verify_budget > 0):
            problems.append(f"verify_budget = {self.verify_budget} (must be > 0 seconds or None)")
        for name in ("n_states", "n_xi", "iters", "check_every"):
            if int(getattr(self, name)) < 1:
                problems.append(f"{name} = {getattr(self, name)} (must be >= 1)")
        if not (math.isfinite(self.lr) and self.lr > 0):
            problems.append(f"lr = {self.lr} (must be > 0)")
        if not (math.isfinite(self.near_share) and 0 <= self.near_share <= 1):
            problems.append(f"near_share = {self.near_share} (must be in [0, 1])")
        if self.roa_level is not None and not (math.isfinite(self.roa_level) and self.roa_level > 0):
            problems.append(f"roa_level = {self.roa_level} (must be > 0, or None)")
        if self.warm_start not in (None, "lqr"):
            problems.append(f"warm_start {self.warm_start!r} (valid: lqr, or None)")
        if self.lqr_weights is not None:
            ok = (isinstance(self.lqr_weights, (list, tuple)) and len(self.lqr_weights) == 2
                  and len(self.lqr_weights[0]) == system.n and len(self.lqr_weights[1]) == system.m)
            if not ok:
                problems.append(f"lqr_weights must be [Q diagonal ({system.n}), R diagonal ({system.m})], "
                                f"got {self.lqr_weights!r}")
        if not (math.isfinite(self.delta) and self.delta >= 0):
            problems.append(f"delta = {self.delta} (must be >= 0)")
        if self.train_box is not None:
            try:
                training_region(system, self.train_box)
            except (TypeError, ValueError) as err:
                problems.append(f"train_box: {err}")
        if self.xi_samples is not None:
            try:
                xi = torch.as_tensor(self.xi_samples, dtype=torch.float64)
            except (TypeError, ValueError) as err:
                raise ValueError(f"invalid training config: xi_samples must be an (N, {system.k}) array of numbers "
                                 f"({err})") from None
            if xi.ndim != 2 or xi.shape[1] != system.k or xi.shape[0] < 1:
                problems.append(f"xi_samples must be (N, {system.k}) for {system.name}, got shape {tuple(xi.shape)}")
            elif not torch.isfinite(xi).all():
                problems.append("xi_samples contain NaN or inf")
        if problems:
            raise ValueError("invalid training config: " + "; ".join(problems))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> TrainConfig:
        return from_fields(cls, data, "config")


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


def training_region(system: UncertainSystem, train_box: list[list[float]] | None) -> UncertainSystem:
    """``system`` with its state box replaced by ``train_box`` (user coordinates) for drawing training
    states; ``system`` itself when ``train_box`` is None. Raises ValueError for a malformed box or
    one that does not hold x* strictly inside."""
    if train_box is None:
        return system
    return dataclasses.replace(system, state_box=tuple(tuple(float(v) for v in side) for side in train_box))


def build_networks(system: UncertainSystem, cfg: TrainConfig) -> tuple[Lyapunov, Controller]:
    """Fresh networks for ``cfg``; inputs are scaled by the state box's half-widths."""
    lo, hi = system.local_box()
    scale = ((hi - lo) / 2).tolist()
    lyapunov = Lyapunov(system.n, cfg.lyapunov_hidden, cfg.lyapunov_out, cfg.alpha_hat, scale)
    controller = Controller(system.n, system.input_box, system.equilibrium_input, cfg.controller_hidden,
                            cfg.init_gain, scale)
    return lyapunov, controller


def resolve_device(name: str) -> torch.device:
    """``cpu``, ``cuda`` or ``cuda:N``; a clear error when the device is not available."""
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise ValueError(f"unknown device {name!r}; valid: cpu, cuda, cuda:N") from err
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' requested but no CUDA GPU is available here; use --device cpu")
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"unsupported device {name!r}; valid: cpu, cuda")
    return device


def draw_xi_samples(system: UncertainSystem, cfg: TrainConfig) -> Tensor:
    """The training samples of xi: explicit ones from the config, else drawn with the run's seed."""
    if cfg.xi_samples is not None:
        return torch.as_tensor(cfg.xi_samples, dtype=torch.float64)
    gen = torch.Generator().manual_seed(10_000 + cfg.seed)
    return system.sample_xi(int(cfg.n_xi), gen)


def warm_start_lqr(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, cfg: TrainConfig,
                   region: Region, generator: torch.Generator, iters: int = 500, n_states: int = 4096) -> dict:
    """Fit the networks to an LQR pair by regression (in place): ``V ~ s z^T P z`` and ``varphi(z) - varphi(0) ~ -K z``.

    ``P``, ``K``: the LQR design for ``cfg.lqr_weights`` (``[Q diagonal, R diagonal]``; None: Bryson's rule) on the
    nominal linearisation; ``s`` puts the quadratic's minimum over the faces of the box at ``1.2 cfg.roa_level``
    (1.2 without a level). States: half uniform in X_delta, half spread over the distance from x*. Returns the
    design's gain, the scale and the final relative errors.
    """
    from drlyap.baselines import lqr_design  # baselines reads run directories, which read training configs

    q, r = cfg.lqr_weights if cfg.lqr_weights is not None else (None, None)
    design = lqr_design(system, q, r)
    half = torch.maximum(-region.lo, region.hi)
    scale = 1.2 * (cfg.roa_level or 1.0) / float((half.square() / torch.linalg.inv(design.P).diagonal()).min())
    ref = next(lyapunov.parameters())
    p_mat, k_mat = (design.P * scale).to(ref), design.K.to(ref)
    opt = torch.optim.Adam(list(lyapunov.parameters()) + list(controller.parameters()), lr=cfg.lr)
    for _ in range(iters):
        z = torch.cat([region.sample(n_states // 2, generator), region.sample_near(n_states - n_states // 2, generator)])
        z = z.to(ref)
        v_target, u_target = ((z @ p_mat) * z).sum(-1), -(z @ k_mat.T)
        v_err = (lyapunov(z) - v_target).square().mean() / v_target.square().mean()
        u_err = (controller.raw(z) - u_target).square().mean() / u_target.square().mean().clamp_min(1e-12)
        opt.zero_grad(set_to_none=True)
        (v_err + u_err).backward()
        opt.step()
    return {"method": "lqr", "K": design.K.tolist(), "P_scale": scale, "v_relative_error": float(v_err.detach()),
            "u_relative_error": float(u_err.detach()), "iterations": iters}


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


def train(cfg: TrainConfig, system: UncertainSystem | None = None, progress: bool = True,
          init: tuple[Lyapunov, Controller] | None = None, extra_states: Tensor | None = None) -> TrainResult:
    """Train a pair for ``cfg``.

    ``init`` warm-starts from given networks (copied, not modified). ``extra_states`` ``(E, n)`` are
    local states (e.g. counterexamples found by the verifier) added to every training batch.
    """
    system = system or get_system(cfg.system)
    if system.name != cfg.system:
        raise ValueError(f"TrainConfig(system={cfg.system!r}) names another system than the one passed "
                         f"({system.name!r}); set TrainConfig(system={system.name!r})")
    cfg = cfg.resolved(system)
    device = resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)

    xi_all = draw_xi_samples(system, cfg)
    xi_train = xi_all.mean(0, keepdim=True) if cfg.method == "baseline" else xi_all
    condition = make_condition(cfg.method, cfg.loss, cfg.wasserstein_radius, cfg.risk_level, xi_train, cfg.decay_rate,
                               cfg.exp_rate)
    region = Region.of(system, cfg.delta)
    lyapunov, controller = build_networks(system, cfg)
    if init:
        if (init[0].phi.sizes != lyapunov.phi.sizes or init[0].alpha_hat != lyapunov.alpha_hat
                or init[1].varphi.sizes != controller.varphi.sizes):
            raise ValueError(f"warm-start networks (V {init[0].phi.sizes}, alpha_hat {init[0].alpha_hat}; pi "
                             f"{init[1].varphi.sizes}) do not match the config (V {lyapunov.phi.sizes}, alpha_hat "
                             f"{lyapunov.alpha_hat}; pi {controller.varphi.sizes})")
        lyapunov, controller = copy.deepcopy(init[0]), copy.deepcopy(init[1])
    lyapunov.to(device)
    controller.to(device)
    if extra_states is not None:
        extra_states = torch.as_tensor(extra_states, dtype=torch.float64)
        if extra_states.ndim != 2 or extra_states.shape[1] != system.n or not torch.isfinite(extra_states).all():
            raise ValueError(f"extra_states must be a finite (E, {system.n}) tensor of local states")
        extra_states = extra_states.float().to(device)

    sampling = region if cfg.train_box is None else Region.of(training_region(system, cfg.train_box), cfg.delta)

    n_near = int(round(float(cfg.near_share) * int(cfg.n_states)))
    level = cfg.roa_level
    warm = None
    if cfg.warm_start == "lqr" and not init:
        warm = warm_start_lqr(system, lyapunov, controller, cfg, region, gen, n_states=min(4096, int(cfg.n_states)))

    def batch() -> Tensor:
        n_uniform = int(cfg.n_states) - n_near
        z = sampling.sample(n_uniform, gen)
        if level is not None:  # up to half of the uniform share from inside (or just outside) the sublevel set
            inside = inside_states(lyapunov, sampling, 1.25 * level, n_uniform // 2, device, gen, tries=1)
            z = torch.cat([inside.double().cpu(), z[: n_uniform - inside.shape[0]]])
        if n_near:
            z = torch.cat([z, sampling.sample_near(n_near, gen)])
        z = z.float().to(device)
        return z if extra_states is None else torch.cat([z, extra_states])

    faces_val = None
    if level is not None:
        faces_val = region.sample_faces(20000, torch.Generator().manual_seed(12345)).float().to(device)

    z_train = batch()
    z_val = region.grid().float().to(device)

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
        check = acceptance_check(system, lyapunov, controller, condition, xi_all.to(device), region,
                                 validation=validation, level=level, faces=faces_val, local=bool(cfg.local_rate))
        check["iteration"] = iteration
        checks.append({k: check[k] for k in ("iteration", "passed", "max_violation", "violating_fraction")}
                      | {"hurwitz": check["jacobian"]["hurwitz"], "n_other_equilibria": len(check["other_equilibria"]),
                         "local_rate_max": check["local_rate_max"]})
        score = (check["passed"], check["jacobian"]["hurwitz"], not check["other_equilibria"],
                 -check["violating_fraction"], -check["max_violation"])
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
            terms = condition.terms(system, lyapunov, controller, z_train)
            loss = condition.loss(terms, cfg.margin, cfg.margin_rate, level)
            if level is not None:  # V above the level on the faces of X: {V <= level} inside X
                loss = loss + torch.relu(level - lyapunov(region.sample_faces(1024, gen).float().to(device))).mean()
            if cfg.local_rate and (iteration - 1) % LOCAL_EVERY == 0:  # V a Lyapunov function of the linearisation
                loss = loss + torch.relu(local_rates(condition, system, lyapunov, controller) + cfg.local_rate).mean()
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
                if run_check(iteration)["passed"]:
                    status = f"passed the acceptance check at iteration {iteration}"
                    break
    finally:
        bar.close()
    if best is None or (checks and checks[-1]["iteration"] != iteration):
        run_check(iteration)
    _, v_state, c_state, check = best
    lyapunov.load_state_dict(v_state)
    controller.load_state_dict(c_state)
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
