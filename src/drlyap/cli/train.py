"""``drlyap systems`` and ``drlyap train``."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
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
    refuse_early,
)
from drlyap.compute import Compute
from drlyap.config import TrainConfig
from drlyap.proof_settings import ProofConfig
from drlyap.recipes import defaults_text


@click.command()
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def systems(as_json: bool) -> None:
    """List the built-in systems with their dimensions and parameters."""
    from drlyap.systems import get_system, system_names

    described = [get_system(name).describe() for name in system_names()]
    if as_json:
        click.echo(json.dumps({"systems": described}, indent=2))
        return
    for d in described:
        params = ", ".join(f"{k}={v:g}" for k, v in d["parameters"].items())
        click.echo(f"{d['name']}: n={d['n']} states {d['states']}, m={d['m']} inputs {d['inputs']}, "
                   f"k={d['k']} uncertain {d['uncertain']}")
        click.echo(f"    parameters: {params}; x* = {[round(v, 4) for v in d['equilibrium']]}; "
                   f"U = {d['input_box']}; test xi = {d['test_xi']}")


def _check_numbers(**given: float | None) -> None:
    """The options of ``train`` whose ranges need no system, so that a bad one is refused before the numerical code
    loads (:meth:`drlyap.config.TrainConfig.validate` checks every field again): a ValueError naming the option and
    the field."""
    rules = {"iters": ("iters", lambda v: v >= 1, ">= 1"),
             "radius": ("wasserstein_radius", lambda v: math.isfinite(v) and v >= 0, "finite and >= 0"),
             "eps": ("risk_level", lambda v: 0 < v < 1, "in (0, 1)"),
             "gamma": ("decay_rate", lambda v: math.isfinite(v) and v >= 0, "finite and >= 0"),
             "exp_rate": ("exp_rate", lambda v: math.isfinite(v) and v >= 0, "finite and >= 0"),
             "local_rate": ("local_rate", lambda v: math.isfinite(v) and v >= 0, "finite and >= 0")}
    for option, value in given.items():
        field, ok, rule = rules[option]
        if value is not None and not ok(value):
            raise ValueError(f"--{option.replace('_', '-')}: {field} = {value} (must be {rule})")


def _widths(text: str | None, option: str) -> list[int] | None:
    """A network's hidden widths from ``W1,W2,...`` ('' or 'none': no hidden layer), or a ValueError naming the
    option; None: the system's."""
    if text is None:
        return None
    if text.strip().lower() in ("", "none"):
        return []
    try:
        widths = [int(part) for part in text.split(",")]
    except ValueError:
        raise ValueError(f"{option} takes widths W1,W2,... (positive integers), got {text!r}") from None
    if any(w < 1 for w in widths):
        raise ValueError(f"{option} takes widths W1,W2,... (positive integers), got {text!r}")
    return widths


@click.command()
@click.argument("system")
@click.option("--method", type=click.Choice(["baseline", "dr"]), default=default(TrainConfig, "method"),
              show_default=True, help="baseline: nominal condition at the mean xi sample; dr: distributionally robust.")
@click.option("--loss", type=click.Choice(["pointwise", "uniform"]), default=default(TrainConfig, "loss"),
              show_default=True, help="DR condition: per-state (pointwise) or over the whole region (uniform).")
@click.option("--radius", type=float, default=None, help="Wasserstein radius r [system default].")
@click.option("--eps", type=float, default=None, help="Risk level eps in (0, 1) [system default].")
@click.option("--gamma", type=float, default=None, help="Decay rate gamma in Vdot + gamma||x-x*|| <= 0.")
@click.option("--exp-rate", type=float, default=None,
              help="alpha of the exponential variant (adds alpha V inside the condition) [system default].")
@click.option("--xi-samples", default=None,
              help="Explicit xi samples 'a,b;c,d;...' (one sample per ';'); default: drawn from the system.")
@click.option("--iters", type=int, default=None,
              help=f"Iteration cap [the system's: {defaults_text('iters')}].")
@click.option("--seed", type=int, default=default(TrainConfig, "seed"), show_default=True)
@click.option("--device", default=default(TrainConfig, "device"), show_default=True, help="cpu or cuda.")
@click.option("--lyapunov-hidden", default=None, metavar="W1,W2,...",
              help="Widths of the hidden layers of V's network phi, comma-separated ('' for none) [the system's].")
@click.option("--lyapunov-skip/--no-lyapunov-skip", default=None,
              help="V as a quadratic form beside the network's term (a linear path to phi's output) [the system's].")
@click.option("--controller-hidden", default=None, metavar="W1,W2,...",
              help="Widths of the controller's hidden layers, comma-separated ('' for none) [the system's].")
