"""Enclosure arithmetic: batched intervals, affine forms and forward-mode dual numbers over them, outward rounded.

A numeric layer that imports only torch. The networks, the systems' dynamics and the decrease conditions are
written once with torch operations; run on these types instead of tensors, the same code returns sound
enclosures of its values and derivatives over boxes. That is how the verifier bounds exactly what training
minimises (no second encoding of any formula).

* :class:`Interval` (:mod:`~drlyap.enclosures.interval`) -- batched interval tensors ``[lo, hi]`` (any shape),
  float64, outward rounded: every computed endpoint is widened by an error bound of the floating-point operation
  that produced it (:mod:`~drlyap.enclosures.rounding`), so it encloses the real value.
* :class:`Affine` (:mod:`~drlyap.enclosures.affine`) -- batched affine forms
  ``c + sum_k g_k e_k + sum_kl q_kl e_k e_l + [r_lo, r_hi]`` over noise symbols ``e_k in [-1, 1]`` (one per box
  dimension, separate for every box of the batch), with an optional exact quadratic part (second-order Taylor
  models); coefficients and remainders are outward rounded as intervals are. Much tighter than intervals over
  boxes because correlations between the coordinates survive. Its linear and quadratic parts are bounded jointly
  by :func:`quadratic_max` (:mod:`~drlyap.enclosures.quadratic`).
* :class:`Dual` (:mod:`~drlyap.enclosures.dual`) -- forward-mode dual numbers whose value and derivative are
  themselves enclosures (intervals, affine forms or duals).
* All implement ``__torch_function__`` and the Python operators (:mod:`~drlyap.enclosures.base`), so code written
  with ``+ - * /``, ``**`` by an int, ``torch.sin/cos/tanh/exp/sqrt/square``, ``torch.stack/cat``, ``unbind``,
  indexing, ``torch.nn.functional.linear`` (so ``nn.Linear`` layers) and ``torch.linalg.vector_norm`` runs
  unchanged on them. Weights met in ``linear`` are read as float64 numbers (exactly); within
  :func:`weight_gradients` they keep their autograd graph, so that a bound can be trained on.

How affine forms enclose each operation:
Linear operations (``+ -``, products with constants, ``linear``, ``sum``, stacking, indexing) are exact
on the linear and quadratic parts. ``x * y`` keeps both first-order parts and the product of the linear
parts (as ``q``), and bounds the other products of deviations (third order and remainders) by intervals.
The smooth unary functions (``tanh``, ``sin``, ``cos``, ``exp``, ``1 / x``) use the second-order Taylor form
about the centre (:meth:`_second_order`: ``f'(c) (x - c)`` and ``f''(c) L^2 / 2`` kept, a third-order
Lagrange remainder over the range); where an input's range is wide, elementwise the first-order form
instead when its error is the smaller (a secant slope with an exact-by-convexity error bound for ``tanh``,
``exp``, ``1 / x``; the midpoint slope with a second-order remainder for ``sin``, ``cos``). ``square`` is
``x * x``; ``sqrt`` keeps the secant form (its quadratic input part passes through scaled by the slope).
Every function falls back elementwise to the interval enclosure where its remainder alone is as wide.
``clamp`` and ``abs`` use the secant with the error's exact range (it is piecewise
linear).
"""

from drlyap.enclosures.affine import Affine
from drlyap.enclosures.base import (
    Enclosure,
    cat,
    constant_like,
    is_enclosure,
    level_of,
    lift,
    lift_pair,
    norm,
    stack,
    weight_gradients,
)
from drlyap.enclosures.dual import Dual
from drlyap.enclosures.interval import Interval
from drlyap.enclosures.quadratic import max_lin_quad, quadratic_max, vertices
from drlyap.enclosures.rounding import EPS, F64, REL1, RELT, TINY, as_f64, round_down, round_up, sum_up

__all__ = [
    "EPS", "F64", "REL1", "RELT", "TINY", "Affine", "Dual", "Enclosure", "Interval", "as_f64", "cat", "constant_like",
    "is_enclosure", "level_of", "lift", "lift_pair", "max_lin_quad", "norm", "quadratic_max", "round_down",
    "round_up", "stack", "sum_up", "vertices", "weight_gradients",
]
