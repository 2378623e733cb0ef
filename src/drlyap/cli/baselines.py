"""``drlyap lqr`` and ``drlyap rl train``: the baselines a learned pair is compared with."""

from __future__ import annotations

import json
from pathlib import Path

import click

from drlyap.cli.common import fail, floats, refuse_early


@click.command()
@click.argument("system")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Run directory to create.")
@click.option("--q", "q_diag", default=None, help="Diagonal of Q, comma-separated [1/half-width(X)^2].")
@click.option("--r", "r_diag", default=None, help="Diagonal of R, comma-separated [1/half-width(U)^2].")
@click.option("--n-init", type=int, default=200, show_default=True,
              help="Initial states of the evaluation at the system's test shift saved in metrics.json.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of those initial states.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (run_dir, gains, metrics) on stdout.")
def lqr(system: str, out: Path, q_diag: str | None, r_diag: str | None, n_init: int, seed: int, as_json: bool) -> None:
    """LQR baseline for SYSTEM: linearise the true model at x*, u* (nominal parameters), solve the
    Riccati equation, save a run directory of kind lqr (K, P) with u = clamp(u* - K z, U).

    SYSTEM is a registered name, package.module:factory or path/to/file.py:factory."""
    refuse_early(systems=[system])

    from drlyap.runs import train_lqr

    try:
        if n_init < 1:
            raise ValueError(f"--n-init must be >= 1, got {n_init}")
        metrics = train_lqr(system, out, floats(q_diag, "--q"), floats(r_diag, "--r"), n_init=n_init, seed=seed)
        gains = json.loads((out / "lqr.json").read_text())
        name = json.loads((out / "run.json").read_text())["system"]["name"]
    except ValueError as err:
        fail(err)
    if as_json:
        click.echo(json.dumps({"run_dir": str(out), "system": name, "gains": gains, "metrics": metrics}))
        return
    click.echo(f"{name} LQR: K = {gains['K']}, closed-loop eigenvalues "
               f"{[complex(*v) for v in gains['closed_loop_eigenvalues']]}")
    ev = metrics.get("evaluations", {}).get("test_xi")
    if ev is not None:
        click.echo(f"  at the test shift xi = {ev['xi']}: {ev['n_success']}/{ev['n']} stabilised "
                   f"({100 * ev['success_rate']:.1f}%)")
    click.echo(f"  saved {out}")


@click.group()
def rl() -> None:
    """Reinforcement-learning baselines (SAC, PPO; needs the extra drlyap[rl])."""


@rl.command("train")
@click.argument("system")
@click.option("--algo", type=click.Choice(["sac", "ppo"]), default="sac", show_default=True)
@click.option("--steps", type=int, default=None,
              help="Environment steps [sac: 20000, ppo: 100000]. Measured on a shared 2-core CPU, one torch "
                   "thread, pendulum: SAC about 6-9 ms per step once learning starts (20000 steps: 2-3 min), "
                   "PPO about 1.0-1.2 ms per step (100000 steps: about 2 min).")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Run directory to create.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (run_dir, system, algo, metrics) on stdout.")
def rl_train(system: str, algo: str, steps: int | None, seed: int, out: Path, as_json: bool) -> None:
    """Train SAC or PPO (stable-baselines3) on SYSTEM's true model at nominal parameters.

    SYSTEM is a registered name, package.module:factory or path/to/file.py:factory.

    The environment (drlyap.envs) steps the true model with RK4 (pendulum: dt 0.05 s, 10 s episodes)
    and rewards -(theta^2 + 0.1 thetadot^2 + 0.001 u^2) (other systems: the normalised analogue).
    """
    refuse_early(systems=[system])

    from drlyap.rl import train_rl

    try:
        metrics = train_rl(system, algo, steps, seed, out)
        name = json.loads((out / "run.json").read_text())["system"]["name"]
    except ValueError as err:
        fail(err)
    if as_json:
        click.echo(json.dumps({"run_dir": str(out), "system": name, "algo": algo, "metrics": metrics}))
        return
    last = metrics["mean_last_returns"]
    click.echo(f"{name} {algo}: {metrics['samples']} steps in {metrics['train_time_s']:.1f} s "
               f"({metrics['ms_per_1000_steps']:.0f} ms per 1000 steps); mean return of the last episodes "
               f"{'-' if last is None else f'{last:.1f}'}")
    click.echo(f"  saved {out}")
