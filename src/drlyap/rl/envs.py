"""Gymnasium environments generated from any :class:`~drlyap.systems.UncertainSystem`'s TRUE model.

``UncertainSystemEnv(system, xi)`` integrates ``xdot = F(x, u, p0 + E xi)`` (the true model, never the
design model) with fixed-step RK4, holding the action over each step (zero-order hold).

* Parameter shift ``xi``: fixed per environment (constructor argument, default zeros).
* Step ``dt`` and episode length: ``system.rl_timing``, else ``system.sim_dt`` and ``system.horizon``
  (pendulums: 0.05 s and 10 s, 200 steps, since ``sim_dt`` = 0.01 would make 1000-step episodes, too
  long for the RL budgets here; mountain car: 1.0 and 500, the gym mountain car's step).
  The episode is *truncated* at the time limit; it never terminates early.
* Observation: the state with angles wrapped into the box around x*, clipped into the state box
  (the physical state itself is never clipped; only what the agent sees), float32, observation space
  = the state box. :func:`observe` is the same map for batched states (used to run a trained agent
  as a feedback ``x -> u`` on any state).
* Action: the input box; actions outside it are clipped before they are applied.
* Reward, in local coordinates ``z = x - x*`` (angles wrapped) and the applied input ``u``:
  ``system.rl_reward_weights`` when declared (pendulums: ``-(theta^2 + 0.1 thetadot^2 + 0.001 u^2)``, the
  paper's), else ``-(sum_i (z_i / h_i)^2 + 0.001 sum_j ((u_j - u*_j) / hu_j)^2)`` with ``h``/``hu`` the
  half-widths of the state/input boxes. See :func:`reward_weights`.
* Reset: a state uniform in the system's test box (the evaluation region), from the env's seeded RNG.

Registered ids (at import of this module): ``drlyap/Pendulum-v0``, ``drlyap/PendulumU9-v0`` and
``drlyap/MountainCar-v0``; ``gymnasium.make("drlyap/Pendulum-v0", xi=(0.1, 0.05))`` works.
:func:`make_env` builds one for any registered system name.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import gymnasium
import numpy as np
import torch
from gymnasium import spaces

from drlyap.simulation import rk4_step
from drlyap.systems import UncertainSystem, get_system

ENV_IDS = {"drlyap/Pendulum-v0": "pendulum", "drlyap/PendulumU9-v0": "pendulum-u9",
           "drlyap/MountainCar-v0": "mountain-car"}


def rl_timing(system: UncertainSystem) -> tuple[float, float]:
    """``(dt, episode_time)`` the RL environment uses for ``system``."""
    return system.rl_timing if system.rl_timing is not None else (system.sim_dt, system.horizon)


def reward_weights(system: UncertainSystem) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal weights ``(state (n,), input (m,))`` of the quadratic cost in local coordinates."""
    if system.rl_reward_weights is not None:
        return tuple(np.array(w, dtype=np.float64) for w in system.rl_reward_weights)
    slo, shi = np.array(system.state_box[0]), np.array(system.state_box[1])
    ulo, uhi = np.array(system.input_box[0]), np.array(system.input_box[1])
    return 4.0 / (shi - slo) ** 2, 0.001 * 4.0 / (uhi - ulo) ** 2


def observe(system: UncertainSystem, x: torch.Tensor) -> np.ndarray:
    """User-coordinate states ``x (B, n)`` -> observations ``(B, n)`` float32 (wrapped, clipped to X)."""
    shown = system.to_user(system.to_local(torch.as_tensor(x, dtype=torch.float64))).numpy().astype(np.float32)
    low, high = (np.array(b, dtype=np.float32) for b in system.state_box)
    return np.clip(shown, low, high)


