"""The ``drlyap`` command line (click). Every command has ``--help``."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import click
import torch

from drlyap.io import proved_percent
from drlyap.systems import get_system, resolve_system, system_names, system_source


def _setup_threads() -> None:
    # The two shared cores of a laptop-class machine: one torch thread unless the user says otherwise.
    value = os.environ.get("DRLYAP_THREADS", "1")
    if not value.isdigit() or int(value) < 1:
        raise click.ClickException(f"DRLYAP_THREADS must be a positive integer, got {value!r}")
    torch.set_num_threads(int(value))


def _floats(text: str | None, what: str) -> list[float] | None:
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise click.BadParameter(f"{what} must be comma-separated numbers, got {text!r}") from None
    if not values or not all(torch.isfinite(torch.tensor(values))):
        raise click.BadParameter(f"{what} must be finite numbers, got {text!r}")
    return values


def _ints(text: str, what: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise click.BadParameter(f"{what} must be comma-separated integers, got {text!r}") from None
    if not values:
        raise click.BadParameter(f"{what} is empty")
    return values


def _proved(result: dict) -> str:
    """The proved share of a verification result, never rounded up to 100% unless it is verified."""
    return proved_percent(result["verified_fraction"], result["status"] == "verified", 4)


def _fail(err: Exception) -> None:
    raise click.ClickException(str(err))


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="drlyap")
def main() -> None:
    """Distributionally robust neural controllers with Lyapunov certificates.

    Train a controller pi and certificate V on an uncertain system from a few samples of its
    parameters, then evaluate the closed loop on the true, shifted system.
    """
    _setup_threads()


@main.command()
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def systems(as_json: bool) -> None:
    """List the built-in systems with their dimensions and parameters."""
    described = [get_system(name).describe() for name in system_names()]
    if as_json:
        click.echo(json.dumps(described, indent=2))
        return
    for d in described:
        params = ", ".join(f"{k}={v:g}" for k, v in d["parameters"].items())
        click.echo(f"{d['name']}: n={d['n']} states {d['states']}, m={d['m']} inputs {d['inputs']}, "
                   f"k={d['k']} uncertain {d['uncertain']}")
        click.echo(f"    parameters: {params}; x* = {[round(v, 4) for v in d['equilibrium']]}; "
                   f"U = {d['input_box']}; test xi = {d['test_xi']}")


@main.command()
@click.argument("system")
@click.option("--method", type=click.Choice(["baseline", "dr"]), default="dr", show_default=True,
              help="baseline: nominal condition at the mean xi sample; dr: distributionally robust.")
@click.option("--loss", type=click.Choice(["pointwise", "uniform"]), default="pointwise", show_default=True,
              help="DR condition: per-state (pointwise) or over the whole region (uniform).")
@click.option("--radius", type=float, default=None, help="Wasserstein radius r [system default].")
@click.option("--eps", type=float, default=None, help="Risk level eps in (0, 1) [system default].")
@click.option("--gamma", type=float, default=None, help="Decay rate gamma in Vdot + gamma||x-x*|| <= 0.")
@click.option("--exp-rate", type=float, default=None,
              help="alpha of the exponential variant (adds alpha V inside the condition) [system default; 0].")
@click.option("--xi-samples", default=None,
              help="Explicit xi samples 'a,b;c,d;...' (one sample per ';'); default: drawn from the system.")
@click.option("--iters", type=int, default=3000, show_default=True, help="Iteration cap.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--device", default="cpu", show_default=True, help="cpu or cuda.")
@click.option("--warm-start", type=click.Path(path_type=Path), default=None,
              help="Start from the networks of this run directory (e.g. a baseline run).")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Run directory to create.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@click.option("--verify/--no-verify", default=True, show_default=True,
              help="Prove the trained condition after training, retraining on counterexamples (CEGIS) until it is "
                   "proved or the rounds/budget run out. --no-verify: training and the acceptance check only.")
@click.option("--verify-rounds", type=int, default=5, show_default=True, help="Retraining rounds at most.")
@click.option("--verify-time", type=float, default=None,
              help="Seconds per proof [the system's: 30; 120 for cartpole and quadrotor2d].")
@click.option("--verify-budget", type=float, default=None, help="Total seconds for the retraining rounds [no limit].")
@click.option("--local-rate", type=float, default=None,
              help="Ask V to decay at this rate near x* on every training sample's linearisation (a loss term; the "
                   "acceptance check then asks V to decrease there) [0: not asked].")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (run_dir, system, metrics) on stdout.")
def train(system: str, method: str, loss: str, radius: float | None, eps: float | None, gamma: float | None,
          exp_rate: float | None, xi_samples: str | None, iters: int, seed: int, device: str, warm_start: Path | None,
          out: Path, quiet: bool, verify: bool, verify_rounds: int, verify_time: float | None,
          verify_budget: float | None, local_rate: float | None, as_json: bool) -> None:
    """Train a controller and Lyapunov certificate for SYSTEM, prove the trained condition, save a run directory.

    SYSTEM is a registered name, package.module:factory or path/to/file.py:factory (see `drlyap systems`).
    The last line says whether the condition is VERIFIED (proved at every state of the box minus the
    delta-ball), VIOLATED (a counterexample) or UNKNOWN (budget ran out).
    """
    from drlyap.cegis import train_certified
    from drlyap.rundir import ensure_new, load_run, save_run
    from drlyap.training import TrainConfig

    try:
        sys_ = resolve_system(system)
        samples = None
        if xi_samples is not None:
            samples = [_floats(part, "--xi-samples") for part in xi_samples.split(";") if part.strip()]
        cfg = TrainConfig(system=sys_.name, method=method, loss=loss, wasserstein_radius=radius, risk_level=eps,
                          decay_rate=gamma, exp_rate=exp_rate, xi_samples=samples, iters=iters, seed=seed,
                          device=device, verify=verify, verify_rounds=verify_rounds, verify_time=verify_time,
                          verify_budget=verify_budget, local_rate=local_rate)
        cfg.resolved(sys_)  # refuse a bad config before anything runs
        ensure_new(out)
        init = None
        if warm_start is not None:
            prior = load_run(warm_start, sys_)
            init = (prior.lyapunov_net, prior.controller_net)

        def show_round(e: dict) -> None:
            v = e["verification"]
            line = (f"  proof round {e['round']}: {v['status'].upper()}, {_proved(v)} of X_delta "
                    f"proved ({v['time_s']:.2f} s)")
            if "counterexamples_added" in e:
                line += (f"; retraining with {e['counterexamples_added']} counterexamples (+{e['neighbours_added']} "
                         f"neighbours, {e['box_centres_added']} box centres)")
            click.echo(line, err=True)

        result = train_certified(cfg, sys_, progress=not quiet, init=init, log=show_round, warn=False)
        save_run(out, result, source=system_source(system, sys_))
    except ValueError as err:
        _fail(err)
    m = result.metrics
    if as_json:
        click.echo(json.dumps({"run_dir": str(out), "system": sys_.name, "method": method, "metrics": m}))
        return
    c = m.get("cegis")
    iterations, seconds = (c["total_iterations"], c["total_time_s"]) if c else (m["iterations"], m["train_time_s"])
    click.echo(f"{sys_.name} {method}: {m['status']} ({iterations} iterations, {seconds:.1f} s in all)")
    acc = m["acceptance"]
    click.echo(f"  acceptance: {'PASSED' if m['passed'] else 'NOT PASSED'}; max violation {acc['max_violation']:.3g} "
               f"on {100 * acc['violating_fraction']:.2f}% of {acc['validation_states']} validation states; "
               f"Hurwitz at x*: {acc['jacobian']['hurwitz']}; other equilibria: {len(acc['other_equilibria'])}")
    if acc.get("local_rate_max") is not None:
        rate = acc["local_rate_max"]
        click.echo(f"  V near x*: Vdot <= {rate:+.3g} V to second order at the worst training sample "
                   f"({'V decreases' if rate < 0 else 'V does NOT decrease along every direction'})")
    if c:
        click.echo(f"  proof: {c['retraining_rounds']} retraining round(s) (kept round {c['returned_round']})")
    click.echo(f"  saved {out}")
    click.echo(certificate_line(m["certificate"]))


def roa_line(r: dict, true_model: bool) -> str:
    """What a :func:`drlyap.verification.certified_roa` result proves, named for what it is."""
    if "error" in r:
        return f"region of attraction: {r['error']}"
    model = "the true model at --xi" if true_model else "the design model at each training sample"
    share = r["share_of_box"]
    size = (f"{100 * share:.2f}% of the box" if share >= 1e-4 or share == 0 else f"{share:.2g} of the box (estimated)"
            ) + f", limited by {r['limited_by']}"
    if r["kind"] == "region of attraction":
        local = r["local"]
        how = ""
        if local.get("method") == "linearisation":
            how = (f"; near x* by the closed-loop linearisation's z'Pz, proved decreasing on {{z'Pz <= "
                   f"{local['q_level']:.3g}}} which contains {{V <= {local['inner_level']:.3g}}}")
        elif local.get("method") == "band":
            low = local["v_on_ellipsoid"][0]
            how = (f"; V proved decreasing on it outside the closed loop's certified ellipsoid {{z'Pz <= "
                   f"{local['q_level']:.3g}}} (--json: roa.band.P), on whose boundary V is as low as {low:.3g} "
                   f"(sampled): " + ("the set reaches beyond the ellipsoid" if local["beyond_ellipsoid"] else
                                     "the set may lie inside the ellipsoid"))
        return (f"region of attraction: CERTIFIED {{V <= {r['level']:.4g}}} ({size}): every trajectory of {model} "
                f"that starts there converges to x*{how}")
    if r["kind"] == "practical stability":
        line = (f"region of attraction: NOT CERTIFIED ({r['local']['reason']}); practical stability instead: "
                f"trajectories of {model} from {{V <= {r['level']:.4g}}} ({size}) end up in "
                f"{{V <= {r['practical_level']:.4g}}}")
    else:
        proved = "none" if r["level"] is None else f"{r['level']:.4g}"  # None: -inf (e.g. V's minimum on the faces)
        line = (f"region of attraction: NOT CERTIFIED (largest proved level {proved}, limited by "
                f"{r['limited_by']}; inside the ball: {r['local']['reason'] or 'proved'})")
    quad = r.get("quadratic")
    if quad and quad.get("proved"):
        line += (f"\n  the closed loop's own quadratic certificate: CERTIFIED region of attraction {{z'Pz <= "
                 f"{quad['q_level']:.4g}}} ({quad['share_of_box']:.3g} of the box, |x_i - x*_i| up to "
                 f"{[float(f'{e:.3g}') for e in quad['extent']]}; P chosen from the closed-loop linearisation, --json: "
                 f"roa.quadratic.P): every trajectory of {model} that starts there converges to x*")
    elif quad:
        line += f"\n  the closed loop's own quadratic certificate: none ({quad['reason']})"
    return line


def certificate_line(cert: dict) -> str:
    """The one line that says what was proved about a run's trained condition."""
    status = cert["status"]
    if status == "not checked":
        return f"certificate: NOT CHECKED ({cert['condition']} condition; run `drlyap verify RUN`)"
    where = cert.get("region", "X_delta")
    if status == "verified":
        return (f"certificate: VERIFIED - the {cert['condition']} condition holds at every state of the {where} "
                f"(proof {cert['time_s']:.2f} s, {cert['boxes']} boxes)")
    share = cert.get("verified_fraction")
    proved = "" if share is None else f"; {100 * share:.4f}% of it proved"
    cex = cert.get("counterexample")
    found = " (found by the falsifier after the proof ran out of time)" if cert.get("counterexample_source") else ""
    extra = f"; counterexample x = {[round(v, 5) for v in cex]}{found}" if cex else ""
    return f"certificate: NOT VERIFIED ({status}) - the {cert['condition']} condition on the {where}{proved}{extra}"


