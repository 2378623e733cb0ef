"""drlyap: distributionally robust neural controllers with Lyapunov certificates.

Python API::

    import drlyap
    drlyap.check_writable("runs/pendulum-dr")                       # a taken path is refused now, not after training
    result = drlyap.train(drlyap.TrainConfig(system="pendulum"))   # trains, then proves the condition
    result.record.certificate_status                                  # 'verified', 'violated' or 'unknown'
    path = drlyap.save_run("runs/pendulum-dr", result)
    run = drlyap.load_run(path)
    u = run.controller(x)      # x: (B, n) tensor in user coordinates -> (B, m)
    v = run.lyapunov(x)        # -> (B,)
    drlyap.evaluate(run.system, run.controller, x0, xi)              # simulate the true model at the shift xi
    drlyap.verify(run, request=drlyap.VerifyRequest(xi=xi, roa=True))  # prove its decrease and region there

The names above are loaded on first use. The first one used sets torch to one thread (as the command line does:
the numbers here were measured that way, and two threads on two shared cores ran up to 45x slower), unless the
environment variable ``DRLYAP_THREADS`` says otherwise; ``drlyap.set_threads(n)`` changes it at any time. It also
asks glibc's malloc to keep freed memory for reuse (:mod:`drlyap.memory`; ``DRLYAP_MALLOC=system`` does not).
"""

from __future__ import annotations

import importlib
import os

_API = {
    "train": "drlyap.training", "fit": "drlyap.training", "TrainResult": "drlyap.training",
    "TrainConfig": "drlyap.config", "SystemDefaults": "drlyap.config",
    "ProofConfig": "drlyap.proof_settings", "Budget": "drlyap.proof_settings", "Compute": "drlyap.compute",
    "ClosedLoop": "drlyap.closed_loop",
    "UncertainSystem": "drlyap.systems", "get_system": "drlyap.systems", "register_system": "drlyap.systems",
    "resolve_system": "drlyap.systems", "system_names": "drlyap.systems",
    "Controller": "drlyap.networks", "Lyapunov": "drlyap.networks",
    "DRPointwise": "drlyap.conditions", "DRUniform": "drlyap.conditions", "Nominal": "drlyap.conditions",
    "TrueDecrease": "drlyap.conditions", "cvar_bound": "drlyap.conditions",
    "wasserstein_radius_guarantee": "drlyap.conditions",
    "Run": "drlyap.runs", "RunDirError": "drlyap.runs", "load_run": "drlyap.runs", "save_run": "drlyap.runs",
    "check_writable": "drlyap.runs",
    "evaluate": "drlyap.simulation", "simulate": "drlyap.simulation",
    "load_policy_run": "drlyap.workflows.policies", "verify": "drlyap.workflows.verify",
    "VerifyRequest": "drlyap.workflows.verify",
}

__all__ = sorted([*_API, "set_threads"])

_threads_set = False


def set_threads(count: int | None = None) -> int:
    """Set torch's thread count: ``count``, else ``DRLYAP_THREADS``, else 1. Returns it."""
    global _threads_set
    value = count if count is not None else os.environ.get("DRLYAP_THREADS", "1")
    if not str(value).isdigit() or int(value) < 1:
        raise ValueError(f"the thread count must be a positive integer, got {value!r} (DRLYAP_THREADS or set_threads)")
    import torch

    from drlyap.memory import keep_freed_memory

    torch.set_num_threads(int(value))
    keep_freed_memory()
    _threads_set = True
    return int(value)


def __getattr__(name: str):
    if name in _API:
        module, attr = _API[name], name
    else:
        raise AttributeError(f"module 'drlyap' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), attr)
    if not _threads_set:
        set_threads()
    globals()[name] = value
    return value
