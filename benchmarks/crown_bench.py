"""Width and cost of the networks' bounds over random boxes: intervals, affine forms and the backward linear relaxation.

Usage::

    python benchmarks/crown_bench.py [--systems cartpole,quadrotor2d] [--hidden 32,32:120,120,120]
                                     [--widths 0.01,0.03,0.1] [--boxes 128] [--samples 512] [--seed 0] [--threads 1]

For each system and each set of hidden layers (``--hidden``: sets separated by ':'), it builds untrained tanh
networks with the system's builder (seeded; no linear path) and bounds the outputs of V's network ``phi`` and of the
controller's network ``varphi`` (before u* and the saturation) over ``--boxes`` random boxes whose sides are a
fraction ``--widths`` of the state box's sides, by

* ``interval`` -- plain interval arithmetic,
* ``affine`` -- ``box_bounds(enclosure="affine")`` (the tighter of the interval and the affine-form bound: what
  the verifier uses from 4 states on),
* ``crown`` -- :func:`drlyap.enclosures.crown.tanh_mlp_bounds`, the backward linear relaxation (every layer's
  pre-activation bounds from its own backward walk).

It prints each width divided by the sampled range (max - min over ``--samples`` uniform points and the corners of
each box; 1.0 is the best possible), the median over boxes and outputs, the ratio affine / crown, and the time per box
in microseconds (the batch timed as one call). Each bound is checked against the sampled values first (a miss exits
with status 1). The networks only: V's square and sum, its gradient and the dynamics are not part of this bound.
"""

from __future__ import annotations

import argparse
import sys
import time

import torch


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--systems", default="cartpole,quadrotor2d", help="comma-separated system names")
    parser.add_argument("--hidden", default="32,32:120,120,120", help="hidden layer sets, ':'-separated [32,32:120,120,120]")
    parser.add_argument("--widths", default="0.01,0.03,0.1", help="box sides as fractions of the state box's sides")
    parser.add_argument("--boxes", type=int, default=128, help="random boxes per row [128]")
    parser.add_argument("--samples", type=int, default=512, help="uniform samples per box (plus its corners) [512]")
    parser.add_argument("--seed", type=int, default=0, help="seed of the networks and the boxes [0]")
    parser.add_argument("--threads", type=int, default=1, help="torch threads [1]")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    from boxes import random_boxes, width_ratio

    from drlyap.enclosures import Interval
    from drlyap.enclosures.crown import mlp_layers, tanh_mlp_bounds
    from drlyap.systems import get_system
    from drlyap.training import TrainConfig, TrainSections
    from drlyap.verification.bounds import box_bounds

    print(f"bound width / sampled range (median over {args.boxes} boxes and outputs; 1.0 = exact), time per box in "
          f"microseconds, torch threads {args.threads}")
    header = (f"{'system':<12} {'n':>2} {'hidden':<12} {'net':<7} {'width':>6} | {'interval':>9} {'affine':>8} "
              f"{'crown':>8} {'aff/crn':>8} | {'us aff':>8} {'us crown':>9}")
    print(header)
    print("-" * len(header))
    for name in args.systems.split(","):
        system = get_system(name)
        n = system.n
        slo, shi = system.local_box()
        for spec in args.hidden.split(":"):
            hidden = [int(w) for w in spec.split(",")]
            cfg = TrainConfig(system=name, seed=args.seed, lyapunov_hidden=hidden, controller_hidden=hidden,
                              controller_skip=False).resolved(system)
            torch.manual_seed(args.seed)
            lyap, ctrl = TrainSections.of(cfg).networks.build(system)
            gen = torch.Generator().manual_seed(args.seed + 1)
            for label, net in (("phi", lyap.phi.double()), ("varphi", ctrl.varphi.double())):
                layers, scale, skip = mlp_layers(net)
                for width in (float(w) for w in args.widths.split(",")):
                    lo, hi, pts = random_boxes(slo, shi, width, args.boxes, args.samples, gen)
                    with torch.no_grad():
                        values = net(pts.reshape(-1, n)).reshape(args.boxes, pts.shape[1], -1)
                    s_lo, s_hi = values.amin(1), values.amax(1)
                    iv = net(Interval(lo, hi))
                    tic = time.perf_counter()
                    af_lo, af_hi, _ = box_bounds(net, lo, hi, "affine")
                    t_af = time.perf_counter() - tic
                    tic = time.perf_counter()
                    cr_lo, cr_hi = tanh_mlp_bounds(layers, scale, lo, hi, skip)
                    t_cr = time.perf_counter() - tic
                    for what, (a, b) in (("affine", (af_lo, af_hi)), ("crown", (cr_lo, cr_hi))):
                        if not bool(((a <= s_lo) & (s_hi <= b)).all()):
                            print(f"UNSOUND: the {what} bound of {label} on {name} misses sampled values", file=sys.stderr)
                            return 1
                    r_int, r_af, r_cr = (width_ratio(*p, s_lo, s_hi) for p in ((iv.lo, iv.hi), (af_lo, af_hi), (cr_lo, cr_hi)))
                    us = 1e6 / args.boxes
                    print(f"{name:<12} {n:>2} {'x'.join(map(str, hidden)):<12} {label:<7} {width:>6.3g} | {r_int:>9.3g} "
                          f"{r_af:>8.3g} {r_cr:>8.3g} {r_af / r_cr:>7.2f}x | {t_af * us:>8.0f} {t_cr * us:>9.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