@main.command()
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--xi", required=True, help="Parameter shift, comma-separated in the system's uncertain order.")
@click.option("--n-init", type=int, default=200, show_default=True, help="Number of initial states.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the initial states.")
@click.option("--horizon", type=float, default=None, help="Simulated time [system default].")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def evaluate(run_dir: Path, xi: str, n_init: int, seed: int, horizon: float | None, as_json: bool) -> None:
    """Simulate RUN_DIR's controller on the true model at parameter shift --xi."""
    from drlyap.experiments import evaluate_run
    from drlyap.rundir import load_run
    from drlyap.simulation import initial_states

    try:
        run = load_run(run_dir) if _run_kind(run_dir) == "lyapunov" else _policy_run_as_run(run_dir)
        shift = run.system.check_xi(_floats(xi, "--xi"))
        if horizon is not None and horizon <= 0:
            raise ValueError(f"--horizon must be > 0, got {horizon}")
        x0 = initial_states(run.system, n_init, torch.Generator().manual_seed(seed))
        result = evaluate_run(run, shift, x0, horizon)
    except ValueError as err:
        _fail(err)
    result["run_dir"] = str(run_dir)
    if as_json:
        click.echo(json.dumps(result))
        return
    click.echo(f"{run.system.name} ({run.config.method}) at xi = {shift.tolist()}: "
               f"{result['n_success']}/{result['n']} stabilised ({100 * result['success_rate']:.1f}%)")
    if result["worst_v_increase"] is not None:
        click.echo(f"  worst one-step increase of V along successful trajectories: {result['worst_v_increase']:.3g}")


