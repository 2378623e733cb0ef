"""Typed records of what a training found, as ``metrics.json`` keeps them: training writes them with ``to_dict``,
and whatever reads a run (the trainer's proof rounds, the reproduction, sweeps, the printed lines) reads them with
``from_dict`` instead of by key. Imports nothing of drlyap, nor torch.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class AcceptanceCheck:
    """The acceptance check of a pair (:func:`drlyap.training.acceptance.acceptance_check`).

    ``passed``: every check below held. ``validation_states``: states of the first check; ``max_violation`` and
    ``violating_fraction``: the trained condition's largest residual there and the share of them where it is > 0
    (with a ``level``: asked only where ``V <= level``, and ``boundary_min``, V's least value on the box's faces, must
    exceed it). ``jacobian``: the true closed-loop Jacobian at x* for each xi sample and their mean
    (``max_real_eigenvalue``, ``hurwitz``, ``labels``). ``other_equilibria``: closed-loop equilibria found in X_delta
    other than x* (each with its local and user state, which xi, the residual norm, and with a ``level`` V there and
    ``in_set``: whether it lies in ``{V <= level}``; only those count against a pair trained for that set:
    :attr:`blocking_equilibria`). ``local_rates``: V's second-order
    decay rate at x* on each of the condition's samples, ``local_rate_max`` the largest (NaN where one is; None in runs
    written before the rates were kept). ``iteration``: the training iteration it was made at (None outside
    training)."""

    passed: bool
    validation_states: int
    max_violation: float
    violating_fraction: float
    jacobian: dict
    other_equilibria: list[dict]
    level: float | None
    boundary_min: float | None
    local_rates: list[float]
    local_rate_max: float | None
    iteration: int | None = None
    extra: dict = field(default_factory=dict)  # keys a later format added, kept as they were read

    @property
    def hurwitz(self) -> bool:
        """Whether the closed-loop Jacobian at x* is Hurwitz at every xi sample and their mean."""
        return bool(self.jacobian["hurwitz"])

    @property
    def blocking_equilibria(self) -> list[dict]:
        """The other equilibria that fail the check: those in the trained set ``{V <= level}``, all of them without a
        level (or in a record written before ``in_set`` was kept)."""
        return [e for e in self.other_equilibria if e.get("in_set", True)]

    def stability(self) -> tuple[bool, bool, bool]:
        """How the check ranks a pair before anything else: passed, Hurwitz at x*, no other equilibrium (in the
        trained set)."""
        return bool(self.passed), self.hurwitz, not self.blocking_equilibria

    def summary(self) -> dict:
        """The line a training's ``checks`` list keeps for it."""
        return {"iteration": self.iteration, "passed": self.passed, "max_violation": self.max_violation,
                "violating_fraction": self.violating_fraction, "hurwitz": self.hurwitz,
                "n_other_equilibria": len(self.other_equilibria), "local_rate_max": self.local_rate_max}

    def to_dict(self) -> dict:
        """As ``metrics.json`` keeps it (``iteration`` only where there is one)."""
        out = {"passed": self.passed, "validation_states": self.validation_states, "max_violation": self.max_violation,
               "violating_fraction": self.violating_fraction, "jacobian": self.jacobian,
               "other_equilibria": self.other_equilibria, "level": self.level, "boundary_min": self.boundary_min,
               "local_rates": self.local_rates, "local_rate_max": self.local_rate_max}
        if self.iteration is not None:
            out["iteration"] = self.iteration
        return out | self.extra

    @classmethod
    def from_dict(cls, data: dict) -> AcceptanceCheck:
        """From ``metrics.json``'s ``acceptance`` (runs written before the local rates were kept read without them)."""
        known = {"passed", "validation_states", "max_violation", "violating_fraction", "jacobian", "other_equilibria",
                 "level", "boundary_min", "local_rates", "local_rate_max", "iteration"}
        return cls(passed=bool(data["passed"]), validation_states=int(data["validation_states"]),
                   max_violation=float(data["max_violation"]), violating_fraction=float(data["violating_fraction"]),
                   jacobian=dict(data["jacobian"]), other_equilibria=list(data["other_equilibria"]),
                   level=data.get("level"), boundary_min=data.get("boundary_min"),
                   local_rates=list(data.get("local_rates") or []), local_rate_max=data.get("local_rate_max"),
                   iteration=data.get("iteration"),
                   extra={k: v for k, v in data.items() if k not in known})


