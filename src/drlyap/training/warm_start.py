"""The warm start (:func:`warm_start_pair`): before training, V is fitted to a quadratic and pi to a linear gain, exactly
for networks without hidden layers or with a linear path beside them, by regression for the others. The pair is the
LQR's (``warm_start = "lqr"``) or the largest invariant ellipsoid of the linearisations (``"ellipsoid"``,
:func:`drlyap.lmi.invariant_ellipsoid`)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.lmi import invariant_ellipsoid
from drlyap.lqr import lqr_design
from drlyap.regions import Region
from drlyap.sections import NetworkSection
from drlyap.systems import UncertainSystem

FACES_SCALE = {"lqr": 1.2, "ellipsoid": 1.06}
"""V's least value on the box's faces after the warm start, per training level: the LQR's quadratic well inside the
box, the ellipsoid (which meets the faces) just above the faces' level of a growing set (1.05)."""


@dataclass(frozen=True)
class Regression:
    """How the warm start fits networks that cannot take the pair exactly: ``iters`` steps of Adam at step size ``lr``,
    each on ``n_states`` states (half uniform in X_delta, half spread over the distance from x*)."""

    lr: float
    iters: int = 500
    n_states: int = 4096


def warm_start_pair(loop: ClosedLoop, networks: NetworkSection, level: float | None, region: Region,
                    generator: torch.Generator, xi: Tensor, rate: float, regression: Regression) -> dict:
    """Fit ``loop``'s networks to a quadratic and a gain (in place): ``V ~ s z^T P z`` and ``varphi(z) - varphi(0) ~ -K z``,
    exactly for a network without hidden layers or with a linear path (:meth:`~drlyap.networks.Lyapunov.set_quadratic`,
    :meth:`~drlyap.networks.Controller.set_linear`), by regression for the others.

    ``P``, ``K``: with ``networks.warm_start == "lqr"`` the LQR design for ``networks.lqr_weights`` (``[Q diagonal, R
    diagonal]``; None: Bryson's rule) on the nominal linearisation; with ``"ellipsoid"`` the largest ellipsoid in the
    box kept invariant at decay ``rate`` for the nominal linearisation and those at the training shifts ``xi (N, k)``.
    ``s`` puts the quadratic's minimum over the faces of the box at :data:`FACES_SCALE` times the training ``level``
    (:attr:`~drlyap.sections.RegionGoal.level`; 1 without a level). The others are fitted by the ``regression``
    (:class:`Regression`). Returns the design's gain, the scale and the final relative errors.
    """
    system, lyapunov, controller = loop.system, loop.lyapunov, loop.controller
    lr, iters, n_states = regression.lr, regression.iters, regression.n_states
    kind = networks.warm_start
    design = _design(system, networks, xi, rate)
    half = torch.maximum(-region.lo, region.hi)
    scale = FACES_SCALE[kind] * (level or 1.0) / float((half.square() / torch.linalg.inv(design.P).diagonal()).min())
    ref = next(lyapunov.parameters())
    p_mat, k_mat = (design.P * scale).to(ref), design.K.to(ref)
    exact = {lyapunov: lyapunov.set_quadratic(design.P * scale), controller: controller.set_linear(design.K.to(design.P))}
    params = [p for net, done in exact.items() if not done for p in net.parameters()]
    opt = torch.optim.Adam(params, lr=lr) if params else None

    def errors() -> tuple[Tensor, Tensor]:
        z = torch.cat([region.sample(n_states // 2, generator), region.sample_near(n_states - n_states // 2, generator)])
        z = z.to(ref)
        v_target, u_target = ((z @ p_mat) * z).sum(-1), -(z @ k_mat.T)
        v_err = (lyapunov(z) - v_target).square().mean() / v_target.square().mean()
        u_err = (controller.raw(z) - u_target).square().mean() / u_target.square().mean().clamp_min(1e-12)
        return v_err, u_err

    if opt is None:  # nothing left to fit: the errors of the exact pair
        with torch.no_grad():
            v_err, u_err = errors()
    else:
        for _ in range(iters):
            v_err, u_err = errors()
            opt.zero_grad(set_to_none=True)
            (v_err + u_err).backward()
            opt.step()
    return {"method": kind, "K": design.K.tolist(), "P_scale": scale, "rate": rate if kind == "ellipsoid" else None,
            "v_relative_error": float(v_err.detach()), "u_relative_error": float(u_err.detach()),
            "iterations": iters if opt else 0}


def _design(system: UncertainSystem, networks: NetworkSection, xi: Tensor, rate: float):
    """The pair's design: the largest invariant ellipsoid (:func:`~drlyap.lmi.invariant_ellipsoid` at ``rate`` for the
    nominal linearisation and those at ``xi (N, k)``) where ``networks.warm_start == "ellipsoid"``, else the LQR design
    (:func:`~drlyap.lqr.lqr_design` for ``networks.lqr_weights``)."""
    if networks.warm_start == "ellipsoid":
        return invariant_ellipsoid(system, xi.double().cpu(), rate)
    q, r = networks.lqr_weights if networks.lqr_weights is not None else (None, None)
    try:
        return lqr_design(system, q, r)
    except ValueError as err:
        raise ValueError(f"{err}; the LQR warm start needs one (TrainConfig.warm_start = 'lqr', the default for a "
                         "system of one's own): declare warm_start=None in the system's defaults, or "
                         "drlyap.config.PAPER_CONDITION for the paper's condition") from None
