"""Width and cost of the verifier's enclosures on random boxes: intervals, mean-value form, affine forms.

Usage::

    python benchmarks/enclosure_bench.py [--systems pendulum,cartpole,quadrotor2d] [--widths 0.01,0.03,0.1]
                                         [--boxes 256] [--samples 512] [--seed 0] [--threads 1] [--hidden 32,32]

For each system (2, 4 and 6 states) it builds untrained tanh networks V and pi with the system's builder (seeded),
each with the hidden layers ``--hidden`` and no linear path beside them (``default``: the system's default
networks, 2x32 where the default has no hidden layer, the quadrotor's), and draws
``--boxes`` random boxes whose sides are a fraction ``--widths`` of the state box's sides, centred uniformly in
the state box. For three quantities

* ``V`` -- the certificate's value,
* ``grad V`` -- its input gradient (the manual backward pass the conditions use),
* ``condition`` -- the components of the DR pointwise decrease condition (``grad V . (f + W xi_j)`` plus the
  Lipschitz and decay terms) with the system's default radius, risk level, decay and ``n_xi`` samples,

it prints the enclosure width divided by the sampled range (max - min over ``--samples`` uniform points and
the corners of each box: an inner estimate of the true range, so 1.0 is the best possible), as the median
over boxes and components, for

* ``interval`` -- plain interval arithmetic,
* ``mean-value`` -- today's verifier bound (``box_bounds(enclosure="mean-value")``: the tighter of the interval
  and the mean-value form),
* ``affine`` -- ``box_bounds(enclosure="affine")`` (the tighter of the interval and the affine-form bound),

the improvement ``mean-value / affine`` and the time per box of each (microseconds, the batch timed as one call).
"""

from __future__ import annotations

import argparse
import copy
import statistics
import sys
import time

import torch


def _timed(fn, *args):
    tic = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - tic


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--systems", default="pendulum,cartpole,quadrotor2d", help="comma-separated system names")
    parser.add_argument("--widths", default="0.01,0.03,0.1", help="box sides as fractions of the state box's sides")
    parser.add_argument("--boxes", type=int, default=256, help="random boxes per system and width [256]")
    parser.add_argument("--samples", type=int, default=512, help="uniform samples per box (plus its corners) [512]")
    parser.add_argument("--seed", type=int, default=0, help="seed of the networks and the boxes [0]")
    parser.add_argument("--threads", type=int, default=1, help="torch threads [1]")
    parser.add_argument("--hidden", default="32,32",
                        help="hidden layers of both networks, comma-separated widths, or 'default' [32,32]")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    from boxes import random_boxes, width_ratio

    from drlyap.closed_loop import ClosedLoop
    from drlyap.conditions import make_condition
    from drlyap.enclosures import Interval
    from drlyap.systems import get_system
    from drlyap.training import TrainConfig, TrainSections
    from drlyap.verification.bounds import box_bounds, condition_objective, value_objective

    widths = [float(w) for w in args.widths.split(",")]
    print(f"enclosure width / sampled range (median over {args.boxes} boxes and components; 1.0 = exact), "
          f"time per box in microseconds, torch threads {args.threads}")
    header = (f"{'system':<12} {'n':>2} {'quantity':<10} {'width':>6} | {'interval':>9} {'mean-value':>10} "
              f"{'affine':>8} {'MV/aff':>7} | {'us int':>7} {'us MV':>7} {'us aff':>7}")
    print(header)
    print("-" * len(header))
    summary: dict[str, list[float]] = {}
    for name in args.systems.split(","):
        system = get_system(name)
        cfg = TrainConfig(system=name, seed=args.seed).resolved(system)
        if args.hidden != "default" or not cfg.lyapunov_hidden or not cfg.controller_hidden:
            hidden = [32, 32] if args.hidden == "default" else [int(w) for w in args.hidden.split(",")]
            cfg = TrainConfig(system=name, seed=args.seed, lyapunov_hidden=hidden, controller_hidden=hidden,
                              controller_skip=False).resolved(system)
        torch.manual_seed(args.seed)
        lyap, ctrl = TrainSections.of(cfg).networks.build(system)
        lyap64, ctrl64 = copy.deepcopy(lyap).double(), copy.deepcopy(ctrl).double()
        loop64 = ClosedLoop(system, lyap64, ctrl64)
        xi = system.sample_xi(int(cfg.n_xi), torch.Generator().manual_seed(10_000 + args.seed))
        cond = make_condition("dr", "pointwise", cfg.wasserstein_radius, cfg.risk_level, xi, cfg.decay_rate)
        quantities = {
            "V": value_objective(lyap),
            "grad V": lambda z, lyap=lyap: lyap.value_and_grad(z)[1],
            "condition": condition_objective(ClosedLoop(system, lyap, ctrl), cond),
        }
        points = {
            "V": lambda z, v=lyap64: v(z).unsqueeze(-1),
            "grad V": lambda z, v=lyap64: v.value_and_grad(z)[1],
            "condition": lambda z, c=cond, loop=loop64: c.components(c.terms(loop, z)),
        }
        slo, shi = system.local_box()
        n = system.n
        gen = torch.Generator().manual_seed(args.seed + 1)
        for width in widths:
            lo, hi, pts = random_boxes(slo, shi, width, args.boxes, args.samples, gen)
            for label, objective in quantities.items():
                with torch.no_grad():
                    values = points[label](pts.reshape(-1, n)).reshape(args.boxes, pts.shape[1], -1)
                s_lo, s_hi = values.amin(1), values.amax(1)
                iv, t_int = _timed(objective, Interval(lo, hi))
                (mv_lo, mv_hi, _), t_mv = _timed(box_bounds, objective, lo, hi, "mean-value")
                (af_lo, af_hi, _), t_af = _timed(box_bounds, objective, lo, hi, "affine")
                for what, (a, b) in (("mean-value", (mv_lo, mv_hi)), ("affine", (af_lo, af_hi))):
                    inside = bool(((a <= s_lo + 1e-9 * s_lo.abs()) & (s_hi <= b + 1e-9 * s_hi.abs())).all())
                    if not inside:
                        print(f"UNSOUND: {what} bound of {label} on {name} misses sampled values", file=sys.stderr)
                        return 1
                r_int = width_ratio(iv.lo, iv.hi, s_lo, s_hi)
                r_mv = width_ratio(mv_lo, mv_hi, s_lo, s_hi)
                r_af = width_ratio(af_lo, af_hi, s_lo, s_hi)
                summary.setdefault(f"{label} n={n}", []).append(r_mv / r_af)
                us = 1e6 / args.boxes
                print(f"{name:<12} {n:>2} {label:<10} {width:>6.3g} | {r_int:>9.3g} {r_mv:>10.3g} {r_af:>8.3g} "
                      f"{r_mv / r_af:>6.1f}x | {t_int * us:>7.0f} {t_mv * us:>7.0f} {t_af * us:>7.0f}")
    print()
    print("mean-value / affine width, geometric mean over widths:")
    for key, ratios in summary.items():
        print(f"  {key:<18} {statistics.geometric_mean(ratios):6.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
