"""``drlyap verify``, ``drlyap lipschitz`` and ``drlyap guarantee``: what a run directory proves."""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from pathlib import Path

import click

from drlyap.cli.common import (
    command_hint,
    compute_options,
    compute_settings,
    default,
    fail,
    floats,
    recorded_source,
    refuse_early,
    run_source_options,
    run_system_of,
)
from drlyap.proof_settings import ENCLOSURES, ProofConfig
from drlyap.recipes import defaults_text

EXIT_CODES = {"verified": 0, "violated": 3, "unknown": 4}
"""``drlyap verify``'s exit status by the outcome of what it was asked (``RunVerification.outcome``); 1: an error, 2: a
usage error."""


def _exit(result) -> None:
    code = EXIT_CODES[str(result.outcome())]
    if code:
        sys.exit(code)


def _band_levels(text: str, roa: bool) -> tuple[float, float]:
    """``--band C1,C2`` read and checked before any work, or a ValueError naming what is wrong (``0 < C1 < C2``; not
    with ``--roa``: :func:`~drlyap.verification.band_claim.band_request`)."""
    from drlyap.verification.band_claim import band_request

    values = floats(text, "--band")
    if len(values) != 2:
        raise ValueError(f"--band takes two levels C1,C2, got {text!r}")
    return band_request((values[0], values[1]), roa)


def _interrupted(run_dir: Path) -> None:
    """Ctrl-C: say what is kept (a long proof's checkpoint in RUN/checkpoints) and exit 130, as ``train`` does."""
    kept = run_dir / "checkpoints"
    if any(kept.glob("proof-*.npz")):
        click.echo(f"drlyap: interrupted; the proof's progress is kept in {kept}: the same command, run again, "
                   "resumes it", err=True)
    else:
        click.echo("drlyap: interrupted; nothing new was written (a proof keeps a checkpoint after 2 s: a shorter "
                   "one starts again)", err=True)
    sys.exit(130)