@main.command()
@click.argument("system")
@click.option("--seeds", default="0", show_default=True, help="Comma-separated training seeds.")
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Output directory [first free runs/reproduce-SYSTEM, -2, -3, ...].")
@click.option("--iters", type=int, default=None, help="Iteration cap per training run [3000].")
@click.option("--device", default="cpu", show_default=True)
@click.option("--verify/--no-verify", default=True, show_default=True,
              help="Prove each pair's trained condition, retraining on counterexamples until proved (as `train`).")
@click.option("--verify-rounds", type=int, default=5, show_default=True, help="Retraining rounds at most.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object with both methods' results.")
def reproduce(system: str, seeds: str, out: Path | None, iters: int | None, device: str, verify: bool,
              verify_rounds: int, as_json: bool) -> None:
    """Reproduce the paper's experiment: baseline vs DR at SYSTEM's test shift, every pair proved.

    SYSTEM is a registered name (`drlyap systems`), package.module:factory or path/to/file.py:factory;
    it must declare a test shift (test_xi) and a training distribution (xi_sampler)."""
    from drlyap.experiments import format_table
    from drlyap.experiments import reproduce as run_reproduce

    seed_list = _ints(seeds, "--seeds")
    log = (lambda s: click.echo(s, err=True)) if as_json else click.echo
    try:
        sys_ = resolve_system(system)
        if out is None:  # first free runs/reproduce-SYSTEM[-K], so that running the quickstart twice just works
            out = Path("runs") / f"reproduce-{sys_.name}"
            k = 2
            while out.exists():
                out, k = Path("runs") / f"reproduce-{sys_.name}-{k}", k + 1
        if verify_rounds < 0:
            raise ValueError(f"--verify-rounds must be >= 0, got {verify_rounds}")
        report = run_reproduce(sys_, seed_list, out, iters=iters, progress=True, device=device,
                               log=log, verify=verify, verify_rounds=verify_rounds, source=system_source(system, sys_))
    except ValueError as err:
        _fail(err)
    if as_json:
        click.echo(json.dumps(report))
        return
    click.echo("")
    click.echo(format_table(report))
    click.echo(f"\nwrote {out} (report.md, report.json, seed*/figures)")


