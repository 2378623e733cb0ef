"""Certified regions of attraction of existing run directories (trains nothing).

Usage::

    python benchmarks/roa_bench.py RUN_DIR [RUN_DIR ...] [--xi V1,V2 | --xi test] [--threads T] [--system SPEC]

Prints one row per run: the system, the LQR weights of its warm start, its training seconds with its proof
rounds (from its metrics), the proof of its trained condition (status, boxes, seconds), plain decrease on the
true model at the shift (``--xi``, default each system's test shift) and the certified region of attraction there
with its share of the state box. Compare runs of one system trained on the same seed with different settings.
"""

from __future__ import annotations

import argparse
import sys
import time

import torch


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="run directories written by 'drlyap train'")
    parser.add_argument("--xi", default="test",
                        help="the shift (comma-separated, or 'test': each system's test shift) ['test']")
    parser.add_argument("--threads", type=int, default=1, help="torch threads [1]")
    parser.add_argument("--system", default=None,
                        help="the system of runs whose system came from a file or module (path/to/file.py:factory)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    from shift import run_shift

    from drlyap.runs import load_run
    from drlyap.systems import resolve_system
    from drlyap.workflows.verify import VerifyRequest, verify

    header = (f"{'run':<24} {'system':<12} {'LQR weights (Q; R)':<28} {'train s':>8} {'trained condition':<18} "
              f"{'boxes':>8} {'proof s':>8} {'true model':<10} {'region of attraction':<22} {'share':>8}")
    print(header)
    print("-" * len(header))
    failures = 0
    system = resolve_system(args.system) if args.system else None
    for path in args.runs:
        try:
            run = load_run(path, system)
            xi = run_shift(run, args.xi)
            tic = time.perf_counter()
            result = verify(run, request=VerifyRequest(xi=xi, roa=True))
            total = time.perf_counter() - tic
        except ValueError as err:
            print(f"{path:<24} error: {err}")
            failures += 1
            continue
        weights = run.config.lqr_weights
        weights_text = "-" if weights is None else "; ".join(",".join(f"{w:g}" for w in part) for part in weights)
        trained, true_model, roa = result.trained, result.true_model, result.roa
        region = (f"{{V <= {roa.level:.3g}}}" + (" in box" if roa.faces == "inward" else "")
                  if roa is not None and roa.certified and roa.kind == "region of attraction" else "none")
        share = roa.share_of_box if roa is not None and roa.certified and roa.share_of_box is not None else None
        train_s = (run.metrics.get("cegis") or {}).get("total_time_s", run.metrics.get("train_time_s"))
        print(f"{str(path)[-24:]:<24} {run.system.name:<12} {weights_text[:28]:<28} "
              f"{'-' if train_s is None else f'{train_s:.1f}':>8} {trained.status:<18} {trained.boxes_processed:>8} "
              f"{trained.time_s:>8.1f} {true_model.status:<10} {region:<22} "
              f"{'-' if share is None else f'{100 * share:.2f}%':>8}")
        print(f"{'':<24} (all proofs {total:.1f} s)")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
