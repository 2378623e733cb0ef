"""What a proof returns: typed results that know what they claim.

Each result carries its claim (the condition, the region it is about -- X_delta, or ``{V <= level}`` of it --,
the shift ``xi`` or the radius, ``delta``), its ``status`` and the numbers behind it. ``to_dict()`` is its JSON
(the form stored in ``metrics.json`` and printed by ``--json``), ``from_dict()`` reads it back. Every sentence the
tool prints about a result comes from :mod:`drlyap.render`; no caller decides again from the numbers what was
proved.

* :class:`ConditionProof` -- a per-state decrease condition proved (or not) by branch and bound on X_delta or on a
  sublevel set ``{V <= level}`` of it;
* :class:`UniformMargin` -- the uniform DR condition's left side bounded over X_delta;
* :class:`RegionOfAttraction` -- a certified sublevel set of V (or only practical stability, or nothing), with the
  closed loop's own quadratic ellipsoid where V's sets are not certified;
* :class:`BandProof` -- the band claim: decrease on ``c1 <= V <= c2`` with the flow entering the box on its faces;
* :class:`CertifiedRadius`, :class:`CertifiedShiftBox` -- the largest proved Wasserstein radius and box of shifts;
* :class:`Certificate` -- the verdict on a run's trained condition, as ``metrics["certificate"]`` records it;
* :class:`RunRobustness`, :class:`RunVerification` -- everything ``drlyap verify`` proves about a run;
* :class:`ProofAttempt` -- what a run of any kind proves at a shift (``drlyap compare``);
* :class:`CoveringCheck` -- the paper's Lipschitz covering certificate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

from drlyap.kinds import Status
from drlyap.verification.result_base import Result
from drlyap.verification.result_base import known as _known
from drlyap.verification.roa_steps import BandRegion, NearProof, QuadraticRegion, Strictness, near_proof_from_dict
from drlyap.wording import condition_region

STATUSES = (Status.VERIFIED, Status.VIOLATED, Status.UNKNOWN)


# --------------------------------------------------------------------------- the condition on a region
@dataclass
class ConditionProof(Result):
    """A per-state condition on X_delta (the state box minus the open ``delta``-ball around x*), or with a
    ``level`` on ``{V <= level}`` of it together with ``V > level`` on the box's faces.

    ``status``: ``verified`` (proved at every state of the region), ``violated`` (a state where the residual is
    > 0, re-checked by direct evaluation, or by the falsifier: ``counterexample_source``) or ``unknown`` (budget
    or time ran out, or boxes reached the minimum size). ``verified_fraction`` is a lower bound of the share of
    X_delta's volume proved (the condition, or ``V > level``). ``sup_bounds``: ``[lower, upper]`` of the
    residual's maximum over the region found on the way. Counterexamples: ``counterexample`` in user
    coordinates, ``counterexample_local`` in local ones, ``counterexample_value`` the float64 residual there,
    ``counterexample_value_float32`` with the networks in float32. ``xi``: the shift of the true model the
    condition is about, when it is one. ``boundary_min_lower`` / ``_upper``: V's minimum on the faces (sublevel
    proofs). ``falsifier``: the search that settled an unknown proof. ``resumed_boxes``: boxes an earlier, interrupted
    run of the same proof had bounded (kept in its checkpoint; ``boxes_processed`` and ``time_s`` count both runs'
    boxes and this run's time). ``source``: ``certificate`` where the verdict is a certificate file that the checker
    confirmed instead of a new proof (``boxes_processed`` is then the certificate's; ``checked_at`` the date of a
    recorded confirmation of the same files, where the checker did not run again). ``partition``: the tree of boxes a verified
    branch and bound proved it on (:class:`~drlyap.verification.partition.Partition`; not part of the JSON, written
    as a certificate file by :mod:`drlyap.runs.certificates`).
    """

    OPTIONAL: ClassVar[tuple[str, ...]] = ("boundary_min_lower", "boundary_min_upper", "counterexample_source",
                                           "falsifier", "xi", "resumed_boxes", "source", "checked_at")
    condition: str
    status: str
    verified_fraction: float
    delta: float
    boxes_processed: int = 0
    boxes_verified: int = 0
    time_s: float = 0.0
    counterexample: list[float] | None = None
    counterexample_local: list[float] | None = None
    counterexample_value: float | None = None
    counterexample_value_float32: float | None = None
    n_counterexample_boxes: int = 0
    n_unverified: int = 0
    unverified_boxes: list[dict] = field(default_factory=list)
    sup_bounds: list[float] = field(default_factory=list)
    stopped: str = ""
    level: float | None = None
    boundary_min_lower: float | None = None
    boundary_min_upper: float | None = None
    counterexample_source: str | None = None
    falsifier: dict | None = None
    xi: list[float] | None = None
    resumed_boxes: int | None = None
    source: str | None = None
    checked_at: str | None = None
    partition: Any = field(default=None, repr=False, compare=False, metadata={"json": False})

    @property
    def verified(self) -> bool:
        return self.status == Status.VERIFIED

    SUMMARY: ClassVar[tuple[str, ...]] = ("condition", "status", "verified_fraction", "delta", "boxes_processed", "time_s",
                                          "stopped", "counterexample", "counterexample_value", "counterexample_source",
                                          "n_unverified", "n_counterexample_boxes", "sup_bounds", "level",
                                          "boundary_min_lower")

    def summary(self) -> dict:
        """The fields a training round records (no box lists; non-finite bounds as None)."""
        out = {k: getattr(self, k) for k in self.SUMMARY}
        out["sup_bounds"] = [v if v is not None and math.isfinite(v) else None for v in (self.sup_bounds or [])]
        return out


@dataclass
class UniformMargin(Result):
    """Bounds of the uniform DR condition's left side over X_delta (``eq: dr_clf_constraint_relaxed``)::

        margin = (r/eps) sup_z ||W^T grad V(z)|| + CVaR_eps_j sup_z (Vdot_j(z) + decay(z))

    ``margin_upper`` is sound (``verified`` when it is <= 0); ``margin_lower`` is attained at evaluated states
    (``violated`` when it is > 0); ``lipschitz_sup``, ``h_sup`` and ``lipschitz_term`` the pieces' brackets.
    ``attained_at``: the local states ``(1 + N, n)`` at which each component's lower bound was found (where the
    suprema lie, up to the search's tolerance). ``partition``: the boxes a verified margin was bounded on (not part
    of the JSON; written as a certificate). It is a claim on all of X_delta: no level, no faces."""

    OPTIONAL: ClassVar[tuple[str, ...]] = ("attained_at",)

    condition: str
    status: str
    margin_upper: float | None
    margin_lower: float | None
    lipschitz_sup: list
    h_sup: list
    lipschitz_term: list
    delta: float
    boxes_processed: int = 0
    time_s: float = 0.0
    stopped: str = ""
    attained_at: list | None = None
    partition: Any = field(default=None, repr=False, compare=False, metadata={"json": False})
    level: ClassVar[None] = None
    boundary_min_lower: ClassVar[None] = None

    @property
    def verified(self) -> bool:
        return self.status == Status.VERIFIED

    @property
    def verified_fraction(self) -> None:
        """The uniform condition is one inequality over the region: no share of it is proved."""
        return None


# --------------------------------------------------------------------------- regions of attraction
@dataclass
class BallProof:
    """V's decrease inside the delta-ball (:func:`~drlyap.verification.roa.local_decrease`): ``Vdot < 0`` on the
    cube ``|z_i| <= cube_i`` minus x* (second order), and ``condition`` (plain decrease with a small decay, per
    sample) on ``region`` (the ball's box minus the open ball of radius ``min(cube)``), proved by ``ring`` (with its
    partition; None where the cube covers the ball)."""

    cube: list[float]
    condition: Any = None
    region: Any = None
    ring: ConditionProof | None = None


@dataclass
class RegionOfAttraction(Result):
    """The largest level ``c`` found with ``S = {V <= c}`` certified, and what is certified about it.

    ``kind``: ``"region of attraction"`` (every trajectory of the condition's model from S converges to x*:
    ``certified``), ``"practical stability"`` (trajectories from S end up in ``{V <= practical_level}``) or None.
    ``local``: the proof near x* (:mod:`~drlyap.verification.roa_steps`; its ``method``: ``second order``,
    ``mean-value Jacobian``, ``linearisation`` or ``band``), ``outer_level`` the level proved outside the
    delta-ball, ``share_of_box`` the share of the state box in S (estimated), ``limited_by`` what stopped the level,
    ``counterexample`` one that did. ``quadratic``: where no sublevel set of V is certified, the closed loop's own
    certified ellipsoid ``{z^T P z <= q_level}`` (not V's); ``band``: the band proof's search; ``strict``: how the
    decrease outside the ball is strict (:func:`~drlyap.verification.roa.sublevel.outer_strictness`; None where no
    level was found). ``xi``: the true model's shift the region is about (None: the condition's own model).
    ``error``: why no search ran (then nothing else is set). ``faces``: how S keeps off the state box's faces:
    ``"above"`` (V above the level there) or ``"inward"`` (S is ``{V <= c}`` cut by the box, and wherever it meets a
    face the flow enters the box; ``exit_min_lower``: V's lower bound where the flow may leave,
    :func:`~drlyap.verification.sublevel.exit_minimum`).
    """

    OPTIONAL: ClassVar[tuple[str, ...]] = ("xi", "error", "exit_min_lower")
    level: float | None = None
    kind: str | None = None
    certified: bool = False
    practical_level: float | None = None
    outer_level: float | None = None
    contains_ball: bool = False
    limited_by: str | None = None
    local: NearProof | None = None
    boundary_min_lower: float | None = None
    ball_max_upper: float | None = None
    share_of_box: float = 0.0
    counterexample: list[float] | None = None
    boxes_processed: int = 0
    time_s: float = 0.0
    delta: float | None = None
    condition: str | None = None
    quadratic: QuadraticRegion | None = None
    band: BandRegion | None = None
    strict: Strictness | None = None
    xi: list[float] | None = None
    error: str | None = None
    faces: str = "above"
    exit_min_lower: float | None = None
    ball: BallProof | None = field(default=None, repr=False, compare=False, metadata={"json": False})
    """Where the set is certified by V's second-order decrease near x*: that proof, what a certificate of the region
    inside the delta-ball writes down (None for the other routes)."""

    @classmethod
    def unavailable(cls, reason: str) -> RegionOfAttraction:
        """No search was possible (e.g. the uniform DR condition has no per-state residual)."""
        return cls(error=reason)

    NESTED: ClassVar[dict[str, type]] = {"quadratic": QuadraticRegion, "band": BandRegion, "strict": Strictness}

    def to_dict(self) -> dict:
        return {"error": self.error} if self.error is not None else super().to_dict()

    @classmethod
    def from_dict(cls, data: dict) -> RegionOfAttraction:
        found = super().from_dict(data)
        found.local = near_proof_from_dict(data.get("local"))
        return found

    @property
    def method(self) -> str | None:
        """How the set was proved near x* (``local.method``)."""
        return None if self.local is None else self.local.method

    @property
    def beyond_ellipsoid(self) -> bool | None:
        """For a band proof: whether the set reaches beyond the closed loop's ellipsoid (sampled); else None."""
        return self.local.beyond_ellipsoid if isinstance(self.local, BandRegion) else None

    @property
    def ellipsoid_certified(self) -> bool:
        """Whether the closed loop's own quadratic region (``quadratic``) is certified."""
        return self.quadratic is not None and self.quadratic.proved