def _run_kind(run_dir: Path) -> str | None:
    from drlyap.rundir import read_run_kind

    return read_run_kind(run_dir).get("kind")


def _policy_run_as_run(run_dir: Path):
    """A non-Lyapunov run (LQR, RL) shaped like :class:`drlyap.rundir.Run` for ``evaluate``."""
    from types import SimpleNamespace

    from drlyap.rundir import load_policy_run

    run = load_policy_run(run_dir)
    return SimpleNamespace(system=run.system, controller=run.controller, lyapunov=run.certificate,
                           config=SimpleNamespace(method=run.label), metrics=run.metrics)


@main.command()
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
    from drlyap.baselines import train_lqr

    try:
        if n_init < 1:
            raise ValueError(f"--n-init must be >= 1, got {n_init}")
        metrics = train_lqr(system, out, _floats(q_diag, "--q"), _floats(r_diag, "--r"), n_init=n_init, seed=seed)
        gains = json.loads((out / "lqr.json").read_text())
        name = json.loads((out / "run.json").read_text())["system"]["name"]
    except ValueError as err:
        _fail(err)
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


@main.group()
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
    from drlyap.rl import train_rl

    try:
        metrics = train_rl(system, algo, steps, seed, out)
        name = json.loads((out / "run.json").read_text())["system"]["name"]
    except ValueError as err:
        _fail(err)
    if as_json:
        click.echo(json.dumps({"run_dir": str(out), "system": name, "algo": algo, "metrics": metrics}))
        return
    last = metrics["mean_last_returns"]
    click.echo(f"{name} {algo}: {metrics['samples']} steps in {metrics['train_time_s']:.1f} s "
               f"({metrics['ms_per_1000_steps']:.0f} ms per 1000 steps); mean return of the last episodes "
               f"{'-' if last is None else f'{last:.1f}'}")
    click.echo(f"  saved {out}")