@click.command()
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--delta", type=float, default=None, help="Radius of the excluded ball around x* [the run's delta].")
@click.option("--xi", default=None,
              help="Also verify plain decrease on the true model at this shift (comma-separated), with the decay of "
                   "--roa-rate.")
@click.option("--time-limit", type=float, default=None,
              help=f"Seconds per branch and bound, besides its box budget [the system's: {defaults_text('verify_time')}].")
@click.option("--roa/--no-roa", default=False, show_default=True,
              help="Certify a sublevel set of V as region of attraction (at --xi it may be cut by the box where "
                   "the flow enters it there).")
@click.option("--roa-boxes", type=int, default=None,
              help="Boxes for --roa's search: the condition on a sublevel set (60%), then decrease inside the ball "
                   "(what that leaves), each bound of V up to a quarter; where that certifies no sublevel set of V but "
                   "the closed loop's own ellipsoid {z'Pz <= c}, as many boxes again for V's decrease outside that "
                   "ellipsoid (the band proof). Budgeted by boxes, the region does not depend on the machine's speed "
                   f"[the system's: {defaults_text('roa_boxes', unset='verify_boxes')}].")
@click.option("--roa-time", type=float, default=None,
              help="A cap on the seconds of --roa's search (and again of its band proof); a search that reaches it "
                   "says so: its region may differ on a faster machine [10x --time-limit].")
@click.option("--roa-above-level/--roa-at-level", default=None,
              help="Whether --roa's search goes above the level the run was trained for (or the level of the run an "
                   "imported pair was exported from), to the largest set it certifies; --roa-at-level: at most that "
                   "level, the run's claim [above].")
@click.option("--roa-rate", type=float, default=None,
              help="At --xi: the decay alpha of the true model's decrease Vdot + alpha V <= 0 proved there and asked of "
                   "its region with --roa, in place of the run's decay terms [0.01, or the run's alpha where smaller: "
                   "a region of attraction needs only a strict decrease, any alpha > 0 (none with a decay gamma "
                   "||z||: the run's)]; with --band, the alpha asked on the band [0.01].")
@click.option("--band", default=None, metavar="C1,C2",
              help="Prove the band claim instead of the decrease at --xi and a region: on the true model at --xi "
                   "(the system's test shift by default), V decreases (Vdot + alpha V <= 0, alpha from --roa-rate) on "
                   "C1 <= V <= C2 over the whole state box, and the flow enters the box wherever V <= C2 on its "
                   "faces: trajectories from {V <= C2} stay in it and reach {V <= C1} (practical stability, the form "
                   "the field's verifiers prove; V need not be least or zero at x*). Written as certificates/band.*.")
@click.option("--claim", default=None, metavar="NAME", callback=lambda _ctx, _param, name: _claim_name(name),
              help="Prove the claim of the kind NAME instead of the run's conditions, as its module in drlyap/claims/ "
                   "proves it (an unknown NAME is refused with the list of those proved by name), at --xi where the "
                   "kind is about a shift; written as certificates/NAME.* where verified.")
@click.option("--uniform", is_flag=True,
              help="Also bound the uniform DR condition's margin at the run's radius, risk level and samples (a "
                   "stricter condition than the pointwise one the default pairs are trained on); a margin proved "
                   "<= 0 is written as certificates/uniform.*.")
@click.option("--max-radius", is_flag=True,
              help="Also find the largest Wasserstein radius for which the DR pointwise condition (the run's eps, "
                   "samples, gamma) is proved, and the largest box of shifts for which decrease on the true model "
                   "is proved (bisection on proofs; each proof gets --time-limit seconds).")
@click.option("--radius-tol", type=float, default=0.01, show_default=True,
              help="Relative width of the bracket [certified, unproved) that --max-radius stops at.")
@click.option("--enclosure", type=click.Choice(ENCLOSURES), default=default(ProofConfig, "enclosure"),
              help="How boxes are bounded: the interval mean-value form, or affine forms with an exact quadratic "
                   "part (second-order Taylor models: far tighter from 4 states on, several times the cost per box) "
                   "[affine from 4 states on, else mean-value]; the region-of-attraction search uses the same.")
@click.option("--reprove", is_flag=True,
              help="Prove every condition anew, even one whose certificate file states the same claim and is confirmed "
                   "by the checker (by default such a certificate is re-checked instead of proved again).")
@compute_options()
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@run_source_options
def verify(run_dir: Path, delta: float | None, xi: str | None, time_limit: float | None, roa: bool,
           roa_boxes: int | None, roa_time: float | None, roa_above_level: bool | None, roa_rate: float | None,
           band: str | None, claim: str | None, uniform: bool,
           max_radius: bool, radius_tol: float, enclosure: str | None, reprove: bool, workers: int, backend: str,
           address: str | None, device: str, as_json: bool, system_spec: str | None, trust_run: bool) -> None:
    """Prove the decrease condition of RUN_DIR on the whole state box minus the delta-ball, or find a counterexample.

    A run trained for a region of attraction (the default of every built-in system but the pendulum, and of your own
    systems) has its condition proved on the sublevel set {V <= level} minus the ball instead, together with
    V > level on the faces of the box.

    Sound bounds (interval mean-value form, or affine forms with --enclosure affine) with branch and bound,
    in float64 with outward rounding. Every proof that ends verified is written as a certificate file into
    RUN_DIR/certificates/ (re-checked by `drlyap check`); a condition whose certificate already states the same
    claim is re-checked by the checker instead of proved again (--reprove: prove it anyway). A long proof keeps its
    progress in RUN_DIR/checkpoints/: the same command, run again after an interruption, resumes it. A pair brought
    with `drlyap import` has no trained condition: its decrease on the true model at --xi (the system's test shift by
    default) is proved, and with --roa its region of attraction; what is verified is written as certificates.

    A run keeps one account of the true model: a verify at another shift replaces true-model.* and removes a region
    certified at the old shift with its certificates (verify copies of the run to keep several shifts).

    Exit status: 0 when every condition asked holds and the region asked for is certified, 3 when one is violated (a
    counterexample), 4 when one is unknown (its budget ran out) or no region was certified, 1 on an error.
    """
    compute = compute_settings(workers, backend, address, device)
    refuse_early(runs=[run_dir], systems=[system_spec])

    from drlyap.runs import load_run, read_run_kind
    from drlyap.workflows.verify import VerifyRequest, clear_checkpoints, run_checkpoints, run_proof
    from drlyap.workflows.verify import verify as prove_run

    try:
        above_level = _checked_options(time_limit, roa_time, roa_boxes, roa, roa_above_level, radius_tol,
                                       xi is not None or band is not None, roa_rate)
        levels = None if band is None else _band_levels(band, roa)
        options = _ProofOptions(time_limit=time_limit, roa_time=roa_time, roa_boxes=roa_boxes, enclosure=enclosure)
        if claim is not None:
            if roa or band is not None or uniform or max_radius:
                raise ValueError("--claim proves that claim alone: not with --roa, --band, --uniform or --max-radius")
            _verify_claim(run_dir, claim, xi, options, compute, as_json, (system_spec, trust_run))
            return
        request = VerifyRequest(delta=delta, roa=roa, uniform=uniform, above_level=above_level, roa_rate=roa_rate,
                                band=levels)
        if read_run_kind(run_dir).get("kind") == "imported":
            _verify_imported(run_dir, xi, options.over(ProofConfig(), compute), request, as_json, system_spec,
                             trust_run)
            return
        run = load_run(run_dir, run_system_of(system_spec), trust_run)
        settings = run_proof(run, options.over(run.proof or ProofConfig(),
                                               dataclasses.replace(compute, checkpoint_dir=run_checkpoints(run))))
        shift = None if xi is None else run.system.check_xi(floats(xi, "--xi"))
        result = prove_run(run, settings, dataclasses.replace(request, xi=shift), reprove=reprove)
        stored = _stored_region(run, result, xi, system_spec) if roa else None
        written = _recorded(run, result, settings, system_spec, radius_tol if max_radius else None)
        clear_checkpoints(run)
    except ValueError as err:
        fail(err)
    except KeyboardInterrupt:
        _interrupted(run_dir)
    _report(result, run.system.name, run.config.method, as_json, ([stored] if stored else []) + written)


def _claim_name(name: str | None) -> str | None:
    """``--claim NAME`` checked against the kinds of claim proved by name, before the numerical code loads."""
    from drlyap.claims.registry import KINDS

    names = [k.name for k in KINDS if k.provable]
    if name is not None and name not in names:
        raise click.BadParameter(f"{name!r} is no claim proved by name; valid: {', '.join(names) or 'none'}")
    return name


def _verify_claim(run_dir: Path, name: str, xi: str | None, options: _ProofOptions, compute, as_json: bool,
                  source: tuple[str | None, bool]) -> None:
    """``drlyap verify --claim NAME``: the claim of that kind proved on the run or imported pair (``source``: the
    system spec and whether the run is trusted, as for the conditions), its certificate written where it is
    verified; the exit status as for the conditions."""
    from drlyap.io import jsonable
    from drlyap.render import claim_lines
    from drlyap.runs import load_imported_run, load_run, read_run_kind
    from drlyap.workflows.claim import prove_claim

    system_spec, trust_run = source
    system = run_system_of(system_spec)
    imported = read_run_kind(run_dir).get("kind") == "imported"
    run = load_imported_run(run_dir, system, trust_run) if imported else load_run(run_dir, system, trust_run)
    base = ProofConfig() if imported else (run.proof or ProofConfig())
    shift = None if xi is None else run.system.check_xi(floats(xi, "--xi"))
    outcome = prove_claim(run, name, options.over(base, compute), shift)
    if as_json:
        click.echo(json.dumps(jsonable({"claims": {name: outcome.to_dict()}, "outcome": outcome.status})))
    else:
        click.echo(f"{run.system.name}: the {name} claim")
        for line in claim_lines(outcome):
            click.echo(line)
        if outcome.certificate is not None:
            recheck = command_hint("check", run_dir, source=recorded_source(run_dir, system_spec))
            click.echo(f"  certificate: {outcome.certificate} (re-check it with `{recheck}`)")
    code = EXIT_CODES[str(outcome.status)]
    if code:
        sys.exit(code)


@dataclasses.dataclass(frozen=True)
class _ProofOptions:
    """The proof settings ``verify``'s options give, over the run's (None: the run's, else the system's)."""

    time_limit: float | None
    roa_time: float | None
    roa_boxes: int | None
    enclosure: str | None

    def over(self, base: ProofConfig, compute) -> ProofConfig:
        """``base`` with these options, bounding its boxes where ``compute`` says."""
        settings = dataclasses.replace(base, roa_time=self.roa_time, roa_boxes=self.roa_boxes,
                                       enclosure=self.enclosure, compute=compute)
        if self.time_limit is not None:
            settings = dataclasses.replace(settings, time_limit=self.time_limit)
        return settings


def _checked_options(time_limit: float | None, roa_time: float | None, roa_boxes: int | None, roa: bool,
                     roa_above_level: bool | None, radius_tol: float, at_shift: bool, roa_rate: float | None) -> bool:
    """``verify``'s numbers checked before any work (a ValueError naming the option); whether the region-of-attraction
    search goes above the run's level."""
    if time_limit is not None and not time_limit > 0:
        raise ValueError(f"--time-limit must be > 0, got {time_limit}")
    if roa_time is not None and not roa_time > 0:
        raise ValueError(f"--roa-time must be > 0, got {roa_time}")
    if roa_boxes is not None and not roa_boxes >= 1:
        raise ValueError(f"--roa-boxes must be >= 1, got {roa_boxes}")
    if roa_above_level is not None and not roa:
        raise ValueError(f"--roa-{'above' if roa_above_level else 'at'}-level goes with --roa (where the "
                         "region-of-attraction search may go)")
    if not radius_tol > 0:
        raise ValueError(f"--radius-tol must be > 0, got {radius_tol}")
    if roa_rate is not None and not (at_shift and math.isfinite(roa_rate) and roa_rate > 0):
        raise ValueError(f"--roa-rate must be > 0 and goes with --xi or --band (the decay asked at the shift), "
                         f"got {roa_rate}" + ("" if at_shift else " without them"))
    return roa_above_level is not False


def _stored_region(run, result, xi: str | None, system_spec: str | None) -> str:
    """The region of attraction recorded in the run's metrics.json, and the line that says where (or why not)."""
    from drlyap.workflows.record import record_region

    try:
        record_region(run, result)
        shift_args = () if xi is None else ("--xi", xi)
        drawn = command_hint("plot", run.path, *shift_args, source=recorded_source(run.path, system_spec))
        return f"  stored in {run.path / 'metrics.json'} (drawn by `{drawn}`)"
    except OSError as err:
        return f"  not stored: {run.path / 'metrics.json'} cannot be written ({err.strerror or err})"


def _recorded(run, result, settings: ProofConfig, system_spec: str | None, radius_tol: float | None) -> list[str]:
    """Write the certificates of what ``result`` proved (and with ``radius_tol``, of the largest radius and shift box,
    searched now): the lines that name them, or say why none was written."""
    from drlyap.render import unwritten_region_line
    from drlyap.runs.certificates import PairFiles
    from drlyap.workflows.record import record_band, record_certificates, record_roa, record_robustness
    from drlyap.workflows.verify import run_robustness

    try:
        recheck = command_hint("check", run.path, source=recorded_source(run.path, system_spec))
        paths = record_certificates(run, result) + record_roa(run, result, settings) + record_band(
            run.path, run.system, result.band, PairFiles.networks(run.path, run.config.alpha_hat))
        written = [f"  certificate: {p} (re-check it with `{recheck}`)" for p in paths]
        unwritten = unwritten_region_line(result.roa, paths)
    except OSError as err:
        written, unwritten = [f"  no certificate written: {run.path} cannot be written ({err.strerror or err})"], None
    if radius_tol is not None:
        result.robustness = run_robustness(run, delta=result.delta, tol=radius_tol, budget=settings.budget(),
                                           total_time=8 * settings.time_limit, trained=result.trained)
        try:
            written += [f"  certificate: {p} (re-check it with `{recheck}`)"
                        for p in record_robustness(run, result.robustness)]
        except OSError as err:
            written.append(f"  the radius and shift box not stored: {run.path} cannot be written "
                           f"({err.strerror or err})")
    return written + ([unwritten] if unwritten else [])


def _report(result, system_name: str, method: str, as_json: bool, lines: list[str]) -> None:
    """Print ``result`` (as one JSON object, or its sentences and then ``lines``) and exit with its outcome's status."""
    if as_json:
        from drlyap.io import jsonable

        click.echo(json.dumps(jsonable(result.to_dict())))
        _exit(result)
        return
    from drlyap.render import verification_lines

    for line in verification_lines(result, system_name, method):
        click.echo(line)
    for line in lines:
        click.echo(line)
    _exit(result)


def _verify_imported(run_dir: Path, xi: str | None, settings: ProofConfig, request, as_json: bool,
                     system_spec: str | None, trust_run: bool) -> None:
    """``drlyap verify`` on an imported pair: decrease on the true model at --xi (the system's test shift by default)
    and with --roa its region of attraction, or with ``request.band`` the band claim there; what is verified is
    written as certificates."""
    from drlyap.render import unwritten_region_line
    from drlyap.runs import load_imported_run
    from drlyap.runs.certificates import PairFiles
    from drlyap.workflows.record import record_band, record_imported_certificates
    from drlyap.workflows.verify import verify_imported

    run = load_imported_run(run_dir, run_system_of(system_spec), trust_run)
    system = run.system
    if xi is None and system.test_xi is None:
        raise ValueError(f"an imported pair has no trained condition: give --xi ({system.k} values)")
    shift = system.check_xi(floats(xi, "--xi") if xi is not None else list(system.test_xi))
    pair = run.info["pair"]
    result = verify_imported(pair, str(run_dir), settings,
                             request=dataclasses.replace(request, xi=shift, uniform=False))
    try:
        recheck = command_hint("check", run_dir, source=recorded_source(run_dir, system_spec))
        if request.band is None:
            paths = record_imported_certificates(run_dir, pair, result, settings.resolved(system))
        else:
            paths = record_band(run_dir, system, result.band, PairFiles.imported(run_dir))
        written = [f"  certificate: {p} (re-check it with `{recheck}`)" for p in paths]
        written += [line for line in [unwritten_region_line(result.roa, paths)] if line]
    except OSError as err:
        written = [f"  no certificate written: {run_dir} cannot be written ({err.strerror or err})"]
    _report(result, system.name, "imported pair", as_json, written)


@click.command("guarantee")
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
@run_source_options
def guarantee(run_dir: Path, dist: str, n: int, method: str, eps_bar: float, seed: int, time_limit: float,
              radius_constants: str | None, as_json: bool, system_spec: str | None, trust_run: bool) -> None:
    """Estimate P(sup_x Vdot + gamma||x - x*|| <= 0) on the true model under a distribution of xi, next to the
    bound (1 - eps)(1 - eps_bar) of the paper's lemma."""
    refuse_early(runs=[run_dir], systems=[system_spec])

    from drlyap.runs import load_run
    from drlyap.workflows.guarantee import Draws
    from drlyap.workflows.guarantee import guarantee as estimate

    try:
        constants = None
        if radius_constants is not None:
            constants = floats(radius_constants, "--radius-constants")
            if len(constants) != 3:
                raise ValueError(f"--radius-constants takes c1,c2,rho, got {radius_constants!r}")
        run = load_run(run_dir, run_system_of(system_spec), trust_run)
        result = estimate(run, Draws(dist, n, seed), method, time_limit=time_limit, eps_bar=eps_bar,
                          radius_constants=constants)
    except ValueError as err:
        fail(err)
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


@click.command()
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--spacing", type=float, default=None, help="Grid spacing in local state units [about 20000 cells].")
@click.option("--xi", default=None, help="Check plain decrease on the true model at this shift instead.")
@click.option("--verify-time", type=float, default=10.0, show_default=True,
              help="Seconds for the branch and bound on the same condition, for comparison (0: skip).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@run_source_options
def lipschitz(run_dir: Path, spacing: float | None, xi: str | None, verify_time: float, as_json: bool,
              system_spec: str | None, trust_run: bool) -> None:
    """Lipschitz covering check of RUN_DIR's condition on a grid of X_delta (the paper's covering argument).

    Certified when the residual at every cell centre is <= -L * rho (L: a sound Lipschitz constant from interval
    gradient bounds, rho: the covering radius); compare with the branch and bound of `drlyap verify`.
    """
    refuse_early(runs=[run_dir], systems=[system_spec])

    from drlyap.io import jsonable
    from drlyap.render import covering_lines
    from drlyap.runs import load_run
    from drlyap.workflows.verify import run_covering

    try:
        if verify_time < 0:
            raise ValueError(f"--verify-time must be >= 0, got {verify_time}")
        run = load_run(run_dir, run_system_of(system_spec), trust_run)
        shift = None if xi is None else run.system.check_xi(floats(xi, "--xi"))
        result = run_covering(run, spacing=spacing, xi=shift, compare_seconds=verify_time)
    except ValueError as err:
        fail(err)
    if as_json:
        click.echo(json.dumps(jsonable(result.to_dict())))
        return
    for line in covering_lines(result, run.system.name, run.config.method):
        click.echo(line)
