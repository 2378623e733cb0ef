"""What a training configuration (:class:`~drlyap.config.TrainConfig`, resolved) builds: the networks, the training
region, the device, the xi samples, and -- the one place they are built from a config -- a run's decrease conditions
(:func:`run_condition`). Training builds a pair from these, and a run directory rebuilds the same objects when it is
loaded (without loading any of the training code)."""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from drlyap.conditions import Condition, DRPointwise, DRUniform, TrueDecrease, make_condition
from drlyap.config import TrainConfig
from drlyap.kinds import Loss, Model
from drlyap.networks import Controller, Lyapunov
from drlyap.systems import UncertainSystem


def training_region(system: UncertainSystem, train_box: list[list[float]] | None) -> UncertainSystem:
    """``system`` with its state box replaced by ``train_box`` (user coordinates) for drawing training
    states; ``system`` itself when ``train_box`` is None. Raises ValueError for a malformed box or
    one that does not hold x* strictly inside."""
    if train_box is None:
        return system
    return dataclasses.replace(system, state_box=tuple(tuple(float(v) for v in side) for side in train_box))


def training_level(cfg: TrainConfig) -> float | None:
    """The sublevel set's level that region-of-attraction training works with: ``(1 + level_margin) roa_level``
    (the claimed and proved set is ``{V <= roa_level}``); None without a level."""
    if cfg.roa_level is None:
        return None
    return float(cfg.roa_level) * (1.0 + float(cfg.level_margin or 0.0))


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


def run_condition(cfg: TrainConfig, xi_samples: Tensor, form: str = "trained") -> Condition:
    """A condition of a run with config ``cfg`` (resolved) at the samples ``xi_samples (N, k)``:

    * ``"trained"``: the condition it was trained on (``xi_samples``: the samples it used; the baseline's is
      their mean, ``(1, k)``);
    * ``"true"``: plain decrease on the TRUE model at the shifts ``xi_samples``, with the run's decay terms (the
      condition that simulation at those shifts tests);
    * ``"pointwise"`` / ``"uniform"``: the DR condition of that form at the run's radius, risk level and decay.
    """
    if form == "trained":
        return make_condition(cfg.method, cfg.loss, cfg.wasserstein_radius, cfg.risk_level, xi_samples,
                              cfg.decay_rate, cfg.exp_rate)
    if form == Model.TRUE:
        return TrueDecrease(xi_samples, cfg.decay_rate, cfg.exp_rate)
    if form == Loss.POINTWISE:
        return DRPointwise(cfg.wasserstein_radius, cfg.risk_level, xi_samples, cfg.decay_rate, cfg.exp_rate)
    if form == Loss.UNIFORM:
        return DRUniform(cfg.wasserstein_radius, cfg.risk_level, xi_samples, cfg.decay_rate, cfg.exp_rate)
    raise ValueError(f"unknown condition form {form!r}; valid: trained, true, pointwise, uniform")
