"""Reinforcement-learning baselines (SAC, PPO from stable-baselines3) on the true-model environments.

stable-baselines3 is an optional extra (``pip install drlyap[rl]``); it is imported lazily, so the
rest of drlyap works without it.

:func:`train_rl` trains on :class:`drlyap.rl.envs.UncertainSystemEnv` at the nominal parameters
(``xi = 0``: the agent sees the true model at the nominal parameters, as the paper's RL baselines
do) and writes a run directory of kind ``rl`` (atomically)::

    RUN_DIR/
      run.json       {"kind": "rl", "format": 2, "system": system.describe()}
      config.json    algo, steps, seed, env settings (dt, episode steps), hyperparameters, wall time
      policy.pt      the policy's weights (tensors only: the policy is rebuilt from config.json, nothing is unpickled)
      metrics.json   samples (= steps, environment transitions), train_time_s, ms per 1000 steps,
                     returns of the last training episodes

Runs of format 1 kept a ``model.zip`` (stable-baselines3's own format, which unpickles objects: loading it can
run code); they load only when trusted (``trust=True``, ``--trust-run``).

Using a trained agent as a feedback (:func:`load_rl_run`): ``controller(x)`` maps user-coordinate
states through :func:`drlyap.rl.envs.observe` (wrap, clip to X) to the deterministic action
(``model.predict(obs, deterministic=True)``, clipped to U). In simulation the action is re-evaluated
at every RK4 stage (continuous feedback), whereas training held it for the env's ``dt``.
``certificate(x)`` is the NEGATED critic value, so that decreasing is the good direction as for V:
SAC ``-min(Q1, Q2)(s, pi(s))``, PPO ``-V(s)``.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from drlyap.runs.directory import RunDirError, atomic_dir, read_run_json, run_record, run_system
from drlyap.runs.policies import PolicyRun
from drlyap.runs.publish import check_writable
from drlyap.runs.validate import load_weights
from drlyap.systems import UncertainSystem, resolve_system, system_source

ALGOS = ("sac", "ppo")

# Defaults that finish in a few minutes on one CPU thread for the pendulum (see ``drlyap rl train --help``).
DEFAULT_STEPS = {"sac": 20_000, "ppo": 100_000}
DEFAULT_HYPER = {
    # rl-zoo's Pendulum-v1 settings, single environment.
    "sac": {"learning_rate": 1e-3, "buffer_size": 100_000, "learning_starts": 1000, "batch_size": 256,
            "gamma": 0.98, "policy_kwargs": {"net_arch": [64, 64]}},
    "ppo": {"learning_rate": 1e-3, "n_steps": 1024, "batch_size": 64, "n_epochs": 10, "gamma": 0.98,
            "gae_lambda": 0.95, "use_sde": True, "sde_sample_freq": 4, "policy_kwargs": {"net_arch": [64, 64]}},
}


def _sb3():
    try:
        import stable_baselines3
    except ImportError as err:  # pragma: no cover - exercised only without the extra
        raise ValueError("RL baselines need stable-baselines3: pip install 'drlyap[rl]'") from err
    return stable_baselines3


def _algo_class(algo: str):
    sb3 = _sb3()
    if algo not in ALGOS:
        raise ValueError(f"unknown algorithm {algo!r}; valid: {', '.join(ALGOS)}")
    return {"sac": sb3.SAC, "ppo": sb3.PPO}[algo]


def train_rl(system: str | UncertainSystem, algo: str, steps: int | None, seed: int, out: str | os.PathLike,
             hyperparameters: dict | None = None, overwrite: bool = False) -> dict:
    """Train ``algo`` (``sac`` or ``ppo``) for ``steps`` environment steps and save a run directory.

    ``system``: an object, or a spec for :func:`drlyap.systems.resolve_system` (recorded in ``run.json``).

    ``hyperparameters`` override the defaults (``DEFAULT_HYPER``) passed to the SB3 constructor.
    Returns the metrics written to ``metrics.json``.
    """
    cls = _algo_class(algo)  # first: a clear error without stable-baselines3
    from stable_baselines3.common.logger import Logger
    from stable_baselines3.common.monitor import Monitor

    from drlyap.rl.envs import UncertainSystemEnv

    source = None
    if isinstance(system, str):
        spec, system = system, resolve_system(system)
        source = system_source(spec, system)
    steps = int(steps if steps is not None else DEFAULT_STEPS[algo])
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    out = Path(out)
    if not overwrite:
        check_writable(out)
    hyper = {**DEFAULT_HYPER[algo], **(hyperparameters or {})}
    env = Monitor(UncertainSystemEnv(system))
    env.reset(seed=seed)
    env.action_space.seed(seed)
    try:
        model = cls("MlpPolicy", env, seed=seed, device="cpu", verbose=0, **hyper)
    except TypeError as err:
        raise ValueError(f"invalid {algo} hyperparameters {hyper}: {err}") from err
    model.set_logger(Logger(folder=None, output_formats=[]))  # its default makes an empty folder in the temp dir
    tic = time.perf_counter()
    model.learn(total_timesteps=steps)
    wall = time.perf_counter() - tic
    base = env.unwrapped
    returns = [float(r) for r in env.get_episode_rewards()]
    config = {"system": system.name, "algo": algo, "steps": steps, "seed": seed, "wall_time_s": wall,
              "xi_train": base.xi.tolist(), "env": {"dt": base.dt, "episode_steps": base.max_steps,
                                                    "reward_state_weights": base.state_weights.tolist(),
                                                    "reward_input_weights": base.input_weights.tolist()},
              "hyperparameters": hyper}
    metrics = {"samples": steps, "train_time_s": wall, "ms_per_1000_steps": 1e6 * wall / steps,
               "episodes": len(returns), "last_returns": returns[-10:],
               "mean_last_returns": float(np.mean(returns[-10:])) if returns else None}

    def fill(tmp: Path) -> None:
        (tmp / "config.json").write_text(json.dumps(config, indent=2) + "\n")
        torch.save({"policy": model.policy.state_dict()}, tmp / "policy.pt")
        (tmp / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
        (tmp / "figures").mkdir()
        (tmp / "run.json").write_text(json.dumps(run_record("rl", system, source), indent=2) + "\n")

    atomic_dir(out, fill, overwrite)
    return metrics


class RLPolicy:
    """A trained SB3 agent as a deterministic feedback and a (negated) value certificate."""

    def __init__(self, system: UncertainSystem, algo: str, model) -> None:
        self.system, self.algo, self.model = system, algo, model
        self._low, self._high = (np.array(b, dtype=np.float64) for b in system.input_box)

    def _obs(self, x: torch.Tensor) -> torch.Tensor:
        """The env's observation map (:func:`drlyap.rl.envs.observe`) in torch: wrap angles, clip to X, float32."""
        x = torch.as_tensor(x)
        if x.ndim != 2 or x.shape[1] != self.system.n:
            raise ValueError(f"{self.system.name} states must have shape (B, {self.system.n}), got {tuple(x.shape)}")
        shown = self.system.to_user(self.system.to_local(x.to(torch.float64))).float()
        low, high = (torch.tensor(b, dtype=torch.float32) for b in self.system.state_box)
        return torch.minimum(torch.maximum(shown, low), high)

    @torch.no_grad()
    def controller(self, x: torch.Tensor) -> torch.Tensor:
        """Deterministic action (as ``model.predict(obs, deterministic=True)``), clipped to U, float64."""
        policy = self.model.policy
        obs = self._obs(x)
        low, high = torch.from_numpy(self._low), torch.from_numpy(self._high)
        if self.algo == "sac":  # tanh-squashed actor in [-1, 1], rescaled to U
            scaled = policy.actor(obs, deterministic=True).double()
            u = low + 0.5 * (scaled + 1.0) * (high - low)
        else:
            u = policy._predict(obs, deterministic=True).double()
        return torch.minimum(torch.maximum(u.reshape(-1, self.system.m), low), high)

    @torch.no_grad()
    def certificate(self, x: torch.Tensor) -> torch.Tensor:
        """Negated critic value: SAC ``-min(Q1, Q2)(s, pi(s))``, PPO ``-V(s)``; ``(B,)`` float64."""
        policy = self.model.policy
        obs = self._obs(x)
        if self.algo == "sac":
            action = policy.actor(obs, deterministic=True)
            value = torch.min(torch.cat(policy.critic(obs, action), dim=1), dim=1).values
        else:
            value = policy.predict_values(obs).reshape(-1)
        return -value.double()


