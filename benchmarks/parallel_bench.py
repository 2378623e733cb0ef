"""Proofs on worker processes: wall and CPU time for 1 and 2 local workers and for Ray with 2 local workers, on
existing run directories (trains nothing), and a model of more workers.

Usage::

    python benchmarks/parallel_bench.py RUN_DIR [RUN_DIR ...] [--boxes N] [--workers 1,2] [--ray 2] [--threads 1]

Each row proves the run's trained condition (on its sublevel set for a region-of-attraction run) with the same box
budget (``--boxes``; default: the run's own, so that the proof finishes) and reports its verdict, the boxes bounded,
the wall time, the CPU time of every process (this one, the fork server and the workers), boxes per second, both
times over the one-process proof's, and whether the partition is the same as the one-process proof's (it must be).
A row ``N local`` starts its workers with the proof (they start once per command: until they are up this process
bounds the boxes); the row ``N local, up`` proves the same again on the workers already up, as a command's later
proofs do (the proof rounds of `train`, the claims of one `verify`).

The model: one process's proof is traced batch by batch (each batch's size and this process's time to sort it out,
``s_b``); a chunk of ``n`` boxes costs ``a + c n`` (fitted on chunks of the run's own region). With ``W`` workers a
batch's chunks (:func:`drlyap.verification.bounding.chunk_sizes`) are dealt in turn and the batch costs the busiest
worker's share, or ``s_b`` where that is longer (the next batch is bounded while this process sorts the last), plus
the measured cost of sending a batch and getting its bounds back (from the two-worker row). Where the queue holds
fewer than a full batch (the frontier of the search) the workers cannot all be busy, which the model keeps: it uses
the proof's own batch sizes.
"""

from __future__ import annotations

import argparse
import sys
import time

import torch


def cpu_seconds() -> float:
    """CPU time (user + system) of this process and of every process below it that is still running (the proof
    workers: they run until the pools are closed)."""
    import os

    from drlyap.lifeline import descendants, process_table

    tick, stats = os.sysconf("SC_CLK_TCK"), process_table()
    return time.process_time() + sum(int(stats[pid][11]) + int(stats[pid][12]) for pid in descendants(stats=stats)) / tick


def _prove(run, boxes: int, compute, batch: int | None = None, keep_partition: bool = False):
    """The run's trained condition proved from scratch with ``boxes`` at most (``batch``: boxes bounded at a time,
    None: the default): ``(proof, wall seconds, CPU seconds of every process)``, the device synchronised before the
    clock starts; the workers' start is in both."""
    import dataclasses

    from drlyap.proof_settings import Budget
    from drlyap.regions import Region
    from drlyap.verification import ProofRules, verify_condition

    budget = Budget(seconds=1e9, boxes=boxes, enclosure=run.proof.enclosure if run.proof else None, compute=compute)
    budget = budget if batch is None else dataclasses.replace(budget, batch=batch)
    region = Region.of(run.system, float(run.config.delta))
    if compute.device.startswith("cuda"):
        torch.cuda.synchronize()
    tic, cpu = time.perf_counter(), cpu_seconds()
    proof = verify_condition(run.loop, run.condition, region, budget, level=run.config.roa_level,
                             rules=ProofRules(keep_partition=keep_partition))
    return proof, time.perf_counter() - tic, cpu_seconds() - cpu


def _same(a, b) -> bool:
    if a.partition is None or b.partition is None:
        return (a.status, a.boxes_processed, a.verified_fraction) == (b.status, b.boxes_processed, b.verified_fraction)
    return all(torch.equal(getattr(a.partition, k), getattr(b.partition, k)) for k in ("parent", "side", "axis", "verdict"))


def _traced(run, boxes: int) -> dict:
    """One process's proof with each batch's size and this process's sorting of it timed, and the cost of a chunk of
    n boxes fitted as a + c n."""
    import drlyap.verification.bounding as bounding
    from drlyap.verification.bounding import ConditionJob

    bb = sys.modules["drlyap.verification.branch_and_bound"]
    batches, sorts = [], []
    in_chunks, sort = bounding.run_in_chunks, bb._Search._sort

    def traced_chunks(job, arrays, size):
        batches.append(int(arrays[0].shape[0]))
        return in_chunks(job, arrays, size)

    def timed_sort(self, *args):
        tic = time.perf_counter()
        out = sort(self, *args)
        sorts.append(time.perf_counter() - tic)
        return out

    bounding.run_in_chunks, bb._Search._sort = traced_chunks, timed_sort
    try:
        proof, wall, cpu = _prove(run, boxes, _compute(1))
    finally:
        bounding.run_in_chunks, bb._Search._sort = in_chunks, sort
    # the cost of a chunk of n boxes: a + c n, from chunks of 256 and 1024 boxes of the run's own region
    from drlyap.regions import Region

    region = Region.of(run.system, float(run.config.delta))
    job = ConditionJob(run.loop.f64, run.condition, run.config.roa_level, proof.partition.enclosure
                       if proof.partition is not None else run.proof.enclosure)
    g = torch.Generator().manual_seed(0)
    centre = region.lo + region.scale * torch.rand(1024, region.n, generator=g, dtype=torch.float64)
    half = region.scale * 0.01
    times = {}
    for n in (256, 1024):
        job(centre[:n] - half, centre[:n] + half)  # warm
        tic = time.perf_counter()
        for _ in range(3):
            job(centre[:n] - half, centre[:n] + half)
        times[n] = (time.perf_counter() - tic) / 3
    c = (times[1024] - times[256]) / (1024 - 256)
    a = max(0.0, times[256] - 256 * c)
    return {"proof": proof, "wall": wall, "cpu": cpu, "batches": batches, "sorts": sorts, "a": a, "c": c}


