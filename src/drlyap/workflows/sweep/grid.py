"""A sweep's grid: seeds x radii x risk levels x methods (:class:`SweepSpec`), and parsing it from the command line."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from drlyap.config import TrainConfig
from drlyap.io import from_fields
from drlyap.kinds import Method
from drlyap.proof_settings import ProofConfig
from drlyap.systems import UncertainSystem, resolve_system

METHODS = (Method.BASELINE, Method.DR)
SPEC_FILE = "sweep.json"  # the grid, in the sweep directory
RESULT_FILE = "result.json"  # a finished combination's row, in its run directory
STAGING = ".staging"  # combinations being written


class SweepError(ValueError):
    """A sweep grid, directory or backend that cannot be used as asked."""


def parse_seeds(text: str) -> list[int]:
    """Seeds from ``"0-9"``, ``"0,2,5"`` or a mix (``"0-4,10"``); ranges are inclusive, duplicates dropped."""
    seeds: list[int] = []
    for part in (p.strip() for p in str(text).split(",")):
        if not part:
            continue
        low, sep, high = part.partition("-")
        try:
            values = range(int(low), int(high) + 1) if sep else [int(part)]
            if sep and int(high) < int(low):
                raise SweepError(f"seeds: range {part!r} runs backwards; write LOW-HIGH with LOW <= HIGH")
        except ValueError as err:
            if isinstance(err, SweepError):
                raise
            raise SweepError(f"seeds: {part!r} is not a seed or a range; valid: '0-9', '0,2,5', '0-4,10' "
                             "(non-negative integers)") from None
        seeds += [s for s in values if s not in seeds]
    if not seeds:
        raise SweepError(f"seeds: no seed in {text!r}; valid: '0-9', '0,2,5', '0-4,10'")
    return seeds


def parse_values(text: str, what: str) -> list[float]:
    """Finite numbers from a comma-separated list (``"0,0.005,0.01"``), duplicates dropped."""
    values: list[float] = []
    for part in (p.strip() for p in str(text).split(",")):
        if not part:
            continue
        try:
            value = float(part)
        except ValueError:
            raise SweepError(f"{what}: {part!r} is not a number; give comma-separated numbers like '0,0.005,0.01'") from None
        if not math.isfinite(value):
            raise SweepError(f"{what}: {part!r} is not finite")
        if value not in values:
            values.append(value)
    if not values:
        raise SweepError(f"{what}: no value in {text!r}; give comma-separated numbers like '0,0.005,0.01'")
    return values


def parse_methods(text: str) -> list[str]:
    """``"dr"``, ``"baseline"``, ``"both"`` or a comma-separated list of the first two."""
    parts = [p.strip() for p in str(text).split(",") if p.strip()]
    methods: list[str] = []
    for part in parts:
        for m in (METHODS if part == "both" else (part,)):
            if m not in METHODS:
                raise SweepError(f"method {m!r}; valid: baseline, dr, both")
            if m not in methods:
                methods.append(m)
    if not methods:
        raise SweepError(f"no method in {text!r}; valid: baseline, dr, both")
    return methods


@dataclass(frozen=True)
class Combination:
    """One point of the grid. The baseline does not use r or eps: they are None there."""

    method: str
    seed: int
    radius: float | None
    eps: float | None

    @property
    def name(self) -> str:
        """Directory name, e.g. ``dr-r0.01-eps0.1-seed3`` or ``baseline-seed3``."""
        if self.method == Method.BASELINE:
            return f"baseline-seed{self.seed}"
        return f"{self.method}-r{self.radius:g}-eps{self.eps:g}-seed{self.seed}"


@dataclass
class SweepSpec:
    """The grid and everything each combination depends on (saved as ``sweep.json``).

    ``system`` is a registered name or a ``module:factory`` / ``file.py:factory`` spec
    (:func:`drlyap.systems.resolve_system`). ``config`` holds further :class:`~drlyap.training.TrainConfig`
    fields applied to every combination (e.g. smaller networks). ``verify``/``verify_rounds``: prove each
    trained pair with up to this many retraining rounds, as ``drlyap train`` does. ``shift_factors``:
    evaluation at k x the system's test shift. ``n_init`` evaluation states per seed; ``horizon`` simulated time (system units,
    ``None``: the system's). ``verify_time_limit``: seconds per branch and bound
    (None: the system's; the proofs of the training rounds are budgeted by boxes, with this as their outer cap).
    """

    system: str
    seeds: list[int]
    radii: list[float]
    eps: list[float]
    methods: list[str] = field(default_factory=lambda: ["dr"])
    iters: int | None = None
    verify: bool = True
    verify_rounds: int = 5
    device: str = "cpu"
    shift_factors: list[float] = field(default_factory=lambda: [1.0, 2.0, 3.0, 4.0, 5.0])
    n_init: int = 200
    horizon: float | None = None
    verify_time_limit: float | None = None
    config: dict = field(default_factory=dict)

    def combinations(self) -> list[Combination]:
        """Every combination, baselines once per seed (they ignore r and eps)."""
        combos = []
        for method in self.methods:
            for seed in self.seeds:
                if method == Method.BASELINE:
                    combos.append(Combination(method, seed, None, None))
                    continue
                combos += [Combination(method, seed, r, e) for e in self.eps for r in self.radii]
        return combos

    def train_config(self, combo: Combination, system: UncertainSystem) -> TrainConfig:
        """The training configuration of one combination (system defaults for what the sweep leaves open), for the
        sweep's resolved ``system``."""
        cfg = TrainConfig(system=system.name, method=combo.method, seed=combo.seed,
                          device=self.device, wasserstein_radius=combo.radius, risk_level=combo.eps, **self.config)
        if self.iters is not None:
            cfg.iters = int(self.iters)
        return cfg

    def proof(self) -> ProofConfig | None:
        """The proof settings of every combination's training (None: trained without proof rounds)."""
        if not self.verify:
            return None
        return ProofConfig(rounds=self.verify_rounds, time_limit=self.verify_time_limit)

    def validate(self) -> None:
        """Check the whole grid before anything runs (every combination's config, the evaluation settings)."""
        system = resolve_system(self.system)
        if system.test_xi is None:
            raise SweepError(f"{self.system} declares no test shift; a sweep evaluates at k x that shift")
        problems = []
        if self.verify_rounds < 0:
            problems.append(f"verify_rounds = {self.verify_rounds} (must be >= 0)")
        if self.n_init < 1:
            problems.append(f"n_init = {self.n_init} (must be >= 1)")
        if self.horizon is not None and not self.horizon > 0:
            problems.append(f"horizon = {self.horizon} (must be > 0)")
        if self.verify_time_limit is not None and not self.verify_time_limit > 0:
            problems.append(f"verify_time_limit = {self.verify_time_limit} (must be > 0)")
        if not self.shift_factors or not all(math.isfinite(k) for k in self.shift_factors):
            problems.append(f"shift_factors = {self.shift_factors} (need finite numbers)")
        if problems:
            raise SweepError("invalid sweep: " + "; ".join(problems))
        for combo in self.combinations():
            try:
                self.train_config(combo, system).resolved(system)
            except (TypeError, ValueError) as err:
                raise SweepError(f"combination {combo.name}: {err}") from None

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> SweepSpec:
        return from_fields(cls, data, "sweep", SweepError)