@dataclass
class ProofRound:
    """One proof round of counterexample-guided training (:func:`drlyap.training.train_cegis`).

    ``round``: 0 for the first training's pair, then one per retraining. ``verification``: the round's proof as
    ``ConditionProof.summary()`` writes it (for the DR uniform condition its margin, ``UniformMargin.to_dict()``),
    with its ``verified``, ``status`` and ``verified_fraction`` (None for the uniform margin);
    ``verify_time_s``, ``train_time_s`` (of the training before it) and ``train_iterations``; ``acceptance_passed``:
    that training's acceptance check. ``stopped``: why no retraining followed where that was the time budget. For a
    round followed by retraining, ``added``: how many states its falsifier added (``counterexamples_added``,
    ``neighbours_added``, ``box_centres_added``), its largest residual and seconds, and the retraining states in all
    (``extra_states``); ``counterexamples``: the violating local states found, ``(C, n)`` float64 (not in
    ``metrics.json``). ``unchanged``: the retraining before this round returned the very pair it started from (its
    weights bitwise equal), so this round proves that pair again.
    """

    round: int
    verification: dict
    verified: bool
    status: str
    verified_fraction: float | None
    verify_time_s: float
    train_time_s: float
    train_iterations: int
    acceptance_passed: bool
    stopped: str | None = None
    added: dict | None = None
    counterexamples: object = None
    unchanged: bool = False

    def to_dict(self) -> dict:
        """As ``metrics["cegis"]["rounds"]`` keeps it (without the counterexamples themselves)."""
        out = {"round": self.round, "verification": self.verification, "verified": self.verified,
               "status": self.status, "verified_fraction": self.verified_fraction,
               "verify_time_s": self.verify_time_s, "train_time_s": self.train_time_s,
               "train_iterations": self.train_iterations, "acceptance_passed": self.acceptance_passed}
        if self.stopped is not None:
            out["stopped"] = self.stopped
        if self.unchanged:
            out["unchanged"] = True
        return out | (self.added or {})

    @classmethod
    def from_dict(cls, data: dict) -> ProofRound:
        """From a round of ``metrics["cegis"]["rounds"]``."""
        base = ("round", "verification", "verified", "status", "verified_fraction", "verify_time_s", "train_time_s",
                "train_iterations", "acceptance_passed")
        added = {k: v for k, v in data.items() if k not in (*base, "stopped", "unchanged")}
        return cls(**{k: data[k] for k in base}, stopped=data.get("stopped"), added=added or None,
                   unchanged=bool(data.get("unchanged", False)))


@dataclass(frozen=True)
class TrainingRecord:
    """What a training recorded about the pair it returned (``metrics.json``'s training keys), read once.

    ``status``, ``passed``, ``iterations``, ``train_time_s``: the training run that gave the pair (``fit``'s words,
    whether its acceptance check passed, its iterations and seconds). ``acceptance``: that check. With proof rounds
    (``drlyap train``'s default): ``rounds`` (every proof round), ``returned_round``, ``retraining_rounds``,
    ``final_proof`` (the returned pair's verdict as ``ConditionProof.to_dict`` writes it); ``total_iterations`` and
    ``total_time_s`` count every round (the training run's own where there were no rounds).
    ``certificate_status``: the verdict on the trained condition (``verified``, ``violated``, ``unknown``,
    ``not checked``; None where the run has none). ``reshape``: the convex programs that grew a quadratic V's set
    after the first fit (:func:`drlyap.training.reshape.grow_quadratic`'s record; None where none ran)."""

    status: str
    passed: bool
    iterations: int
    train_time_s: float
    acceptance: AcceptanceCheck
    total_iterations: int
    total_time_s: float
    rounds: tuple[ProofRound, ...] = ()
    returned_round: int | None = None
    retraining_rounds: int | None = None
    final_proof: dict | None = None
    certificate_status: str | None = None
    reshape: dict | None = None

    @property
    def proved_in_rounds(self) -> bool:
        """Whether the training had proof rounds (counterexample-guided training)."""
        return self.retraining_rounds is not None

    @staticmethod
    def readable(metrics: dict) -> bool:
        """Whether ``metrics`` holds a training's record (an RL baseline's run, for one, does not)."""
        return all(k in metrics for k in ("status", "passed", "iterations", "train_time_s", "acceptance"))

    @classmethod
    def from_metrics(cls, metrics: dict) -> TrainingRecord:
        """From a run's ``metrics.json`` (or ``TrainResult.metrics``)."""
        cegis = metrics.get("cegis") or {}
        certificate = metrics.get("certificate") or {}
        iterations, seconds = int(metrics["iterations"]), float(metrics["train_time_s"])
        return cls(status=metrics["status"], passed=bool(metrics["passed"]), iterations=iterations,
                   train_time_s=seconds, acceptance=AcceptanceCheck.from_dict(metrics["acceptance"]),
                   total_iterations=int(cegis.get("total_iterations", iterations)),
                   total_time_s=float(cegis.get("total_time_s", seconds)),
                   rounds=tuple(ProofRound.from_dict(r) for r in cegis.get("rounds", ())),
                   returned_round=cegis.get("returned_round"), retraining_rounds=cegis.get("retraining_rounds"),
                   final_proof=cegis.get("final"), certificate_status=certificate.get("status"),
                   reshape=metrics.get("reshape"))