# --------------------------------------------------------------------------- the covering check
@dataclass
class CoveringCheck(Result):
    """The paper's Lipschitz covering certificate on a grid of X_delta (``lemma: nominal_nn_lf``).

    ``certified`` (sound): ``max_residual`` (a sound bound at the cell centres) ``<= -lipschitz_sound *
    covering_radius``; ``certified_estimate`` the same with ``safety`` times the largest sampled gradient
    (``lipschitz_sampled``, not sound). ``spacing_needed`` / ``samples_needed``: the grid at which the sound test
    would pass with the same constant and maximum (None when the maximum is >= 0). ``verifier``: the branch and
    bound on the same condition, for comparison."""

    LIPSCHITZ_NOTE: ClassVar[str] = ("lipschitz_sound: interval enclosure of the gradient over every cell (sound); "
                                     "lipschitz_sampled: max gradient norm at the centres (an estimate from below)")
    condition: str
    delta: float
    spacing: float
    per_axis: list[int]
    cells: int
    covering_radius: float
    max_residual: float
    max_residual_float64: float
    max_residual_in_x_delta: float
    lipschitz_sound: float
    lipschitz_sampled: float
    safety: float
    required_max_residual: float
    certified: bool
    certified_estimate: bool
    spacing_needed: float | None = None
    samples_needed: float | None = None
    verifier: ConditionProof | None = None
    time_s: float = 0.0

    def to_dict(self) -> dict:
        out = super().to_dict()
        out["lipschitz_note"] = self.LIPSCHITZ_NOTE
        return out

    @classmethod
    def from_dict(cls, data: dict) -> CoveringCheck:
        out = cls(**_known(cls, data))
        if isinstance(out.verifier, dict):
            out.verifier = ConditionProof.from_dict(out.verifier)
        return out