@main.command()
@click.argument("run_dirs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--xi", required=True, help="Parameter shift, comma-separated in the system's uncertain order.")
@click.option("--n-init", type=int, default=200, show_default=True, help="Number of initial states.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the initial states.")
@click.option("--horizon", type=float, default=None, help="Simulated time [system default].")
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Write compare.json, compare.md and figures (certificate and input over time) here.")
@click.option("--certify-time", type=float, default=10.0, show_default=True,
              help="Seconds of sound verification per check of a Lyapunov or LQR run at --xi (0 skips it).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def compare(run_dirs: tuple[Path, ...], xi: str, n_init: int, seed: int, horizon: float | None, out: Path | None,
            certify_time: float, as_json: bool) -> None:
    """Compare runs of any kind (lyapunov, lqr, rl) at parameter shift --xi on the true model.

    Per run: success rate; samples used in training (Lyapunov: model evaluations at training states,
    n_states x iterations with the default resampling; RL: environment steps; LQR: 0); training wall
    time; and how often the certificate (V, z'Pz for LQR, the negated critic value for RL) increases
    along successful trajectories (a step counts when it rises by more than 1e-4 of that trajectory's
    range; lower is better, 0 means monotone); and what each run proves on the true model at --xi,
    by the sound verifier over the whole region: the decrease condition (learned pairs with their
    own gamma, LQR's z'Pz with a scale-free decay alpha z'Pz) and the certified region of attraction (a sublevel
    set of the certificate from which every trajectory converges to x*).
    """
    from drlyap.comparison import compare_runs, format_comparison

    try:
        if horizon is not None and horizon <= 0:
            raise ValueError(f"--horizon must be > 0, got {horizon}")
        if certify_time < 0:
            raise ValueError(f"--certify-time must be >= 0, got {certify_time}")
        report = compare_runs(list(run_dirs), _floats(xi, "--xi"), n_init, seed, out, horizon,
                              certify_time if certify_time > 0 else None, progress=True)
    except ValueError as err:
        _fail(err)
    if as_json:
        click.echo(json.dumps(report))
        return
    click.echo(format_comparison(report))
    if out is not None:
        click.echo(f"\nwrote {out} (compare.md, compare.json, figures/)")


