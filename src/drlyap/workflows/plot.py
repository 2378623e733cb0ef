"""The figures of one trained pair (``drlyap plot RUN_DIR``).

Simulates the run on the true model at a shift and hands the data to :mod:`drlyap.plotting`
(which only draws): a phase portrait with labelled level sets of V and the certified set, V(t) and u(t) with
the input limits, and heatmaps of V and of the decrease residual on the plane.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch import Tensor

from drlyap import plotting
from drlyap.render import region_label
from drlyap.runs import Run, load_run
from drlyap.simulation import Trajectories, initial_states, simulate, success_mask
from drlyap.verification import RegionOfAttraction
from drlyap.workflows.verify import VerifyRequest, run_proof, verify


def region_to_draw(run: Run, roa: RegionOfAttraction | None, recorded: bool = False) -> dict | None:
    """``{"level", "certified", "label"}`` for :func:`~drlyap.plotting.draw_phase`, or None when there is no
    level. ``recorded``: ``roa`` was read from the run's ``metrics.json``, not proved here (the label says so: a run
    directory may come from anyone)."""
    if roa is None:
        return None
    where = (plotting.shift_text(run.system, roa.xi) + " (true model)" if roa.xi is not None
             else "the trained condition (design model)")
    label = region_label(roa, where)
    if not label:
        return None
    if recorded:
        label = f"as metrics.json records it, not re-proved here: {label}"
    return {"level": float(roa.level), "certified": bool(roa.certified), "label": label, "recorded": recorded}


def decrease_residual(run: Run, x: Tensor, xi: Tensor | None) -> Tensor:
    """The residual of plain decrease on the true model at ``xi`` (``Vdot + gamma |z| (+ alpha V)``, float64
    networks) at user states ``x (B, n)`` -> ``(B,)``: the condition ``verify --xi`` proves."""
    system = run.system
    condition = run.true_condition(torch.zeros(system.k, dtype=torch.float64) if xi is None else xi)
    return run.loop.exact(condition, system.to_local(x.to(torch.float64)))


@dataclass(frozen=True)
class PlotSettings:
    """What :func:`plot_run` draws: the true model at the shift ``xi`` (None: the system's test shift, or the nominal
    model), ``n_init`` trajectories in the phase portrait from initial states drawn with ``seed``, over ``horizon``
    units of simulated time (None: the system's), V and the decrease residual on a grid of ``per_axis`` points a side;
    the certified set: ``roa`` True proves it now (each proof at most ``time_limit`` seconds), False draws none, None
    the one in ``metrics["certificate"]["roa"]`` when the run has one."""

    xi: Sequence[float] | None = None
    n_init: int = 20
    seed: int = 0
    roa: bool | None = None
    time_limit: float = 30.0
    per_axis: int = 160
    horizon: float | None = None


def plot_run(run_dir: str | os.PathLike, settings: PlotSettings = PlotSettings(), out: str | os.PathLike | None = None,
             *, system=None, trust: bool = False) -> dict:
    """Write the figures of one Lyapunov run to ``out`` (default ``RUN_DIR/figures``) and return what was drawn.

    ``settings``: what is drawn (:class:`PlotSettings`; with ``roa`` True the certified sublevel set is proved now,
    :func:`drlyap.workflows.verify.verify` at its shift). ``system``, ``trust``: as :func:`drlyap.runs.load_run`.
    Returns ``{"run_dir", "xi", "n", "n_success", "region", "figures": [paths]}``.
    """
    run = load_run(run_dir, system, trust)
    system = run.system
    n_init, horizon = settings.n_init, settings.horizon
    if n_init < 1:
        raise ValueError(f"--n-init must be >= 1, got {n_init}")
    xi = settings.xi
    if xi is None and system.test_xi is not None:
        xi = system.test_xi
    shift = None if xi is None else system.check_xi(xi)
    folder = Path(out) if out is not None else Path(run_dir) / "figures"
    folder.mkdir(parents=True, exist_ok=True)
    where = plotting.shift_text(system, shift)
    region, missing = _region(run, shift, settings.roa, settings.time_limit)

    x0 = initial_states(system, n_init, torch.Generator().manual_seed(settings.seed))
    starts = [tuple(float(v) for v in s) for s in getattr(system, "reference_states", ()) or ()] or \
        [tuple(v) for v in x0[:3].tolist()]
    both = simulate(system, run.controller, torch.cat([x0, torch.tensor(starts, dtype=torch.float64)]), shift,
                    horizon=horizon)  # one simulation: the per-step cost dominates, not the batch
    traj = Trajectories(both.t, both.x[:, :n_init], both.u[:, :n_init])
    ref = Trajectories(both.t, both.x[:, n_init:], both.u[:, n_init:])
    success, _ = success_mask(system, traj.x)
    grid = plotting.lyapunov_grid(system, run.lyapunov, settings.per_axis)
    title = (f"{system.name} ({run.config.method}), true model at {where}\n"
             f"{int(success.sum())}/{n_init} stabilised; {_region_note(region, missing)}")
    paths = [plotting.phase_portrait(system, traj, success.tolist(), folder / "phase_portrait.png", title, grid,
                                     region, run.config.delta)]
    paths += _reference_figures(run, ref, starts, folder, f"{system.name} ({run.config.method}), true model at {where}")
    paths.append(_decrease_figure(run, grid, shift, folder, where))
    return {"run_dir": str(run_dir), "xi": None if shift is None else shift.tolist(), "n": n_init,
            "n_success": int(success.sum()), "region": region, "figures": [str(p) for p in paths]}


def _region(run: Run, shift: Tensor | None, roa: bool | None, time_limit: float) -> tuple[dict | None, str]:
    """The certified set to draw (:func:`region_to_draw`; proved now with ``roa`` True, read from metrics.json with
    None, none with False) and the words of why none is drawn."""
    if roa:
        proof = replace(run_proof(run), time_limit=time_limit, roa_time=time_limit)
        found = verify(run, proof, VerifyRequest(xi=shift, roa=True)).roa
        missing = found.error or "the verifier certified no sublevel set of V (level <= 0)"
        if found.error is not None:
            found = None
        elif found.xi is None and shift is not None:
            found.xi = shift.tolist()
    elif roa is None:
        found = run.certificate.region_of_attraction() if run.certificate else None
        missing = "none stored in metrics.json; --roa computes one"
    else:
        found, missing = None, "--no-roa"
    region = region_to_draw(run, found, recorded=roa is None)
    if found is not None and region is None:
        missing = f"the verifier's level is {found.level}: no sublevel set certified"
    return region, missing


def _region_note(region: dict | None, missing: str) -> str:
    """What the phase portrait's title says of the shaded set."""
    if region is None:
        return f"no certified set drawn ({missing})"
    note = "shaded: " + ("certified" if region["certified"] else "not certified")
    if region["recorded"]:
        note = "shaded: " + ("recorded as certified in metrics.json (`drlyap check` re-proves it)"
                             if region["certified"] else "recorded in metrics.json, not certified")
    return note


def _reference_figures(run: Run, ref: Trajectories, starts: list[tuple], folder: Path, title: str) -> list[Path]:
    """V(t) and u(t), and the states over time, from the reference ``starts`` (``ref``: their trajectories)."""
    system = run.system
    series = {}
    for i, start in enumerate(starts):
        text = ", ".join(f"{v:.3g}" for v in start)
        series[f"from ({text})"] = (ref.t, run.lyapunov(ref.x[:, i]), ref.u[:, i])
    return [plotting.time_series(series, folder / "certificate_and_input.png", title,
                                 value_label="V(x(t))", input_label=plotting.input_label(system),
                                 time_label=plotting.time_label(system), limits=plotting.input_limits(system),
                                 input_names=system.input_names),
            plotting.states_over_time(system, {label: (ref.t, ref.x[:, i]) for i, label in enumerate(series)},
                                      folder / "states.png", title)]


def _decrease_figure(run: Run, grid: tuple, shift: Tensor | None, folder: Path, where: str) -> Path:
    """The heatmap of the decrease residual on the plane of ``grid`` (blank inside the delta-ball)."""
    system = run.system
    gx, gy, gv = grid
    x = plotting.plane_states(system, gx, gy)
    residual = decrease_residual(run, x, shift)
    residual[system.to_local(x).norm(dim=-1) < run.config.delta] = float("nan")
    condition = "Vdot + gamma |x - x*|" + (" + alpha V" if run.config.exp_rate else "")
    return plotting.decrease_map(system, grid, residual.reshape(gx.shape), folder / "decrease_map.png",
                                 f"{system.name} ({run.config.method}), true model at {where}", condition,
                                 run.config.delta)
