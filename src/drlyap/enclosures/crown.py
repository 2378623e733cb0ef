"""Backward linear relaxation (CROWN-style) of a tanh MLP's outputs over boxes, outward rounded.

For ``y = W_L t_{L-1} + b_L (+ S t_0)``, ``t_j = tanh(h_j)``, ``h_j = W_j t_{j-1} + b_j``, ``t_0 = z / s``, a row ``c``
of the output is bounded above over a box by walking back from ``c . y``: each ``tanh`` is replaced by two parallel
lines ``k x + lo <= tanh(x) <= k x + hi`` on its pre-activation range (:func:`tanh_lines`; the line above where the
coefficient is positive, below where it is negative), and each affine layer is folded into the coefficients, until
``c . y <= A . t_0 + const``, whose largest value on the box is exact. The pre-activation ranges come from the same
backward walk, layer by layer (every neuron of a layer is a row), so each layer's bound uses the relaxations of the
layers below it.

Sound in floating point: the two lines of each tanh hold on the whole range (their offsets are the extremes of
``tanh(x) - k x``, found where its derivative vanishes and enclosed with intervals), and every rounding of the walk
(the products ``A * k``, ``M @ W`` and the sums of the constants) is bounded by ``gamma_n = (n + 2) eps`` times the
sum of the magnitudes it rounds, the bound of a float64 dot product of ``n`` terms, added to the constant; the
result is rounded up once more. Torch operations only, so it runs on any device.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from drlyap.enclosures.interval import Interval
from drlyap.enclosures.rounding import EPS, F64, REL1, TINY, round_down, round_up


def tanh_lines(lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Slopes ``k`` and offsets ``(below, above)``, each shaped like ``lo``, with ``k x + below <= tanh(x) <= k x +
    above`` for every real ``x`` in ``[lo, hi]``: ``k`` the chord's slope (the derivative at the centre where the
    range is a point), the offsets the extremes of ``g(x) = tanh(x) - k x`` on the range, rounded outward.

    ``g`` is largest and smallest at the ends of the range or where ``g' = sech^2 - k`` vanishes, at ``+-x0`` with
    ``cosh(x0) = 1 / sqrt(k)``. Each computed ``x0`` is bracketed by ``[x0 - e, x0 + e]`` whose ends give ``g'``
    strictly opposite signs (by intervals), so the root lies inside, and ``g`` is enclosed over the bracket's part
    in the range by the mean-value form; where a bracket does not show the sign change, over the whole range."""
    mid, width = (lo + hi) / 2, hi - lo
    chord = (torch.tanh(hi) - torch.tanh(lo)) / torch.where(width > 0, width, 1.0)
    k = torch.where(width > 1e-9 * (1 + mid.abs()), chord, 1 - torch.tanh(mid).square()).clamp(0.0, 1.0)
    k = torch.where(k < 1e-300, torch.zeros_like(k), k)

    def g_at(x: Tensor) -> Interval:  # tanh(x) - k x on a point
        return Interval(x, x).tanh() - Interval(x, x) * Interval(k, k)

    def g_over(a: Tensor, b: Tensor) -> Interval:  # mean-value form of g over [a, b] about its centre
        c = (a + b) / 2
        slope = (Interval.const(1.0, a.device) - Interval(a, b).tanh().square()) - Interval(k, k)
        return g_at(c) + slope * (Interval(a, b) - Interval(c, c))

    def dg_sign(x: Tensor) -> tuple[Tensor, Tensor]:  # g'(x) surely > 0, surely < 0
        d = (Interval.const(1.0, x.device) - Interval(x, x).tanh().square()) - Interval(k, k)
        return d.lo > 0, d.hi < 0

    ends = [g_at(lo), g_at(hi)]
    below, above = torch.minimum(ends[0].lo, ends[1].lo), torch.maximum(ends[0].hi, ends[1].hi)
    interior = k > 0  # k = 0: g = tanh, increasing, no interior extreme
    x0 = torch.acosh(torch.clamp(1 / torch.sqrt(torch.where(interior, k, torch.ones_like(k))), min=1.0))
    eps = 1e-9 * (1 + x0)
    bracketed = interior & (k < 1 - 1e-12)  # near k = 1 the two roots merge at 0: the whole range instead
    for sign in (1.0, -1.0):
        left, right = sign * x0 - eps, sign * x0 + eps
        up_left, down_left = dg_sign(left)
        up_right, down_right = dg_sign(right)
        # g' = sech^2 - k falls through its root at +x0 and rises through it at -x0
        bracketed = bracketed & ((up_left & down_right) if sign > 0 else (down_left & up_right))
        a, b = torch.maximum(left, lo), torch.minimum(right, hi)
        meets = interior & (a <= b)
        part = g_over(torch.where(meets, a, lo), torch.where(meets, b, lo))
        below = torch.where(meets, torch.minimum(below, part.lo), below)
        above = torch.where(meets, torch.maximum(above, part.hi), above)
    whole = g_over(lo, hi)  # where a root is not bracketed: g over the whole range
    below = torch.where(interior & ~bracketed, torch.minimum(below, whole.lo), below)
    above = torch.where(interior & ~bracketed, torch.maximum(above, whole.hi), above)
    return k, below, above


def _gamma(n: int) -> float:
    """A bound of the relative error of a float64 dot product of ``n`` terms (``n u / (1 - n u)``, padded)."""
    return (n + 2) * EPS