@click.option("--controller-skip/--no-controller-skip", default=None,
              help="A linear gain beside the controller's network (its LQR warm start) [the system's].")
@click.option("--warm-start", type=click.Path(path_type=Path), default=None,
              help="Start from the networks of this run directory (e.g. a baseline run).")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Run directory to create.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@click.option("--verify/--no-verify", default=True, show_default=True,
              help="Prove the trained condition after training, retraining on counterexamples (CEGIS; for the uniform "
                   "loss, on the states where its margin's suprema lie) until it is proved or the rounds/budget run "
                   "out. --no-verify: training and the acceptance check only.")
@click.option("--check/--no-check", "check", default=True, show_default=True,
              help="Re-check the proved condition's certificate with the independent checker (its own arithmetic, as "
                   "`drlyap check`) once the run is saved, and record it (certificates/trained.check.json): `drlyap "
                   "verify` then takes the certificate without proving or checking it again.")
@click.option("--verify-rounds", type=int, default=default(ProofConfig, "rounds"), show_default=True,
              help="Retraining rounds at most.")
@click.option("--verify-boxes", type=int, default=None,
              help="Boxes per proof round: the work budget that makes the same command give the same pair on any "
                   f"machine [the system's: {defaults_text('verify_boxes')}].")
@click.option("--verify-time", type=float, default=None,
              help=f"Outer cap in seconds of each proof round, reported when hit [the system's: "
                   f"{defaults_text('round_time')}].")
@click.option("--verify-budget", type=float, default=None,
              help="Total seconds for the retraining rounds [no limit; a limit makes the pair depend on the machine's "
                   "speed].")
@click.option("--local-rate", type=float, default=None,
              help="Ask V to decay at this rate near x* on every training sample's linearisation (a loss term; the "
                   "acceptance check then asks V to decrease there) [0: not asked].")
@compute_options(with_device=False)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (run_dir, system, metrics) on stdout.")
def train(system: str, method: str, loss: str, radius: float | None, eps: float | None, gamma: float | None,
          exp_rate: float | None, xi_samples: str | None, iters: int, seed: int, device: str,
          lyapunov_hidden: str | None, lyapunov_skip: bool | None, controller_hidden: str | None,
          controller_skip: bool | None, warm_start: Path | None,
          out: Path, quiet: bool, verify: bool, check: bool, verify_rounds: int, verify_boxes: int | None,
          verify_time: float | None, verify_budget: float | None, local_rate: float | None, workers: int, backend: str,
          address: str | None, as_json: bool) -> None:
    """Train a controller and Lyapunov certificate for SYSTEM, prove the trained condition, save a run directory.

    SYSTEM is a registered name, package.module:factory or path/to/file.py:factory (see `drlyap systems`).
    The certificate line says whether the condition is VERIFIED (proved at every state of the region it trained for:
    the box minus the delta-ball, or a sublevel set {V <= c} of it), VIOLATED (a counterexample) or UNKNOWN (budget ran
    out); after a proof, the lines below it whether the independent checker confirmed its certificate (--no-check: not
    run; a certificate it does not confirm makes the verdict NOT VERIFIED and the exit status 1). OUT is written only
    when training and its proofs end: interrupted (Ctrl-C, exit status 130), nothing is
    saved but a long proof's progress, kept beside OUT (a hidden folder .OUT.proofs): the same command, run again,
    trains the same pair and resumes that proof.
    """
    refuse_early(runs=[warm_start], systems=[system])

    from drlyap.runs.publish import check_writable, proof_checkpoints

    try:  # what needs no system is checked before the numerical code loads
        _check_numbers(iters=iters, radius=radius, eps=eps, gamma=gamma, exp_rate=exp_rate, local_rate=local_rate)
        if verify_rounds < 0:
            raise ValueError(f"--verify-rounds must be >= 0, got {verify_rounds}")
        shapes = {"lyapunov_hidden": _widths(lyapunov_hidden, "--lyapunov-hidden"),
                  "controller_hidden": _widths(controller_hidden, "--controller-hidden"),
                  "lyapunov_skip": lyapunov_skip, "controller_skip": controller_skip}
        samples = None
        if xi_samples is not None:
            samples = [floats(part, "--xi-samples") for part in xi_samples.split(";") if part.strip()]
        proof = None
        compute = compute_settings(workers, backend, address, device)
        if verify:
            proof = ProofConfig(rounds=verify_rounds, max_boxes=verify_boxes, round_time=verify_time,
                                total_time=verify_budget,
                                compute=dataclasses.replace(compute, checkpoint_dir=str(proof_checkpoints(out))))
            proof.validate()
        check_writable(out)
        config = TrainConfig(system=system, method=method, loss=loss, wasserstein_radius=radius, risk_level=eps,
                             decay_rate=gamma, exp_rate=exp_rate, xi_samples=samples, iters=iters, seed=seed,
                             device=device, local_rate=local_rate, **shapes)  # system: the spec, until resolved
    except ValueError as err:
        fail(err)

    sys_, source, result = _train_and_save(system, config, proof, out, quiet, warm_start)
    checked = _check_saved(out, sys_, compute, source) if check else None
    refused = checked is not None and not all(r.ok for r in checked)  # the verdict is never stronger than the checker's
    _report(result, method, out, sys_, source, checked, as_json)
    if refused:
        sys.exit(1)


