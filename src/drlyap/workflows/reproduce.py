"""The paper's experiments end to end (``drlyap reproduce``): train baseline and DR, evaluate on the true shifted model.

``reproduce`` trains, for each seed, the baseline (nominal condition at the mean of the xi samples)
and the DR pair with the system's paper settings, evaluates both at the paper's test shift on the
paper's 10 initial states and on 200 more, prints a table, and draws the paper's figures.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import torch

from drlyap import plotting
from drlyap.compute import Compute
from drlyap.kernels import describe as describe_kernels
from drlyap.kernels import float_kernels
from drlyap.kinds import Method
from drlyap.progress import progress as show_progress
from drlyap.render import ACCEPTANCE_LEGEND, decrease_cell, proof_round_line, roa_cell
from drlyap.runs import Run, atomic_dir, check_writable, load_run, save_run
from drlyap.simulation import evaluate, initial_states, score, simulate
from drlyap.systems import UncertainSystem, resolve_system, system_source
from drlyap.training import TrainConfig, train
from drlyap.verification import ProofConfig
from drlyap.workflows.plot import region_to_draw
from drlyap.workflows.record import record_certificates, record_region, record_roa
from drlyap.workflows.verify import VerifyRequest
from drlyap.workflows.verify import verify as prove_run

METHODS = (Method.BASELINE, Method.DR)
KERNELS_LINE = "float kernels:"
SWEEP = (1, 2, 3, 4, 5)  # evaluation shifts, as multiples of the paper's test shift


def test_initial_states(system: UncertainSystem, seed: int, n_paper: int = 10, n_more: int = 200) -> tuple:
    """The evaluation initial states for a seed: ``n_paper`` as in the paper and ``n_more`` others."""
    gen = torch.Generator().manual_seed(20_000 + seed)
    return initial_states(system, n_paper, gen), initial_states(system, n_more, gen)


def evaluate_run(run: Run, xi: torch.Tensor | None, x0: torch.Tensor, horizon: float | None = None) -> dict:
    """Evaluate a loaded run from ``x0`` on the true model at ``xi`` (see :func:`simulation.evaluate`)."""
    return evaluate(run.system, run.controller, x0, xi, lyapunov=run.lyapunov, horizon=horizon)


def summary_row(result: dict) -> dict:
    return {k: result[k] for k in ("n", "n_success", "success_rate", "worst_v_increase")}


def reproduce(system: str | UncertainSystem, seeds: Sequence[int], out: Path, iters: int | None = None,
              progress: bool = True, device: str = "cpu", log=print, n_more: int = 200, sweep: Sequence[int] = SWEEP,
              verify: bool = True, verify_rounds: int = 5, verify_time: float | None = None,
              source: dict | None = None, horizon: float | None = None, compute: Compute = Compute()) -> dict:
    """Run the paper's experiment for ``system`` (an object, or a spec for
    :func:`drlyap.systems.resolve_system`) and write everything under ``out`` (atomically).

    Any system works that declares ``test_xi`` and an ``xi_sampler``. Returns a JSON-friendly dict with
    per-seed, per-method results and the paths of the figures. Both pairs are trained as :func:`drlyap.train` does:
    with ``verify``, counterexample-guided rounds (at most ``verify_rounds``) until the verifier proves their trained
    condition; then each pair's decrease on the true model at the test shift and its certified region of attraction
    there are proved (:func:`drlyap.workflows.verify.verify`, ``verify_time`` seconds per check, three times that
    for the region; None: the run's seconds per proof, 30 or the system's) and stored in its
    ``metrics["certificate"]``. ``verify_time`` also caps the seconds of each proof of the training rounds (None:
    the system's cap; they are budgeted by boxes).
    ``horizon``: simulated time of every evaluation and figure (None: the system's). ``source``
    (:func:`drlyap.systems.system_source`) is recorded in each run directory; by default it is derived from a spec,
    or the registry name. ``compute``: where the proofs bound their boxes (:class:`~drlyap.compute.Compute`).
    """
    if isinstance(system, str):
        spec, system = system, resolve_system(system)
        source = system_source(spec, system)
    proof = ProofConfig(rounds=verify_rounds, time_limit=verify_time).with_compute(compute) if verify else None
    missing = [f for f in ("test_xi", "xi_sampler") if getattr(system, f) is None]
    if missing:
        raise ValueError(f"{system.name} declares no {' and no '.join(missing)}; reproduce needs a test shift "
                         "(UncertainSystem.test_xi) and a training distribution (UncertainSystem.xi_sampler)")
    check_writable(out)
    system_name = system.name
    if not seeds:
        raise ValueError("need at least one seed")
    xi_test = torch.tensor(system.test_xi, dtype=torch.float64)
    report: dict = {"system": system_name, "test_xi": list(system.test_xi), "seeds": list(seeds), "sweep": list(sweep),
                    "verify": verify, "verify_rounds": verify_rounds, "results": []}

    def fill(tmp: Path) -> None:
        bar = show_progress(len(seeds) * len(METHODS) * (2 + len(sweep)), f"{system_name} evaluations", progress)
        for seed in seeds:
            x_paper, x_more = test_initial_states(system, seed, n_more=n_more)
            runs: dict[str, Run] = {}
            paper_trajs, paper_ok = {}, {}
            for method in METHODS:
                cfg = TrainConfig(system=system_name, method=method, seed=seed, device=device)
                if iters is not None:
                    cfg.iters = iters
                result = train(cfg, system, proof, progress=progress, warn=False,
                               log=(lambda entry, m=method, s=seed: log(f"seed {s} {m}: {proof_round_line(entry)[2:]}"))
                               if progress else None)
                run_dir = save_run(tmp / f"seed{seed}" / method, result, source=source)
                run = load_run(run_dir, system)
                paper_traj = simulate(system, run.controller, x_paper, xi_test, horizon=horizon)  # drawn below too
                paper = score(system, paper_traj, xi_test, run.lyapunov, horizon=horizon)
                paper_trajs[method], paper_ok[method] = paper_traj, paper["success"]
                more = evaluate_run(run, xi_test, x_more, horizon)
                bar.update(2)
                run.keep({"evaluations": {"paper_10": paper, "more_200": more}})
                region = ver = None
                if verify:  # what the pair proves on the true model at the test shift (the figures draw its region)
                    checks = (run.proof if verify_time is None else replace(run.proof, time_limit=verify_time)
                              ).with_compute(compute)
                    ver = prove_run(run, checks, VerifyRequest(xi=xi_test, roa=True))
                    record_region(run, ver)
                    record_certificates(run, ver)  # the proofs that ended verified, re-checkable by drlyap check
                    record_roa(run, ver, checks)
                    region = ver.roa
                runs[method] = run
                swept = {}
                for k in sweep:
                    swept[k] = evaluate_run(run, k * xi_test, x_more, horizon)["n_success"]
                    bar.update(1)
                record, acc = result.record, result.acceptance
                true_model = None if ver is None else ver.true_model
                row = {"seed": seed, "method": method, "passed_acceptance": record.passed,
                       "acceptance_status": record.status, "max_violation": acc.max_violation,
                       "violating_fraction": acc.violating_fraction, "hurwitz": acc.hurwitz,
                       "other_equilibria": len(acc.other_equilibria),
                       "iterations": record.iterations, "train_time_s": record.total_time_s,
                       "certificate": record.certificate_status,
                       "true_model": None if true_model is None else true_model.status,
                       "true_model_fraction": None if true_model is None else true_model.verified_fraction,
                       "roa": roa_cell(region),
                       "paper_10": summary_row(paper), "more_200": summary_row(more), "sweep_200": swept,
                       "run_dir": str(Path(out) / f"seed{seed}" / method)}
                report["results"].append(row)
                log(format_row(row))
            figures = draw_figures(system, runs, xi_test, paper_trajs, paper_ok, tmp / f"seed{seed}" / "figures", seed, horizon)
            report.setdefault("figures", {})[str(seed)] = [str(Path(out) / f"seed{seed}" / "figures" / f.name)
                                                          for f in figures]
        bar.close()
        report["float_kernels"] = float_kernels(device)
        report["figures"]["sweep"] = str(Path(out) / "shift_sweep.png")
        plotting.sweep_plot(system.name, sweep, report["results"], tmp / "shift_sweep.png", list(system.test_xi))
        (tmp / "report.json").write_text(json.dumps(report, indent=2) + "\n")
        (tmp / "report.md").write_text(format_table(report) + "\n")

    atomic_dir(Path(out), fill, overwrite=False)
    return report


def draw_figures(system: UncertainSystem, runs: dict[str, Run], xi: torch.Tensor, trajs: dict, ok: dict,
                 folder: Path, seed: int, horizon: float | None = None) -> list[Path]:
    """Figs. 2/5 (phase portraits of both controllers from their simulated ``trajs``, ``ok``: which of them the
    evaluation scored a success), 3a/3b (V(t), u(t) from the reference state) and the states over time from the same
    state (``states.png``)."""
    folder.mkdir(parents=True, exist_ok=True)
    levels = {method: plotting.lyapunov_grid(system, run.lyapunov) for method, run in runs.items()}
    shift = ", ".join(f"{n}{v:+g}" for n, v in zip(system.uncertain, xi.tolist()))
    regions = {method: region_to_draw(run, run.certificate.region_of_attraction() if run.certificate else None)
               for method, run in runs.items()}
    phase = plotting.phase_portraits(system, trajs, ok, folder / "trajectories.png",
                                     f"{system.name}, true model at {shift} (seed {seed})", levels, regions)
    start = torch.tensor([system.figure_starts(seed)[0]], dtype=torch.float64)
    series, states = {}, {}
    for method, run in runs.items():
        traj = simulate(system, run.controller, start, xi, horizon=horizon)
        series[method] = (traj.t, run.lyapunov(traj.x[:, 0]), traj.u[:, 0])
        states[method] = (traj.t, traj.x[:, 0])
    where = ", ".join(f"{v:.3g}" for v in start[0].tolist())
    title = f"{system.name} from ({where}), true model at {shift} (seed {seed})"
    ts = plotting.time_series(series, folder / "certificate_and_input.png", title,
                              input_label=plotting.input_label(system), time_label=plotting.time_label(system),
                              limits=plotting.input_limits(system), input_names=system.input_names)
    xs = plotting.states_over_time(system, states, folder / "states.png", title)
    return [phase, ts, xs]


def format_row(row: dict) -> str:
    p, m = row["paper_10"], row["more_200"]
    return (f"seed {row['seed']} {row['method']:>8}: {p['n']} test states {p['n_success']:>2}/{p['n']}, "
            f"{m['n']} more {m['n_success']:>3}/{m['n']}, acceptance check "
            f"{'PASSED' if row['passed_acceptance'] else 'not passed'} (max violation {row['max_violation']:.3g}, "
            f"violating {100 * row['violating_fraction']:.2f}% of the validation states, closed-loop Jacobian at x* "
            f"Hurwitz at every xi sample: {row['hurwitz']}, other equilibria found: {row['other_equilibria']}), "
            f"{row['train_time_s']:.0f}s, "
            f"certificate {row['certificate'].upper()}; at the test shift: decrease {_decrease(row)}, region of "
            f"attraction {row['roa'] or '-'}")


def _decrease(row: dict) -> str:
    return decrease_cell(row["true_model"], row["true_model_fraction"])


def format_table(report: dict) -> str:
    first = report["results"][0] if report["results"] else {"paper_10": {"n": 10}, "more_200": {"n": 200}}
    lines = [f"## {report['system']} at test shift xi = {report['test_xi']}", "",
             f"| seed | method | {first['paper_10']['n']} test states | {first['more_200']['n']} more | acceptance "
             "| max violation | violating % | Hurwitz | other eq. | train s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    lines[2] += " trained condition (verifier) | decrease on the true model at the test shift | certified region of attraction |"
    lines[3] += "---|---|---|"
    for r in report["results"]:
        lines.append(f"| {r['seed']} | {r['method']} | {r['paper_10']['n_success']}/{r['paper_10']['n']} | "
                     f"{r['more_200']['n_success']}/{r['more_200']['n']} | "
                     f"{'passed' if r['passed_acceptance'] else 'not passed'} | {r['max_violation']:.3g} | "
                     f"{100 * r['violating_fraction']:.2f} | {r['hurwitz']} | {r['other_equilibria']} | "
                     f"{r['train_time_s']:.0f} | {r['certificate']} | {_decrease(r)} | {r['roa'] or '-'} |")
    if "float_kernels" in report:
        lines += ["", f"{KERNELS_LINE} {describe_kernels(report['float_kernels'])} (the digits depend on them)"]
    lines += ["", ACCEPTANCE_LEGEND]
    factors = report["sweep"]
    lines += ["", f"Success on the {report['results'][0]['more_200']['n']} more states at k x the test shift:", "",
              "| seed | method | " + " | ".join(f"k={k}" for k in factors) + " |",
              "|---|---|" + "---|" * len(factors)]
    for r in report["results"]:
        lines.append(f"| {r['seed']} | {r['method']} | " + " | ".join(str(r["sweep_200"][k]) for k in factors) + " |")
    return "\n".join(lines)
