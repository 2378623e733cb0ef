"""Running a sweep (:func:`run_sweep`) into its directory, resuming it, and its tables.

The sweep directory::

    OUT/sweep.json          the grid (a rerun with a different grid is refused)
    OUT/<combination>/      one complete run directory per finished combination, with result.json
    OUT/results.csv         one row per combination (failed ones with their error)
    OUT/results.json        the grid, the rows, a summary per (method, radius, eps) and the wall time
    OUT/figures/sweep.png   success, verified share and certified region against the radius

A running sweep owns its directory (a lock file: a second sweep, or a run written into it, is refused). Resuming is
running the same sweep again: finished combinations are read back from their ``result.json`` once their weights
load and match the recorded sha256, and not redone; failed, interrupted and damaged ones run again. A damaged or
missing ``sweep.json`` is rebuilt when the finished combinations on disk record the same grid (its sha256). Every
task seeds its own training and evaluation and its proofs are budgeted by work (boxes), so a combination gives
the same numbers on either backend and on a busy machine, unless a proof hit its outer time cap (reported).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import shutil
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from drlyap import plotting
from drlyap.io import jsonable, write_json
from drlyap.runs.publish import LOCK_FILE, DirectoryLock, RunDirError, check_writable
from drlyap.runs.validate import load_weights
from drlyap.workflows.sweep.backends import Backend, LocalBackend
from drlyap.workflows.sweep.grid import RESULT_FILE, SPEC_FILE, STAGING, Combination, SweepError, SweepSpec
from drlyap.workflows.sweep.task import file_sha256, spec_sha256


def _recorded_grids(out: Path) -> set[str]:
    """The grid sha256 recorded by the finished combinations in ``out``."""
    grids = set()
    for path in out.glob(f"*/{RESULT_FILE}"):
        try:
            grids.add(json.loads(path.read_text()).get("spec_sha256"))
        except (OSError, json.JSONDecodeError, AttributeError):
            continue
    return grids - {None}


def _prepare(spec: SweepSpec, out: Path) -> None:
    """Give ``out`` (owned by this process) its ``sweep.json``, or check that the one there holds the same grid; a
    damaged or missing one is rebuilt when the finished combinations record this grid."""
    path = out / SPEC_FILE
    wanted = jsonable(spec.to_dict())
    stored = None
    if path.exists():
        try:
            stored = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            grids = _recorded_grids(out)
            if grids != {spec_sha256(wanted)}:
                raise SweepError(f"{path} is damaged ({err}) and the combinations in {out} do not record this grid; "
                                 "rerun with the sweep's own options to rebuild it, or choose another --out") from None
            write_json(path, wanted)  # rebuilt: every finished combination was run with this grid
            stored = wanted
    if stored is not None:
        if stored != wanted:
            diff = sorted(k for k in set(stored) | set(wanted) if stored.get(k) != wanted.get(k))
            shown = "; ".join(f"{k}: stored {stored.get(k)!r}, asked {wanted.get(k)!r}" for k in diff)
            raise SweepError(f"{out} holds a different sweep ({shown}); rerun with the same grid to resume it, "
                             "or choose another --out")
    elif any(p for p in out.iterdir() if p.name not in (STAGING, LOCK_FILE)):
        if _recorded_grids(out) != {spec_sha256(wanted)}:
            raise SweepError(f"{out} exists and is not a sweep directory (no {SPEC_FILE}); choose another --out")
        write_json(path, wanted)  # rebuilt from the finished combinations, which all record this grid
    else:
        write_json(path, wanted)
    shutil.rmtree(out / STAGING, ignore_errors=True)  # half-done tasks of an interrupted sweep (none runs: locked)


def finished_row(out: Path, combo: Combination) -> dict | None:
    """The stored row of a finished combination, or None if it has to run (missing, incomplete, failed, or damaged:
    weights that do not load or do not match the recorded sha256). A damaged combination directory is removed; a
    folder at a combination's name that the sweep did not write (no ``result.json``) is a :class:`SweepError`."""
    folder = out / combo.name
    path = folder / RESULT_FILE
    if not folder.exists():
        return None
    if not path.is_file() and not path.is_symlink():  # every combination the sweep publishes carries its result.json
        raise SweepError(f"{folder} was not written by this sweep (no {RESULT_FILE}): move it away or choose another "
                         "--out; the sweep removes nothing it did not write")
    row = None
    try:
        row = json.loads(path.read_text())
        weights = folder / "weights.pt"
        intact = ((folder / "run.json").is_file() and row.get("status") == "ok" and row.get("name") == combo.name
                  and row.get("weights_sha256") == file_sha256(weights))
        if intact:
            load_weights(weights)
    except (OSError, json.JSONDecodeError, UnicodeDecodeError, AttributeError, RunDirError):
        intact = False
    if not intact:
        shutil.rmtree(folder, ignore_errors=True)  # redone below; the sweep owns its directory
        return None
    return row


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
    if not out.exists():
        check_writable(out)
    with DirectoryLock(out, "a sweep"):
        return _run_locked(spec, out, backend, on_result, figures, start)


def _run_locked(spec: SweepSpec, out: Path, backend: Backend | None, on_result: Callable[[dict, int, int], None] | None,
                figures: bool, start: float) -> dict:
    _prepare(spec, out)
    combos = spec.combinations()
    rows: dict[str, dict] = {}
    todo = []
    damaged = []
    for combo in combos:
        existed = (out / combo.name).exists()
        row = finished_row(out, combo)
        if row is None:
            todo.append(combo)
            if existed:
                damaged.append(combo.name)
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
    extra = {"backend": backend.name, "computed": sorted(computed), "reused": reused, "damaged": damaged,
             "failed": sum(r["status"] != "ok" for r in rows.values()), "wall_s": time.perf_counter() - start}
    extra["figures"] = []
    report = write_tables(out, spec, list(rows.values()), extra)
    if figures and any(r["status"] == "ok" for r in rows.values()):
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
