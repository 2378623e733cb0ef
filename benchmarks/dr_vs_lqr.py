"""The DR pair against saturated LQR on systems of one's own, with the defaults a user gets.

Usage::

    python benchmarks/dr_vs_lqr.py [SYSTEM_FILE ...] [--out DIR] [--seed S]

For each system file (default: the 2-state systems of ``benchmarks/systems/``, written as the README's "Your own
system" shows and not tuned for), runs what a user would, one command at a time with one torch thread::

    drlyap train FILE:make --out DIR/NAME-dr --seed S
    drlyap lqr FILE:make --out DIR/NAME-lqr
    drlyap compare DIR/NAME-dr DIR/NAME-lqr --xi TEST --system FILE:make --out DIR/NAME-compare

and prints one row per system: the share of the box each run's certified region of attraction covers at the
system's test shift (the same search for both, :func:`drlyap.workflows.compare.certify`), the certified shift box of
each (decrease on the true model for every shift within s times the test shift) and the seconds of each command.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def drlyap(*args: str) -> float:
    """Run ``drlyap ARGS`` with one torch thread; its wall seconds (a failure stops the benchmark)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", DRLYAP_THREADS="1", MPLBACKEND="Agg")
    start = time.perf_counter()
    command = [sys.executable, "-c", "from drlyap.cli import main; main()", *args]
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode not in (0, 3, 4):  # 3, 4: a condition violated or unknown, still a result
        sys.exit(f"drlyap {' '.join(args)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return time.perf_counter() - start


def shift_of(spec: str) -> str:
    """The system's test shift, as `--xi` takes it."""
    from drlyap.systems import resolve_system

    system = resolve_system(spec)
    return ",".join(f"{v:g}" for v in system.test_xi)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="*", help="system files defining make() [benchmarks/systems/*.py]")
    parser.add_argument("--out", default="runs/dr-vs-lqr", help="where the runs go [runs/dr-vs-lqr]")
    parser.add_argument("--seed", type=int, default=0, help="training seed [0]")
    args = parser.parse_args(argv)
    files = [Path(f) for f in args.files] or sorted((HERE / "systems").glob("*.py"))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"{'system':<16} {'DR region':>10} {'LQR region':>11} {'DR shift box':>13} {'LQR shift box':>14} "
          f"{'train s':>8} {'compare s':>10}")
    for file in files:
        name, spec = file.stem, f"{file}:make"
        dr, lqr, cmp = out / f"{name}-dr", out / f"{name}-lqr", out / f"{name}-compare"
        train_s = None if dr.exists() else drlyap("train", spec, "--out", str(dr), "--seed", str(args.seed))
        if not lqr.exists():
            drlyap("lqr", spec, "--out", str(lqr))
        compare_s = None if cmp.exists() else drlyap("compare", str(dr), str(lqr), "--xi", shift_of(spec),
                                                      "--system", spec, "--out", str(cmp))
        rows = {row["kind"]: row["certified"] for row in json.loads((cmp / "compare.json").read_text())["rows"]}

        def share(row: dict) -> str:
            return f"{100 * row['roa_share']:.1f}%" if row.get("roa_certified") else "none"

        def box(row: dict) -> str:
            s = (row.get("robustness") or {}).get("shift_box_s")
            return "none" if s is None else f"{s:.3g} x"

        def secs(value: float | None) -> str:  # None: the run directory was there already
            return "-" if value is None else f"{value:.1f}"

        print(f"{name:<16} {share(rows['lyapunov']):>10} {share(rows['lqr']):>11} {box(rows['lyapunov']):>13} "
              f"{box(rows['lqr']):>14} {secs(train_s):>8} {secs(compare_s):>10}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
