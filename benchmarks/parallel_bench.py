"""Proofs on worker processes: wall time and boxes per second for 1 and 2 local workers and for Ray with 2 local
workers, on existing run directories (trains nothing), and a model of 16 and 64 workers.

Usage::

    python benchmarks/parallel_bench.py RUN_DIR [RUN_DIR ...] [--boxes N] [--workers 1,2] [--ray 2] [--threads 1]

Each row proves the run's trained condition (on its sublevel set for a region-of-attraction run) with the same box
budget (``--boxes``; default: the run's own, so that the proof finishes) and reports its verdict, the boxes bounded,
the wall time (the workers' start included: they start once per command), boxes per second, and whether the
partition is the same as the one-worker proof's (it must be).

The model: one process's proof is timed batch by batch (the time to bound each batch of ``n_b`` boxes, fitted as
``a + c n_b`` on chunks of its boxes, and this process's own time to sort it out, ``s_b``); with ``W`` workers each
batch costs ``max(a + c n_b / W, s_b)`` (the next batch is bounded while this process sorts the last) plus the
measured time to send a batch and get its bounds back (from the two-worker row). Batches hold at most 4,096 boxes;
where the queue holds fewer (the frontier of the search) the workers cannot all be busy, which the model keeps: it
uses the proof's own batch sizes.
"""

from __future__ import annotations

import argparse
import sys
import time

import torch


def _prove(run, boxes: int, compute, batch: int | None = None, keep_partition: bool = False):
    """The run's trained condition proved from scratch with ``boxes`` at most (``batch``: boxes bounded at a time,
    None: the default): ``(proof, wall seconds)``, the device synchronised before the clock starts."""
    import dataclasses

    from drlyap.config import Budget
    from drlyap.regions import Region
    from drlyap.verification import verify_condition

    budget = Budget(seconds=1e9, boxes=boxes, enclosure=run.proof.enclosure if run.proof else None, compute=compute)
    budget = budget if batch is None else dataclasses.replace(budget, batch=batch)
    region = Region.of(run.system, float(run.config.delta))
    if compute.device.startswith("cuda"):
        torch.cuda.synchronize()
    tic = time.perf_counter()
    proof = verify_condition(run.loop, run.condition, region, budget, level=run.config.roa_level,
                             keep_partition=keep_partition)
    return proof, time.perf_counter() - tic


def _same(a, b) -> bool:
    if a.partition is None or b.partition is None:
        return (a.status, a.boxes_processed, a.verified_fraction) == (b.status, b.boxes_processed, b.verified_fraction)
    return all(torch.equal(getattr(a.partition, k), getattr(b.partition, k)) for k in ("parent", "side", "axis", "verdict"))


def _traced(run, boxes: int) -> dict:
    """One process's proof with each batch's bounding and sorting timed, and the per-box cost fitted."""
    import drlyap.verification.branch_and_bound as bb
    from drlyap.verification.bounding import ConditionJob

    batches, sorts = [], []
    bound, sort = ConditionJob.__call__, bb._Search._sort

    def timed_bound(self, lo, hi):
        tic = time.perf_counter()
        out = bound(self, lo, hi)
        batches.append((lo.shape[0], time.perf_counter() - tic))
        return out

    def timed_sort(self, *args):
        tic = time.perf_counter()
        out = sort(self, *args)
        sorts.append(time.perf_counter() - tic)
        return out

    ConditionJob.__call__, bb._Search._sort = timed_bound, timed_sort
    try:
        proof, wall = _prove(run, boxes, _compute(1))
        # the cost of a chunk of n boxes: a + c n, from chunks of 512 and 4096 boxes of the run's own region
        from drlyap.regions import Region

        region = Region.of(run.system, float(run.config.delta))
        job = ConditionJob(run.loop.f64, run.condition, run.config.roa_level, proof.partition.enclosure
                           if proof.partition is not None else run.proof.enclosure)
        g = torch.Generator().manual_seed(0)
        centre = region.lo + region.scale * torch.rand(4096, region.n, generator=g, dtype=torch.float64)
        half = region.scale * 0.01
        times = {}
        for n in (512, 4096):
            job(centre[:n] - half, centre[:n] + half)  # warm
            tic = time.perf_counter()
            for _ in range(3):
                job(centre[:n] - half, centre[:n] + half)
            times[n] = (time.perf_counter() - tic) / 3
    finally:
        ConditionJob.__call__, bb._Search._sort = bound, sort
    c = (times[4096] - times[512]) / (4096 - 512)
    a = max(0.0, times[512] - 512 * c)
    return {"proof": proof, "wall": wall, "batches": batches, "sorts": sorts, "a": a, "c": c}


