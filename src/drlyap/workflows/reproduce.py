"""The paper's experiments end to end (``drlyap reproduce``): train baseline and DR, evaluate on the true shifted model.

``reproduce`` trains, for each seed, the baseline (nominal condition at the mean of the xi samples)
and the DR pair with the system's paper settings, evaluates both at the paper's test shift on the
paper's 10 initial states and on 200 more, prints a table, and draws the paper's figures.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, replace
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


@dataclass(frozen=True)
class ReproduceSettings:
    """What :func:`reproduce` runs: for each of ``seeds``, both pairs trained (``iters``: the iteration cap, None: the
    system's; on ``device``), evaluated from the paper's 10 initial states and ``n_more`` others at the test shift and
    at the multiples ``sweep`` of it, over ``horizon`` units of simulated time (None: the system's). With ``verify``,
    counterexample-guided rounds (at most ``verify_rounds``) until the verifier proves each pair's trained condition,
    then its decrease on the true model at the test shift and its certified region of attraction there
    (``verify_time`` seconds per check, also the cap of each proof of the training rounds; None: the system's)."""

    seeds: Sequence[int]
    iters: int | None = None
    device: str = "cpu"
    n_more: int = 200
    sweep: Sequence[int] = SWEEP
    horizon: float | None = None
    verify: bool = True
    verify_rounds: int = 5
    verify_time: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "seeds", tuple(self.seeds))
        object.__setattr__(self, "sweep", tuple(self.sweep))


def reproduce(system: str | UncertainSystem, settings: ReproduceSettings, out: Path, *, source: dict | None = None,
              compute: Compute = Compute(), progress: bool = True, log=print) -> dict:
    """Run the paper's experiment for ``system`` (an object, or a spec for
    :func:`drlyap.systems.resolve_system`) as ``settings`` says (:class:`ReproduceSettings`) and write everything
    under ``out`` (atomically).

    Any system works that declares ``test_xi`` and an ``xi_sampler``. Returns a JSON-friendly dict with
    per-seed, per-method results and the paths of the figures. Both pairs are trained as :func:`drlyap.train` does;
    with ``settings.verify``, each pair's decrease on the true model at the test shift and its certified region of
    attraction there are proved (:func:`drlyap.workflows.verify.verify`; None ``verify_time``: the run's seconds per
    proof, 30 or the system's) and stored in its ``metrics["certificate"]``.
    ``source`` (:func:`drlyap.systems.system_source`) is recorded in each run directory; by default it is derived from
    a spec, or the registry name. ``compute``: where the proofs bound their boxes (:class:`~drlyap.compute.Compute`).
    ``progress``: progress bars and the proof rounds' lines (through ``log``, which also gets each result's line).
    """
    if isinstance(system, str):
        spec, system = system, resolve_system(system)
        source = system_source(spec, system)
    proof = ProofConfig(rounds=settings.verify_rounds, time_limit=settings.verify_time).with_compute(compute) \
        if settings.verify else None
    missing = [f for f in ("test_xi", "xi_sampler") if getattr(system, f) is None]
    if missing:
        raise ValueError(f"{system.name} declares no {' and no '.join(missing)}; reproduce needs a test shift "
                         "(UncertainSystem.test_xi) and a training distribution (UncertainSystem.xi_sampler)")
    check_writable(out)
    if not settings.seeds:
        raise ValueError("need at least one seed")
    work = _Reproduction(system, settings, Path(out), proof, source, compute, progress, log)
    atomic_dir(Path(out), work.fill, overwrite=False)
    return work.report


class _Reproduction:
    """One :func:`reproduce` while it runs: its inputs, and the report it fills."""

    def __init__(self, system: UncertainSystem, settings: ReproduceSettings, out: Path, proof: ProofConfig | None,
                 source: dict | None, compute: Compute, progress: bool, log) -> None:
        self.system, self.settings, self.out, self.proof = system, settings, out, proof
        self.source, self.compute, self.progress, self.log = source, compute, progress, log
        self.xi_test = torch.tensor(system.test_xi, dtype=torch.float64)
        self.report: dict = {"system": system.name, "test_xi": list(system.test_xi), "seeds": list(settings.seeds),
                             "sweep": list(settings.sweep), "verify": settings.verify,
                             "verify_rounds": settings.verify_rounds, "results": []}

    def fill(self, tmp: Path) -> None:
        """Every seed's runs, figures and rows under ``tmp``, then the sweep figure and the report files."""
        system, settings, report = self.system, self.settings, self.report
        bar = show_progress(len(settings.seeds) * len(METHODS) * (2 + len(settings.sweep)),
                            f"{system.name} evaluations", self.progress)
        for seed in settings.seeds:
            self._seed(tmp, seed, bar)
        bar.close()
        report["float_kernels"] = float_kernels(settings.device)
        report["figures"]["sweep"] = str(self.out / "shift_sweep.png")
        plotting.sweep_plot(system.name, settings.sweep, report["results"], tmp / "shift_sweep.png",
                            list(system.test_xi))
        (tmp / "report.json").write_text(json.dumps(report, indent=2) + "\n")
        (tmp / "report.md").write_text(format_table(report) + "\n")

    def _seed(self, tmp: Path, seed: int, bar) -> None:
        """Both methods' runs of ``seed``, their rows and the seed's figures."""
        x_paper, x_more = test_initial_states(self.system, seed, n_more=self.settings.n_more)
        runs: dict[str, Run] = {}
        paper_trajs, paper_ok = {}, {}
        for method in METHODS:
            runs[method], paper_trajs[method], paper_ok[method] = self._method(tmp, seed, method, x_paper, x_more, bar)
        figures = draw_figures(self.system, runs, self.xi_test, paper_trajs, paper_ok, tmp / f"seed{seed}" / "figures",
                               seed, self.settings.horizon)
        self.report.setdefault("figures", {})[str(seed)] = [str(self.out / f"seed{seed}" / "figures" / f.name)
                                                            for f in figures]

    def _method(self, tmp: Path, seed: int, method: str, x_paper: torch.Tensor, x_more: torch.Tensor, bar) -> tuple:
        """Train, save, evaluate and prove one pair; its row goes into the report. Returns the run, its trajectories
        from the paper's states and which of them succeeded."""
        system, settings, log, xi_test, horizon = self.system, self.settings, self.log, self.xi_test, self.settings.horizon
        cfg = TrainConfig(system=system.name, method=method, seed=seed, device=settings.device)
        if settings.iters is not None:
            cfg.iters = settings.iters
        result = train(cfg, system, self.proof, progress=self.progress, warn=False,
                       log=(lambda entry, m=method, s=seed: log(f"seed {s} {m}: {proof_round_line(entry)[2:]}"))
                       if self.progress else None)
        run = load_run(save_run(tmp / f"seed{seed}" / method, result, source=self.source), system)
        paper_traj = simulate(system, run.controller, x_paper, xi_test, horizon=horizon)  # drawn below too
        paper = score(system, paper_traj, xi_test, run.lyapunov, horizon=horizon)
        more = evaluate_run(run, xi_test, x_more, horizon)
        bar.update(2)
        run.keep({"evaluations": {"paper_10": paper, "more_200": more}})
        ver = self._prove(run) if settings.verify else None
        swept = {}
        for k in settings.sweep:
            swept[k] = evaluate_run(run, k * xi_test, x_more, horizon)["n_success"]
            bar.update(1)
        row = _result_row(result, seed, method, ver, paper, more, swept, str(self.out / f"seed{seed}" / method))
        self.report["results"].append(row)
        log(format_row(row))
        return run, paper_traj, paper["success"]

    def _prove(self, run: Run):
        """What the pair proves on the true model at the test shift (the figures draw its region), recorded in its
        run directory."""
        verify_time = self.settings.verify_time
        checks = (run.proof if verify_time is None else replace(run.proof, time_limit=verify_time)
                  ).with_compute(self.compute)
        ver = prove_run(run, checks, VerifyRequest(xi=self.xi_test, roa=True))
        record_region(run, ver)
        record_certificates(run, ver)  # the proofs that ended verified, re-checkable by drlyap check
        record_roa(run, ver, checks)
        return ver


def _result_row(result, seed: int, method: str, ver, paper: dict, more: dict, swept: dict, run_dir: str) -> dict:
    """The report's row of one pair: its training ``result``, what ``ver`` proved at the test shift (None: not
    proved), its evaluations and where it is."""
    record, acc = result.record, result.acceptance
    true_model = None if ver is None else ver.true_model
    return {"seed": seed, "method": method, "passed_acceptance": record.passed,
            "acceptance_status": record.status, "max_violation": acc.max_violation,
            "violating_fraction": acc.violating_fraction, "hurwitz": acc.hurwitz,
            "other_equilibria": len(acc.other_equilibria),
            "iterations": record.iterations, "train_time_s": record.total_time_s,
            "certificate": record.certificate_status,
            "true_model": None if true_model is None else true_model.status,
            "true_model_fraction": None if true_model is None else true_model.verified_fraction,
            "roa": roa_cell(None if ver is None else ver.roa),
            "paper_10": summary_row(paper), "more_200": summary_row(more), "sweep_200": swept,
            "run_dir": run_dir}


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
