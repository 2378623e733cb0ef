"""``drlyap reproduce``, ``drlyap compare`` and ``drlyap sweep``: experiments over several runs."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from drlyap.cli.common import (
    compute_options,
    compute_settings,
    default,
    fail,
    floats,
    refuse_early,
    run_source_options,
    run_system_of,
)
from drlyap.config import TrainConfig
from drlyap.proof_settings import ProofConfig
from drlyap.recipes import defaults_text


def seed_values(text: str) -> list[int]:
    """Seeds from ``"0-9"``, ``"0,2,5"`` or a mix (the one syntax of every ``--seeds``); a usage error otherwise."""
    from drlyap.workflows.sweep import parse_seeds

    try:
        return parse_seeds(text)
    except ValueError as err:
        raise click.BadParameter(str(err), param_hint="--seeds") from None


@click.command()
@click.argument("system")
@click.option("--seeds", default="0", show_default=True, help="Training seeds: '0-9', '0,2,5' or '0-4,10'.")
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Output directory [first free runs/reproduce-SYSTEM, -2, -3, ...].")
@click.option("--iters", type=int, default=None,
              help=f"Iteration cap per training run [the system's: {defaults_text('iters')}].")
@click.option("--device", default=default(TrainConfig, "device"), show_default=True)
@click.option("--verify/--no-verify", default=True, show_default=True,
              help="Prove each pair's trained condition, retraining on counterexamples until proved (as `train`).")
@click.option("--verify-rounds", type=int, default=default(ProofConfig, "rounds"), show_default=True,
              help="Retraining rounds at most.")
@click.option("--verify-time", type=float, default=None,
              help=f"Seconds per proof at the test shift [the system's: {defaults_text('verify_time')}], also the "
                   f"cap of each proof round in training [the system's cap: {defaults_text('round_time')}; the rounds "
                   "are budgeted by boxes].")
@click.option("--horizon", type=float, default=None, help="Simulated time of the evaluations [system default].")
@compute_options(with_device=False)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object with both methods' results.")
def reproduce(system: str, seeds: str, out: Path | None, iters: int | None, device: str, verify: bool,
              verify_rounds: int, verify_time: float | None, horizon: float | None, workers: int, backend: str,
              address: str | None, as_json: bool) -> None:
    """Reproduce the paper's experiment: baseline vs DR at SYSTEM's test shift, every pair proved.

    SYSTEM is a registered name (`drlyap systems`), package.module:factory or path/to/file.py:factory;
    it must declare a test shift (test_xi) and a training distribution (xi_sampler)."""
    refuse_early(systems=[system])

    from drlyap.systems import resolve_system, system_source
    from drlyap.workflows.reproduce import ReproduceSettings, format_table
    from drlyap.workflows.reproduce import reproduce as run_reproduce

    seed_list = seed_values(seeds)
    compute = compute_settings(workers, backend, address, device)
    log = (lambda s: click.echo(s, err=True)) if as_json else click.echo
    try:
        sys_ = resolve_system(system)
        if out is None:  # first free runs/reproduce-SYSTEM[-K], so that running the quickstart twice just works
            out = Path("runs") / f"reproduce-{sys_.name}"
            k = 2
            while out.exists():
                out, k = Path("runs") / f"reproduce-{sys_.name}-{k}", k + 1
            if k > 2:
                log(f"runs/reproduce-{sys_.name} exists: writing {out} (--out names the folder)")
        if verify_rounds < 0:
            raise ValueError(f"--verify-rounds must be >= 0, got {verify_rounds}")
        for name, value in (("--verify-time", verify_time), ("--horizon", horizon)):
            if value is not None and not value > 0:
                raise ValueError(f"{name} must be > 0, got {value}")
        settings = ReproduceSettings(seeds=seed_list, iters=iters, device=device, horizon=horizon, verify=verify,
                                     verify_rounds=verify_rounds, verify_time=verify_time)
        report = run_reproduce(sys_, settings, out, source=system_source(system, sys_), compute=compute, progress=True,
                               log=log)
    except ValueError as err:
        fail(err)
    if as_json:
        click.echo(json.dumps(report))
        return
    click.echo("")
    click.echo(format_table(report))
    click.echo(f"\nwrote {out} (report.md, report.json, seed*/figures)")


@click.command()
@click.argument("run_dirs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--xi", required=True, help="Parameter shift, comma-separated in the system's uncertain order.")
@click.option("--n-init", type=int, default=200, show_default=True, help="Number of initial states.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the initial states.")
@click.option("--horizon", type=float, default=None, help="Simulated time [system default].")
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Write compare.json, compare.md and figures (certificate and input over time) here.")
@click.option("--certify-time", type=float, default=10.0, show_default=True,
              help="Seconds of sound verification per check of a run at --xi (0 skips it).")
@compute_options()
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@run_source_options
def compare(run_dirs: tuple[Path, ...], xi: str, n_init: int, seed: int, horizon: float | None, out: Path | None,
            certify_time: float, workers: int, backend: str, address: str | None, device: str, as_json: bool,
            system_spec: str | None, trust_run: bool) -> None:
    """Compare runs of any kind (lyapunov, lqr, rl, imported) at parameter shift --xi on the true model.

    Per run: success rate; samples used in training (Lyapunov: model evaluations at training states,
    n_states x iterations with the default resampling; RL: environment steps; LQR: 0); training wall
    time; and how often the Lyapunov function or its stand-in (V, z'Pz for LQR, the negated critic value for
    RL) increases along successful trajectories (a step counts when it rises by more than 1e-4 of that trajectory's
    range; lower is better, 0 means monotone); and what each run proves on the true model at --xi,
    by the sound verifier over the whole region: the decrease condition (learned pairs with their
    own gamma, LQR's z'Pz with a scale-free decay alpha z'Pz; an RL policy's deterministic actor, or an imported
    controller without V, with the z'Pz of its linearisation, where x* is its equilibrium) and the certified region
    of attraction (a sublevel set of that function from which every trajectory converges to x*).
    """
    refuse_early(runs=run_dirs, systems=[system_spec])

    from drlyap.workflows.compare import CompareSettings, compare_runs, format_comparison

    compute = compute_settings(workers, backend, address, device)
    try:
        if horizon is not None and horizon <= 0:
            raise ValueError(f"--horizon must be > 0, got {horizon}")
        if certify_time < 0:
            raise ValueError(f"--certify-time must be >= 0, got {certify_time}")
        settings = CompareSettings(xi=floats(xi, "--xi"), n_init=n_init, seed=seed, horizon=horizon,
                                   certify_time_limit=certify_time if certify_time > 0 else None)
        report = compare_runs(list(run_dirs), settings, out, progress=True, system=run_system_of(system_spec),
                              trust=trust_run, compute=compute)
    except ValueError as err:
        fail(err)
    if as_json:
        click.echo(json.dumps(report))
        return
    click.echo(format_comparison(report))
    if out is not None:
        click.echo(f"\nwrote {out} (compare.md, compare.json, figures/)")


@click.command("sweep")
@click.argument("system")
@click.option("--seeds", default="0-4", show_default=True, help="Training seeds: '0-9', '0,2,5' or '0-4,10'.")
@click.option("--radius", default=None, help="Wasserstein radii r, comma-separated [the system's default].")
@click.option("--eps", default=None, help="Risk levels eps, comma-separated [the system's default].")
@click.option("--method", default="dr", show_default=True,
              help="dr, baseline or both (the baseline ignores r and eps: one run per seed).")
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Sweep directory; rerunning the same sweep into it resumes it [runs/sweep-SYSTEM].")
@click.option("--backend", type=click.Choice(["local", "ray"]), default="local", show_default=True,
              help="local: worker processes on this machine; ray: one Ray task per combination (pip install drlyap[ray]).")
@click.option("--workers", type=int, default=1, show_default=True,
              help="Concurrent combinations (local processes, or CPUs of a local Ray), one torch thread each.")
@click.option("--address", default=None, help="Ray cluster to join ('auto', 'ray://HOST:10001'); default: start Ray here.")
@click.option("--iters", type=int, default=None,
              help=f"Iteration cap per training run [the system's: {defaults_text('iters')}].")
@click.option("--verify/--no-verify", default=True, show_default=True,
              help="Prove each trained pair with counterexample-guided rounds, as `train` does.")
@click.option("--verify-rounds", type=int, default=default(ProofConfig, "rounds"), show_default=True,
              help="Retraining rounds at most per pair.")
@click.option("--device", default=default(TrainConfig, "device"), show_default=True,
              help="cpu or cuda (for every combination).")
@click.option("--shifts", default="1,2,3,4,5", show_default=True, help="Evaluate at these multiples of the test shift.")
@click.option("--n-init", type=int, default=200, show_default=True, help="Evaluation initial states per seed.")
@click.option("--verify-time-limit", type=float, default=None,
              help=f"Seconds per branch and bound [the system's: {defaults_text('verify_time')}; the proof rounds are "
                   "budgeted by boxes, with this as their cap].")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (progress goes to stderr).")
def sweep(system: str, seeds: str, radius: str | None, eps: str | None, method: str, out: Path | None, backend: str,
          workers: int, address: str | None, iters: int | None, verify: bool, verify_rounds: int, device: str,
          shifts: str, n_init: int, verify_time_limit: float, as_json: bool) -> None:
    """Train, verify and evaluate every combination of seeds x radii x eps for SYSTEM; resumable.

    SYSTEM is a registered name (`drlyap systems`), package.module:factory or path/to/file.py:factory.
    One run directory per combination under --out, plus results.csv, results.json and figures/sweep.png.
    Running the same command again continues an interrupted sweep and retries failed combinations.
    """
    refuse_early(systems=[system])

    from drlyap.systems import resolve_system
    from drlyap.workflows import sweep as sw

    try:
        sys_ = resolve_system(system)
        spec = sw.SweepSpec(system=system, seeds=seed_values(seeds),
                            radii=sw.parse_values(radius, "--radius") if radius else [sys_.defaults.wasserstein_radius],
                            eps=sw.parse_values(eps, "--eps") if eps else [sys_.defaults.risk_level],
                            methods=sw.parse_methods(method), iters=iters, verify=verify, verify_rounds=verify_rounds,
                            device=device, shift_factors=sw.parse_values(shifts, "--shifts"), n_init=n_init,
                            verify_time_limit=verify_time_limit)
        spec.validate()
        if backend == "local":
            from drlyap.sections import resolve_device

            resolve_device(device)
        out = out or Path("runs") / f"sweep-{sys_.name}"
        total = len(spec.combinations())
        log = (lambda s: click.echo(s, err=True)) if as_json else click.echo
        bar = None
        if sys.stderr.isatty() and not as_json:  # piped: the per-combination lines below are the progress
            from drlyap.progress import progress

            bar = progress(total, f"sweep {sys_.name}")

        def on_result(row: dict, done: int, total: int) -> None:
            if bar is not None:
                bar.update(1)
                bar.write(sw.format_row(row))
            else:
                log(f"[{done}/{total}] {sw.format_row(row)}")

        with sw.make_backend(backend, workers, address) as runner:
            report = sw.run_sweep(spec, out, runner, on_result=on_result)
        if bar is not None:
            bar.close()
    except ValueError as err:
        fail(err)
    if as_json:
        click.echo(json.dumps(report))
    else:
        click.echo("")
        click.echo(sw.format_summary(report))
        damaged = f", {len(report['damaged'])} damaged one(s) redone" if report["damaged"] else ""
        click.echo(f"\n{len(report['computed'])} combination(s) run, {len(report['reused'])} reused from an earlier run"
                   f"{damaged}, {report['failed']} failed; {report['wall_s']:.1f} s on the {report['backend']} backend")
        figure = ", figures/sweep.png" if report["figures"] else ""
        click.echo(f"wrote {out} (results.csv, results.json{figure}, one run directory per finished combination)")
    if report["failed"]:
        click.echo(f"Error: {report['failed']} of {len(report['rows'])} combination(s) failed (see their error above "
                   "and in results.csv); rerun the same command to retry them", err=True)
        sys.exit(1)