# --------------------------------------------------------------------------- robustness
@dataclass
class _Search(Result):
    """The bracket ``certified <= v* < unproved`` of a bisection on proofs (:mod:`drlyap.verification.robustness`)."""

    unproved: float | None = None
    unproved_status: str | None = None
    unproved_by: str | None = None
    witness: dict | None = None
    relative_gap: float | None = None
    stopped: str = ""
    reason: str | None = None
    proofs: int = 0
    probes: list = field(default_factory=list)
    time_s: float = 0.0
    sampled_upper: float | None = None
    decay_rate: float = 0.0
    exp_rate: float = 0.0
    delta: float = 0.0
    level: float | None = None  # proved on {V <= level} of X_delta only (a region-of-attraction run's set)


@dataclass
class CertifiedRadius(_Search):
    """The largest Wasserstein radius ``radius`` (r*) for which the DR pointwise condition (risk level
    ``risk_level``, ``n_samples`` samples, the decay terms) is proved over X_delta; None when not even at 0."""

    quantity: str = "wasserstein_radius"
    radius: float | None = None
    risk_level: float = 0.1
    n_samples: int = 0
    condition_radius: float = 0.0
    proof: Any = field(default=None, repr=False, compare=False, metadata={"json": False})
    """The :class:`ConditionProof`, with its partition, of the search's own proof at r* (None where r* is the radius
    of an earlier proof, or none is proved): what a certificate of the radius writes down."""


