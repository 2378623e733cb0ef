"""The settings of a run, resolved once where the user's input enters (the CLI, the Python API) and passed down as
typed objects: a system's defaults (:class:`SystemDefaults`), the training configuration (:class:`TrainConfig`),
the proof settings (:class:`ProofConfig`) and one proof's work (:class:`Budget`).

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

from drlyap.compute import Compute, compute_problems
from drlyap.io import from_fields
from drlyap.kinds import Enclosure, Loss, Method, choice


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


ENCLOSURES = tuple(e.value for e in Enclosure)
"""The enclosures the verifier can bound boxes with (the first is the default below 4 states)."""


def default_enclosure(n: int) -> Enclosure:
    """The enclosure for an ``n``-state system: ``affine`` from 4 states on (11-25x tighter there,
    ``benchmarks/enclosure_bench.py``), else ``mean-value`` (about 3x cheaper per box; in 2 states boxes are
    few and the pendulum's proofs take about a second either way)."""
    return Enclosure.AFFINE if n >= 4 else Enclosure.MEAN_VALUE


def check_enclosure(enclosure: str) -> Enclosure:
    """``enclosure`` as an :class:`~drlyap.kinds.Enclosure`, else a ValueError naming the valid ones."""
    return choice(Enclosure, enclosure, "enclosure")


@dataclass(frozen=True)
class Budget:
    """How much one proof may do, and how finely: at most ``boxes`` boxes bounded and ``seconds`` of wall time
    (whichever ends first; the result's ``stopped`` says which), boxes split no finer than ``min_width`` (of the
    box's sides), ``batch`` boxes bounded at a time, with ``enclosure`` (None: :func:`default_enclosure`), where
    ``compute`` says (:class:`Compute`: this process by default)."""

    seconds: float = 30.0
    boxes: int = 2_000_000
    min_width: float = 1e-4
    batch: int = 4096
    enclosure: Enclosure | None = None
    compute: Compute = Compute()

    def __post_init__(self) -> None:
        # seconds may be spent (<= 0) where a proof hands what is left of its time to its last step: it stops at once
        if not (math.isfinite(self.seconds) and int(self.boxes) >= 1 and self.min_width > 0 and int(self.batch) >= 1):
            raise ValueError(f"a proof budget needs finite seconds, boxes >= 1, min_width > 0 and batch >= 1, got {self}")
        if self.enclosure is not None:
            object.__setattr__(self, "enclosure", check_enclosure(self.enclosure))
        if not isinstance(self.compute, Compute):
            raise ValueError(f"a proof budget's compute must be a Compute, got {type(self.compute).__name__}")

    def enclosure_for(self, n: int) -> Enclosure:
        """The enclosure to bound boxes of an ``n``-state system with."""
        return self.enclosure or default_enclosure(n)

    def share(self, fraction: float, least_seconds: float = 0.0) -> Budget:
        """The same budget scaled by ``fraction`` (seconds at least ``least_seconds``, boxes at least 1)."""
        return dataclasses.replace(self, seconds=max(least_seconds, self.seconds * fraction),
                                   boxes=max(1, int(self.boxes * fraction)))

    def with_seconds(self, seconds: float) -> Budget:
        return dataclasses.replace(self, seconds=seconds)


ROA_TIME_CAP = 10.0
"""The time cap of the region-of-attraction search of ``verify --roa`` where ``ProofConfig.roa_time`` is None, in
multiples of the checks' ``time_limit`` (300 s on the 2-state systems): the search is budgeted by boxes
(``ProofConfig.roa_boxes``), and its default ends in well under a minute there."""

DEFAULT_SETTLE_STARTS = 4096
"""Falsifier starts of a verdict (:func:`~drlyap.verification.falsifier.settle_unknown`): about 1.6 s on the
quadrotor, one thread."""


@dataclass(frozen=True)
class ProofConfig:
    """Every setting of a run's proofs: the counterexample-guided rounds after training (``drlyap train``) and the
    checks of ``drlyap verify``. ``None`` fields are resolved from the system (:meth:`resolved`).

    Proofs: at most ``max_boxes`` boxes each (None: the system's ``defaults.verify_boxes``), ``min_width``,
    ``enclosure`` (None: affine from 4 states on); the checks of ``verify`` stop after ``time_limit`` seconds too
    (None: ``defaults.verify_time``: 30, 900 for the cart-pole, 3600 for the quadrotor), the proofs of the training rounds
    after ``round_time`` (None: ``time_limit`` when given, else ``defaults.round_time``, an outer cap: the rounds
    are budgeted by boxes, so that the same command gives the same pair on a busy machine).
    Rounds: at most ``rounds`` retraining rounds, all within ``total_time`` seconds (None: no limit, the default: a
    limit makes the pair depend on machine speed); each trains
    ``iters_per_round`` iterations (None: half the run's ``iters``) on the states collected so far (at most
    ``max_extra``, repeated ``replicate`` times in every batch): the proof's counterexample, the centres of at most
    ``keep_boxes`` unverified boxes, and a falsifier's counterexamples (``falsifier_starts`` starts, None: 512
    uniform, or 2,048 half near x* where training draws states near x*; ``falsifier_steps`` ascent steps; each with
    ``neighbours`` jittered copies); and, with ``box_weight`` > 0, the verifier's own bound over at most
    ``train_boxes`` boxes the proof left open (certified training, :mod:`drlyap.training.boxes`; 0 of either: off).
    ``settle_starts``: falsifier starts that settle an unknown verdict.
    ``stop_at_counterexample``: a proof of the rounds ends at the first batch of boxes holding a confirmed
    violation instead of spending its whole budget (None: ``defaults.stop_at_counterexample``; its verified
    fraction then counts every box not yet proved as unproved).
    ``retrain``: what the retraining rounds train, ``"pair"`` (V and pi) or ``"controller"`` (V kept as the first
    fit left it, so its sets stay where that fit put them; None: ``defaults.retrain``).
    Checks of ``verify``: ``uniform_time`` seconds for the uniform DR margin; the region of attraction's search
    (``verify --roa``) does at most ``roa_boxes`` boxes (None: the system's ``defaults.roa_boxes``, else its
    ``verify_boxes``; its steps' shares: :func:`~drlyap.verification.roa.certified_roa`), so that the region does
    not depend on the machine's speed, and stops after ``roa_time`` seconds at most (None: :data:`ROA_TIME_CAP` x
    ``time_limit``, an outer cap whose hitting the result reports); ``band_time`` caps its band proof's seconds (None:
    ``roa_time`` again; 0: off), which gets ``roa_boxes`` boxes again.
    Where the boxes are bounded (:class:`Compute`; how fast, never what is proved, so a run does not record them):
    ``workers``, ``backend``, ``address``, ``device``, ``checkpoint_dir`` and ``checkpoint_every`` for proofs that
    resume, ``progress``.
    """

    rounds: int = 5
    time_limit: float | None = None
    total_time: float | None = None
    max_boxes: int | None = None
    round_time: float | None = None
    min_width: float = 1e-4
    enclosure: Enclosure | None = None
    iters_per_round: int | None = None
    max_extra: int = 2000
    replicate: int = 2
    keep_boxes: int = 200
    train_boxes: int = 1024
    box_weight: float = 1.0
    falsifier_starts: int | None = None
    falsifier_steps: int = 30
    neighbours: int = 3
    settle_starts: int = DEFAULT_SETTLE_STARTS
    stop_at_counterexample: bool | None = None
    retrain: str | None = None
    uniform_time: float = 3.0
    roa_time: float | None = None
    roa_boxes: int | None = None
    band_time: float | None = None
    workers: int = 1
    backend: str = "local"
    address: str | None = None
    device: str = "cpu"
    checkpoint_dir: str | None = None
    checkpoint_every: float = 2.0
    progress: bool = False

    def validate(self) -> None:
        """A ValueError naming every setting out of range."""
        problems = compute_problems(self.workers, self.backend, self.address, self.device)
        if int(self.rounds) < 0:
            problems.append(f"rounds = {self.rounds} (must be >= 0)")
        for name in ("time_limit", "total_time", "roa_time", "round_time"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                problems.append(f"{name} = {value} (must be > 0 seconds)")
        if self.band_time is not None and not (math.isfinite(self.band_time) and self.band_time >= 0):
            problems.append(f"band_time = {self.band_time} (must be >= 0 seconds)")
        if not (math.isfinite(self.box_weight) and self.box_weight >= 0):
            problems.append(f"box_weight = {self.box_weight} (must be >= 0)")
        if not (math.isfinite(self.uniform_time) and self.uniform_time > 0):
            problems.append(f"uniform_time = {self.uniform_time} (must be > 0 seconds)")
        if not self.min_width > 0 or (self.max_boxes is not None and int(self.max_boxes) < 1):
            problems.append(f"min_width = {self.min_width} (> 0) / max_boxes = {self.max_boxes} (>= 1)")
        if self.roa_boxes is not None and int(self.roa_boxes) < 1:
            problems.append(f"roa_boxes = {self.roa_boxes} (must be >= 1)")
        if self.iters_per_round is not None and int(self.iters_per_round) < 1:
            problems.append(f"iters_per_round = {self.iters_per_round} (must be >= 1)")
        if int(self.max_extra) < 1 or int(self.replicate) < 1:
            problems.append(f"max_extra = {self.max_extra} / replicate = {self.replicate} (must be >= 1)")
        for name in ("keep_boxes", "train_boxes", "falsifier_steps", "neighbours", "settle_starts"):
            if int(getattr(self, name)) < 0:
                problems.append(f"{name} = {getattr(self, name)} (must be >= 0)")
        if self.falsifier_starts is not None and int(self.falsifier_starts) < 0:
            problems.append(f"falsifier_starts = {self.falsifier_starts} (must be >= 0)")
        if self.retrain is not None and self.retrain not in RETRAIN:
            problems.append(f"retrain = {self.retrain!r} (valid: {', '.join(RETRAIN)})")
        if self.enclosure is not None and self.enclosure not in ENCLOSURES:
            problems.append(f"enclosure {self.enclosure!r} (valid: {', '.join(ENCLOSURES)})")
        if problems:
            raise ValueError("invalid proof settings: " + "; ".join(problems))

    def resolved(self, system) -> ProofConfig:
        """A copy with the system's defaults filled in (seconds and boxes per proof and of the region-of-attraction
        search, the enclosure), validated."""
        self.validate()
        d = system.defaults
        out = dataclasses.replace(self, time_limit=float(self.time_limit or d.verify_time),
                                  max_boxes=int(self.max_boxes or d.verify_boxes),
                                  roa_boxes=int(self.roa_boxes or d.roa_boxes or d.verify_boxes),
                                  round_time=float(self.round_time or self.time_limit or d.round_time),
                                  enclosure=Enclosure(self.enclosure or default_enclosure(system.n)),
                                  stop_at_counterexample=bool(d.stop_at_counterexample
                                                              if self.stop_at_counterexample is None
                                                              else self.stop_at_counterexample),
                                  retrain=str(self.retrain or d.retrain))
        out.validate()  # the system's defaults too
        return out

    @property
    def is_resolved(self) -> bool:
        return None not in (self.time_limit, self.max_boxes, self.round_time, self.enclosure)

    def budget(self, seconds: float | None = None) -> Budget:
        """The :class:`Budget` of one check of ``verify`` (``seconds`` instead of ``time_limit`` when given)."""
        if not self.is_resolved:
            raise ValueError("resolve the proof settings for a system first (ProofConfig.resolved)")
        return Budget(seconds=float(seconds if seconds is not None else self.time_limit), boxes=int(self.max_boxes),
                      min_width=self.min_width, enclosure=self.enclosure, compute=self.compute)

    def with_compute(self, compute: Compute) -> ProofConfig:
        """The same settings, bounding their boxes where ``compute`` says."""
        return dataclasses.replace(self, workers=compute.workers, backend=compute.backend, address=compute.address,
                                   device=compute.device, checkpoint_dir=compute.checkpoint_dir,
                                   checkpoint_every=compute.checkpoint_every, progress=compute.progress)

    @property
    def compute(self) -> Compute:
        """Where the boxes of these proofs are bounded (:class:`Compute`)."""
        return Compute(workers=int(self.workers), backend=self.backend, address=self.address, device=self.device,
                       checkpoint_dir=None if self.checkpoint_dir is None else str(self.checkpoint_dir),
                       checkpoint_every=float(self.checkpoint_every), progress=bool(self.progress))

    def roa_budget(self) -> Budget:
        """The :class:`Budget` of the region-of-attraction search of ``verify --roa``: ``roa_boxes`` boxes, and
        ``roa_time`` seconds at most (None: :data:`ROA_TIME_CAP` x ``time_limit``)."""
        budget = self.budget(self.roa_time if self.roa_time is not None else ROA_TIME_CAP * self.time_limit)
        return dataclasses.replace(budget, boxes=int(self.roa_boxes or self.max_boxes))

    def round_budget(self) -> Budget:
        """The :class:`Budget` of each proof of the training rounds: ``max_boxes`` boxes, ``round_time`` seconds at
        most."""
        return self.budget(self.round_time)

    def to_dict(self) -> dict:
        """The settings a run records: what its proofs were asked, not where they ran (:data:`COMPUTE_FIELDS` are
        left out)."""
        return {k: v for k, v in dataclasses.asdict(self).items() if k not in COMPUTE_FIELDS}

    @classmethod
    def from_dict(cls, data: dict) -> ProofConfig:
        return from_fields(cls, data, "proof settings")


RETRAIN = ("pair", "controller")
"""What the retraining rounds of :class:`ProofConfig` may train."""

COMPUTE_FIELDS = ("workers", "backend", "address", "device", "checkpoint_dir", "checkpoint_every", "progress")
"""The fields of :class:`ProofConfig` that say where its proofs run (:class:`Compute`), not what they prove."""


def legacy_proof(data: dict) -> ProofConfig | None:
    """The proof settings an older run's ``config.json`` held (``verify``, ``verify_rounds``, ``verify_time``,
    ``verify_budget``), or None when it was trained without proof rounds."""
    if data.get("verify") is False:
        return None
    return ProofConfig(rounds=int(data.get("verify_rounds", 5)), time_limit=data.get("verify_time"),
                       total_time=data.get("verify_budget"))