def _plain(value) -> bool:
    """Whether ``value`` is JSON data of numbers, flags and short names only (nothing a constructor could import)."""
    if isinstance(value, dict):
        return all(isinstance(k, str) and _plain(v) for k, v in value.items())
    if isinstance(value, list):
        return all(_plain(v) for v in value)
    return value is None or isinstance(value, (bool, int, float)) or (isinstance(value, str) and len(value) <= 64)


def _rebuild(cls, algo: str, system: UncertainSystem, config: dict, path: Path):
    """The agent of an RL run rebuilt from its config (algorithm, hyperparameters, the env's spaces) with the
    policy's weights read as tensors."""
    from drlyap.rl.envs import UncertainSystemEnv

    hyper = config.get("hyperparameters") or DEFAULT_HYPER[algo]
    if not isinstance(hyper, dict) or not _plain(hyper) or set(hyper.get("policy_kwargs") or {}) - {"net_arch", "use_sde"}:
        raise RunDirError(f"{path / 'config.json'}: hyperparameters must be numbers, flags and names (policy_kwargs: "
                          "net_arch only), as drlyap writes them")
    hyper = dict(hyper)
    if algo == "sac":
        hyper["buffer_size"] = 1  # the replay buffer is not part of a trained policy
    try:
        model = cls("MlpPolicy", UncertainSystemEnv(system), seed=int(config.get("seed", 0)), device="cpu",
                    verbose=0, **hyper)
    except (TypeError, ValueError) as err:
        raise RunDirError(f"{path / 'config.json'}: cannot rebuild the {algo} policy ({err})") from None
    state = load_weights(path / "policy.pt")
    try:
        model.policy.load_state_dict(state["policy"])
    except (KeyError, RuntimeError) as err:
        raise RunDirError(f"{path}: policy.pt does not fit config.json ({str(err).splitlines()[0]})") from None
    return model