def _compute(workers: int, backend: str = "local"):
    from drlyap.compute import Compute

    return Compute(workers=workers, backend=backend)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="run directories written by 'drlyap train'")
    parser.add_argument("--boxes", type=int, default=None, help="boxes per proof [the run's own budget]")
    parser.add_argument("--workers", default="1,2", help="local worker counts to time [1,2]")
    parser.add_argument("--ray", type=int, default=2, help="Ray workers to time (0: none) [2]")
    parser.add_argument("--model", default="2,16,64", help="worker counts the model predicts [2,16,64]")
    parser.add_argument("--threads", type=int, default=1, help="torch threads [1]")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    from drlyap.parallel import close_pools
    from drlyap.runs import load_run
    from drlyap.workflows.verify import run_proof

    header = (f"{'run':<24} {'workers':<9} {'status':<8} {'boxes':>10} {'wall s':>8} {'boxes/s':>9} {'vs 1':>6} "
              f"{'same partition':>15}")
    print(header)
    print("-" * len(header))
    models = []
    for path in args.runs:
        run = load_run(path)
        boxes = args.boxes or run_proof(run).max_boxes
        trace = _traced(run, boxes)
        base = trace["proof"]
        rows = [("1 (traced)", trace["proof"], trace["wall"])]
        kinds = [(int(w), "local") for w in args.workers.split(",") if int(w) > 1]
        kinds += [(args.ray, "ray")] if args.ray else []
        for workers, backend in kinds:
            try:
                proof, wall = _prove(run, boxes, _compute(workers, backend))
            except ValueError as err:  # e.g. Ray not installed
                print(f"{str(path)[-24:]:<24} {backend} {workers}: {err}")
                continue
            finally:
                close_pools()  # each row starts its own workers (their start is in its wall time)
            rows.append((f"{workers} {backend}", proof, wall))
        for label, proof, wall in rows:
            print(f"{str(path)[-24:]:<24} {label:<9} {proof.status:<8} {proof.boxes_processed:>10,} {wall:>8.1f} "
                  f"{proof.boxes_processed / wall:>9,.0f} {trace['wall'] / wall:>6.2f} {str(_same(base, proof)):>15}")
        ipc = None
        two = [r for r in rows if r[0] == "2 local"]
        sizes = [n for n, _ in trace["batches"]]
        if two:  # what two workers cost beyond the model's compute: sending and receiving, per batch
            ideal = sum(max(trace["a"] + trace["c"] * n / 2, s) for n, s in zip(sizes, trace["sorts"]))
            ipc = max(0.0, (two[0][2] - ideal) / max(len(sizes), 1))
        models.append((path, trace, sizes, ipc))
    print()
    print("model (per batch: the larger of the workers' a + c n / W and this process's sorting of the batch before, "
          "which overlap, plus the measured transfer; batches as the proof made them)")
    for path, trace, sizes, ipc in models:
        total = sum(sizes)
        full = sum(1 for n in sizes if n >= 4096)
        print(f"{str(path)[-24:]}: {len(sizes)} batches ({full} full, {len(sizes) - full} smaller: the frontier), "
              f"a = {1e3 * trace['a']:.1f} ms, c = {1e6 * trace['c']:.1f} us/box, sorting {sum(trace['sorts']):.1f} s, "
              f"transfer {1e3 * (ipc or 0):.1f} ms/batch")
        for w in [int(v) for v in args.model.split(",")]:
            t = sum(max(trace["a"] + trace["c"] * n / w, s) + (ipc or 0) for n, s in zip(sizes, trace["sorts"]))
            print(f"  {w:>3} workers: {t:8.1f} s, {total / t:,.0f} boxes/s, {trace['wall'] / t:5.1f}x one process")
    return 0


if __name__ == "__main__":
    sys.exit(main())
