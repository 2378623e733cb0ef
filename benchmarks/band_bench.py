"""The band claim on pairs brought from ONNX: wall and CPU time of ``verify --band`` and of its check, on 1 and 2
workers, for existing run directories (trains nothing).

Usage::

    python benchmarks/band_bench.py RUN_DIR:C1,C2 [RUN_DIR:C1,C2 ...] [--workers 1,2] [--boxes N] [--system SPEC]

Each run is exported (``drlyap export``) and imported (``drlyap import``) into a temporary folder, as a pair trained
elsewhere would be, then the band claim ``C1 <= V <= C2`` at the system's test shift is proved from scratch with
``Vdot + 0.01 V <= 0`` and at most ``--boxes`` boxes (default: the system's proof budget), once per number of
workers, and its certificate is checked by ``drlyap check``'s code on one process. A row: the system, V's and the
controller's hidden widths, the band, the workers, the verdict, the share of the box where the decrease or V outside
the band is proved, boxes bounded, the proof's wall and CPU seconds (every process: this one, the fork server and the
workers), the check's wall seconds, and whether the partition is the same as the first row's (it must be; ``-`` where
the proof, not verified, kept none).

The pairs of the field's published sizes, as measured in docs/results/band.md, are trained with::

    drlyap train pendulum --lyapunov-hidden 40,40 --controller-hidden 10,10 --out runs/p40
    drlyap train cartpole --lyapunov-hidden 128,128 --controller-hidden 32,32 --out runs/c128
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from parallel_bench import cpu_seconds  # noqa: E402


def _imported(run_dir: Path, folder: Path, system=None):
    """The run exported to ONNX and imported into ``folder``: the imported run (``info["pair"]``). ``system``: the
    run's system where it is a user's (resolved from ``--system``)."""
    from drlyap.runs import load_run
    from drlyap.runs.imported import import_run, load_imported_run
    from drlyap.workflows.export import export_run

    run = load_run(run_dir, system)
    export_run(run, folder / "export")
    import_run(run.system, folder / "export" / "controller.onnx", folder / "imported",
               folder / "export" / "lyapunov.onnx")
    return run, load_imported_run(folder / "imported", run.system)


def _row(run, imported, band: tuple[float, float], workers: int, boxes: int | None, folder: Path) -> dict:
    from drlyap.checker.check import check_certificate
    from drlyap.compute import Compute
    from drlyap.proof_settings import ProofConfig
    from drlyap.runs.certificates import networks_digest, read_certificate, system_digest
    from drlyap.runs.validate import load_weights
    from drlyap.workflows.record import record_band
    from drlyap.workflows.verify import VerifyRequest, verify_imported

    system, pair = run.system, imported.info["pair"]
    proof = ProofConfig(max_boxes=boxes, time_limit=3600.0, compute=Compute(workers=workers))
    tic, cpu = time.perf_counter(), cpu_seconds()
    found = verify_imported(pair, str(folder), proof, request=VerifyRequest(
        xi=torch.as_tensor(system.test_xi, dtype=torch.float64), band=band)).band
    wall, cpu = time.perf_counter() - tic, cpu_seconds() - cpu
    check = None
    if found.verified:
        files = [folder / "imported" / "graphs.json", folder / "imported" / "tensors.pt"]
        record_band(folder / "imported", system, found, files, None)
        header, arrays = read_certificate(folder / "imported", "band")
        import json

        weights = {"graphs": json.loads(files[0].read_text()), "tensors": load_weights(files[1])}
        tic = time.perf_counter()
        result = check_certificate("band", header, arrays, system, weights,
                                   networks_digest([f.read_bytes() for f in files]), system_digest(system))
        check = ("CHECKED" if result.ok else "NOT CONFIRMED", time.perf_counter() - tic)
    cfg = run.config
    return {"system": system.name, "V": cfg.lyapunov_hidden, "pi": cfg.controller_hidden, "band": band,
            "workers": workers, "status": found.status, "boxes": found.decrease.boxes_processed, "wall": wall,
            "proved": found.verified_fraction,
            "cpu": cpu, "check": check, "partition": found.decrease.partition}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="RUN_DIR:C1,C2")
    parser.add_argument("--workers", default="1,2")
    parser.add_argument("--boxes", type=int, default=None)
    parser.add_argument("--system", default=None, help="the runs' system, where it is a user's (path/to/file.py:make)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print("| system | V hidden | pi hidden | band | workers | verdict | share of the box proved | boxes | proof wall s "
          "| proof CPU s | check | same partition |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for spec in args.runs:
        path, levels = spec.rsplit(":", 1)
        band = tuple(float(v) for v in levels.split(","))
        with tempfile.TemporaryDirectory() as tmp:
            system = None
            if args.system is not None:
                from drlyap.systems import resolve_system

                system = resolve_system(args.system)
            run, imported = _imported(Path(path), Path(tmp), system)
            first = None
            for workers in (int(w) for w in args.workers.split(",")):
                row = _row(run, imported, band, workers, args.boxes, Path(tmp))
                first = first or row["partition"]
                same = "-" if row["partition"] is None else "yes" if all(
                    torch.equal(getattr(row["partition"], k), getattr(first, k)) for k in ("parent", "verdict")) else "NO"
                check = "-" if row["check"] is None else f"{row['check'][0]} {row['check'][1]:.2f} s"
                print(f"| {row['system']} | {row['V']} | {row['pi']} | {band[0]:g}..{band[1]:g} | {workers} | "
                      f"{row['status']} | {100 * row['proved']:.4f}% | {row['boxes']} | {row['wall']:.2f} | "
                      f"{row['cpu']:.2f} | {check} | {same} |", flush=True)


if __name__ == "__main__":
    main()
