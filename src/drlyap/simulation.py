"""Batched closed-loop simulation and evaluation on the *true* perturbed model.

Trajectories integrate ``xdot = F(x, pi(x), p0 + E xi)`` (never the linearised design model) with
fixed-step RK4, all initial states at once. Angle coordinates are kept as the physical angle; the
feedback sees them wrapped into the box around x* (:meth:`UncertainSystem.to_local`).

A trajectory *succeeds* when, over the last ``settle_fraction`` of the horizon, every coordinate of
the wrapped deviation ``x - x*`` stays within ``success_tol`` times the half-width of the state box
(defaults per system: 2% of the half-width over the last 10% of the horizon).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from drlyap.systems import UncertainSystem

Policy = Callable[[Tensor], Tensor]
"""``policy(x (B, n) in user coordinates) -> u (B, m)``."""


@dataclass
class Trajectories:
    """Simulated trajectories: ``t (T,)``, ``x (T, B, n)`` user coordinates, ``u (T, B, m)``."""

    t: Tensor
    x: Tensor
    u: Tensor


def rk4_step(rhs: Callable[[Tensor], Tensor], x: Tensor, dt: float, k1: Tensor | None = None) -> Tensor:
    """One classical Runge-Kutta step of ``xdot = rhs(x)`` for ``x (B, n)`` (``k1``: ``rhs(x)`` when the caller
    has it)."""
    k1 = rhs(x) if k1 is None else k1
    k2 = rhs(x + 0.5 * dt * k1)
    k3 = rhs(x + 0.5 * dt * k2)
    k4 = rhs(x + dt * k3)
    return x + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)


@torch.no_grad()
def simulate(system: UncertainSystem, policy: Policy, x0: Tensor, xi: Tensor | None, dt: float | None = None,
             horizon: float | None = None) -> Trajectories:
    """Integrate the true closed loop from ``x0 (B, n)`` at the parameter shift ``xi`` ((k,) or (B, k)).

    The input is held at ``policy(x)`` inside each RK4 stage (continuous-time feedback).
    """
    dt = float(system.sim_dt if dt is None else dt)
    horizon = float(system.horizon if horizon is None else horizon)
    if not (dt > 0 and horizon > 0):
        raise ValueError(f"dt and horizon must be > 0, got dt={dt}, horizon={horizon}")
    if x0.ndim != 2 or x0.shape[1] != system.n:
        raise ValueError(f"initial states must have shape (B, {system.n}), got {tuple(x0.shape)}")
    if not torch.isfinite(x0).all():
        raise ValueError("initial states contain NaN or inf")
    if xi is not None:
        xi = torch.as_tensor(xi, dtype=x0.dtype)
        if xi.ndim == 1:
            xi = system.check_xi(xi).to(x0.dtype)
        elif xi.shape != (x0.shape[0], system.k) or not torch.isfinite(xi).all():
            raise ValueError(f"xi must be (k,) or (B, k) = ({x0.shape[0]}, {system.k}) and finite, got {tuple(xi.shape)}")
    steps = max(1, round(horizon / dt))

    params = system.params(xi, x0)  # p0 + E xi, the same at every stage

    def rhs(x: Tensor) -> Tensor:
        return system.dynamics(x, policy(x), params)

    xs, us = [x0], []
    x = x0
    for _ in range(steps):
        u = policy(x)
        us.append(u)
        x = rk4_step(rhs, x, dt, k1=system.dynamics(x, u, params))
        xs.append(x)
    us.append(policy(x))
    t = torch.arange(steps + 1, dtype=x0.dtype, device=x0.device) * dt
    return Trajectories(t=t, x=torch.stack(xs), u=torch.stack(us))


def normalized_deviation(system: UncertainSystem, x: Tensor) -> Tensor:
    """``max_i |x_i - x*_i| / half_width_i`` with angles wrapped, for ``x (..., n)`` -> ``(...)``."""
    flat = x.reshape(-1, system.n)
    z = system.to_local(flat)
    lo, hi = system.local_box()
    half = ((hi - lo) / 2).to(z)
    return (z.abs() / half).amax(-1).reshape(x.shape[:-1])


def wrap_steps(system: UncertainSystem, x: Tensor) -> Tensor:
    """``(T-1, B)``: True where a step of ``x (T, B, n)`` crosses the angle wrap of the box around x*
    (a certificate on the box jumps there; it is not a change along the trajectory)."""
    if not system.angle_dims:
        return torch.zeros(x.shape[0] - 1, x.shape[1], dtype=torch.bool, device=x.device)
    idx = list(system.angle_dims)
    z = system.to_local(x.reshape(-1, system.n)).reshape(x.shape)
    return ((z[1:, :, idx] - z[:-1, :, idx]) - (x[1:, :, idx] - x[:-1, :, idx])).abs().amax(-1) > 1.0


def success_mask(system: UncertainSystem, x: Tensor) -> tuple[Tensor, Tensor]:
    """Per-trajectory success ``(B,)`` and normalised deviation ``(T, B)`` for states ``x (T, B, n)``."""
    dev = normalized_deviation(system, x)
    settle = max(1, int(round(system.settle_fraction * (dev.shape[0] - 1))))
    tail = dev[-settle - 1:]
    return torch.isfinite(tail).all(0) & (tail.amax(0) <= system.success_tol), dev


def initial_states(system: UncertainSystem, count: int, generator: torch.Generator,
                   box: tuple | None = None) -> Tensor:
    """``count`` initial states ``(count, n)`` uniform in ``box`` (default: the system's test box)."""
    if count < 1:
        raise ValueError(f"number of initial states must be >= 1, got {count}")
    lo, hi = (torch.tensor(b, dtype=torch.float64) for b in (box or system.test_box))
    return lo + (hi - lo) * torch.rand(count, system.n, generator=generator, dtype=torch.float64)


@torch.no_grad()
def score(system: UncertainSystem, traj: Trajectories, xi: Tensor | None,
          lyapunov: Callable[[Tensor], Tensor] | None = None, dt: float | None = None,
          horizon: float | None = None) -> dict:
    """Score trajectories ``traj`` simulated on the true model at ``xi`` with step ``dt`` over ``horizon`` (None:
    the system's), as :func:`evaluate` does."""
    success, dev = success_mask(system, traj.x)
    worst = None
    if lyapunov is not None:
        v = lyapunov(traj.x.reshape(-1, system.n)).reshape(dev.shape)
        dv = (v[1:] - v[:-1]).masked_fill(wrap_steps(system, traj.x), float("-inf"))
        if success.any():
            worst = float(dv[:, success].max())
    return {
        "n": int(traj.x.shape[1]),
        "n_success": int(success.sum()),
        "success_rate": float(success.double().mean()),
        "success": success.tolist(),
        "final_distance": dev[-1].tolist(),
        "worst_v_increase": worst,
        "xi": None if xi is None else torch.as_tensor(xi).reshape(-1).tolist(),
        "dt": float(system.sim_dt if dt is None else dt),
        "horizon": float(system.horizon if horizon is None else horizon),
        "success_tol": system.success_tol,
    }


@torch.no_grad()
def evaluate(system: UncertainSystem, policy: Policy, x0: Tensor, xi: Tensor | None,
             lyapunov: Callable[[Tensor], Tensor] | None = None, dt: float | None = None,
             horizon: float | None = None) -> dict:
    """Simulate from ``x0 (B, n)`` on the true model at ``xi`` and score the closed loop.

    Returns a JSON-friendly dict: ``n``, ``n_success``, ``success_rate``, ``success`` (per state),
    ``final_distance`` (normalised deviation at the end, per state), ``worst_v_increase`` (largest
    one-step increase of ``lyapunov`` along successful trajectories, steps across the angle wrap
    excluded; None without ``lyapunov``), and the settings used (``dt``, ``horizon``, ``success_tol``).
    """
    return score(system, simulate(system, policy, x0, xi, dt, horizon), xi, lyapunov, dt, horizon)
