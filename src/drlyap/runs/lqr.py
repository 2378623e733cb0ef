"""LQR run directories (``drlyap lqr``): the design on disk, and its loader for :func:`load_policy_run`.

Layout (written atomically)::

    RUN_DIR/
      run.json       {"kind": "lqr", "format": 1, "system": system.describe()}
      config.json    system, Q, R, xi used for the design
      lqr.json       K, P, A, B, closed-loop eigenvalues of A - B K
      metrics.json   samples (0), train_time_s, closed-loop eigenvalues, optional evaluations
      figures/
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from pathlib import Path

import torch

from drlyap.io import write_json
from drlyap.lqr import LQRDesign, lqr_design
from drlyap.runs.directory import RunDirError, atomic_dir, read_run_json, run_record, run_system
from drlyap.runs.policies import PolicyRun
from drlyap.runs.publish import check_writable
from drlyap.simulation import evaluate, initial_states
from drlyap.systems import UncertainSystem, resolve_system, system_source


def save_lqr_run(out: str | os.PathLike, design: LQRDesign, metrics: dict | None = None, overwrite: bool = False,
                 design_time_s: float = 0.0, source: dict | None = None) -> Path:
    """Write an LQR design as a run directory of kind ``lqr`` (atomically); ``source``: see
    :func:`drlyap.runs.directory.run_record`."""
    system = design.system
    eigs = design.closed_loop_eigenvalues

    def fill(tmp: Path) -> None:
        write_json(tmp / "config.json", {"system": system.name, "Q": design.Q.tolist(), "R": design.R.tolist(),
                                          "xi": design.xi, "weights": "Bryson: 1/half-width^2 (default) or user-given"})
        write_json(tmp / "lqr.json", {"K": design.K.tolist(), "P": design.P.tolist(), "A": design.A.tolist(),
                                       "B": design.B.tolist(),
                                       "closed_loop_eigenvalues": [[v.real, v.imag] for v in eigs]})
        write_json(tmp / "metrics.json", {"samples": 0, "train_time_s": design_time_s,
                                           "closed_loop_eigenvalues": [[v.real, v.imag] for v in eigs]}
                    | (metrics or {}))
        (tmp / "figures").mkdir()
        write_json(tmp / "run.json", run_record("lqr", system, source))

    return atomic_dir(Path(out), fill, overwrite)


def train_lqr(system: str | UncertainSystem, out: str | os.PathLike, Q: Sequence[float] | None = None,
              R: Sequence[float] | None = None, evaluate_test: bool = True, n_init: int = 200, seed: int = 0) -> dict:
    """Design LQR for a system (an object, or a spec for :func:`drlyap.systems.resolve_system`), optionally
    evaluate it at the system's test shift, save a run dir.

    Returns the metrics dict written to ``metrics.json``.
    """
    source = None
    if isinstance(system, str):
        spec, system = system, resolve_system(system)
        source = system_source(spec, system)
    check_writable(out)
    system.check_finite()
    tic = time.perf_counter()
    design = lqr_design(system, Q, R)
    elapsed = time.perf_counter() - tic
    metrics: dict = {"samples": 0, "train_time_s": elapsed}
    if evaluate_test and system.test_xi is not None:
        x0 = initial_states(system, n_init, torch.Generator().manual_seed(seed))
        xi = torch.tensor(system.test_xi, dtype=torch.float64)
        metrics["evaluations"] = {"test_xi": evaluate(system, design.controller, x0, xi, lyapunov=design.certificate)}
    save_lqr_run(out, design, metrics, design_time_s=elapsed, source=source)
    return json.loads((Path(out) / "metrics.json").read_text())


def load_lqr_run(path: str | os.PathLike, system: UncertainSystem | None = None, trust: bool = False) -> PolicyRun:
    """An LQR run directory as a :class:`PolicyRun` (``system``, ``trust``: as :func:`drlyap.runs.load_run`)."""
    path = Path(path)
    info, config, gains, metrics = read_run_json(path, "lqr", "run.json", "config.json", "lqr.json", "metrics.json")
    system = run_system(path, config["system"], system, info, trust)
    t = {k: torch.tensor(gains[k], dtype=torch.float64) for k in ("K", "P", "A", "B")}
    if t["K"].shape != (system.m, system.n) or t["P"].shape != (system.n, system.n):
        raise RunDirError(f"{path}: K/P shapes {tuple(t['K'].shape)}/{tuple(t['P'].shape)} do not fit {system.name}")
    design = LQRDesign(system, torch.tensor(config["Q"], dtype=torch.float64), torch.tensor(config["R"], dtype=torch.float64),
                       t["A"], t["B"], t["K"], t["P"], config.get("xi"))
    return PolicyRun(path, "lqr", system, design.controller, design.certificate, 0, metrics.get("train_time_s"), "lqr",
                     config, metrics, {"design": design})

