"""``drlyap evaluate`` and ``drlyap plot``: a run on the true model."""

from __future__ import annotations

import json
from pathlib import Path

import click

from drlyap.cli.common import fail, floats, refuse_early, run_source_options, run_system_of


def _writable_folder(folder: Path) -> None:
    """A ValueError naming ``folder`` where figures cannot be written there (checked before any work)."""
    import tempfile

    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".probe-"):
            pass
    except OSError as err:
        raise ValueError(f"cannot write the figures to {folder} ({err.strerror or err}); choose another --out") from None


@click.command()
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--xi", required=True, help="Parameter shift, comma-separated in the system's uncertain order.")
@click.option("--n-init", type=int, default=200, show_default=True, help="Number of initial states.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the initial states.")
@click.option("--horizon", type=float, default=None, help="Simulated time [system default].")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@run_source_options
def evaluate(run_dir: Path, xi: str, n_init: int, seed: int, horizon: float | None, as_json: bool,
             system_spec: str | None, trust_run: bool) -> None:
    """Simulate RUN_DIR's controller (a run of any kind) on the true model at parameter shift --xi."""
    refuse_early(runs=[run_dir], systems=[system_spec])

    import torch

    from drlyap.simulation import evaluate as score
    from drlyap.simulation import initial_states
    from drlyap.workflows.policies import load_policy_run

    try:
        run = load_policy_run(run_dir, run_system_of(system_spec), trust_run)
        shift = run.system.check_xi(floats(xi, "--xi"))
        if horizon is not None and horizon <= 0:
            raise ValueError(f"--horizon must be > 0, got {horizon}")
        x0 = initial_states(run.system, n_init, torch.Generator().manual_seed(seed))
        result = score(run.system, run.controller, x0, shift, lyapunov=run.certificate, horizon=horizon)
    except ValueError as err:
        fail(err)
    result["run_dir"] = str(run_dir)
    if as_json:
        click.echo(json.dumps(result))
        return
    what = run.config.get("method") if run.kind == "lyapunov" else run.label
    click.echo(f"{run.system.name} ({what}) at xi = {shift.tolist()}: "
               f"{result['n_success']}/{result['n']} stabilised ({100 * result['success_rate']:.1f}%)")
    if result["worst_v_increase"] is not None:
        click.echo(f"  worst one-step increase of V along successful trajectories: {result['worst_v_increase']:.3g}")


@click.command()
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--xi", default=None, help="Shift of the true model, comma-separated [the system's test shift, or nominal].")
@click.option("--n-init", type=int, default=20, show_default=True, help="Number of trajectories in the phase portrait.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of their initial states.")
@click.option("--roa/--no-roa", default=None,
              help="Compute the certified sublevel set of V now at --xi (--roa) or draw none (--no-roa) "
                   "[the one stored in metrics.json, if any].")
@click.option("--time-limit", type=float, default=30.0, show_default=True, help="Seconds for --roa's branch and bound.")
@click.option("--horizon", type=float, default=None, help="Simulated time [system default].")
@click.option("--out", type=click.Path(path_type=Path), default=None, help="Folder for the PNGs [RUN_DIR/figures].")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object with the written paths.")
@run_source_options
def plot(run_dir: Path, xi: str | None, n_init: int, seed: int, roa: bool | None, time_limit: float,
         horizon: float | None, out: Path | None, as_json: bool, system_spec: str | None, trust_run: bool) -> None:
    """Figures of RUN_DIR on the true model: phase portrait with labelled level sets of V and the certified set,
    V(t) and u(t) with the input limits, and heatmaps of V and of the decrease condition."""
    refuse_early(runs=[run_dir], systems=[system_spec])

    from drlyap.workflows.plot import PlotSettings, plot_run

    try:
        if time_limit <= 0:
            raise ValueError(f"--time-limit must be > 0, got {time_limit}")
        _writable_folder(out if out is not None else run_dir / "figures")  # checked before any work
        settings = PlotSettings(xi=floats(xi, "--xi"), n_init=n_init, seed=seed, roa=roa, time_limit=time_limit,
                                horizon=horizon)
        result = plot_run(run_dir, settings, out, system=run_system_of(system_spec), trust=trust_run)
    except ValueError as err:
        fail(err)
    if as_json:
        click.echo(json.dumps(result))
        return
    region = result["region"]
    click.echo(f"{result['n_success']}/{result['n']} trajectories stabilised; "
               + (region["label"] if region else "no certified set drawn"))
    for path in result["figures"]:
        click.echo(f"wrote {path}")
