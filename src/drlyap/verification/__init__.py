"""Sound verification of a closed loop's decrease conditions by branch and bound (SPEC §5, §6).

For a closed loop (:class:`~drlyap.closed_loop.ClosedLoop`: the system, V and pi) and a decrease condition of
:mod:`drlyap.conditions`, the verifier proves ``residual(z) <= 0`` for every local state ``z`` of a region X_delta
(the state box minus the open delta-ball, a :class:`drlyap.regions.Region`), or finds a state where it fails,
within a :class:`Budget`. It bounds exactly the objects training uses: the condition's own
``terms``/``components`` and the networks' and the system's own code, run on the enclosure types of
:mod:`drlyap.enclosures` (float64, outward rounded), so a verified box and a zero loss are about the same formula.
Every public function takes ``(loop, condition, region, budget)`` and returns a typed result of
:mod:`~drlyap.verification.results`.

Modules:

* :class:`~drlyap.proof_settings.Budget` (one proof's work) and :class:`~drlyap.proof_settings.ProofConfig` (every
  proof setting of a run) live in :mod:`drlyap.proof_settings`;
* :mod:`~drlyap.verification.results` -- the typed results;
* :mod:`~drlyap.verification.bounds` -- bounds of a function over boxes (interval, mean-value and affine forms);
* :mod:`~drlyap.verification.branch_and_bound` -- :func:`verify_condition`, :func:`maximize`, :func:`uniform_margin`;
* :mod:`~drlyap.verification.sublevel` -- the condition on ``{V <= level}`` with V above the level on the faces
  (:func:`verify_sublevel`), and :func:`prove_trained`: a run's trained condition, settled by the falsifier where
  the proof runs out;
* :mod:`~drlyap.verification.falsifier` -- gradient search for counterexamples (:func:`falsify`) and
  :func:`settle_unknown`;
* :mod:`~drlyap.verification.roa` -- certified regions of attraction (:func:`certified_roa`), one module per proof;
* :mod:`~drlyap.verification.linearisation` -- the closed loop's linearisation and its quadratic Lyapunov function;
* :mod:`~drlyap.verification.robustness` -- :func:`certified_radius` (the largest proved Wasserstein radius) and
  :func:`certified_shift_box` (the largest proved box of shifts on the true model);
* :mod:`~drlyap.verification.covering` -- the paper's Lipschitz covering check.
"""

from drlyap.proof_settings import ENCLOSURES, Budget, ProofConfig, default_enclosure
from drlyap.verification.bounds import box_bounds, combine_lower, combine_upper, condition_objective
from drlyap.verification.branch_and_bound import (
    Exempt,
    ProofRules,
    StartFrom,
    maximize,
    uniform_margin,
    verify_condition,
)
from drlyap.verification.covering import lipschitz_covering
from drlyap.verification.falsifier import falsify, settle_unknown
from drlyap.verification.results import (
    Certificate,
    CertifiedRadius,
    CertifiedShiftBox,
    ConditionProof,
    CoveringCheck,
    ProofAttempt,
    RegionOfAttraction,
    RunRobustness,
    RunVerification,
    UniformMargin,
)
from drlyap.verification.roa import certified_roa, local_decrease
from drlyap.verification.robustness import (
    SearchLimits,
    certified_radius,
    certified_shift_box,
    shift_box_condition,
    shift_scale,
)
from drlyap.verification.sublevel import boundary_minimum, prove_trained, verify_sublevel

__all__ = [
    "ENCLOSURES", "Budget", "Certificate", "CertifiedRadius", "CertifiedShiftBox", "ConditionProof", "Exempt",
    "CoveringCheck", "ProofAttempt", "ProofConfig", "ProofRules", "RegionOfAttraction", "SearchLimits", "StartFrom",
    "RunRobustness",
    "RunVerification", "UniformMargin", "boundary_minimum", "box_bounds", "certified_radius", "certified_roa",
    "certified_shift_box", "combine_lower", "combine_upper", "condition_objective", "default_enclosure", "falsify",
    "lipschitz_covering", "local_decrease", "maximize", "prove_trained", "settle_unknown", "shift_box_condition",
    "shift_scale", "uniform_margin", "verify_condition", "verify_sublevel",
]
