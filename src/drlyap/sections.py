"""The five sections of a training configuration, each a typed object that builds what it is about.

A :class:`~drlyap.config.TrainConfig` is what the user types and what ``config.json`` stores: flat keywords, resolved
once against the system. :meth:`TrainSections.of` splits a resolved config into its sections, and everything below
the edge reads a section, never the whole config:

* :class:`ConditionSection` -- the condition the pair is trained to satisfy: it builds a run's conditions
  (the one place they are built from a config) and the hinge's margins;
* :class:`NetworkSection` -- the networks' sizes and start: it builds fresh networks;
* :class:`SamplingSection` -- where the training states and the xi samples come from: it builds X_delta, the
  region states are drawn in, and the xi samples;
* :class:`RegionGoal` -- region-of-attraction training (the level, the weights that shape the set): it gives the
  level training works with and the level asked on the faces;
* :class:`Schedule` -- how long, how fast and where: it resolves the device.

A run directory rebuilds its networks and conditions from these sections without loading any of the training code.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from drlyap.conditions import Condition, DRPointwise, DRUniform, TrueDecrease, make_condition
from drlyap.config import TrainConfig
from drlyap.kinds import Loss, Method, Model
from drlyap.networks import Controller, Lyapunov
from drlyap.regions import Region
from drlyap.systems import UncertainSystem

GROW_FACES_MARGIN = 0.05  # growing sets: V asked above (1 + this) level on the faces, room for the proof of V > level


@dataclass(frozen=True)
class ConditionSection:
    """The condition trained on (paper Sec. IV): ``method`` (baseline: the nominal condition at the samples' mean;
    dr: the Wasserstein DR condition of the form ``loss``) at radius ``wasserstein_radius`` and risk level
    ``risk_level``, with decay ``decay_rate ||x - x*||`` and ``exp_rate V``; the hinge's ``margin`` and
    ``margin_rate V``, and the local decay ``local_rate`` asked at x* (0: none)."""

    method: Method
    loss: Loss
    wasserstein_radius: float
    risk_level: float
    decay_rate: float
    exp_rate: float
    margin: float
    margin_rate: float
    local_rate: float

    def training_samples(self, xi_samples: Tensor) -> Tensor:
        """The samples ``(N, k)`` the trained condition uses: all of ``xi_samples``, the baseline their mean ``(1, k)``."""
        return xi_samples.mean(0, keepdim=True) if self.method == Method.BASELINE else xi_samples

    def build(self, xi_samples: Tensor, form: str = "trained") -> Condition:
        """A condition of the run at the samples ``xi_samples (N, k)``:

        * ``"trained"``: the condition it was trained on (``xi_samples``: the samples it used, see
          :meth:`training_samples`);
        * ``"true"``: plain decrease on the TRUE model at the shifts ``xi_samples``, with the run's decay terms (the
          condition that simulation at those shifts tests);
        * ``"pointwise"`` / ``"uniform"``: the DR condition of that form at the run's radius, risk level and decay.
        """
        if form == "trained":
            return make_condition(self.method, self.loss, self.wasserstein_radius, self.risk_level, xi_samples,
                                  self.decay_rate, self.exp_rate)
        if form == Model.TRUE:
            return TrueDecrease(xi_samples, self.decay_rate, self.exp_rate)
        if form == Loss.POINTWISE:
            return DRPointwise(self.wasserstein_radius, self.risk_level, xi_samples, self.decay_rate, self.exp_rate)
        if form == Loss.UNIFORM:
            return DRUniform(self.wasserstein_radius, self.risk_level, xi_samples, self.decay_rate, self.exp_rate)
        raise ValueError(f"unknown condition form {form!r}; valid: trained, true, pointwise, uniform")

    @property
    def uniform(self) -> bool:
        """Whether it is the DR uniform condition: one inequality over the whole region, no per-state residual."""
        return self.method == Method.DR and self.loss == Loss.UNIFORM


@dataclass(frozen=True)
class NetworkSection:
    """The networks: V's hidden sizes, whether a linear path runs beside them (``lyapunov_skip``), output width and
    ``alpha_hat``; pi's hidden sizes, whether a linear path runs beside them (``controller_skip``) and the scale of its
    output layer at initialisation; the warm start (``"lqr"``, ``"ellipsoid"`` or None) and the LQR's
    ``lqr_weights`` ([Q diagonal, R diagonal]; None: Bryson's rule)."""

    lyapunov_hidden: list[int]
    lyapunov_skip: bool
    lyapunov_out: int
    alpha_hat: float
    controller_hidden: list[int]
    controller_skip: bool
    init_gain: float
    warm_start: str | None
    lqr_weights: list[list[float]] | None

    def build(self, system: UncertainSystem) -> tuple[Lyapunov, Controller]:
        """Fresh networks (drawn from torch's global generator); inputs are scaled by the state box's half-widths."""
        lo, hi = system.local_box()
        scale = ((hi - lo) / 2).tolist()
        lyapunov = Lyapunov(system.n, self.lyapunov_hidden, self.lyapunov_out, self.alpha_hat, scale, self.lyapunov_skip)
        controller = Controller(system.n, system.input_box, system.equilibrium_input, self.controller_hidden,
                                self.init_gain, scale, self.controller_skip)
        return lyapunov, controller


@dataclass(frozen=True)
class SamplingSection:
    """Where training draws from: ``n_states`` states per batch (a fresh batch each iteration where ``resample``) in
    X_delta (the box minus the ball of radius ``delta``; ``train_box``: another box, user coordinates), shares
    ``near_share`` near x* and ``adversarial_share`` moved by ascent; ``n_xi`` samples of xi drawn with the run's
    seed, or the explicit ``xi_samples`` (N, k)."""

    n_states: int
    n_xi: int
    xi_samples: list[list[float]] | None
    delta: float
    resample: bool
    near_share: float
    adversarial_share: float
    train_box: list[list[float]] | None

    def xi(self, system: UncertainSystem, seed: int) -> Tensor:
        """The training samples of xi ``(N, k)`` float64: the explicit ones, else drawn with ``seed``."""
        if self.xi_samples is not None:
            return torch.as_tensor(self.xi_samples, dtype=torch.float64)
        return system.sample_xi(int(self.n_xi), torch.Generator().manual_seed(10_000 + seed))

    def region(self, system: UncertainSystem) -> Region:
        """X_delta: the state box minus the open ball of radius ``delta`` around x*."""
        return Region.of(system, float(self.delta))

    def sampling_region(self, system: UncertainSystem) -> Region:
        """The region training states are drawn in: X_delta, or ``train_box`` minus the same ball."""
        if self.train_box is None:
            return self.region(system)
        return Region.of(system.with_state_box(self.train_box), float(self.delta))

    def counts(self) -> tuple[int, int]:
        """How many states of a batch are drawn near x* and how many are adversarial."""
        return (int(round(float(self.near_share) * int(self.n_states))),
                int(round(float(self.adversarial_share) * int(self.n_states))))


@dataclass(frozen=True)
class RegionGoal:
    """Region-of-attraction training: the claimed set ``{V <= roa_level}`` (None: the paper's condition on all of
    X_delta), trained on ``{V <= (1 + level_margin) roa_level}``; the hinge's weight outside the set
    (``outside_weight``), the term raising V where the set holds a violation (``exclude_weight``), the one pulling
    the set out towards the faces (``grow_weight``), the convex programs that grow a quadratic V's set after
    training (``reshape_steps``), whether only the faces the flow may leave hold V above the trained level
    (``exit_faces``) and by how much more (``exit_margin``)."""

    roa_level: float | None
    level_margin: float
    outside_weight: float
    exclude_weight: float
    grow_weight: float
    reshape_steps: int
    exit_faces: bool
    exit_margin: float

    @property
    def level(self) -> float | None:
        """The level training works with: ``(1 + level_margin) roa_level``; None without a level."""
        if self.roa_level is None:
            return None
        return float(self.roa_level) * (1.0 + float(self.level_margin or 0.0))

    @property
    def faces_level(self) -> float | None:
        """The level V is asked above on the box's faces: :attr:`level`, ``GROW_FACES_MARGIN`` above it where the set
        grows; None without a level."""
        return self._on_faces(self.level)

    @property
    def entry_level(self) -> float | None:
        """The level V must exceed where the flow enters the box: with ``exit_faces`` the claimed ``roa_level`` (the
        claimed set stays inside the box), else :attr:`level`; None without a level."""
        return float(self.roa_level) if self.exit_faces and self.roa_level is not None else self.level

    @property
    def entry_faces_level(self) -> float | None:
        """What :attr:`faces_level` is to :attr:`level`, for :attr:`entry_level`: the level V is asked above where
        the flow enters the box (:attr:`faces_level` without ``exit_faces``)."""
        return self._on_faces(self.entry_level)

    @property
    def exit_faces_level(self) -> float | None:
        """With ``exit_faces``, the level V is asked above where the flow may leave the box: :attr:`faces_level` times
        ``1 + exit_margin``; None without ``exit_faces`` or a level (then :attr:`faces_level` holds on every face)."""
        faces = self.faces_level
        return None if faces is None or not self.exit_faces else faces * (1.0 + float(self.exit_margin or 0.0))

    def _on_faces(self, level: float | None) -> float | None:
        """``level`` as asked on the faces in training: ``GROW_FACES_MARGIN`` above it where the set grows."""
        return None if level is None else level * (1 + GROW_FACES_MARGIN if self.grow_weight else 1.0)


@dataclass(frozen=True)
class Schedule:
    """How training runs: Adam's step size ``lr``, at most ``iters`` iterations, the acceptance check every
    ``check_every``, the ``seed`` of every draw and the ``device`` (``cpu``, ``cuda``, ``cuda:N``)."""

    lr: float
    iters: int
    check_every: int
    seed: int
    device: str

    def torch_device(self) -> torch.device:
        """The device, with a clear error where it is not available."""
        return resolve_device(self.device)


@dataclass(frozen=True)
class TrainSections:
    """A resolved :class:`~drlyap.config.TrainConfig` as its sections (see the module docstring)."""

    system: str
    condition: ConditionSection
    networks: NetworkSection
    sampling: SamplingSection
    goal: RegionGoal
    schedule: Schedule

    @classmethod
    def of(cls, cfg: TrainConfig) -> TrainSections:
        """The sections of the resolved config ``cfg``: every field of it in exactly one section."""
        if cfg.missing():
            raise ValueError(f"the training config leaves {cfg.missing()} open: resolve it first "
                             "(TrainConfig.resolved(system))")

        def section(kind):
            return kind(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(kind)})

        return cls(cfg.system, section(ConditionSection), section(NetworkSection), section(SamplingSection),
                   section(RegionGoal), section(Schedule))


SECTIONS = (ConditionSection, NetworkSection, SamplingSection, RegionGoal, Schedule)
"""The section types, in the order of :class:`TrainSections`."""


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
