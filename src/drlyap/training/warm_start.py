"""The LQR warm start (:func:`warm_start_lqr`): before training, V is fitted to the LQR's quadratic and pi to its gain,
exactly for networks without hidden layers, by regression for the others."""

from __future__ import annotations

import torch
from torch import Tensor

from drlyap.lqr import lqr_design
from drlyap.networks import Controller, Lyapunov
from drlyap.regions import Region
from drlyap.sections import NetworkSection
from drlyap.systems import UncertainSystem


def warm_start_lqr(system: UncertainSystem, lyapunov: Lyapunov, controller: Controller, networks: NetworkSection,
                   level: float | None, lr: float, region: Region, generator: torch.Generator, iters: int = 500,
                   n_states: int = 4096) -> dict:
    """Fit the networks to an LQR pair (in place): ``V ~ s z^T P z`` and ``varphi(z) - varphi(0) ~ -K z``, exactly for
    a network without hidden layers (:meth:`~drlyap.networks.Lyapunov.set_quadratic`,
    :meth:`~drlyap.networks.Controller.set_linear`), by regression for the others.

    ``P``, ``K``: the LQR design for ``networks.lqr_weights`` (``[Q diagonal, R diagonal]``; None: Bryson's rule) on
    the nominal linearisation; ``s`` puts the quadratic's minimum over the faces of the box at 1.2 times the training
    ``level`` (:attr:`~drlyap.sections.RegionGoal.level`; 1.2 without a level). The regression runs Adam at step
    size ``lr``; states: half uniform in X_delta, half spread over the distance from x*. Returns the design's gain,
    the scale and the final relative errors.
    """
    q, r = networks.lqr_weights if networks.lqr_weights is not None else (None, None)
    try:
        design = lqr_design(system, q, r)
    except ValueError as err:
        raise ValueError(f"{err}; the LQR warm start needs one (TrainConfig.warm_start = 'lqr', the default for a "
                         "system of one's own): declare warm_start=None in the system's defaults, or "
                         "drlyap.config.PAPER_CONDITION for the paper's condition") from None
    half = torch.maximum(-region.lo, region.hi)
    scale = 1.2 * (level or 1.0) / float((half.square() / torch.linalg.inv(design.P).diagonal()).min())
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
    return {"method": "lqr", "K": design.K.tolist(), "P_scale": scale, "v_relative_error": float(v_err.detach()),
            "u_relative_error": float(u_err.detach()), "iterations": iters if opt else 0}

