"""Sweeps: train, verify and evaluate every combination of seeds x radii x risk levels x methods.

A :class:`SweepSpec` is the grid; :func:`run_sweep` runs each combination as one task on a
:class:`Backend` (:class:`LocalBackend`: worker processes of the standard library, one torch thread
each; :class:`RayBackend`: one Ray task per combination, locally or on a cluster) and collects the
results as they finish. One task (:func:`run_combination`):

1. trains the pair as ``drlyap train`` does (:func:`drlyap.cegis.train_certified`: counterexample-guided
   rounds until the trained condition is proved, at most ``verify_rounds``; ``verify=False`` skips them);
2. saves it as a run directory (:func:`drlyap.rundir.save_run`) in a staging folder;
3. verifies it (:func:`drlyap.verification.verify_run` at the system's test shift with ``roa=True``):
   the trained condition over X_delta, the plain decrease on the true model at the test shift, and
   the certified region of attraction there;
4. evaluates it on the true model at k x the test shift (:func:`drlyap.experiments.evaluate_run`)
   from the seed's evaluation states (:func:`drlyap.experiments.test_initial_states`);
5. writes ``result.json`` into the run directory and renames the staging folder to
   ``OUT/<combination>/``: a combination directory exists only when it is complete.

The sweep directory::

    OUT/sweep.json          the grid (a rerun with a different grid is refused)
    OUT/<combination>/      one complete run directory per finished combination, with result.json
    OUT/results.csv         one row per combination (failed ones with their error)
    OUT/results.json        the grid, the rows, a summary per (method, radius, eps) and the wall time
    OUT/figures/sweep.png   success, verified share and certified region against the radius

Resuming is running the same sweep again: finished combinations are read back from their
``result.json`` and not redone; failed and interrupted ones run again. Every task seeds its own
training and evaluation, so a combination gives the same numbers on either backend as long as no
time limit stopped a branch and bound: the proof rounds retrain on the counterexamples the time-limited
verifier found, so with ``verify`` a retrained pair can differ between a fast and a slow worker.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import shutil
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch

from drlyap.io import from_fields
from drlyap.rundir import jsonable, write_json
from drlyap.systems import UncertainSystem, resolve_system, system_source
from drlyap.training import TrainConfig

METHODS = ("baseline", "dr")
SPEC_FILE = "sweep.json"
RESULT_FILE = "result.json"
STAGING = ".staging"


class SweepError(ValueError):
    """A sweep grid, directory or backend that cannot be used as asked."""


# ----------------------------------------------------------------------------------------------- grid


def parse_seeds(text: str) -> list[int]:
    """Seeds from ``"0-9"``, ``"0,2,5"`` or a mix (``"0-4,10"``); ranges are inclusive, duplicates dropped."""
    seeds: list[int] = []
    for part in (p.strip() for p in str(text).split(",")):
        if not part:
            continue
        low, sep, high = part.partition("-")
        try:
            values = range(int(low), int(high) + 1) if sep else [int(part)]
            if sep and int(high) < int(low):
                raise SweepError(f"seeds: range {part!r} runs backwards; write LOW-HIGH with LOW <= HIGH")
        except ValueError as err:
            if isinstance(err, SweepError):
                raise
            raise SweepError(f"seeds: {part!r} is not a seed or a range; valid: '0-9', '0,2,5', '0-4,10' "
                             "(non-negative integers)") from None
        seeds += [s for s in values if s not in seeds]
    if not seeds:
        raise SweepError(f"seeds: no seed in {text!r}; valid: '0-9', '0,2,5', '0-4,10'")
    return seeds


def parse_values(text: str, what: str) -> list[float]:
    """Finite numbers from a comma-separated list (``"0,0.005,0.01"``), duplicates dropped."""
    values: list[float] = []
    for part in (p.strip() for p in str(text).split(",")):
        if not part:
            continue
        try:
            value = float(part)
        except ValueError:
            raise SweepError(f"{what}: {part!r} is not a number; give comma-separated numbers like '0,0.005,0.01'") from None
        if not math.isfinite(value):
            raise SweepError(f"{what}: {part!r} is not finite")
        if value not in values:
            values.append(value)
    if not values:
        raise SweepError(f"{what}: no value in {text!r}; give comma-separated numbers like '0,0.005,0.01'")
    return values


def parse_methods(text: str) -> list[str]:
    """``"dr"``, ``"baseline"``, ``"both"`` or a comma-separated list of the first two."""
    parts = [p.strip() for p in str(text).split(",") if p.strip()]
    methods: list[str] = []
    for part in parts:
        for m in (METHODS if part == "both" else (part,)):
            if m not in METHODS:
                raise SweepError(f"method {m!r}; valid: baseline, dr, both")
            if m not in methods:
                methods.append(m)
    if not methods:
        raise SweepError(f"no method in {text!r}; valid: baseline, dr, both")
    return methods


@dataclass(frozen=True)
class Combination:
    """One point of the grid. The baseline does not use r or eps: they are None there."""

    method: str
    seed: int
    radius: float | None
    eps: float | None

    @property
    def name(self) -> str:
        """Directory name, e.g. ``dr-r0.01-eps0.1-seed3`` or ``baseline-seed3``."""
        if self.method == "baseline":
            return f"baseline-seed{self.seed}"
        return f"{self.method}-r{self.radius:g}-eps{self.eps:g}-seed{self.seed}"


@dataclass
class SweepSpec:
    """The grid and everything each combination depends on (saved as ``sweep.json``).

    ``system`` is a registered name or a ``module:factory`` / ``file.py:factory`` spec
    (:func:`drlyap.systems.resolve_system`). ``config`` holds further :class:`~drlyap.training.TrainConfig`
    fields applied to every combination (e.g. smaller networks). ``verify``/``verify_rounds``: prove each
    trained pair with up to this many retraining rounds, as ``drlyap train`` does. ``shift_factors``:
    evaluation at k x the system's test shift. ``n_init`` evaluation states per seed; ``horizon`` simulated time (system units,
    ``None``: the system's). ``verify_time_limit``: seconds per branch and bound.
    """

    system: str
    seeds: list[int]
    radii: list[float]
    eps: list[float]
    methods: list[str] = field(default_factory=lambda: ["dr"])
    iters: int | None = None
    verify: bool = True
    verify_rounds: int = 5
    device: str = "cpu"
    shift_factors: list[float] = field(default_factory=lambda: [1.0, 2.0, 3.0, 4.0, 5.0])
    n_init: int = 200
    horizon: float | None = None
    verify_time_limit: float = 30.0
    config: dict = field(default_factory=dict)

    def combinations(self) -> list[Combination]:
        """Every combination, baselines once per seed (they ignore r and eps)."""
        combos = []
        for method in self.methods:
            for seed in self.seeds:
                if method == "baseline":
                    combos.append(Combination(method, seed, None, None))
                    continue
                combos += [Combination(method, seed, r, e) for e in self.eps for r in self.radii]
        return combos

    def train_config(self, combo: Combination, system: UncertainSystem | None = None) -> TrainConfig:
        """The training configuration of one combination (system defaults for what the sweep leaves open).

        ``system``: the resolved ``self.system``, when the caller has it (a file spec is imported on each resolve).
        """
        system = system or resolve_system(self.system)
        cfg = TrainConfig(system=system.name, method=combo.method, seed=combo.seed,
                          device=self.device, wasserstein_radius=combo.radius, risk_level=combo.eps,
                          verify=self.verify, verify_rounds=self.verify_rounds, verify_time=self.verify_time_limit,
                          **self.config)
        if self.iters is not None:
            cfg.iters = int(self.iters)
        return cfg

    def validate(self) -> None:
        """Check the whole grid before anything runs (every combination's config, the evaluation settings)."""
        system = resolve_system(self.system)
        if system.test_xi is None:
            raise SweepError(f"{self.system} declares no test shift; a sweep evaluates at k x that shift")
        problems = []
        if self.verify_rounds < 0:
            problems.append(f"verify_rounds = {self.verify_rounds} (must be >= 0)")
        if self.n_init < 1:
            problems.append(f"n_init = {self.n_init} (must be >= 1)")
        if self.horizon is not None and not self.horizon > 0:
            problems.append(f"horizon = {self.horizon} (must be > 0)")
        if not self.verify_time_limit > 0:
            problems.append(f"verify_time_limit = {self.verify_time_limit} (must be > 0)")
        if not self.shift_factors or not all(math.isfinite(k) for k in self.shift_factors):
            problems.append(f"shift_factors = {self.shift_factors} (need finite numbers)")
        if problems:
            raise SweepError("invalid sweep: " + "; ".join(problems))
        for combo in self.combinations():
            try:
                self.train_config(combo, system).resolved(system)
            except (TypeError, ValueError) as err:
                raise SweepError(f"combination {combo.name}: {err}") from None

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> SweepSpec:
        return from_fields(cls, data, "sweep", SweepError)


# ----------------------------------------------------------------------------------------------- one task


def _verification_summary(ver: dict) -> dict:
    trained, true_model, roa = ver["trained"], ver.get("true_model", {}), ver.get("roa") or {}
    return {
        "trained_condition": trained.get("status"),
        "trained_verified_fraction": trained.get("verified_fraction"),
        "test_decrease": true_model.get("status"),
        "test_verified_fraction": true_model.get("verified_fraction"),
        "roa_certified": bool(roa.get("certified", False)),
        "roa_share": float(roa["share_of_box"]) if roa.get("certified") else 0.0,
        "verify_time_s": sum(float(v.get("time_s") or 0.0) for v in (trained, true_model)),
    }


def run_combination(spec_dict: dict, combo_dict: dict, out: str, threads: int = 1) -> dict:
    """Train, save, verify and evaluate one combination into ``out/<name>/`` (the worker's task).

    Never raises: a failure comes back as a row with ``status = "failed"``, the error and the last
    lines of its traceback. Returns the row (also written to ``out/<name>/result.json`` on success).
    """
    torch.set_num_threads(threads)
    spec, combo = SweepSpec.from_dict(spec_dict), Combination(**combo_dict)
    row: dict = {"name": combo.name, **dataclasses.asdict(combo)}
    tic = time.perf_counter()
    staging = Path(out) / STAGING / combo.name
    try:
        from drlyap.cegis import train_certified
        from drlyap.experiments import evaluate_run, test_initial_states
        from drlyap.rundir import load_run, save_run
        from drlyap.verification import verify_run

        system = resolve_system(spec.system)
        result = train_certified(spec.train_config(combo, system), system, progress=False, warn=False)
        if staging.exists():
            shutil.rmtree(staging)
        save_run(staging, result, source=system_source(spec.system, system))
        run = load_run(staging)
        system = run.system
        xi_test = torch.tensor(system.test_xi, dtype=torch.float64)
        m = result.metrics
        row.update({"passed_acceptance": bool(m["passed"]), "iterations": int(m["iterations"]),
                    "train_time_s": float(m.get("cegis", {}).get("total_time_s", m["train_time_s"])),
                    "violating_fraction": float(m["acceptance"]["violating_fraction"])})
        ver = verify_run(run, xi=xi_test, roa=True, time_limit=spec.verify_time_limit)
        row.update(_verification_summary(ver))
        _, x0 = test_initial_states(system, combo.seed, n_more=spec.n_init)
        success = {}
        for k in spec.shift_factors:
            ev = evaluate_run(run, k * xi_test, x0, spec.horizon)
            success[f"{k:g}"] = ev["success_rate"]
        row["success"] = success
        row["status"] = "ok"
        row["error"] = None
        row["task_time_s"] = time.perf_counter() - tic
        row["run_dir"] = combo.name
        run.metrics["sweep"] = {k: row[k] for k in ("trained_condition", "test_decrease", "roa_share", "success")}
        run.save_metrics()
        write_json(staging / RESULT_FILE, row)
        final = Path(out) / combo.name
        if final.exists():
            shutil.rmtree(final)
        os.replace(staging, final)
        return jsonable(row)
    except Exception as err:  # a failing combination is recorded, the others go on
        shutil.rmtree(staging, ignore_errors=True)
        lines = traceback.format_exc().strip().splitlines()
        row.update({"status": "failed", "error": f"{type(err).__name__}: {err}", "traceback": lines[-6:],
                    "task_time_s": time.perf_counter() - tic})
        return jsonable(row)


# ----------------------------------------------------------------------------------------------- backends


Task = tuple[dict, dict, str]  # (spec dict, combination dict, sweep directory): the arguments of run_combination


class Backend:
    """Runs tasks (:func:`run_combination` arguments) and yields their rows as they finish, in any order."""

    name = "backend"

    def run(self, tasks: Sequence[Task]) -> Iterator[dict]:
        raise NotImplementedError

    def __enter__(self) -> Backend:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Release what the backend started."""


def _init_worker(threads: int) -> None:
    os.environ["OMP_NUM_THREADS"] = str(threads)
    torch.set_num_threads(threads)


def _crashed(task: Task, err: BaseException) -> dict:
    combo = Combination(**task[1])
    return {"name": combo.name, **task[1], "status": "failed", "error": f"worker crashed: {type(err).__name__}: {err}",
            "traceback": [], "task_time_s": None}


class LocalBackend(Backend):
    """``workers`` local processes (``spawn``, standard library), ``threads`` torch threads each."""

    name = "local"

    def __init__(self, workers: int = 1, threads: int = 1) -> None:
        if workers < 1 or threads < 1:
            raise SweepError(f"workers and threads must be >= 1, got {workers} and {threads}")
        self.workers, self.threads = workers, threads
        self._pool = None

    def run(self, tasks: Sequence[Task]) -> Iterator[dict]:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        if not tasks:
            return
        self._pool = ProcessPoolExecutor(max_workers=min(self.workers, len(tasks)),
                                         mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_init_worker, initargs=(self.threads,))
        futures = {self._pool.submit(run_combination, *task, self.threads): task for task in tasks}
        try:
            for future in as_completed(futures):
                try:
                    yield future.result()
                except Exception as err:  # the worker process died (e.g. killed, out of memory)
                    yield _crashed(futures[future], err)
        finally:
            self.close()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


class RayBackend(Backend):
    """One Ray task per combination. Without ``address`` Ray starts locally with ``workers`` CPUs;
    with one (``"auto"``, ``"ray://host:10001"``, ``"host:6379"``) it joins that cluster. Each task asks
    for one CPU and uses ``threads`` torch threads; workers must be able to ``import drlyap``."""

    name = "ray"

    def __init__(self, workers: int = 1, threads: int = 1, address: str | None = None) -> None:
        try:
            import ray
        except ImportError:
            raise SweepError("the Ray backend needs Ray: pip install 'drlyap[ray]' (or pip install 'ray>=2.9')") from None
        if workers < 1 or threads < 1:
            raise SweepError(f"workers and threads must be >= 1, got {workers} and {threads}")
        self.ray, self.threads, self._started = ray, threads, False
        if not ray.is_initialized():
            env = {"env_vars": {"OMP_NUM_THREADS": str(threads)}}
            if address:
                ray.init(address=address, runtime_env=env, log_to_driver=False)
            else:
                ray.init(num_cpus=workers, include_dashboard=False, runtime_env=env, log_to_driver=False,
                         configure_logging=False)
            self._started = True

    def run(self, tasks: Sequence[Task]) -> Iterator[dict]:
        ray = self.ray
        remote = ray.remote(num_cpus=1, max_retries=0)(run_combination)
        pending = {remote.remote(*task, self.threads): task for task in tasks}
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    task = pending.pop(ref)
                    try:
                        yield ray.get(ref)
                    except Exception as err:  # the worker died
                        yield _crashed(task, err)
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)

    def close(self) -> None:
        if self._started:
            self.ray.shutdown()
            self._started = False


def make_backend(kind: str, workers: int = 1, address: str | None = None, threads: int = 1) -> Backend:
    """``"local"`` or ``"ray"``; ``address`` only for Ray."""
    if kind == "local":
        if address:
            raise SweepError("--address is for --backend ray; the local backend runs on this machine")
        return LocalBackend(workers, threads)
    if kind == "ray":
        return RayBackend(workers, threads, address)
    raise SweepError(f"backend {kind!r}; valid: local, ray")


# ----------------------------------------------------------------------------------------------- driver


def _prepare(spec: SweepSpec, out: Path) -> None:
    """Create ``out`` with ``sweep.json``, or check that an existing one holds the same grid."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / SPEC_FILE
    wanted = jsonable(spec.to_dict())
    if path.exists():
        try:
            stored = json.loads(path.read_text())
        except json.JSONDecodeError as err:
            raise SweepError(f"{path} is not valid JSON ({err}); remove it or choose another --out") from None
        if stored != wanted:
            diff = sorted(k for k in set(stored) | set(wanted) if stored.get(k) != wanted.get(k))
            shown = "; ".join(f"{k}: stored {stored.get(k)!r}, asked {wanted.get(k)!r}" for k in diff)
            raise SweepError(f"{out} holds a different sweep ({shown}); rerun with the same grid to resume it, "
                             "or choose another --out")
    elif any(p for p in out.iterdir() if p.name != STAGING):
        raise SweepError(f"{out} exists and is not a sweep directory (no {SPEC_FILE}); choose another --out")
    else:
        write_json(path, wanted)
    shutil.rmtree(out / STAGING, ignore_errors=True)  # half-done tasks of an interrupted sweep


def finished_row(out: Path, combo: Combination) -> dict | None:
    """The stored row of a finished combination, or None if it has to run (missing, incomplete, failed)."""
    path = out / combo.name / RESULT_FILE
    if not (path.is_file() and (out / combo.name / "run.json").is_file()):
        return None
    try:
        row = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return row if row.get("status") == "ok" and row.get("name") == combo.name else None


CSV_COLUMNS = ("name", "status", "method", "seed", "radius", "eps", "passed_acceptance", "iterations", "train_time_s",
               "trained_condition", "trained_verified_fraction", "test_decrease", "test_verified_fraction",
               "roa_certified", "roa_share", "task_time_s", "error")


def summarise(rows: Sequence[dict], factors: Sequence[float]) -> list[dict]:
    """Per (method, eps, radius): number of seeds, failures, and mean / min / max of success at each
    shift factor, verified counts and certified share of the box."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["method"], r.get("eps"), r.get("radius")), []).append(r)
    out = []
    for (method, eps, radius), group in groups.items():
        ok = [r for r in group if r["status"] == "ok"]
        entry: dict = {"method": method, "eps": eps, "radius": radius, "n": len(group), "failed": len(group) - len(ok)}
        if ok:
            def stats(values: list[float]) -> dict:
                return {"mean": sum(values) / len(values), "min": min(values), "max": max(values)}

            entry["success"] = {f"{k:g}": stats([r["success"][f"{k:g}"] for r in ok]) for k in factors}
            entry["trained_verified"] = sum(r["trained_condition"] == "verified" for r in ok)
            entry["test_verified"] = sum(r["test_decrease"] == "verified" for r in ok)
            entry["test_verified_fraction"] = stats([float(r["test_verified_fraction"] or 0.0) for r in ok])
            entry["roa_share"] = stats([r["roa_share"] for r in ok])
            entry["passed_acceptance"] = sum(bool(r["passed_acceptance"]) for r in ok)
        out.append(entry)
    return out


def write_tables(out: Path, spec: SweepSpec, rows: Sequence[dict], extra: dict | None = None) -> dict:
    """``results.csv`` and ``results.json`` from the rows (sorted by combination order of the grid)."""
    order = {c.name: i for i, c in enumerate(spec.combinations())}
    rows = sorted(rows, key=lambda r: order.get(r["name"], len(order)))
    factors = spec.shift_factors
    columns = list(CSV_COLUMNS) + [f"success_{k:g}x" for k in factors]
    tmp = out / ".results.csv.tmp"
    with open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        for r in rows:
            flat = dict(r)
            for k in factors:
                flat[f"success_{k:g}x"] = (r.get("success") or {}).get(f"{k:g}")
            writer.writerow(flat)
    os.replace(tmp, out / "results.csv")
    report = {"spec": spec.to_dict(), "rows": list(rows), "summary": summarise(rows, factors), **(extra or {})}
    tmp = out / ".results.json.tmp"
    write_json(tmp, report)
    os.replace(tmp, out / "results.json")
    return jsonable(report)


def run_sweep(spec: SweepSpec, out: str | os.PathLike, backend: Backend | None = None,
              on_result: Callable[[dict, int, int], None] | None = None, figures: bool = True) -> dict:
    """Run (or resume) the sweep ``spec`` into ``out`` on ``backend`` (default: one local worker).

    Finished combinations (a complete ``out/<name>/`` with an ``ok`` ``result.json``) are read back,
    the others run. ``on_result(row, done, total)`` is called as each task finishes. Returns the report
    written to ``results.json``: ``rows``, ``summary``, ``computed`` and ``reused`` (combination names),
    ``failed`` (count) and ``wall_s`` (seconds of this invocation).
    """
    start = time.perf_counter()
    out = Path(out)
    _prepare(spec, out)
    combos = spec.combinations()
    rows: dict[str, dict] = {}
    todo = []
    for combo in combos:
        row = finished_row(out, combo)
        if row is None:
            todo.append(combo)
        else:
            rows[combo.name] = row
    reused = sorted(rows)
    spec_dict = jsonable(spec.to_dict())
    tasks = [(spec_dict, dataclasses.asdict(c), str(out)) for c in todo]
    own = backend is None
    backend = backend or LocalBackend(1)
    computed = []
    try:
        for row in backend.run(tasks):
            rows[row["name"]] = row
            computed.append(row["name"])
            write_tables(out, spec, list(rows.values()))  # a killed sweep still leaves a table of what finished
            if on_result is not None:
                on_result(row, len(rows), len(combos))
    finally:
        if own:
            backend.close()
    try:
        (out / STAGING).rmdir()  # empty once every task has moved its directory into place
    except OSError:
        pass
    extra = {"backend": backend.name, "computed": sorted(computed), "reused": reused,
             "failed": sum(r["status"] != "ok" for r in rows.values()), "wall_s": time.perf_counter() - start}
    report = write_tables(out, spec, list(rows.values()), extra)
    if figures and any(r["status"] == "ok" for r in rows.values()):
        from drlyap import plotting

        path = plotting.against_radius(report["summary"], spec.shift_factors, out / "figures" / "sweep.png",
                                       f"{spec.system}: {len(spec.seeds)} seeds, min-max band over seeds")
        report["figures"] = [str(path)]
        report = write_tables(out, spec, list(rows.values()), {**extra, "figures": [str(path)]})
        report["wall_s"] = time.perf_counter() - start
    return report


def format_summary(report: dict) -> str:
    """A Markdown table of the summary: one line per (method, eps, radius)."""
    factors = [f"{k:g}" for k in report["spec"]["shift_factors"]]
    lines = ["| method | eps | r | seeds | success at " + ", ".join(f"{k}x" for k in factors)
             + " (mean [min, max]) | trained condition verified | decrease at test shift verified "
             "| share of X_delta proved at test shift (mean [min, max]) | certified ROA share (mean [min, max]) | failed |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for s in report["summary"]:
        ok = s["n"] - s["failed"]
        if ok:
            succ = "; ".join(f"{v['mean']:.2f} [{v['min']:.2f}, {v['max']:.2f}]" for v in (s["success"][k] for k in factors))
            roa, frac = s["roa_share"], s["test_verified_fraction"]
            cells = (f"{succ} | {s['trained_verified']}/{ok} | {s['test_verified']}/{ok} | "
                     f"{100 * frac['mean']:.3f}% [{100 * frac['min']:.3f}, {100 * frac['max']:.3f}] | "
                     f"{100 * roa['mean']:.1f}% [{100 * roa['min']:.1f}, {100 * roa['max']:.1f}]")
        else:
            cells = "- | - | - | - | -"
        lines.append(f"| {s['method']} | {_num(s['eps'])} | {_num(s['radius'])} | {s['n']} | {cells} | {s['failed']} |")
    return "\n".join(lines)


def format_row(row: dict) -> str:
    """One line for a finished combination."""
    if row["status"] != "ok":
        return f"{row['name']}: FAILED: {row['error']}"
    succ = ", ".join(f"{k}x {100 * v:.0f}%" for k, v in row["success"].items())
    return (f"{row['name']}: trained condition {row['trained_condition']}, decrease at test shift {row['test_decrease']}, "
            f"certified ROA {100 * row['roa_share']:.1f}% of the box; success {succ} ({row['task_time_s']:.0f} s)")


def _num(value: float | None) -> str:
    return "-" if value is None else f"{value:g}"
