"""The settings of a run's training, resolved once where the user's input enters (the CLI, the Python API) and passed
down as typed objects: a system's defaults (:class:`SystemDefaults`, which hold its proofs' defaults too) and the
training configuration (:class:`TrainConfig`). The proof settings (:class:`~drlyap.proof_settings.ProofConfig`) and
one proof's work (:class:`~drlyap.proof_settings.Budget`) are :mod:`drlyap.proof_settings`'.

This module imports neither torch nor the rest of drlyap but its leaf helpers (:mod:`drlyap.io`, the words of
:mod:`drlyap.kinds`), so the command line reads its defaults from these classes without loading the numerical code.
Every default of these settings lives here.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, fields

from drlyap.io import from_fields
from drlyap.kinds import Loss, Method


@dataclass(frozen=True)
class SystemDefaults:
    """A system's defaults for the settings a :class:`~drlyap.training.TrainConfig` (and a
    :class:`~drlyap.verification.ProofConfig`) leaves open (``None``): the one place every default of those lives.

    A system declares only what differs (``UncertainSystem(..., defaults={"delta": 0.5, "margin": 0.1})`` or a
    ``SystemDefaults``); the field defaults below are the rest. Units: ``wasserstein_radius`` in the units of xi,
    ``delta`` and ``train_box`` in local state units, ``lr`` per Adam step, ``verify_time`` seconds per check of
    ``verify``, ``verify_boxes`` boxes per proof (the work budget that makes the proof rounds of training give the
    same pair on an idle and on a loaded machine), ``roa_boxes`` those of ``verify --roa``'s search (None: as many),
    ``round_time`` the outer cap in seconds of each proof of those
    rounds (reported when hit).

    Unless a system declares otherwise, training is for a region of attraction ``{V <= 1}``: the decay ``0.3 V``, an
    LQR warm start, the hinge at full weight outside the set too, violating states pushed out, the set pulled out
    towards the faces and V's decay asked near x* (docs/results/user-system.md: on two 2-state systems this
    certified more of the box than the paper's condition and than saturated LQR). :data:`PAPER_CONDITION` declares
    the paper's condition on all of X_delta instead.
    """

    wasserstein_radius: float = 0.01  # r
    risk_level: float = 0.1  # eps
    decay_rate: float = 0.0  # gamma of gamma ||z||
    exp_rate: float = 0.3  # alpha of alpha V (the exponential variant)
    n_states: int = 3600  # training states per batch
    n_xi: int = 5  # samples of xi drawn from the system's distribution
    delta: float = 0.1  # radius of the excluded ball around x*
    lr: float = 0.002  # Adam's step size
    iters: int = 3000  # iteration cap of training
    alpha_hat: float = 1.0
    lyapunov_hidden: tuple[int, ...] = (32, 32)
    controller_hidden: tuple[int, ...] = (32, 32)
    controller_skip: bool = False
    lyapunov_skip: bool = False
    margin: float = 0.0
    near_share: float = 0.0
    train_box: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    roa_level: float | None = 1.0
    level_margin: float = 0.0
    margin_rate: float = 0.0
    outside_weight: float = 1.0
    exclude_weight: float = 0.01
    grow_weight: float = 0.03
    local_rate: float = 0.3
    adversarial_share: float = 0.0
    reshape_steps: int = 0
    exit_faces: bool = False
    exit_margin: float = 0.0
    warm_start: str | None = "lqr"
    lqr_weights: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    verify_time: float = 30.0  # seconds per check of `verify`
    verify_boxes: int = 200_000  # boxes per proof: about 30 s of a 2-state proof on one thread of a laptop core
    roa_boxes: int | None = None  # boxes of the region-of-attraction search of `verify --roa` (None: verify_boxes)
    round_time: float = 300.0  # outer cap (seconds) of each proof of the training rounds
    stop_at_counterexample: bool = False  # a proof of the training rounds ends at its first confirmed violation
    retrain: str = "pair"  # what the retraining rounds train: "pair", or "controller" (V kept as the first fit left it)

    def __post_init__(self) -> None:
        for f in fields(self):
            object.__setattr__(self, f.name, _frozen(getattr(self, f.name)))

    @classmethod
    def of(cls, value: SystemDefaults | Mapping | None, what: str = "defaults") -> SystemDefaults:
        """``value`` as defaults: itself, or a mapping of field names (an unknown name is an error that lists
        the valid ones); sequences are stored as tuples."""
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        if not isinstance(value, Mapping):
            raise ValueError(f"{what} must be a SystemDefaults or a dict of its fields, got {type(value).__name__}")
        known = [f.name for f in fields(cls)]
        unknown = sorted(set(value) - set(known))
        if unknown:
            raise ValueError(f"{what}: unknown keys {unknown}; valid: {known}")
        return cls(**value)

    def to_dict(self) -> dict:
        """The defaults as JSON-friendly values (tuples as lists)."""
        return {f.name: _thawed(getattr(self, f.name)) for f in fields(self)}


PAPER_CONDITION = {"decay_rate": 1.0, "exp_rate": 0.0, "roa_level": None, "outside_weight": 0.0, "exclude_weight": 0.0,
                   "grow_weight": 0.0, "local_rate": 0.0, "adversarial_share": 0.0, "warm_start": None}
"""The defaults that train the paper's condition on all of X_delta (decay gamma ||z||, no sublevel set, no warm
start), where :class:`SystemDefaults` train for a region of attraction: a system keeps the paper's condition by
declaring them (``defaults={**PAPER_CONDITION, ...}``; the pendulum does). A :class:`TrainConfig` cannot ask for it
on its own: its None fields take the system's defaults."""


