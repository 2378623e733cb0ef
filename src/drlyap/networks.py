"""The Lyapunov function V and the controller pi, pinned at the equilibrium by construction.

Both act on local coordinates ``z = x - x*`` (angles wrapped, see :mod:`drlyap.systems`)::

    V(z)  = || phi(z) - phi(0) ||^2 + alpha_hat ||z / s||^2        (V(0) = 0, V > 0 elsewhere)
    pi(z) = u* + sat( varphi(z) - varphi(0) )                         (pi(0) = u*)

``varphi`` may carry a linear path beside its hidden layers (``skip``: ``varphi(z) = mlp(z) + L z / s``), so that
the controller is a linear gain plus a network's correction; the LQR warm start then sets ``L`` to the LQR gain and
the correction to 0. ``phi`` may carry one too: V is then a quadratic form plus a network's term,
``||A z / s + mlp(z) - mlp(0)||^2 + alpha_hat ||z / s||^2``, and the warm start sets ``A`` to the LQR quadratic and
the network's term to 0.

``phi`` and ``varphi`` are tanh MLPs whose first layer sees ``z / s``, with ``s`` the half-widths of
the state box, so every coordinate enters on the same scale; the quadratic term uses the same
scaled coordinates (the paper writes ``alpha_hat ||x||^2``; scaling keeps V meaningful when the
coordinates have very different units, as in the mountain car). ``sat`` is the paper's clamp to the input
box U with a *straight-through* gradient: the forward value is exactly ``clamp(., u_min, u_max)``,
the backward pass treats it as the identity, so a saturated controller still receives gradient
(a smooth tanh saturation was measured to freeze saturated controllers at initialisation). The
verifier bounds the real clamp. The input gradient of V is written out (one manual backward pass
through phi) so that training differentiates it once more with a single ordinary backward.

Every forward and gradient method here also runs on the enclosure types of :mod:`drlyap.enclosures`
(the verifier passes boxes instead of tensors): the verifier bounds these networks by running this
very code, not a copy of it.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from drlyap.enclosures import constant_like, is_enclosure


def origin_like(z) -> object:
    """The local origin ``z = 0`` (the state x*) as a batch of one, of the same kind as ``z (B, n)``."""
    zero = torch.zeros(1, z.shape[1], dtype=z.dtype, device=z.device)
    return constant_like(z, zero)


def clamp(v, low: Tensor, high: Tensor):
    """``min(max(v, low), high)`` elementwise for ``v (B, m)`` (a tensor or an enclosure)."""
    if is_enclosure(v):
        return v.clamp(low, high)
    return torch.minimum(torch.maximum(v, low), high)  # the enclosures' order (the same wherever low <= high)


class TanhMLP(nn.Module):
    """A fully connected network with tanh hidden activations and a linear output layer; with ``skip``, plus a
    linear map of its (scaled) input, ``skip.weight (out, in)`` without bias."""

    def __init__(self, sizes: Sequence[int], input_scale: Sequence[float] | None = None, skip: bool = False) -> None:
        super().__init__()
        if len(sizes) < 2 or any(int(s) < 1 for s in sizes):
            raise ValueError(f"layer sizes must be >= 2 positive integers, got {list(sizes)}")
        self.sizes = [int(s) for s in sizes]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(self.sizes[:-1], self.sizes[1:]))
        self.skip = nn.Linear(self.sizes[0], self.sizes[-1], bias=False) if skip else None
        scale = torch.ones(self.sizes[0]) if input_scale is None else torch.as_tensor(input_scale, dtype=torch.float32)
        self.register_buffer("input_scale", scale)  # inputs are divided by this before the first layer

    # the layers are indexed, not sliced: a slice of a ModuleList builds a new ModuleList on every call (measured:
    # a fifth of a simulation's time)
    def forward(self, z: Tensor) -> Tensor:
        """``z (B, in) -> (B, out)``."""
        layers = self.layers
        h = zs = z / self.input_scale
        for i in range(len(layers) - 1):
            h = torch.tanh(layers[i](h))
        return self._output(h, zs)

    def forward_with_hidden(self, z: Tensor) -> tuple[Tensor, list[Tensor]]:
        """Output and the list of hidden activations (needed for the manual input gradient)."""
        layers = self.layers
        hidden = []
        h = zs = z / self.input_scale
        for i in range(len(layers) - 1):
            h = torch.tanh(layers[i](h))
            hidden.append(h)
        return self._output(h, zs), hidden

    def _output(self, h: Tensor, zs: Tensor) -> Tensor:
        """The output layer on the last hidden activations ``h``, plus the linear path on the scaled input ``zs``."""
        out = self.layers[-1](h)
        return out if self.skip is None else out + self.skip(zs)

    def vjp(self, hidden: list[Tensor], v: Tensor) -> Tensor:
        """``J(z)^T v`` for a cotangent ``v (B, out)``, given the hidden activations at ``z``."""
        layers = self.layers
        g = F.linear(v, layers[-1].weight.T)
        for i in range(len(layers) - 2, -1, -1):
            g = F.linear(g * (1 - hidden[i].square()), layers[i].weight.T)
        if self.skip is not None:
            g = g + F.linear(v, self.skip.weight.T)
        return g / self.input_scale


class Lyapunov(nn.Module):
    """``V(z) = ||phi(z) - phi(0)||^2 + alpha_hat ||z / s||^2``, with ``phi: R^n -> R^p`` a tanh MLP (with ``skip``,
    plus a linear map of ``z / s``)."""

    def __init__(self, n: int, hidden: Sequence[int] = (32, 32), out: int = 8, alpha_hat: float = 1.0,
                 input_scale: Sequence[float] | None = None, skip: bool = False) -> None:
        super().__init__()
        if alpha_hat <= 0:
            raise ValueError(f"alpha_hat must be > 0 so that V is positive definite, got {alpha_hat}")
        self.phi = TanhMLP([n, *hidden, out], input_scale, skip)
        self.alpha_hat = float(alpha_hat)

    def forward(self, z: Tensor) -> Tensor:
        """``z (B, n) -> V (B,)``."""
        d = self.phi(z) - self.phi(origin_like(z))
        zs = z / self.phi.input_scale
        return d.square().sum(-1) + zs.square().sum(-1) * self.alpha_hat

    def value_and_grad(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """``V (B,)`` and ``grad V (B, n)`` at ``z (B, n)``, differentiable in the weights."""
        out, hidden = self.phi.forward_with_hidden(z)
        d = out - self.phi(origin_like(z))
        zs = z / self.phi.input_scale
        value = d.square().sum(-1) + zs.square().sum(-1) * self.alpha_hat
        grad = self.phi.vjp(hidden, d * 2.0) + zs / self.phi.input_scale * (2.0 * self.alpha_hat)
        return value, grad

    def set_quadratic(self, p: Tensor) -> bool:
        """Without hidden layers, or with a linear path beside them, set V to ``z^T p z`` (``p (n, n)`` float64) as
        closely as its form allows, in place, and return True (the network's term, with a linear path, then starts
        at 0); otherwise change nothing and return False. V is ``||A z/s||^2 + alpha_hat ||z/s||^2``: ``A^T A`` is
        ``s p s - alpha_hat I`` with negative eigenvalues clipped to 0 (V then lies above ``z^T p z`` there), its
        leading ``out`` directions when the output has fewer rows than states."""
        phi = self.phi
        if phi.skip is None and len(phi.layers) != 1:
            return False
        layer, s = (phi.layers[0] if phi.skip is None else phi.skip), phi.input_scale.to(p)
        m = s[:, None] * p * s[None, :] - self.alpha_hat * torch.eye(p.shape[0], dtype=p.dtype)
        eig, vec = torch.linalg.eigh((m + m.T) / 2)
        rows = (eig.clamp_min(0).sqrt()[:, None] * vec.T).flip(0)  # largest first
        weight = torch.zeros(layer.weight.shape, dtype=p.dtype)
        count = min(weight.shape[0], rows.shape[0])
        weight[:count] = rows[:count]
        with torch.no_grad():
            layer.weight.copy_(weight)
            for bias in (phi.layers[-1].bias, layer.bias):
                if bias is not None:
                    bias.zero_()
            if phi.skip is not None:
                phi.layers[-1].weight.zero_()
        return True


def saturate(v: Tensor, low: Tensor, high: Tensor) -> Tensor:
    """``clamp(v, low, high)`` for ``v (B, m)`` with a straight-through (identity) gradient.

    On enclosures it is the real clamp (what is verified is the forward value)."""
    clamped = clamp(v, low, high)
    return clamped if is_enclosure(v) else v + (clamped - v).detach()


class Controller(nn.Module):
    """``pi(z) = u* + sat(varphi(z) - varphi(0))`` with outputs inside the input box U; with ``skip``, ``varphi``
    holds a linear path beside its hidden layers (:class:`TanhMLP`)."""

    def __init__(self, n: int, input_box: tuple[Sequence[float], Sequence[float]], u_star: Sequence[float],
                 hidden: Sequence[int] = (32, 32), init_gain: float = 10.0,
                 input_scale: Sequence[float] | None = None, skip: bool = False) -> None:
        super().__init__()
        m = len(u_star)
        self.varphi = TanhMLP([n, *hidden, m], input_scale, skip)
        with torch.no_grad():
            self.varphi.layers[-1].weight.mul_(init_gain)
        # float64 buffers: the verifier reads u* and U exactly (a float32 u* would move the equilibrium)
        lo, hi = (torch.as_tensor(b, dtype=torch.float64) for b in input_box)
        us = torch.as_tensor(u_star, dtype=torch.float64)
        self.register_buffer("u_star", us)
        self.register_buffer("room_low", lo - us)
        self.register_buffer("room_high", hi - us)

    def set_linear(self, k: Tensor) -> bool:
        """Set ``varphi(z) - varphi(0)`` to ``-k z`` (``k (m, n)`` float64) exactly, in place, and return True: without
        hidden layers by the only layer, with a linear path by that path (the output layer then starts at 0, so the
        hidden layers' correction is 0 and learns from there); otherwise change nothing and return False."""
        varphi = self.varphi
        if varphi.skip is None and len(varphi.layers) != 1:
            return False
        layer = varphi.layers[0] if varphi.skip is None else varphi.skip
        with torch.no_grad():
            layer.weight.copy_(-k * varphi.input_scale.to(k)[None, :])
            if varphi.skip is None:
                layer.bias.zero_()
            else:
                varphi.layers[-1].weight.zero_()
                varphi.layers[-1].bias.zero_()
        return True

    def raw(self, z: Tensor) -> Tensor:
        """The unsaturated offset ``varphi(z) - varphi(0)``, ``(B, m)``."""
        return self.varphi(z) - self.varphi(origin_like(z))

    def forward(self, z: Tensor) -> Tensor:
        """``z (B, n) -> u (B, m)``."""
        u_star, low, high = self.u_star, self.room_low, self.room_high
        if not is_enclosure(z):  # computed in the dtype of the states (float32 in training)
            u_star, low, high = u_star.to(z.dtype), low.to(z.dtype), high.to(z.dtype)
        return u_star + saturate(self.raw(z), low, high)


class QuadraticLyapunov(nn.Module):
    """``V(z) = z^T P z`` with a symmetric positive definite ``P (n, n)`` (e.g. LQR's Riccati solution).

    The same interface as :class:`Lyapunov`, so the conditions and the verifier accept it.
    """

    def __init__(self, P: Tensor) -> None:
        super().__init__()
        P = torch.as_tensor(P, dtype=torch.float64)
        self.register_buffer("P", (P + P.T) / 2)

    def forward(self, z: Tensor) -> Tensor:
        """``z (B, n) -> V (B,)``."""
        return (F.linear(z, self.P) * z).sum(-1)

    def value_and_grad(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """``V (B,)`` and ``grad V = 2 P z (B, n)``."""
        pz = F.linear(z, self.P)
        return (pz * z).sum(-1), pz * 2.0


class LinearController(nn.Module):
    """``pi(z) = u* + clamp(-K z, U - u*)`` with a gain ``K (m, n)`` (e.g. LQR); same interface as
    :class:`Controller`."""

    def __init__(self, K: Tensor, input_box: tuple[Sequence[float], Sequence[float]], u_star: Sequence[float]) -> None:
        super().__init__()
        lo, hi = (torch.as_tensor(b, dtype=torch.float64) for b in input_box)
        us = torch.as_tensor(u_star, dtype=torch.float64)
        self.register_buffer("K", torch.as_tensor(K, dtype=torch.float64))
        self.register_buffer("u_star", us)
        self.register_buffer("room_low", lo - us)
        self.register_buffer("room_high", hi - us)

    def forward(self, z: Tensor) -> Tensor:
        """``z (B, n) -> u (B, m)``."""
        return self.u_star + clamp(F.linear(z, -self.K), self.room_low, self.room_high)