@main.command()
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--delta", type=float, default=None, help="Radius of the excluded ball around x* [the run's delta].")
@click.option("--xi", default=None, help="Also verify plain decrease on the true model at this shift (comma-separated).")
@click.option("--time-limit", type=float, default=None,
              help="Seconds per branch and bound [the run's seconds per proof: 30; 120 for cartpole, quadrotor2d].")
@click.option("--roa/--no-roa", default=False, show_default=True, help="Certify a sublevel set of V as region of attraction.")
@click.option("--roa-time", type=float, default=None,
              help="Seconds for --roa's search: the condition on a sublevel set, then decrease inside the ball "
                   "[3x --time-limit]; where that certifies no sublevel set of V but the closed loop's own ellipsoid "
                   "{z'Pz <= c}, as many seconds again for V's decrease outside that ellipsoid (the band proof).")
@click.option("--max-radius", is_flag=True,
              help="Also find the largest Wasserstein radius for which the DR pointwise condition (the run's eps, "
                   "samples, gamma) is proved, and the largest box of shifts for which decrease on the true model "
                   "is proved (bisection on proofs; each proof gets --time-limit seconds).")
@click.option("--radius-tol", type=float, default=0.01, show_default=True,
              help="Relative width of the bracket [certified, unproved) that --max-radius stops at.")
@click.option("--enclosure", type=click.Choice(["mean-value", "affine"]), default=None,
              help="How boxes are bounded: the interval mean-value form, or affine forms with an exact quadratic "
                   "part (second-order Taylor models: far tighter from 4 states on, several times the cost per box) "
                   "[affine from 4 states on, else mean-value]; the region-of-attraction search uses the same.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def verify(run_dir: Path, delta: float | None, xi: str | None, time_limit: float | None, roa: bool,
           roa_time: float | None, max_radius: bool, radius_tol: float, enclosure: str | None, as_json: bool) -> None:
    """Prove the decrease condition of RUN_DIR on the whole state box minus the delta-ball, or find a counterexample.

    A run trained for a region of attraction (cartpole's default) has its condition proved on the sublevel set
    {V <= level} minus the ball instead, together with V > level on the faces of the box.

    Sound bounds (interval mean-value form, or affine forms with --enclosure affine) with branch and bound,
    in float64 with outward rounding.
    """
    from drlyap.io import jsonable
    from drlyap.rundir import load_run
    from drlyap.verification import run_robustness, verify_run
    from drlyap.verification.robustness import robustness_lines

    try:
        if time_limit is not None and not time_limit > 0:
            raise ValueError(f"--time-limit must be > 0, got {time_limit}")
        if roa_time is not None and not roa_time > 0:
            raise ValueError(f"--roa-time must be > 0, got {roa_time}")
        if not radius_tol > 0:
            raise ValueError(f"--radius-tol must be > 0, got {radius_tol}")
        run = load_run(run_dir)
        if time_limit is None:
            time_limit = float(run.config.verify_time or 30.0)
        shift = None if xi is None else run.system.check_xi(_floats(xi, "--xi"))
        result = verify_run(run, delta=delta, xi=shift, time_limit=time_limit, roa=roa, enclosure=enclosure,
                            roa_time=roa_time)
        if max_radius:
            result["robustness"] = jsonable(run_robustness(run, delta=delta, tol=radius_tol, time_limit=time_limit,
                                                           total_time=8 * time_limit))
    except ValueError as err:
        _fail(err)
    if as_json:
        click.echo(json.dumps(result))
        return

    def show(res: dict, title: str) -> None:
        where = "X_delta" if res.get("level") is None else f"X_delta (condition or V > {res['level']:g})"
        click.echo(f"{title}: {res['status'].upper()}; verified {_proved(res)} of {where} "
                   f"({res['boxes_processed']} boxes, {res['time_s']:.2f} s, {res['stopped']})")
        if res.get("level") is not None:
            low = res.get("boundary_min_lower")
            inside = low is not None and low > res["level"]
            digits = 6 if low is None or inside or f"{low:.6g}" != f"{res['level']:.6g}" else 12  # 0.9999999 is not 1
            bound = "unbounded (time limit)" if low is None else f">= {low:.{digits}g}"
            click.echo(f"  on {{V <= {res['level']:g}}} only; min of V on the box's faces {bound} (so the set lies "
                       f"inside the box: {'proved' if inside else 'NOT proved'})")
        if res["counterexample"] is not None:
            by = " (the falsifier's, after the proof ran out of time)" if res.get("counterexample_source") else ""
            click.echo(f"  counterexample x = {[round(v, 6) for v in res['counterexample']]}{by} with residual "
                       f"{res['counterexample_value']:.4g} > 0 (float32 networks: {res['counterexample_value_float32']:.4g})")
        elif res["status"] != "verified":
            click.echo(f"  {res['n_unverified']} boxes left unverified")

    click.echo(f"{run.system.name} ({run.config.method}), delta = {result['delta']:g}")
    trained = result["trained"]
    if "margin_upper" not in trained:
        show(trained, f"  trained condition ({trained['condition']})")
    uni = result["uniform"]

    def num(value) -> str:  # bounds left unbounded by a time limit come back as None
        return "unbounded" if value is None else f"{value:.4g}"

    click.echo(f"  uniform DR condition: {uni['status'].upper()}; margin in [{num(uni['margin_lower'])}, "
               f"{num(uni['margin_upper'])}] (<= 0 required), (r/eps) L_h <= {num(uni['lipschitz_term'][1])}")
    if "true_model" in result:
        show(result["true_model"], f"  true model at xi = {result['true_model']['xi']}")
    if result["roa"] is not None:
        click.echo("  " + roa_line(result["roa"], "true_model" in result))
    if "robustness" in result:
        for line in robustness_lines(result["robustness"]):
            click.echo(f"  {line}")


@main.command("guarantee")
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--dist", "dist", default="train", show_default=True,
              help="Distribution of xi: 'train' (the system's own), 'normal:M1,M2;S1,S2', 'uniform:L1,L2;H1,H2' "
                   "or 'point:V1,V2'.")
@click.option("--n", "n", type=int, default=1000, show_default=True, help="Number of draws of xi.")
@click.option("--method", type=click.Choice(["sampling", "verifier"]), default="sampling", show_default=True,
              help="sampling: dense grid of X_delta per draw (optimistic); verifier: branch and bound per distinct "
                   "draw (unknown counts as failing; pendulum: about 0.5 s per draw).")