def _frozen(value):
    return tuple(_frozen(v) for v in value) if isinstance(value, (list, tuple)) else value


def _thawed(value):
    return [_thawed(v) for v in value] if isinstance(value, (list, tuple)) else value


RESOLVED = ("wasserstein_radius", "risk_level", "decay_rate", "exp_rate", "n_states", "n_xi", "delta", "lr", "iters",
            "alpha_hat", "lyapunov_hidden", "lyapunov_skip", "controller_hidden", "controller_skip", "margin",
            "near_share", "train_box", "roa_level", "level_margin", "margin_rate", "outside_weight", "exclude_weight",
            "grow_weight", "local_rate", "adversarial_share", "reshape_steps", "exit_faces", "exit_margin", "warm_start",
            "lqr_weights")
"""The fields a config leaves to its system (``None``) and :meth:`TrainConfig.resolved` fills."""

OPTIONAL = ("train_box", "roa_level", "warm_start", "lqr_weights")
"""Of :data:`RESOLVED`, those that may stay None (no training box of its own, the paper's condition on all of
X_delta, no warm start, Bryson's weights)."""

LEGACY_PROOF_KEYS = ("verify", "verify_rounds", "verify_time", "verify_budget")
"""Proof settings older runs stored in ``config.json`` (now a :class:`~drlyap.verification.ProofConfig`)."""


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


_KINDS = {
    "system": "str", "method": "str", "loss": "str", "device": "str", "warm_start": "str",
    "wasserstein_radius": "number", "risk_level": "number", "decay_rate": "number", "exp_rate": "number",
    "delta": "number", "lr": "number", "alpha_hat": "number", "margin": "number", "near_share": "number",
    "roa_level": "number", "level_margin": "number", "margin_rate": "number", "outside_weight": "number",
    "exclude_weight": "number", "grow_weight": "number", "exit_margin": "number", "local_rate": "number",
    "adversarial_share": "number",
    "init_gain": "number", "n_states": "int", "n_xi": "int", "iters": "int", "reshape_steps": "int",
    "check_every": "int", "seed": "int", "lyapunov_out": "int",
    "resample": "bool", "controller_skip": "bool", "lyapunov_skip": "bool", "exit_faces": "bool",
    "lyapunov_hidden": "sizes", "controller_hidden": "sizes"}
