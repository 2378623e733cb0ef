"""drlyap: distributionally robust neural controllers with Lyapunov certificates.

Python API::

    import drlyap
    result = drlyap.train(drlyap.TrainConfig(system="pendulum"))   # trains, then proves the condition
    result.metrics["certificate"]["status"]                          # 'verified', 'violated' or 'unknown'
    run = drlyap.load_run("runs/reproduce-pendulum/seed0/dr")
    u = run.controller(x)      # x: (B, n) tensor in user coordinates -> (B, m)
    v = run.lyapunov(x)        # -> (B,)
"""

import drlyap.baselines  # noqa: F401  (registers the lqr run loader)
import drlyap.rl  # noqa: F401  (registers the rl run loader; stable-baselines3 is imported only when used)
from drlyap.cegis import train_certified as train
from drlyap.conditions import DRPointwise, DRUniform, Nominal, cvar_bound, wasserstein_radius_guarantee
from drlyap.networks import Controller, Lyapunov
from drlyap.rundir import Run, RunDirError, load_run, save_run
from drlyap.simulation import evaluate, simulate
from drlyap.systems import UncertainSystem, get_system, register_system, resolve_system, system_names
from drlyap.training import TrainConfig

__all__ = [
    "Controller", "DRPointwise", "DRUniform", "Lyapunov", "Nominal", "Run", "RunDirError", "TrainConfig",
    "UncertainSystem", "cvar_bound", "evaluate", "get_system", "load_run", "register_system", "resolve_system", "save_run",
    "simulate", "system_names", "train", "wasserstein_radius_guarantee",
]
