"""Time the sound verifier on existing run directories (trains nothing).

Usage::

    python benchmarks/verify_bench.py RUN_DIR [RUN_DIR ...] [--delta D] [--xi V1,V2 | --xi test] [--time-limit S] [--threads T]

Prints one row per run and check: status, verified share of X_delta, boxes processed, boxes per second
and seconds. Rows: the run's trained condition, the uniform DR margin and, with ``--xi``, plain
decrease on the true model at that shift.
"""

from __future__ import annotations

import argparse
import sys
import time

import torch


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="run directories written by 'drlyap train'")
    parser.add_argument("--delta", type=float, default=None, help="radius of the excluded ball [each run's delta]")
    parser.add_argument("--xi", default=None,
                        help="also verify the true model at this shift (comma-separated, or 'test': each system's test shift)")
    parser.add_argument("--time-limit", type=float, default=30.0, help="seconds per branch and bound [30]")
    parser.add_argument("--threads", type=int, default=1, help="torch threads [1]")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    import dataclasses

    from shift import run_shift

    from drlyap.runs import load_run
    from drlyap.workflows.verify import VerifyRequest, run_proof, verify

    header = f"{'run':<36} {'check':<20} {'status':<9} {'verified':>10} {'boxes':>8} {'boxes/s':>9} {'seconds':>8}"
    print(header)
    print("-" * len(header))
    failures = 0
    for path in args.runs:
        try:
            run = load_run(path)
            xi = run_shift(run, args.xi)
            tic = time.perf_counter()
            proof = dataclasses.replace(run_proof(run), time_limit=args.time_limit)
            result = verify(run, proof, VerifyRequest(delta=args.delta, xi=xi, uniform=True)).to_dict()
            total = time.perf_counter() - tic
        except ValueError as err:
            print(f"{path:<36} error: {err}")
            failures += 1
            continue
        rows = [("trained: " + result["trained"]["condition"], result["trained"])]
        if result.get("uniform") not in (None, result["trained"]):
            rows.append(("uniform margin", result["uniform"]))
        if "true_model" in result:
            rows.append(("true model at xi", result["true_model"]))
        for label, res in rows:
            boxes, secs = res["boxes_processed"], res["time_s"]
            frac = res.get("verified_fraction")
            frac_text = "-" if frac is None else f"{100 * frac:.4f}%"
            if "margin_upper" in res:
                frac_text = f"m<={res['margin_upper']:.3g}"
            rate = "-" if res.get("source") == "certificate" else f"{boxes / max(secs, 1e-9):.0f}"  # nothing bounded
            print(f"{str(path)[-36:]:<36} {label[:20]:<20} {res['status']:<9} {frac_text:>10} {boxes:>8} "
                  f"{rate:>9} {secs:>8.2f}")
        print(f"{'':<36} {'(all checks)':<20} {'':<9} {'':>10} {'':>8} {'':>9} {total:>8.2f}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
