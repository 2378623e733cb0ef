"""Sound verification of the learned decrease condition by branch and bound (SPEC §5, §6).

For a trained pair (V, pi) and a decrease condition of :mod:`drlyap.conditions`, the verifier proves
``residual(z) <= 0`` for every local state ``z`` of X_delta (the state box minus the open delta-ball, a
:class:`drlyap.regions.Region`), or finds a state where it fails. It bounds exactly the objects training
uses: the condition's own ``terms``/``components`` and the networks' and the system's own code, run on
the enclosure types of :mod:`drlyap.enclosures` (float64, outward rounded), so a verified box and a zero
loss are about the same formula.

Modules:

* :mod:`~drlyap.verification.bounds` -- bounds of a function over boxes (interval and mean-value forms);
* :mod:`~drlyap.verification.branch_and_bound` -- :func:`verify_condition`, :func:`maximize`, :func:`uniform_margin`;
* :mod:`~drlyap.verification.roa` -- :func:`certified_roa` (regions of attraction reaching x*, or practical
  stability where the proof inside the ball fails), :func:`local_decrease`, and :func:`verify_sublevel` /
  :func:`prove_trained` (the condition of region-of-attraction training: on ``{V <= level}``, V above the
  level on the box's faces); where a proof runs out of time, :func:`prove_trained` asks the falsifier;
* :mod:`~drlyap.verification.falsifier` -- gradient search for counterexamples (:func:`falsify`) and
  :func:`settle_unknown`: an ``unknown`` proof becomes ``violated`` at a state where a violation is certain;
* :mod:`~drlyap.verification.covering` -- the paper's Lipschitz covering check;
* :mod:`~drlyap.verification.runs` -- :func:`run_condition`, :func:`verify_run` on run directories;
* :mod:`~drlyap.verification.robustness` -- :func:`certified_radius` (the largest proved Wasserstein radius),
  :func:`certified_shift_box` (the largest proved box of shifts on the true model), :func:`run_robustness`.
"""

from drlyap.enclosures import Affine, Dual, Interval, norm
from drlyap.verification.bounds import (
    ENCLOSURES,
    box_bounds,
    combine_lower,
    combine_upper,
    condition_objective,
    default_enclosure,
)
from drlyap.verification.branch_and_bound import (
    VerificationResult,
    as_region,
    maximize,
    uniform_margin,
    verify_condition,
)
from drlyap.verification.covering import lipschitz_covering
from drlyap.verification.falsifier import falsify, settle_unknown
from drlyap.verification.roa import certified_roa, local_decrease, prove_trained, verify_sublevel
from drlyap.verification.robustness import (
    certified_radius,
    certified_shift_box,
    run_robustness,
    shift_box_condition,
    shift_scale,
)
from drlyap.verification.runs import run_condition, verify_run

__all__ = [
    "ENCLOSURES", "Affine", "Dual", "Interval", "VerificationResult", "as_region", "box_bounds", "certified_roa", "combine_lower",
    "certified_radius", "certified_shift_box", "combine_upper", "condition_objective", "default_enclosure",
    "falsify", "lipschitz_covering", "local_decrease", "maximize", "norm", "prove_trained", "run_condition", "run_robustness",
    "settle_unknown", "shift_box_condition", "shift_scale", "uniform_margin", "verify_condition", "verify_run", "verify_sublevel",
]