def _train_and_save(spec: str, config: TrainConfig, proof: ProofConfig | None, out: Path, quiet: bool,
                    warm_start: Path | None) -> tuple:
    """Resolve the system ``spec`` and ``config`` for it, train (from the networks of ``warm_start``, if given) and
    save the run at ``out``: the system, its source and the training result. An error or an interruption exits, with
    ``out`` not written."""
    from drlyap.runs.publish import proof_checkpoints

    try:
        from drlyap.render import proof_round_line
        from drlyap.runs import load_run, save_run
        from drlyap.systems import resolve_system, system_source
        from drlyap.training import train as train_pair

        sys_ = resolve_system(spec)
        source = system_source(spec, sys_)
        cfg = dataclasses.replace(config, system=sys_.name).resolved(sys_)  # a bad one is refused here
        if proof is not None:
            proof = proof.resolved(sys_)
        init = None
        if warm_start is not None:
            prior = load_run(warm_start, sys_)
            init = (prior.lyapunov_net, prior.controller_net)
        result = train_pair(cfg, sys_, proof, progress=not quiet, init=init,
                            log=lambda entry: click.echo(proof_round_line(entry), err=True), warn=False)
        save_run(out, result, source=source)  # atomic: an interrupted save leaves nothing at OUT
        shutil.rmtree(proof_checkpoints(out), ignore_errors=True)
    except ValueError as err:
        fail(err)
    except OSError as err:  # a file drlyap writes on the way (what publishing OUT meets is a ValueError above)
        fail(f"cannot write {err.filename or out}: {err.strerror or err}; {out} was not written")
    except KeyboardInterrupt:
        kept = proof_checkpoints(out)
        if any(kept.glob("proof-*.npz")):
            click.echo(f"drlyap: interrupted; {out} was not written; the proof's progress is kept in {kept}: the same "
                       "command resumes it", err=True)
        else:
            click.echo(f"drlyap: interrupted; nothing was saved ({out} is written only when training and its proofs "
                       "end)", err=True)
        sys.exit(130)
    return sys_, source, result


def _report(result, method: str, out: Path, system, source: dict | None, checked: list | None, as_json: bool) -> None:
    """Print what training saved at ``out`` (``method``: as the command line names it): the record, the certificate's
    verdict and the checker's ``checked``."""
    refused = checked is not None and not all(r.ok for r in checked)
    m = result.metrics
    if as_json:
        click.echo(json.dumps({"run_dir": str(out), "system": system.name, "method": method, "metrics": m,
                               "check": None if checked is None else [r.to_dict() for r in checked],
                               "confirmed": None if checked is None else not refused}))
        return
    from drlyap.render import certificate_line, check_lines, cut_set_line, training_lines
    from drlyap.sections import TrainSections
    from drlyap.verification import Certificate

    for line in training_lines(system.name, method, result.record):
        click.echo(line)
    click.echo(f"  saved {out}")
    click.echo(certificate_line(Certificate.from_dict(m["certificate"]),
                                command_hint("verify", out, source=source), confirmed=not refused))
    for line in check_lines(checked or []):
        click.echo(f"  {line}")
    if result.config.exit_faces and system.test_xi is not None and not refused:
        click.echo(cut_set_line(TrainSections.of(result.config).goal.level, system.test_xi,
                                command_hint("verify", out, source=source)))


def _check_saved(out: Path, system, compute: Compute, source: dict | None) -> list | None:
    """The checker's results on the saved run's trained certificate (None where the proof wrote none); the run stays
    saved whatever happens here."""
    if not (out / "certificates" / "trained.json").is_file():
        return None
    from drlyap.checker import check_run

    try:
        return check_run(out, system, names=["trained"], compute=compute)
    except KeyboardInterrupt:
        click.echo(f"drlyap: interrupted while checking; {out} is saved, its certificate not yet re-checked "
                   f"({command_hint('check', out, source=source)} does it)", err=True)
        sys.exit(130)
    except ValueError as err:
        fail(f"{out} is saved, but its certificate could not be re-checked: {err}")
