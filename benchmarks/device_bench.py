"""Proofs and training on a GPU beside the CPU: wall time, boxes per second and milliseconds per training iteration.

Usage::

    python benchmarks/device_bench.py [RUN_DIR ...] [--devices cpu,cuda] [--batches 4096,65536] [--boxes N]
                                      [--train pendulum,cartpole] [--train-devices cpu,cuda] [--threads 1]

Proof rows: each run's trained condition (on its sublevel set for a region-of-attraction run) proved from scratch in
this process on each device with each batch size (boxes bounded at a time; the CLI's is 4,096), with the run's own
box budget (``--boxes`` changes it). ``same leaves``: whether the proof's leaves (each box and its verdict, in any
order) are the ones of the first row's proof: the partition of a finished proof does not depend on where or how many
boxes at a time it was bounded.

Training rows: :func:`drlyap.training.fit` (training alone, the system's defaults, seed 0) on each device: its
seconds, iterations, milliseconds per iteration (the acceptance checks' time left out) and whether its pair passed.
The CPU rows use ``--threads`` torch threads; a device that is not there is reported in one line and skipped.
"""

from __future__ import annotations

import argparse
import hashlib
import sys

import numpy as np
import torch


def _leaf_digest(proof, region) -> str | None:
    """sha256 of the proof's leaves (box and verdict), sorted, so that the order in which they were made is left out."""
    from drlyap.regions import box_grid
    from drlyap.verification.partition import INTERNAL

    part = proof.partition
    if part is None:
        return None
    lo, hi = part.boxes(*box_grid(region.lo, region.hi, part.grid))
    leaf = part.verdict != INTERNAL
    rows = torch.cat([lo[leaf], hi[leaf], part.verdict[leaf].to(torch.float64)[:, None]], 1).numpy()
    rows = rows[np.lexsort(rows.T[::-1])]
    return hashlib.sha256(rows.tobytes()).hexdigest()


def _available(device: str) -> str | None:
    from drlyap.parallel import check_device

    try:
        check_device(device)
    except ValueError as err:
        return str(err)
    return None


def proof_rows(paths: list[str], devices: list[str], batches: list[int], boxes: int | None) -> None:
    from parallel_bench import _prove

    from drlyap.compute import Compute
    from drlyap.regions import Region
    from drlyap.runs import load_run
    from drlyap.workflows.verify import run_proof

    header = (f"{'run':<24} {'device':<7} {'batch':>7} {'status':<8} {'boxes':>10} {'wall s':>8} {'boxes/s':>9} "
              f"{'same leaves':>12}")
    print(header)
    print("-" * len(header))
    for path in paths:
        run = load_run(path)
        budget = boxes or run_proof(run).max_boxes
        first = None
        for device in devices:
            if (why := _available(device)) is not None:
                print(f"{str(path)[-24:]:<24} {device}: {why}")
                continue
            for batch in batches:
                proof, wall, _ = _prove(run, budget, Compute(device=device), batch, keep_partition=True)
                digest = _leaf_digest(proof, Region.of(run.system, float(run.config.delta)))
                first = first or digest
                print(f"{str(path)[-24:]:<24} {device:<7} {batch:>7,} {proof.status:<8} {proof.boxes_processed:>10,} "
                      f"{wall:>8.1f} {proof.boxes_processed / wall:>9,.0f} {str(digest == first):>12}", flush=True)


def training_rows(systems: list[str], devices: list[str]) -> None:
    from drlyap.systems import get_system
    from drlyap.training import TrainConfig, fit

    header = f"{'system':<14} {'device':<7} {'iterations':>10} {'train s':>8} {'ms/iter':>8} {'passed':>7}"
    print(header)
    print("-" * len(header))
    for name in systems:
        system = get_system(name)
        for device in devices:
            if (why := _available(device)) is not None:
                print(f"{name:<14} {device}: {why}")
                continue
            cfg = TrainConfig(system=name, device=device).resolved(system)
            metrics = fit(cfg, system, progress=False).metrics
            print(f"{name:<14} {device:<7} {metrics['iterations']:>10,} {metrics['train_time_s']:>8.1f} "
                  f"{metrics['ms_per_iteration']:>8.2f} {str(metrics['passed']):>7}", flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="*", help="run directories written by 'drlyap train'")
    parser.add_argument("--devices", default="cpu,cuda", help="devices of the proof rows [cpu,cuda]")
    parser.add_argument("--batches", default="4096,65536", help="boxes bounded at a time [4096,65536]")
    parser.add_argument("--boxes", type=int, default=None, help="boxes per proof [the run's own budget]")
    parser.add_argument("--train", default="", help="systems whose default training is timed (comma-separated) [none]")
    parser.add_argument("--train-devices", default="cpu,cuda", help="devices of the training rows [cpu,cuda]")
    parser.add_argument("--threads", type=int, default=1, help="torch threads [1]")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.runs:
        proof_rows(args.runs, args.devices.split(","), [int(b) for b in args.batches.split(",")], args.boxes)
    if args.train:
        print()
        training_rows(args.train.split(","), args.train_devices.split(","))
    return 0


if __name__ == "__main__":
    sys.exit(main())
