"""Reinforcement-learning baselines on the true model (optional extra ``drlyap[rl]``).

* :mod:`~drlyap.rl.envs` -- gymnasium environments generated from any system's TRUE model;
* :mod:`~drlyap.rl.agents` -- SAC and PPO (stable-baselines3): training, RL run directories and their loader.

Importing this package registers the ``rl`` run loader; gymnasium and stable-baselines3 are imported only when
used.
"""

from drlyap.rl.agents import ALGOS, load_rl_run, train_rl

__all__ = ["ALGOS", "load_rl_run", "train_rl"]
