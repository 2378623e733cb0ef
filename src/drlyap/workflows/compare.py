"""Comparing controllers of any kind (Lyapunov pairs, LQR, RL) on the true model (``drlyap compare``).

Every run is simulated from the same initial states at one shift; the table reports success (as
:func:`drlyap.simulation.evaluate`), samples and training time, how often the certificate increases
along successful trajectories (:func:`monotonicity`), and what each run *proves*: the sound verifier's
verdict for Lyapunov pairs (:func:`certify`). Figures follow the paper's Figs. 3/4.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch import Tensor

from drlyap import plotting
from drlyap.closed_loop import ClosedLoop
from drlyap.compute import Compute
from drlyap.conditions import TrueDecrease
from drlyap.io import jsonable
from drlyap.kinds import Enclosure
from drlyap.networks import LinearController, QuadraticLyapunov
from drlyap.progress import progress as show_progress
from drlyap.proof_settings import ProofConfig
from drlyap.regions import Region
from drlyap.render import COMPARE_LEGEND, attempt_cells
from drlyap.runs import PolicyRun, atomic_dir, check_writable, read_run_kind
from drlyap.runs.imported import quadratic_loop, rl_actor_graph
from drlyap.simulation import initial_states, simulate, success_mask, wrap_steps
from drlyap.systems import UncertainSystem
from drlyap.verification import (
    Budget,
    CertifiedRadius,
    CertifiedShiftBox,
    ProofAttempt,
    SearchLimits,
    certified_roa,
    certified_shift_box,
    shift_scale,
    verify_condition,
)
from drlyap.verification.roa import region_rate
from drlyap.workflows.policies import load_policy_run
from drlyap.workflows.verify import VerifyRequest, run_proof, run_robustness, verify


def monotonicity(system: UncertainSystem, x: Tensor, values: Tensor, success: Tensor, rel_tol: float = 1e-4) -> dict:
    """How often a certificate increases along successful trajectories.

    ``x (T, B, n)`` states, ``values (T, B)`` certificate along them, ``success (B,)``. A step counts
    as an increase when ``v(t+1) - v(t) > rel_tol * (max_t v - min_t v)`` of that trajectory (so that
    float32 rounding of a network near x* is not counted). Steps where an angle crosses the wrap
    (the certificate lives on the box, not the circle) are left out. Returns ``increase_fraction``
    (increasing steps / counted steps over successful trajectories), ``monotone_fraction`` (successful
    trajectories with no increase) and ``counted_steps``; None values without successful trajectories.
    """
    dv = values[1:] - values[:-1]
    valid = torch.isfinite(dv) & ~wrap_steps(system, x)
    span = (values.amax(0) - values.amin(0)).clamp_min(0)
    increase = (dv > rel_tol * span) & valid
    ok = success.bool()
    if not ok.any():
        return {"increase_fraction": None, "monotone_fraction": None, "counted_steps": 0}
    counted = int(valid[:, ok].sum())
    return {"increase_fraction": float(increase[:, ok].sum()) / max(counted, 1),
            "monotone_fraction": float((~increase[:, ok].any(0)).double().mean()),
            "counted_steps": counted}


def score_run(run: PolicyRun, x0: Tensor, xi: Tensor, horizon: float | None = None) -> dict:
    """Simulate ``run`` from ``x0`` on the true model at ``xi``: success (as :func:`simulation.evaluate`),
    certificate monotonicity along successful trajectories, samples and training time."""
    system = run.system
    tic = time.perf_counter()
    traj = simulate(system, run.controller, x0, xi, horizon=horizon)
    success, dev = success_mask(system, traj.x)
    row = {"run_dir": str(run.path), "kind": run.kind, "label": run.label, "system": system.name,
           "n": int(x0.shape[0]), "n_success": int(success.sum()), "success_rate": float(success.double().mean()),
           "success": success.tolist(), "samples": run.samples, "train_time_s": run.train_time_s,
           "distinct_states": run.info.get("distinct_states")}
    if run.certificate is not None:
        values = run.certificate(traj.x.reshape(-1, system.n)).reshape(dev.shape)
        row["certificate"] = monotonicity(system, traj.x, values, success)
    else:
        row["certificate"] = {"increase_fraction": None, "monotone_fraction": None, "counted_steps": 0}
    row["simulation_s"] = time.perf_counter() - tic
    return row


def certify(run: PolicyRun, xi: Tensor, time_limit: float, compute: Compute = Compute()) -> ProofAttempt:
    """What a run *proves* at the shift ``xi`` on the true model, by the sound verifier over X_delta:
    the decrease condition and the largest certified sublevel set (region of attraction).

    Lyapunov pairs: ``Vdot + gamma||z|| (+ alpha V) <= 0`` with the run's own gamma and delta
    (:func:`drlyap.workflows.verify.verify`). LQR: ``d/dt z'Pz + alpha z'Pz <= 0``, a decay that does not
    depend on the scale of P, with alpha half the rate ``lambda_min(Q + K'RK) / lambda_max(P)`` that the
    linearisation guarantees, and the system's default delta (:func:`certify_loop`). Imported pairs
    (``drlyap import``): their V from ONNX with the system's default gamma and alpha, or the quadratic V of the
    closed loop's linearisation with its scale-free decay as LQR's. RL runs: the deterministic actor, read from the
    policy's layers as a graph (:func:`drlyap.runs.imported.rl_actor_graph`), with the quadratic V of its
    linearisation; where x* is not an equilibrium of the actor or the linearisation is not Hurwitz, the attempt's
    ``note`` says so and nothing is proved (the critics certify nothing).

    ``robustness`` (None when nothing is proved): the certified Wasserstein radius of the DR pointwise condition at
    the run's samples (Lyapunov pairs; None for LQR, which has no samples) and the certified box of shifts for
    decrease on the true model with the row's decay (:mod:`drlyap.verification.robustness`; each proof
    ``time_limit`` seconds, each search at most 4x that). ``compute``: where the proofs bound their boxes.
    """
    search = Budget(seconds=time_limit, enclosure=Enclosure.MEAN_VALUE, compute=compute)
    if run.kind == "lyapunov":
        lyap_run = run.info["run"]
        settings = run_proof(lyap_run, replace(lyap_run.proof or ProofConfig(), time_limit=time_limit).with_compute(compute))
        result = verify(lyap_run, settings, VerifyRequest(xi=xi, roa=True))
        roa = result.roa
        robust = run_robustness(lyap_run, budget=search, total_time=4 * time_limit, trained=result.trained)
        main = result.main
        return ProofAttempt(status=main.status, verified_fraction=main.verified_fraction,
                            counterexample=main.counterexample, time_s=main.time_s, roa_certified=roa.certified,
                            roa_kind=roa.kind, roa_share=roa.share_of_box,
                            robustness=_robust_summary(robust.radius, robust.shift_box), level=main.level)
    if run.kind == "lqr":
        system, design = run.system, run.info["design"]
        loop = ClosedLoop(system, QuadraticLyapunov(design.P),
                          LinearController(design.K, system.input_box, system.equilibrium_input))
        # scale-free decay alpha V: half the rate z'(Q + K'RK)z / z'Pz >= lambda_min / lambda_max of the linearisation
        rate = float(torch.linalg.eigvalsh(design.Q + design.K.T @ design.R @ design.K).min()
                     / torch.linalg.eigvalsh(design.P).max())
        return certify_loop(loop, xi, time_limit, 0.0, 0.5 * max(rate, 0.0), compute)
    # --- imported pairs and RL actors (drlyap import; drlyap.runs.imported) ---
    if run.kind == "imported":
        pair = run.info["pair"]
        return certify_loop(pair.loop, xi, time_limit, pair.decay_rate, pair.exp_rate, compute)
    if run.kind == "rl":
        try:
            actor = rl_actor_graph(run.system, run.config["algo"], run.info["agent"].model.policy)
            loop, checks = quadratic_loop(run.system, actor, f"the {run.config['algo']} policy")
        except ValueError as err:
            return ProofAttempt(status="none", note=f"{err}; nothing is proved")
        return certify_loop(loop, xi, time_limit, 0.0, checks["exp_rate"], compute)
    return ProofAttempt(status="none", note="no certificate")


def certify_loop(loop: ClosedLoop, xi: Tensor, time_limit: float, decay_rate: float, exp_rate: float,
                 compute: Compute = Compute()) -> ProofAttempt:
    """What a closed loop proves at the shift ``xi (k,)`` on the true model over the system's X_delta (its default
    delta), as ``drlyap verify RUN --xi XI --roa`` proves a run there: decrease ``Vdot + gamma ||z|| + alpha V <= 0``
    (``decay_rate`` gamma; alpha the strict decrease a region of attraction asks,
    :func:`~drlyap.verification.roa.region_rate` of ``exp_rate``), the certified region of attraction by the same
    search in the same budget (the system's boxes, a cap of 10x ``time_limit`` seconds), and the certified box of
    shifts with the loop's own decay (``time_limit`` seconds per proof; the search at most 4x that). What ``certify``
    runs for LQR, imported pairs and RL actors."""
    system = loop.system
    checks = ProofConfig(time_limit=time_limit).resolved(system).with_compute(compute)
    search = Budget(seconds=time_limit, enclosure="mean-value", compute=compute)
    rate = region_rate(decay_rate, exp_rate)
    rate = exp_rate if rate is None else rate
    condition = TrueDecrease(xi[None], decay_rate=decay_rate, exp_rate=rate)
    region = Region.of(system, system.defaults.delta)
    result = verify_condition(loop, condition, region, search)
    roa = certified_roa(loop, condition, region, checks.roa_budget(), band_time=checks.band_time)
    box = certified_shift_box(loop, region, shift_scale(system), search, decay=(decay_rate, exp_rate),
                              limits=SearchLimits(total_time=4 * time_limit))
    return ProofAttempt(status=result.status, verified_fraction=result.verified_fraction,
                        counterexample=result.counterexample, time_s=result.time_s, roa_certified=roa.certified,
                        roa_kind=roa.kind, roa_share=roa.share_of_box, decay_rate=decay_rate,
                        exp_rate=rate if rate or not decay_rate else None,  # a scale-free decay is shown
                        robustness=_robust_summary(None, box))


def _robust_summary(radius: CertifiedRadius | None, box: CertifiedShiftBox) -> dict:
    """The numbers of a certified radius / shift box search that the comparison keeps."""
    out = {"shift_box_s": box.s, "shift_box": box.box, "shift_box_reason": box.reason, "shift_scale": box.scale,
           "shift_decay": [box.decay_rate, box.exp_rate], "time_s": box.time_s}
    if radius is not None:
        out.update(radius=radius.radius, radius_unproved=radius.unproved, risk_level=radius.risk_level,
                   n_samples=radius.n_samples, radius_reason=radius.reason)
        out["time_s"] += radius.time_s
    else:
        out.update(radius=None, radius_reason="no Wasserstein condition (no samples)")
    return out


@dataclass(frozen=True)
class CompareSettings:
    """What :func:`compare_runs` measures: every run at the shift ``xi`` of the true model, from the same ``n_init``
    initial states (drawn from each system's test box with ``seed``), over ``horizon`` units of simulated time (None:
    the system's); with ``certify_time_limit`` (seconds per check of a run; None: none) what each run proves there
    (:func:`certify`)."""

    xi: Sequence[float]
    n_init: int = 200
    seed: int = 0
    horizon: float | None = None
    certify_time_limit: float | None = 10.0


def compare_runs(paths: Sequence[str | os.PathLike], settings: CompareSettings, out: str | os.PathLike | None = None,
                 *, progress: bool = True, system=None, trust: bool = False, compute: Compute = Compute()) -> dict:
    """Score every run directory as ``settings`` says (:class:`CompareSettings`); with ``out``, write compare.json,
    compare.md and figures.

    ``system``, ``trust``: how runs whose system came from a file or module are loaded
    (:func:`drlyap.runs.load_run`). ``progress``: report scoring progress on stderr (:func:`drlyap.progress.progress`).
    ``compute``: where the proofs bound their boxes (:class:`~drlyap.compute.Compute`).
    """
    xi, n_init, seed, horizon = settings.xi, settings.n_init, settings.seed, settings.horizon
    if not paths:
        raise ValueError("give at least one run directory")
    if n_init < 1:
        raise ValueError(f"--n-init must be >= 1, got {n_init}")
    if out is not None:
        check_writable(out)
    runs = [_load(p, system, trust) for p in paths]
    shifts = [run.system.check_xi(xi) for run in runs]
    rows = []
    bar = show_progress(len(runs), "compare: scoring runs", progress)
    for run, shift in zip(runs, shifts):
        x0 = initial_states(run.system, n_init, torch.Generator().manual_seed(seed))
        row = score_run(run, x0, shift, horizon)
        if settings.certify_time_limit is not None:
            row["certified"] = jsonable(certify(run, shift, settings.certify_time_limit, compute).to_dict())
        rows.append(row)
        bar.update(1)
    bar.close()
    report = {"xi": [float(v) for v in xi], "n_init": n_init, "seed": seed, "rows": rows}
    if out is not None:
        def fill(tmp: Path) -> None:
            figures = compare_figures(runs, shifts, tmp / "figures", horizon, seed)
            report["figures"] = [str(Path(out) / "figures" / f.name) for f in figures]
            (tmp / "compare.json").write_text(json.dumps(report, indent=2) + "\n")
            (tmp / "compare.md").write_text(format_comparison(report) + "\n")

        atomic_dir(Path(out), fill)
    return report


def _load(path, system, trust: bool) -> PolicyRun:
    """A run of the comparison; ``system`` (the one ``--system`` names) serves the runs made for it."""
    named = system if system is not None and read_run_kind(path).get("system", {}).get("name") == system.name else None
    return load_policy_run(path, named, trust)


def compare_figures(runs: Sequence[PolicyRun], shifts: Sequence[Tensor], folder: Path,
                    horizon: float | None = None, seed: int = 0) -> list[Path]:
    """Like the paper's Figs. 3/4: Lyapunov function (V, z^T P z, or negated value) and input over time, one
    figure per start state of the first run's system (:meth:`UncertainSystem.figure_starts`: its reference states,
    else states drawn from its test box with ``seed``)."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, start in enumerate(runs[0].system.figure_starts(seed)):
        series = {}
        for run, shift in zip(runs, shifts):
            x0 = torch.tensor([start], dtype=torch.float64)
            if x0.shape[1] != run.system.n:
                continue
            traj = simulate(run.system, run.controller, x0, shift, horizon=horizon)
            value = run.certificate(traj.x[:, 0]) if run.certificate is not None else torch.full_like(traj.t, float("nan"))
            series[f"{run.label} ({run.path.name})"] = (traj.t, value, traj.u[:, 0])
        where = ", ".join(f"{v:.3g}" for v in start)
        shift = ", ".join(f"{v:+g}" for v in shifts[0].tolist())
        system = runs[0].system
        paths.append(plotting.time_series(series, folder / f"certificate_and_input_{i}.png",
                                          f"{system.name} from ({where}), true model at xi = ({shift})",
                                          value_label="certificate: V, z'Pz or -value",
                                          input_label=plotting.input_label(system), time_label=plotting.time_label(system),
                                          limits=plotting.input_limits_of([run.system for run in runs]),
                                          input_names=system.input_names))
    return paths


def format_comparison(report: dict) -> str:
    """A markdown table of a :func:`compare_runs` report."""
    lines = [f"## comparison at xi = {report['xi']} ({report['n_init']} initial states, seed {report['seed']})", "",
             "| run | kind | system | success | samples | train s | certificate increases | monotone trajectories "
             "| verified decrease at xi | certified region of attraction at xi | certified radius; shift box |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        c = r["certificate"]
        inc = "-" if c["increase_fraction"] is None else f"{100 * c['increase_fraction']:.2f}%"
        mono = "-" if c["monotone_fraction"] is None else f"{100 * c['monotone_fraction']:.0f}%"
        t = "-" if r["train_time_s"] is None else f"{r['train_time_s']:.1f}"
        cert = r.get("certified")
        proof, roa, robust = attempt_cells(None if cert is None else ProofAttempt.from_dict(cert))
        if cert is not None and cert.get("note") and cert.get("verified_fraction") is None:
            proof = f"{proof}: {cert['note']}"  # why nothing was proved (e.g. x* is not the policy's equilibrium)
        lines.append(f"| {r['run_dir']} | {r['label']} | {r['system']} | {r['n_success']}/{r['n']} "
                     f"({100 * r['success_rate']:.1f}%) | {r['samples'] if r['samples'] is not None else '-'} | {t} | "
                     f"{inc} | {mono} | {proof} | {roa} | {robust} |")
    return "\n".join([*lines, "", COMPARE_LEGEND])