@click.option("--eps-bar", type=float, default=0.05, show_default=True, help="Confidence slack eps_bar of the lemma.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the draws.")
@click.option("--time-limit", type=float, default=5.0, show_default=True, help="Seconds per draw (--method verifier).")
@click.option("--radius-constants", default=None,
              help="c1,c2,rho of eq. wasserstein_r_guarantee: also report r_N(eps_bar) for the run's k and N.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def guarantee_cmd(run_dir: Path, dist: str, n: int, method: str, eps_bar: float, seed: int, time_limit: float,
                  radius_constants: str | None, as_json: bool) -> None:
    """Estimate P(sup_x Vdot + gamma||x - x*|| <= 0) on the true model under a distribution of xi, next to the
    bound (1 - eps)(1 - eps_bar) of the paper's lemma."""
    from drlyap.guarantee import guarantee
    from drlyap.rundir import load_run

    try:
        constants = None
        if radius_constants is not None:
            constants = _floats(radius_constants, "--radius-constants")
            if len(constants) != 3:
                raise ValueError(f"--radius-constants takes c1,c2,rho, got {radius_constants!r}")
        run = load_run(run_dir)
        result = guarantee(run, dist, n, method=method, seed=seed, eps_bar=eps_bar, time_limit=time_limit,
                           radius_constants=constants)
    except ValueError as err:
        _fail(err)
    if as_json:
        click.echo(json.dumps(result))
        return
    lo, hi = result["interval_clopper_pearson"]
    click.echo(f"{result['system']} ({result['method']}), xi ~ {dist}, {n} draws ({result['n_distinct']} distinct), "
               f"check: {method}")
    click.echo(f"  decrease holds on the true model over X_delta for {result['holds']}/{n} draws: "
               f"{100 * result['fraction']:.2f}% (95% Clopper-Pearson [{100 * lo:.2f}%, {100 * hi:.2f}%])")
    if result["unknown"]:
        click.echo(f"  {result['unknown']} distinct draws unknown (time limit), counted as failing")
    worst = result["worst_sup_residual"]
    if worst is not None:
        click.echo(f"  worst sup_x residual over the draws: {worst:.4g}")
    click.echo(f"  lemma bound (1 - eps)(1 - eps_bar) = (1 - {result['eps']:g})(1 - {result['eps_bar']:g}) = "
               f"{result['bound']:.4f}"
               + ("" if result["bound_applies"] else " (not for this run: it needs the uniform DR condition)"))
    click.echo(f"  the bound assumes r = r_N(eps_bar) (run: r = {result['radius']:g}, N = {result['n_xi']}) and a "
               "light-tailed true distribution")
    rg = result.get("radius_guarantee")
    if rg is not None:
        click.echo(f"  r_N(eps_bar) = {rg['r_N']:.4g} for c1={rg['c1']:g}, c2={rg['c2']:g}, rho={rg['rho']:g}, k={rg['k']}, "
                   f"N={rg['N']}: the run's radius is {'enough' if rg['radius_sufficient'] else 'too small'}")