@dataclass
class CertifiedShiftBox(_Search):
    """The largest ``s`` for which decrease on the TRUE model is proved over X_delta for every shift in the box
    ``[-s scale, s scale]`` (``box``: per parameter, in its units); None when not even at xi = 0."""

    quantity: str = "shift_box"
    s: float | None = None
    box: dict | None = None
    scale: list[float] = field(default_factory=list)
    parameters: list[str] = field(default_factory=list)
    proof: Any = field(default=None, repr=False, compare=False, metadata={"json": False})
    """The :class:`ConditionProof`, with its partition, of the search's proof at s* (None where none is proved): what
    a certificate of the shift box writes down."""


@dataclass
class RunRobustness(Result):
    """A run's certified radius (at its samples) and shift box; for a baseline run also the radius around the one
    sample it trained on (their mean)."""

    OPTIONAL: ClassVar[tuple[str, ...]] = ("radius_training_sample",)
    method: str
    trained_radius: float | None
    delta: float
    radius: CertifiedRadius
    shift_box: CertifiedShiftBox
    radius_training_sample: CertifiedRadius | None = None

    @classmethod
    def from_dict(cls, data: dict) -> RunRobustness:
        own = data.get("radius_training_sample")
        return cls(data["method"], data.get("trained_radius"), data["delta"], CertifiedRadius.from_dict(data["radius"]),
                   CertifiedShiftBox.from_dict(data["shift_box"]), None if own is None else CertifiedRadius.from_dict(own))


@dataclass
class ProofAttempt(Result):
    """What a run of any kind proves at a shift on the true model (``drlyap compare``): the decrease condition's
    ``status`` and proved share (``"none"`` for a run with nothing to prove) on X_delta, or with ``level`` on
    ``{V <= level}`` of it, the certified region of attraction (``roa_certified``, ``roa_kind``, ``roa_share``), the
    decay asked (``decay_rate``; ``exp_rate`` for LQR's scale-free ``alpha z'Pz``) and the robustness searches'
    numbers (``robustness``)."""

    OPTIONAL: ClassVar[tuple[str, ...]] = ("exp_rate", "note", "counterexample", "time_s", "roa_kind", "decay_rate",
                                           "level")
    status: str
    verified_fraction: float | None = None
    counterexample: list[float] | None = None
    time_s: float | None = None
    roa_certified: bool | None = None
    roa_kind: str | None = None
    roa_share: float | None = None
    decay_rate: float | None = None
    exp_rate: float | None = None
    robustness: dict | None = None
    note: str | None = None
    level: float | None = None