_REQUIRED = ("system", "method", "loss", "check_every", "seed", "device", "lyapunov_out", "init_gain",
             "resample")


@dataclass
class TrainConfig:
    """Everything a training run depends on (saved verbatim as ``config.json``).

    ``None`` fields take the system's defaults (:class:`~drlyap.systems.SystemDefaults`) when the config is
    resolved (:meth:`resolved`), once, where the user's input enters (the CLI, :func:`drlyap.train`); everything
    below takes resolved configs. The proof settings are a :class:`~drlyap.verification.ProofConfig` of their own.
    """

    system: str = "pendulum"
    method: Method = Method.DR  # baseline (nominal condition at the sample mean) or dr
    loss: Loss = Loss.POINTWISE  # DR loss: pointwise or uniform
    wasserstein_radius: float | None = None  # r
    risk_level: float | None = None  # eps
    decay_rate: float | None = None  # gamma in Vdot + gamma ||x - x*|| <= 0
    exp_rate: float | None = None  # alpha of the exponential variant (adds alpha V inside the hinge)
    n_states: int | None = None  # M training states
    n_xi: int | None = None  # N samples of xi drawn from the system's distribution
    xi_samples: list[list[float]] | None = None  # explicit samples (N, k); overrides n_xi
    delta: float | None = None  # radius of the excluded ball around x* (local coordinates)
    lr: float | None = None  # Adam's step size (system default; 0.002)
    iters: int | None = None  # iteration cap (system default; 3000)
    check_every: int = 250  # acceptance check period (iterations)
    seed: int = 0
    device: str = "cpu"
    lyapunov_hidden: list[int] | None = None
    lyapunov_out: int = 8
    alpha_hat: float | None = None
    controller_hidden: list[int] | None = None
    # a linear path from the scaled state to the controller's output beside its hidden layers: pi is a linear gain
    # plus a network's correction (the LQR warm start sets the gain and starts the correction at 0)
    controller_skip: bool | None = None
    lyapunov_skip: bool | None = None  # the same for V's phi: V is a quadratic form plus a network's term
    init_gain: float = 10.0  # scale of the controller's output layer at initialisation
    margin: float | None = None  # training hinge is (residual + margin)_+: pushes the condition past zero
    resample: bool = True  # draw a fresh uniform batch of n_states every iteration (False: one fixed set)
    # share of each batch drawn evenly over the distance from x* (Region.sample_near) instead of uniformly:
    # with 4 or more states a uniform batch holds almost no states near x*, where local stability is decided
    near_share: float | None = None
    # Box ((low...), (high...)) in user coordinates the training states are drawn from; None: the system's X. Only
    # where training samples: the networks' input scaling, the acceptance check, the verifier and success keep X.
    train_box: list[list[float]] | None = None
    # Region-of-attraction training: the condition is asked only of {V <= roa_level}, and a hinge keeps V above
    # roa_level on the faces of X (so the set lies inside X and is forward invariant once the condition holds
    # on it); half of each batch is drawn inside the set. None: the paper's condition on all of X_delta.
    roa_level: float | None = None
    # region-of-attraction training: the condition is trained on {V <= (1 + level_margin) roa_level}, the set that
    # is claimed and proved being {V <= roa_level}: training grows the set until the condition is tight on its
    # boundary, and the margin leaves room for the proof there. 0: trained on the claimed set itself
    level_margin: float | None = None
    margin_rate: float | None = None  # adds margin_rate * V to the hinge: a margin that scales with V (0 at x*)
    # region-of-attraction training: the weight of the hinge at states outside {V <= roa_level} (0: the condition is
    # asked of the set only; > 0: the controller also learns to bring the states outside into it, as the paper's
    # condition on all of X_delta does, while the claim stays on the set)
    outside_weight: float | None = None
    # region-of-attraction training: a state inside {V <= roa_level} that violates the condition adds
    # exclude_weight (roa_level - V)_+ / roa_level, which raises V there (the set leaves out what no controller
    # can fix, e.g. where gravity exceeds the control force); 0: none
    exclude_weight: float | None = None
    # region-of-attraction training: grow_weight (V - roa_level)_+ / roa_level on the training states pulls the set
    # out towards the box (V is then asked above 1.05 roa_level on the faces, so the set keeps off them); 0: none
    grow_weight: float | None = None
    # V's local decay rate asked at x*: a hinge (lambda_j + local_rate)_+ on conditions.local_rates at every training
    # sample (every LOCAL_EVERY iterations), and the acceptance check then asks lambda_j < 0. 0: neither.
    local_rate: float | None = None
    # share of each batch held by adversarial states: a persistent set moved every iteration by one step of projected
    # ascent on the residual, kept inside the training set {V <= (1 + level_margin) roa_level} (X_delta without a
    # level); 2% of it redrawn each iteration (in 6 states uniform draws miss where the condition fails). 0: none
    adversarial_share: float | None = None
    reshape_steps: int | None = None  # convex programs growing a quadratic V's set after training (training/reshape)
    # region-of-attraction training: V is held above the trained level only on the faces where the flow may leave the
    # box (training/states.may_leave), elsewhere above the claimed level roa_level; with a level margin, the set cut by
    # the box then grows past the claimed one where the flow enters the box (verify --roa --roa-above-level)
    exit_faces: bool | None = None
    # with exit_faces: V asked above (1 + exit_margin) times the trained level where the flow may leave (the set cut by
    # the box then ends at the exits above the level the condition was trained to; a decrease proved there reaches it)
    exit_margin: float | None = None
    # "lqr": before training, fit V to the LQR's z^T P z (scaled to 1.2 times the training level, or 1, on the faces)
    # and pi to its gain (exactly without hidden layers or with a linear path, else by regression); lqr_weights = [Q
    # diagonal, R diagonal] (None: Bryson's rule); "ellipsoid": the same with drlyap.lmi's largest invariant ellipsoid
    warm_start: str | None = None
    lqr_weights: list[list[float]] | None = None

    def type_problems(self) -> list[str]:
        """The fields whose value has the wrong type (numbers where numbers belong, integers for counts, strings,
        a boolean), each named with what would be valid; fields left None are not checked."""
        problems = []
        for f in dataclasses.fields(self):
            value, kind = getattr(self, f.name), _KINDS.get(f.name)
            if value is None or kind is None:
                if value is None and f.name in _REQUIRED:
                    problems.append(f"{f.name} is missing (null)")
                continue
            if kind == "number" and not _is_number(value):
                problems.append(f"{f.name} = {value!r} (must be a number)")
            elif kind == "int" and not (isinstance(value, int) and not isinstance(value, bool)):
                problems.append(f"{f.name} = {value!r} (must be an integer)")
            elif kind == "str" and not isinstance(value, str):
                problems.append(f"{f.name} = {value!r} (must be a string)")
            elif kind == "bool" and not isinstance(value, bool):
                problems.append(f"{f.name} = {value!r} (must be true or false)")
            elif kind == "sizes" and not (isinstance(value, (list, tuple)) and all(
                    isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in value)):
                problems.append(f"{f.name} = {value!r} (must be a list of positive integers; [] for a linear map)")
        return problems

    def resolved(self, system) -> TrainConfig:
        """A copy with ``None`` fields filled from ``system.defaults``, explicit xi samples as lists of floats
        (a tensor or an array is accepted), validated for ``system``."""
        cfg = copy.deepcopy(self)
        defaults = system.defaults.to_dict()
        for name in RESOLVED:
            if getattr(cfg, name) is None:
                setattr(cfg, name, defaults[name])
        if cfg.xi_samples is not None and hasattr(cfg.xi_samples, "tolist"):  # a tensor or an array
            cfg.xi_samples = cfg.xi_samples.tolist()
        cfg.validate(system)
        cfg.method, cfg.loss = Method(cfg.method), Loss(cfg.loss)
        return cfg

    def missing(self) -> list[str]:
        """The fields a resolved config has filled that this one leaves open (empty once resolved)."""
        return [name for name in RESOLVED if getattr(self, name) is None and name not in OPTIONAL]

    def validate(self, system) -> None:
        """A ValueError naming every field that is of the wrong type or out of range for ``system``."""
        problems = self.type_problems()
        if problems:
            raise ValueError("invalid training config: " + "; ".join(problems))
        if self.method not in tuple(Method):
            problems.append(f"method {self.method!r} (valid: {', '.join(Method)})")
        if self.loss not in tuple(Loss):
            problems.append(f"loss {self.loss!r} (valid: {', '.join(Loss)})")
        for name in ("wasserstein_radius", "decay_rate", "exp_rate", "margin", "alpha_hat", "margin_rate", "outside_weight",
                     "exclude_weight", "grow_weight", "local_rate", "level_margin"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                problems.append(f"{name} = {value} (must be finite and >= 0)")
        if not 0 < self.risk_level < 1:
            problems.append(f"risk_level = {self.risk_level} (must be in (0, 1))")
        if self.reshape_steps < 0:
            problems.append(f"reshape_steps = {self.reshape_steps} (must be >= 0)")
        for name in ("n_states", "n_xi", "iters", "check_every"):
            if int(getattr(self, name)) < 1:
                problems.append(f"{name} = {getattr(self, name)} (must be >= 1)")
        if not (math.isfinite(self.lr) and self.lr > 0):
            problems.append(f"lr = {self.lr} (must be > 0)")
        for name in ("near_share", "adversarial_share"):
            if not (math.isfinite(getattr(self, name)) and 0 <= getattr(self, name) <= 1):
                problems.append(f"{name} = {getattr(self, name)} (must be in [0, 1])")
        if self.adversarial_share and self.method == Method.DR and self.loss == Loss.UNIFORM:
            problems.append("adversarial_share needs a per-state condition (the uniform DR loss has none to ascend)")
        if self.near_share + self.adversarial_share > 1:
            problems.append(f"near_share + adversarial_share = {self.near_share + self.adversarial_share} (must be <= 1)")
        if self.roa_level is not None and not (math.isfinite(self.roa_level) and self.roa_level > 0):
            problems.append(f"roa_level = {self.roa_level} (must be > 0, or None)")
        if not (math.isfinite(self.exit_margin) and self.exit_margin >= 0):
            problems.append(f"exit_margin = {self.exit_margin} (must be >= 0)")
        elif self.exit_margin and not self.exit_faces:
            problems.append(f"exit_margin = {self.exit_margin} needs exit_faces = True")
        for name in ("level_margin", "exit_faces"):
            if getattr(self, name) and self.roa_level is None:
                problems.append(f"{name} = {getattr(self, name)} needs a region-of-attraction level (roa_level)")
        if self.warm_start not in (None, "lqr", "ellipsoid"):
            problems.append(f"warm_start {self.warm_start!r} (valid: lqr, ellipsoid, or None)")
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
                system.with_state_box(self.train_box)
            except (TypeError, ValueError) as err:
                problems.append(f"train_box: {err}")
        if self.xi_samples is not None:
            rows = self.xi_samples
            shape_ok = isinstance(rows, (list, tuple)) and len(rows) >= 1 and all(
                isinstance(row, (list, tuple)) and len(row) == system.k and all(_is_number(v) for v in row)
                for row in rows)
            if not shape_ok:
                problems.append(f"xi_samples must be an (N, {system.k}) array of numbers for {system.name} (N >= 1), "
                                f"got {_short(rows)}")
            elif not all(math.isfinite(v) for row in rows for v in row):
                problems.append("xi_samples contain NaN or inf")
        if problems:
            raise ValueError("invalid training config: " + "; ".join(problems))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> TrainConfig:
        """The config stored as ``data`` (a run's ``config.json``); the proof settings older runs kept in it
        (``verify*``, see :func:`legacy_proof`) are left to the run's proof record."""
        return from_fields(cls, {k: v for k, v in data.items() if k not in LEGACY_PROOF_KEYS}, "config")