class _Walk:
    """The backward walk over one network: its layers, input range and the relaxations found so far."""

    def __init__(self, layers: Sequence[tuple[Tensor, Tensor]], t0_lo: Tensor, t0_hi: Tensor) -> None:
        self.layers = layers
        self.t0 = (t0_lo, t0_hi)
        self.t0_mag = torch.maximum(t0_lo.abs(), t0_hi.abs())  # (B, n): |t_0| at most
        self.relax: list[tuple[Tensor, Tensor, Tensor, Tensor]] = []  # per hidden layer: k, below, above, |h| max

    def upper(self, c: Tensor, i: int, skip: Tensor | None = None) -> Tensor:
        """An upper bound ``(B, q)`` of ``c . h_i`` over the boxes (``c (B, q, m_i)``; ``h_i`` layer i's
        pre-activation, i = 1 .. L; with ``skip`` (m_L, n), of ``c . (h_L + skip t_0)``)."""
        w, b = self.layers[i - 1]
        a = c @ w
        t_mag = self.t0_mag if i == 1 else None
        err = self._product_error(c, w, t_mag)
        const = (c * b).sum(-1)
        err = err + _gamma(b.shape[-1]) * (c.abs() * b.abs()).sum(-1)
        for j in range(i - 1, 0, -1):  # a multiplies t_j = tanh(h_j)
            k, below, above, h_mag = self.relax[j - 1]
            off = torch.where(a >= 0, a * above[:, None], a * below[:, None])
            const = const + off.sum(-1)
            err = err + _gamma(off.shape[-1] + 1) * off.abs().sum(-1) + EPS * const.abs()
            m = a * k[:, None]
            err = err + EPS * (m.abs() * h_mag[:, None]).sum(-1)  # m's own rounding, times |h_j|
            w, b = self.layers[j - 1]
            const = const + (m * b).sum(-1)
            err = err + _gamma(b.shape[-1] + 1) * (m.abs() * b.abs()).sum(-1) + EPS * const.abs()
            a = m @ w
            err = err + self._product_error(m, w, self.t0_mag if j == 1 else None)
        if skip is not None:
            a = a + c @ skip
            err = err + self._product_error(c, skip, self.t0_mag) + EPS * (a.abs() * self.t0_mag[:, None]).sum(-1)
        lo, hi = self.t0
        val = torch.where(a >= 0, a * hi[:, None], a * lo[:, None])
        err = err + _gamma(val.shape[-1] + 1) * val.abs().sum(-1)
        total = const + val.sum(-1)
        return round_up(total + round_up(err, 1e-6) + EPS * (const.abs() + val.abs().sum(-1)), REL1)

    @staticmethod
    def _product_error(m: Tensor, w: Tensor, t_mag: Tensor | None) -> Tensor:
        """A bound ``(B, q)`` of ``|(fl(m @ w) - m @ w) . t|`` for ``|t| <= t_mag`` (None: 1, a tanh layer)."""
        weight = (m.abs() @ w.abs())  # (B, q, n)
        mags = weight.sum(-1) if t_mag is None else (weight * t_mag[:, None]).sum(-1)
        return _gamma(w.shape[0]) * mags

    def bounds(self, i: int, skip: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Lower and upper bounds ``(B, m_i)`` of every neuron of ``h_i`` (with ``skip``: of the output plus the
        path)."""
        m = self.layers[i - 1][0].shape[0]
        batch = self.t0[0].shape[0]
        eye = torch.eye(m, dtype=F64, device=self.t0[0].device).expand(batch, m, m)
        return -self.upper(-eye, i, skip), self.upper(eye, i, skip)


def tanh_mlp_bounds(layers: Sequence[tuple[Tensor, Tensor]], input_scale: Tensor, lo: Tensor, hi: Tensor,
                    skip: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Lower and upper bounds ``(B, out)`` of a tanh MLP's outputs over the boxes ``[lo, hi]`` (``(B, n)`` each), by
    the backward linear relaxation of the module docstring. ``layers``: ``(weight (m_j, m_{j-1}), bias (m_j,))`` of
    each linear layer, float64 (a float32 network's weights are exact in float64), tanh between them; the input is
    divided by ``input_scale (n,)`` first; ``skip (out, n)``: a linear path from the scaled input added to the
    output (:class:`~drlyap.networks.TanhMLP`'s ``skip``)."""
    s = input_scale.to(F64)
    t0_lo = round_down(torch.minimum(lo / s, hi / s), REL1)
    t0_hi = round_up(torch.maximum(lo / s, hi / s), REL1)
    walk = _Walk([(w.to(F64), b.to(F64)) for w, b in layers], t0_lo, t0_hi)
    for i in range(1, len(layers)):
        h_lo, h_hi = walk.bounds(i)
        k, below, above = tanh_lines(h_lo, h_hi)
        walk.relax.append((k, below, above, torch.maximum(h_lo.abs(), h_hi.abs()) + TINY))
    return walk.bounds(len(layers), None if skip is None else skip.to(F64))


def mlp_layers(net) -> tuple[list[tuple[Tensor, Tensor]], Tensor, Tensor | None]:
    """``(layers, input_scale, skip)`` of a :class:`~drlyap.networks.TanhMLP` for :func:`tanh_mlp_bounds`, float64."""
    layers = [(layer.weight.detach().to(F64), layer.bias.detach().to(F64)) for layer in net.layers]
    skip = None if net.skip is None else net.skip.weight.detach().to(F64)
    return layers, net.input_scale.detach().to(F64), skip


__all__ = ["mlp_layers", "tanh_lines", "tanh_mlp_bounds"]