# --------------------------------------------------------------------------- a run's certificate and verification
@dataclass
class Certificate(Result):
    """What was proved about a run's trained condition (``metrics["certificate"]``): ``status`` ``verified``,
    ``violated``, ``unknown`` or ``not checked``; ``level`` the sublevel set it is about (None: all of X_delta);
    ``rounds`` the retraining rounds; ``true_model`` and ``roa``: the run's decrease at the test shift and its
    certified region there, where a reproduction proved them."""

    OPTIONAL: ClassVar[tuple[str, ...]] = ("true_model", "roa")
    status: str
    condition: str
    region: str | None = None
    level: float | None = None
    delta: float | None = None
    verified_fraction: float | None = None
    time_s: float | None = None
    boxes: int | None = None
    counterexample: list[float] | None = None
    counterexample_source: str | None = None
    rounds: int | None = None
    margin_upper: float | None = None
    true_model: dict | None = None
    roa: dict | None = None

    @property
    def verified(self) -> bool:
        return self.status == Status.VERIFIED

    @classmethod
    def of(cls, proof: ConditionProof | UniformMargin, delta: float, rounds: int | None = None) -> Certificate:
        """What ``proof`` of a run's trained condition established: ``status`` ``verified`` (proved at every state of
        X_delta = the state box minus the open ball of radius ``delta`` around x*; with a ``level`` in the proof, at
        every state of X_delta with ``V <= level``, and ``V > level`` on the box's boundary), ``violated`` (a
        counterexample state, re-checked) or ``unknown`` (time or box budget ran out); ``verified_fraction`` a lower
        bound of the share of X_delta proved; ``rounds`` the retraining rounds before it."""
        level = getattr(proof, "level", None)
        return cls(status=proof.status, condition=proof.condition, region=condition_region(level, delta), level=level,
                   delta=delta, verified_fraction=proof.verified_fraction, time_s=proof.time_s,
                   boxes=proof.boxes_processed, counterexample=getattr(proof, "counterexample", None),
                   counterexample_source=getattr(proof, "counterexample_source", None), rounds=rounds,
                   margin_upper=getattr(proof, "margin_upper", None))

    def to_dict(self) -> dict:
        if self.status == "not checked":
            return {"status": self.status, "condition": self.condition}
        return super().to_dict()

    def region_of_attraction(self) -> RegionOfAttraction | None:
        """The certified region stored with the certificate, with the shift it is about, or None."""
        if not isinstance(self.roa, dict) or "level" not in self.roa:
            return None
        roa = RegionOfAttraction.from_dict(self.roa)
        if "xi" not in self.roa and self.true_model:  # older runs kept the shift with the true model's proof only
            roa.xi = self.true_model.get("xi")
        return roa


@dataclass
class BandProof(Result):
    """The band claim's verdict (:mod:`~drlyap.verification.band_claim`). ``low``, ``high``: ``c1``, ``c2``; ``xi``:
    the shift of the true model; ``exp_rate``: the ``alpha`` of the decrease asked on the band; ``decrease``: the
    branch and bound on the band (its ``partition`` is the certificate's); ``exit_min_lower`` / ``exit_min_upper``: V's
    least value where the flow may leave the box through a face (lower bound, and a value at a face point where it
    does: ``inf`` where none), which must exceed ``c2``. ``status``: ``verified`` where both hold, ``violated`` where a
    state of the band breaks the decrease or a face point with ``V <= c2`` has the flow leaving or running along the
    face, else ``unknown`` (``reason``). ``asked``: the condition proved on the band (:mod:`drlyap.conditions`; not part
    of the JSON, written into the certificate)."""

    OPTIONAL: ClassVar[tuple[str, ...]] = ("xi",)
    low: float
    high: float
    status: str
    exp_rate: float
    decrease: ConditionProof
    exit_min_lower: float
    exit_min_upper: float
    time_s: float
    reason: str = ""
    xi: list[float] | None = None
    asked: Any = field(default=None, repr=False, compare=False, metadata={"json": False})

    @property
    def verified(self) -> bool:
        return self.status == Status.VERIFIED

    @property
    def condition(self) -> str:
        return self.decrease.condition

    @property
    def verified_fraction(self) -> float:
        """A lower bound of the share of the state box where the decrease, or V outside the band, is proved."""
        return self.decrease.verified_fraction

    @property
    def counterexample(self) -> list[float] | None:
        return self.decrease.counterexample

    @property
    def counterexample_value(self) -> float | None:
        return self.decrease.counterexample_value

    @classmethod
    def from_dict(cls, data: dict) -> BandProof:
        return cls(**_known(cls, data) | {"decrease": ConditionProof.from_dict(data["decrease"])})


