"""An independent checker of certificate files (``drlyap check RUN``): a small float64 interval arithmetic of its own
(:mod:`~drlyap.checker.arith`), its own reading of V, pi and the claimed condition (:mod:`~drlyap.checker.model`),
and the box-by-box check (:mod:`~drlyap.checker.check`). It shares no bounding code with the verifier."""

from drlyap.checker.check import CheckResult, check_run

__all__ = ["CheckResult", "check_run"]
