"""An independent checker of certificate files (``drlyap check RUN``): a small float64 interval arithmetic of its own
(:mod:`~drlyap.checker.arith`), its own reading of V, pi and the claimed condition (:mod:`~drlyap.checker.model`),
the box-by-box check (:mod:`~drlyap.checker.check`) and the check of a run's certificates together
(:mod:`~drlyap.checker.run`). It shares no bounding code with the verifier."""

from drlyap.checker.check import CheckResult
from drlyap.checker.run import check_run

__all__ = ["CheckResult", "check_run"]