def load_rl_run(path: str | os.PathLike, system: UncertainSystem | None = None, trust: bool = False) -> PolicyRun:
    """Load a run directory of kind ``rl`` as a :class:`drlyap.runs.PolicyRun` (``system``, ``trust``: as
    :func:`drlyap.runs.load_run`; an older run's pickled ``model.zip`` is read only with ``trust``)."""
    path = Path(path)
    info, config, metrics = read_run_json(path, "rl", "run.json", "config.json", "metrics.json")
    if not isinstance(config.get("system"), str) or config.get("algo") not in ALGOS:
        raise RunDirError(f"{path / 'config.json'}: an RL run's config needs 'system' and 'algo' (one of "
                          f"{', '.join(ALGOS)})")
    system = run_system(path, config["system"], system, info, trust)
    algo = config["algo"]
    cls = _algo_class(algo)
    if (path / "policy.pt").is_file():
        model = _rebuild(cls, algo, system, config, path)
    elif (path / "model.zip").is_file():
        if not trust:
            raise RunDirError(f"{path}: model.zip is a pickled stable-baselines3 model; loading it can run code. "
                              "Retrain the agent (runs now keep policy.pt) or trust the run (--trust-run, trust=True)")
        try:
            model = cls.load(path / "model.zip", device="cpu")
        except (OSError, ValueError, KeyError) as err:
            raise RunDirError(f"cannot load the {algo} model of {path}: {err}") from err
    else:
        raise RunDirError(f"{path}: the RL run has no policy.pt")
    agent = RLPolicy(system, algo, model)
    return PolicyRun(path, "rl", system, agent.controller, agent.certificate, int(config["steps"]),
                     metrics.get("train_time_s"), f"rl-{algo}", config, metrics, {"agent": agent})

