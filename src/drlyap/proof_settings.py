"""The settings of a run's proofs, resolved once where the user's input enters (the CLI, the Python API) and passed down
as typed objects: every proof setting of a run (:class:`ProofConfig`), one proof's work (:class:`Budget`) and the
enclosures boxes are bounded with. The training settings are :mod:`drlyap.config`'s.

Like :mod:`drlyap.config`, this module imports neither torch nor the rest of drlyap but its leaf helpers, so the
command line reads its defaults from these classes without loading the numerical code.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from drlyap.compute import Compute
from drlyap.io import from_fields
from drlyap.kinds import Enclosure, choice

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
    ``compute``: where the boxes are bounded (:class:`Compute`: workers, backend, device, checkpoints, progress; how
    fast, never what is proved, so a run does not record it).
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
    compute: Compute = Compute()

    def validate(self) -> None:
        """A ValueError naming every setting out of range."""
        problems = [] if isinstance(self.compute, Compute) else [
            f"compute must be a Compute, got {type(self.compute).__name__}"]
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
        return dataclasses.replace(self, compute=compute)

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
        """The settings a run records: what its proofs were asked, not where they ran (``compute`` is left out)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "compute"}

    @classmethod
    def from_dict(cls, data: dict) -> ProofConfig:
        return from_fields(cls, data, "proof settings")


RETRAIN = ("pair", "controller")
"""What the retraining rounds of :class:`ProofConfig` may train."""


def legacy_proof(data: dict) -> ProofConfig | None:
    """The proof settings an older run's ``config.json`` held (``verify``, ``verify_rounds``, ``verify_time``,
    ``verify_budget``), or None when it was trained without proof rounds."""
    if data.get("verify") is False:
        return None
    return ProofConfig(rounds=int(data.get("verify_rounds", 5)), time_limit=data.get("verify_time"),
                       total_time=data.get("verify_budget"))
