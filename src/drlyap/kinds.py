"""The closed sets of words drlyap's settings and results are made of, one string enum each: a member equals its
string (``Method.DR == "dr"``), JSON writes it as that string, and ``Method("dr")`` reads it back, so run directories
and user code that pass strings keep working. Imports nothing.
"""

from __future__ import annotations

from enum import StrEnum


class Method(StrEnum):
    """How a pair is trained: on the DR condition at every sample (``dr``), or on the nominal condition at the
    samples' mean (``baseline``)."""

    DR = "dr"
    BASELINE = "baseline"


class Loss(StrEnum):
    """Which DR condition a ``dr`` pair trains on: the pointwise one (a residual per state) or the uniform one."""

    POINTWISE = "pointwise"
    UNIFORM = "uniform"


class Model(StrEnum):
    """Which dynamics a decrease condition is about: the control-affine design model ``f + W xi`` or the TRUE
    parametric model ``F(x, u, p0 + E xi)``."""

    DESIGN = "design"
    TRUE = "true"


class Status(StrEnum):
    """How a proof ended: proved at every state (``verified``), a state where the condition fails (``violated``), the
    budget ran out first (``unknown``), or the condition could not be evaluated (``error``)."""

    VERIFIED = "verified"
    VIOLATED = "violated"
    UNKNOWN = "unknown"
    ERROR = "error"


class Enclosure(StrEnum):
    """How the verifier bounds a function over a box: the tighter of the interval bound and the mean-value form
    (``mean-value``), or second-order affine forms (``affine``)."""

    MEAN_VALUE = "mean-value"
    AFFINE = "affine"


def choice(kind: type[StrEnum], value: object, what: str) -> StrEnum:
    """``value`` as a member of ``kind``, or a ValueError naming ``what`` and the valid words."""
    try:
        return kind(value)
    except ValueError:
        raise ValueError(f"unknown {what} {value!r}; valid: {', '.join(m.value for m in kind)}") from None
