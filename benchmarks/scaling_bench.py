"""Scaling with the number of states: training, success under the shift and the proof, for 2, 4 and 6 states.

Usage::

    python benchmarks/scaling_bench.py [--systems pendulum,cartpole,quadrotor2d] [--seed 0]
                                       [--verify-time 60] [--threads 1] [--json OUT]

For each system it trains a DR pair as ``drlyap train SYSTEM --seed SEED`` does (``drlyap.train``:
the system's defaults, proof rounds until the trained condition is verified or 5 rounds are spent, 30 s per
proof, 120 s for cart-pole and quadrotor; these train for a region of attraction with an LQR warm start), then
reports

* training states: states per batch x iterations (all rounds), the certificate's status and the seconds in all;
* success under the shift: stabilised of 200 test-box states on the true model at the system's ``test_xi``
  (``drlyap evaluate --n-init 200 --seed 7``);
* the proof of the trained condition (on ``{V <= roa_level}`` for region-of-attraction training) with the
  mean-value enclosure (the old default) and the affine enclosure, ``--verify-time`` seconds each on the same
  pair: status, proved share, boxes processed and seconds.

Timings depend on the machine and its load: compare rows of one run.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import sys
import time

import torch


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--systems", default="pendulum,cartpole,quadrotor2d", help="comma-separated system names")
    parser.add_argument("--seed", type=int, default=0, help="training seed [0]")
    parser.add_argument("--verify-time", type=float, default=60.0, help="seconds per proof [60]")
    parser.add_argument("--threads", type=int, default=1, help="torch threads [1]")
    parser.add_argument("--json", default=None, help="also write the rows as JSON to this file")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    from drlyap.proof_settings import Budget
    from drlyap.regions import Region
    from drlyap.simulation import evaluate, initial_states
    from drlyap.systems import get_system
    from drlyap.training import TrainConfig, train
    from drlyap.verification import prove_trained

    rows = []
    for name in [s.strip() for s in args.systems.split(",") if s.strip()]:
        system = get_system(name)
        tic = time.perf_counter()
        result = train(TrainConfig(system=name, seed=args.seed), system, progress=False, warn=False)
        train_s = time.perf_counter() - tic
        cfg, m = result.config, result.metrics
        ctrl = copy.deepcopy(result.controller).double()

        def policy(x, ctrl=ctrl, system=system):
            return ctrl(system.to_local(x))

        x0 = initial_states(system, 200, torch.Generator().manual_seed(7))
        ev = evaluate(system, policy, x0, torch.tensor(system.test_xi, dtype=torch.float64))
        iterations = m.get("cegis", {}).get("total_iterations", m["iterations"])
        row = {"system": name, "states": system.n, "inputs": system.m, "batch": int(cfg.n_states),
               "iterations": iterations, "training_states": int(cfg.n_states) * iterations,
               "certificate": m["certificate"]["status"], "train_s": round(train_s, 1), "roa_level": cfg.roa_level,
               "success": f"{ev['n_success']}/{ev['n']}"}
        for enclosure in ("mean-value", "affine"):
            proof = prove_trained(result.loop, result.condition, Region.of(system, float(cfg.delta)),
                                  Budget(seconds=args.verify_time, boxes=50_000_000, enclosure=enclosure), cfg.roa_level)
            row[enclosure] = {"status": proof.status, "proved": proof.verified_fraction,
                              "boxes": proof.boxes_processed, "time_s": round(proof.time_s, 1)}
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)

    head = ("| system | states | batch x iterations | certificate | train + proof s | success at test_xi | proof, mean-value "
            "(status, proved, boxes, s) | proof, affine (status, proved, boxes, s) |")
    print(head)
    print("|" + "---|" * 8)
    for r in rows:
        cells = []
        for enclosure in ("mean-value", "affine"):
            p = r[enclosure]
            proved = math.floor(1e5 * p["proved"]) / 1e3  # rounded down: never "100%" for what is not proved
            cells.append(f"{p['status']}, {proved:.3f}%, {p['boxes']:,}, {p['time_s']}")
        print(f"| {r['system']} | {r['states']} | {r['batch']} x {r['iterations']} | {r['certificate']} | {r['train_s']} "
              f"| {r['success']} | {cells[0]} | {cells[1]} |")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