@dataclass
class RunVerification(Result):
    """Everything ``drlyap verify`` proves about a run: its trained condition (a :class:`ConditionProof`, or a
    :class:`UniformMargin` for the uniform DR condition), the uniform DR margin when asked, with a shift the decrease on the
    true model there (``true_model``), the certified region (``roa``), the robustness searches and a band claim
    (``band``, :class:`BandProof`).

    ``main`` is what the run's status is about: the true model at the shift when one was given, else the trained
    condition."""

    OPTIONAL: ClassVar[tuple[str, ...]] = ("uniform", "true_model", "robustness", "roa_rate", "band")
    run_dir: str
    system: str
    method: str
    loss: str | None
    delta: float
    enclosure: str
    trained: Any
    uniform: UniformMargin | None = None
    true_model: ConditionProof | None = None
    roa: RegionOfAttraction | None = None
    robustness: RunRobustness | None = None
    roa_rate: float | None = None  # the decay alpha V asked at the shift where it is not the run's
    band: BandProof | None = None

    @property
    def main(self):
        """The true model's decrease where it was proved, else the trained condition, else the band claim (an imported
        pair asked only that)."""
        for proof in (self.true_model, self.trained, self.band):
            if proof is not None:
                return proof
        raise ValueError("a verification holds no proof")

    @property
    def status(self) -> str:
        return self.main.status

    def outcome(self) -> str:
        """The verdict on everything that was asked: ``verified`` where every condition proved holds and the region
        asked for (``roa``) is certified (V's, or the closed loop's own ellipsoid); ``violated`` where a condition has
        a counterexample; else ``unknown``. The robustness searches report values, not verdicts."""
        proofs = [p for p in (self.trained, self.uniform, self.true_model, self.band) if p is not None]
        if any(p.status == Status.VIOLATED for p in proofs):
            return Status.VIOLATED
        region = self.roa is None or (self.roa.error is None and (self.roa.certified or self.roa.ellipsoid_certified))
        return Status.VERIFIED if region and all(p.status == Status.VERIFIED for p in proofs) else Status.UNKNOWN

    def to_dict(self) -> dict:
        out = super().to_dict()
        out["outcome"] = self.outcome()
        out["roa"] = None if self.roa is None else self.roa.to_dict()
        main = self.main
        out.update(status=main.status, condition=main.condition, verified_fraction=main.verified_fraction,
                   counterexample=getattr(main, "counterexample", None),
                   counterexample_value=getattr(main, "counterexample_value", None), time_s=main.time_s)
        return out

    @classmethod
    def from_dict(cls, data: dict) -> RunVerification:
        proof = proof_from_dict
        roa = data.get("roa")
        rob = data.get("robustness")
        band = None if data.get("band") is None else BandProof.from_dict(data["band"])
        return cls(data["run_dir"], data["system"], data["method"], data.get("loss"), data["delta"], data["enclosure"],
                   proof(data["trained"]), proof(data.get("uniform")), proof(data.get("true_model")),
                   None if roa is None else RegionOfAttraction.from_dict(roa),
                   None if rob is None else RunRobustness.from_dict(rob), data.get("roa_rate"), band)


def proof_from_dict(data: dict | None) -> ConditionProof | UniformMargin | None:
    """A condition's proof as its ``to_dict`` wrote it: the uniform DR condition's margin where it holds one, else a
    :class:`ConditionProof`; None stays None."""
    if data is None:
        return None
    return UniformMargin.from_dict(data) if "margin_upper" in data else ConditionProof.from_dict(data)