class UncertainSystemEnv(gymnasium.Env):
    """A gymnasium environment for the true model of ``system`` at the fixed shift ``xi``."""

    metadata = {"render_modes": []}

    def __init__(self, system: str | UncertainSystem = "pendulum", xi: Sequence[float] | None = None,
                 dt: float | None = None, episode_time: float | None = None, render_mode: str | None = None) -> None:
        super().__init__()
        self.system = get_system(system) if isinstance(system, str) else system
        if render_mode is not None:
            raise ValueError(f"render_mode {render_mode!r} is not supported (no rendering)")
        self.render_mode = None
        s = self.system
        self.xi = s.check_xi(xi if xi is not None else [0.0] * s.k)
        default_dt, default_time = rl_timing(s)
        self.dt = float(dt if dt is not None else default_dt)
        episode_time = float(episode_time if episode_time is not None else default_time)
        if not (math.isfinite(self.dt) and self.dt > 0 and math.isfinite(episode_time) and episode_time > 0):
            raise ValueError(f"dt and episode_time must be > 0, got {self.dt}, {episode_time}")
        self.max_steps = max(1, round(episode_time / self.dt))
        self.observation_space = spaces.Box(np.array(s.state_box[0], dtype=np.float32),
                                            np.array(s.state_box[1], dtype=np.float32), dtype=np.float32)
        self.action_space = spaces.Box(np.array(s.input_box[0], dtype=np.float32),
                                       np.array(s.input_box[1], dtype=np.float32), dtype=np.float32)
        self.state_weights, self.input_weights = reward_weights(s)
        self._u_star = np.array(s.equilibrium_input)
        self._test_low, self._test_high = np.array(s.test_box[0]), np.array(s.test_box[1])
        self._x = torch.tensor([s.equilibrium], dtype=torch.float64)
        self._steps = 0
        # p0 + E xi, computed once: the RK4 stages call the dynamics directly (the env's hot path).
        self._params = s.params(self.xi, self._x)
        self._x_star = np.array(s.equilibrium)
        self._angles = list(s.angle_dims)

    @property
    def state(self) -> np.ndarray:
        """The physical state (user coordinates, angles not wrapped), float64 ``(n,)``."""
        return self._x[0].numpy().copy()

    def reward(self, x: np.ndarray, u: np.ndarray) -> float:
        """``-(z^T Wx z + (u - u*)^T Wu (u - u*))`` at state ``x (n,)`` and applied input ``u (m,)``."""
        z = np.asarray(x, dtype=np.float64).reshape(self.system.n) - self._x_star
        z[self._angles] = np.remainder(z[self._angles] + math.pi, 2 * math.pi) - math.pi
        du = np.asarray(u, dtype=np.float64) - self._u_star
        return -float(np.sum(self.state_weights * z**2) + np.sum(self.input_weights * du**2))

    def _obs(self) -> np.ndarray:
        z = self._x[0].numpy() - self._x_star
        z[self._angles] = np.remainder(z[self._angles] + math.pi, 2 * math.pi) - math.pi
        obs = (z + self._x_star).astype(np.float32)
        return np.clip(obs, self.observation_space.low, self.observation_space.high)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        if options and "state" in options:
            x0 = np.asarray(options["state"], dtype=np.float64).reshape(self.system.n)
        else:
            x0 = self.np_random.uniform(self._test_low, self._test_high)
        self._x = torch.tensor(x0, dtype=torch.float64).reshape(1, -1)
        self._steps = 0
        return self._obs(), {"state": self.state}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        u = np.clip(np.asarray(action, dtype=np.float64).reshape(self.system.m), self.action_space.low,
                    self.action_space.high)
        reward = self.reward(self.state, u)
        u_t = torch.as_tensor(u, dtype=torch.float64).reshape(1, -1)
        self._x = rk4_step(lambda x: self.system.dynamics(x, u_t, self._params), self._x, self.dt)
        self._steps += 1
        if not torch.isfinite(self._x).all():
            raise RuntimeError(f"{self.system.name}: the state became non-finite at step {self._steps}")
        truncated = self._steps >= self.max_steps
        return self._obs(), reward, False, truncated, {"state": self.state}


def make_env(system_name: str, xi: Sequence[float] | None = None, **kwargs) -> UncertainSystemEnv:
    """An environment for a registered system name at shift ``xi`` (default zeros)."""
    return UncertainSystemEnv(system_name, xi, **kwargs)


def _register() -> None:
    for env_id, name in ENV_IDS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point="drlyap.rl.envs:UncertainSystemEnv", kwargs={"system": name})


_register()