def _modelled(trace: dict, workers: int, transfer: float) -> float:
    """Seconds of a proof on ``workers`` workers: per batch, its chunks dealt in turn, the busiest worker's share (or
    this process's sorting of the batch before, which overlaps it), plus ``transfer``."""
    from drlyap.verification.bounding import chunk_sizes

    total = 0.0
    for n, s in zip(trace["batches"], trace["sorts"]):
        load = [0.0] * workers
        for i, size in enumerate(chunk_sizes(n)):
            load[i % workers] += trace["a"] + trace["c"] * size
        total += max(max(load), s) + transfer
    return total


def _compute(workers: int, backend: str = "local"):
    from drlyap.compute import Compute

    return Compute(workers=workers, backend=backend)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="run directories written by 'drlyap train'")
    parser.add_argument("--boxes", type=int, default=None, help="boxes per proof [the run's own budget]")
    parser.add_argument("--workers", default="1,2", help="local worker counts to time [1,2]")
    parser.add_argument("--ray", type=int, default=2, help="Ray workers to time (0: none) [2]")
    parser.add_argument("--model", default="2,4,8", help="worker counts the model predicts [2,4,8]")
    parser.add_argument("--threads", type=int, default=1, help="torch threads [1]")
    args = parser.parse_args(argv)
    import drlyap

    drlyap.set_threads(args.threads)  # and malloc's settings, as the command line has them

    from drlyap.parallel import close_pools
    from drlyap.runs import load_run
    from drlyap.workflows.verify import run_proof

    header = (f"{'run':<24} {'workers':<12} {'status':<8} {'boxes':>10} {'wall s':>8} {'CPU s':>8} {'boxes/s':>9} "
              f"{'wall/1':>7} {'CPU/1':>6} {'same partition':>15}")
    print(header)
    print("-" * len(header))
    models = []
    for path in args.runs:
        run = load_run(path)
        boxes = args.boxes or run_proof(run).max_boxes
        trace = _traced(run, boxes)
        base = trace["proof"]
        rows = [("1 (traced)", trace["proof"], trace["wall"], trace["cpu"])]
        kinds = [(int(w), "local") for w in args.workers.split(",") if int(w) > 1]
        kinds += [(args.ray, "ray")] if args.ray else []
        for workers, backend in kinds:
            try:
                proof, wall, cpu = _prove(run, boxes, _compute(workers, backend))
                rows.append((f"{workers} {backend}", proof, wall, cpu))
                if backend == "local":  # the same again, on the workers already up
                    proof, wall, cpu = _prove(run, boxes, _compute(workers, backend))
                    rows.append((f"{workers} local, up", proof, wall, cpu))
            except ValueError as err:  # e.g. Ray not installed
                print(f"{str(path)[-24:]:<24} {backend} {workers}: {err}")
            finally:
                close_pools()  # each row starts its own workers (their start is in its wall time)
        for label, proof, wall, cpu in rows:
            print(f"{str(path)[-24:]:<24} {label:<12} {proof.status:<8} {proof.boxes_processed:>10,} {wall:>8.1f} "
                  f"{cpu:>8.1f} {proof.boxes_processed / wall:>9,.0f} {wall / trace['wall']:>7.2f} "
                  f"{cpu / trace['cpu']:>6.2f} {str(_same(base, proof)):>15}")
        ipc = None
        two = [r for r in rows if r[0] == "2 local"]
        if two:  # what two workers cost beyond the model's compute: sending and receiving, per batch
            ipc = max(0.0, (two[0][2] - _modelled(trace, 2, 0.0)) / max(len(trace["batches"]), 1))
        models.append((path, trace, ipc))
    print()
    print("model (per batch: its chunks dealt to the workers in turn, the busiest worker's share or this process's "
          "sorting of the batch before, which overlap, plus the measured transfer; batches as the proof made them)")
    for path, trace, ipc in models:
        sizes = trace["batches"]
        full = sum(1 for n in sizes if n >= 4096)
        print(f"{str(path)[-24:]}: {len(sizes)} batches ({full} full, {len(sizes) - full} smaller: the frontier), "
              f"a = {1e3 * trace['a']:.1f} ms a chunk, c = {1e6 * trace['c']:.1f} us/box, sorting "
              f"{sum(trace['sorts']):.1f} s, transfer {1e3 * (ipc or 0):.1f} ms/batch")
        for w in [int(v) for v in args.model.split(",")]:
            t = _modelled(trace, w, ipc or 0.0)
            print(f"  {w:>3} workers: {t:8.1f} s, {sum(sizes) / t:,.0f} boxes/s, {trace['wall'] / t:5.1f}x one process")
    return 0


if __name__ == "__main__":
    sys.exit(main())