@main.command()
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--spacing", type=float, default=None, help="Grid spacing in local state units [about 20000 cells].")
@click.option("--xi", default=None, help="Check plain decrease on the true model at this shift instead.")
@click.option("--verify-time", type=float, default=10.0, show_default=True,
              help="Seconds for the branch and bound on the same condition, for comparison (0: skip).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def lipschitz(run_dir: Path, spacing: float | None, xi: str | None, verify_time: float, as_json: bool) -> None:
    """Lipschitz covering check of RUN_DIR's condition on a grid of X_delta (the paper's covering argument).

    Certified when the residual at every cell centre is <= -L * rho (L: a sound Lipschitz constant from interval
    gradient bounds, rho: the covering radius); compare with the branch and bound of `drlyap verify`.
    """
    from drlyap.rundir import load_run
    from drlyap.verification import lipschitz_covering

    try:
        if verify_time < 0:
            raise ValueError(f"--verify-time must be >= 0, got {verify_time}")
        run = load_run(run_dir)
        shift = None if xi is None else run.system.check_xi(_floats(xi, "--xi"))
        result = lipschitz_covering(run, spacing=spacing, xi=shift, verify_time=verify_time)
    except ValueError as err:
        _fail(err)
    if as_json:
        click.echo(json.dumps(result))
        return
    click.echo(f"{run.system.name} ({run.config.method}), {result['condition']}, delta = {result['delta']:g}")
    click.echo(f"  grid: {result['cells']} cells ({' x '.join(map(str, result['per_axis']))}), spacing <= "
               f"{result['spacing']:.4g}, covering radius rho = {result['covering_radius']:.4g}")
    click.echo(f"  max residual at the cell centres: {result['max_residual']:.4g} (in X_delta: "
               f"{result['max_residual_in_x_delta']:.4g})")
    click.echo(f"  Lipschitz constant: {result['lipschitz_sound']:.4g} (sound, interval gradient bounds); "
               f"{result['lipschitz_sampled']:.4g} (largest sampled gradient)")
    click.echo(f"  covering certificate: {'CERTIFIED' if result['certified'] else 'NOT CERTIFIED'} "
               f"(needs max residual <= -L rho = {result['required_max_residual']:.4g}); with {result['safety']:g} x the "
               f"sampled L: {'holds' if result['certified_estimate'] else 'fails'}")
    if result["spacing_needed"] is not None:
        click.echo(f"  spacing needed with this L and maximum: {result['spacing_needed']:.3g} "
                   f"(about {result['samples_needed']:.3g} samples)")
    ver = result["verifier"]
    if ver is not None:
        click.echo(f"  branch and bound: {ver['status'].upper()}, verified {_proved(ver)} "
                   f"({ver['boxes_processed']} boxes, {ver['time_s']:.2f} s)")


@main.command()
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
def plot(run_dir: Path, xi: str | None, n_init: int, seed: int, roa: bool | None, time_limit: float,
         horizon: float | None, out: Path | None, as_json: bool) -> None:
    """Figures of RUN_DIR on the true model: phase portrait with labelled level sets of V and the certified set,
    V(t) and u(t) with the input limits, and heatmaps of V and of the decrease condition."""
    from drlyap.figures import plot_run

    try:
        if time_limit <= 0:
            raise ValueError(f"--time-limit must be > 0, got {time_limit}")
        result = plot_run(run_dir, xi=_floats(xi, "--xi"), n_init=n_init, seed=seed, roa=roa, out=out,
                          time_limit=time_limit, horizon=horizon)
    except ValueError as err:
        _fail(err)
    if as_json:
        click.echo(json.dumps(result))
        return
    region = result["region"]
    click.echo(f"{result['n_success']}/{result['n']} trajectories stabilised; "
               + (region["label"] if region else "no certified set drawn"))
    for path in result["figures"]:
        click.echo(f"wrote {path}")


@main.command("sweep")
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
@click.option("--iters", type=int, default=None, help="Iteration cap per training run [the system's default].")
@click.option("--verify/--no-verify", default=True, show_default=True,
              help="Prove each trained pair with counterexample-guided rounds, as `train` does.")
@click.option("--verify-rounds", type=int, default=5, show_default=True, help="Retraining rounds at most per pair.")
@click.option("--device", default="cpu", show_default=True, help="cpu or cuda (for every combination).")
@click.option("--shifts", default="1,2,3,4,5", show_default=True, help="Evaluate at these multiples of the test shift.")
@click.option("--n-init", type=int, default=200, show_default=True, help="Evaluation initial states per seed.")
@click.option("--verify-time-limit", type=float, default=30.0, show_default=True, help="Seconds per branch and bound.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (progress goes to stderr).")
def sweep(system: str, seeds: str, radius: str | None, eps: str | None, method: str, out: Path | None, backend: str,
          workers: int, address: str | None, iters: int | None, verify: bool, verify_rounds: int, device: str,
          shifts: str, n_init: int, verify_time_limit: float, as_json: bool) -> None:
    """Train, verify and evaluate every combination of seeds x radii x eps for SYSTEM; resumable.

    SYSTEM is a registered name (`drlyap systems`), package.module:factory or path/to/file.py:factory.
    One run directory per combination under --out, plus results.csv, results.json and figures/sweep.png.
    Running the same command again continues an interrupted sweep and retries failed combinations.
    """
    from drlyap import sweep as sw

    try:
        sys_ = resolve_system(system)
        defaults = _train_defaults(sys_)
        spec = sw.SweepSpec(system=system, seeds=sw.parse_seeds(seeds),
                            radii=sw.parse_values(radius, "--radius") if radius else [defaults["wasserstein_radius"]],
                            eps=sw.parse_values(eps, "--eps") if eps else [defaults["risk_level"]],
                            methods=sw.parse_methods(method), iters=iters, verify=verify, verify_rounds=verify_rounds,
                            device=device, shift_factors=sw.parse_values(shifts, "--shifts"), n_init=n_init,
                            verify_time_limit=verify_time_limit)
        spec.validate()
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
        _fail(err)
    if as_json:
        click.echo(json.dumps(report))
        return
    click.echo("")
    click.echo(sw.format_summary(report))
    click.echo(f"\n{len(report['computed'])} combination(s) run, {len(report['reused'])} reused from an earlier run, "
               f"{report['failed']} failed; {report['wall_s']:.1f} s on the {report['backend']} backend")
    click.echo(f"wrote {out} (results.csv, results.json, figures/sweep.png, one run directory per combination)")


def _train_defaults(system) -> dict:
    """The resolved training defaults of ``system`` (radius, risk level, ...)."""
    from drlyap.training import TrainConfig

    return TrainConfig(system=system.name).resolved(system).to_dict()


if __name__ == "__main__":
    main()
