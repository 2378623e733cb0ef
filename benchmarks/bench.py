"""drlyap benchmark: prints a table of training and simulation speed on this machine.

    python benchmarks/bench.py            # all rows
    python benchmarks/bench.py --quick    # skip the train-to-passing rows

Rows:
- ms per DR training iteration (pointwise loss, 3600 states x 5 samples for the pendulum, 1600 x 3
  for the mountain car), forward + backward + Adam step, median over repeated timed blocks;
- time and iterations until a DR pair passes the acceptance check (seed 0, paper settings), and until its
  trained condition is proved (the default `drlyap train`: training + counterexample-guided proof rounds);
- simulated trajectory-steps per second (RK4 on the true model, 1000 trajectories).
Run it on an otherwise idle machine: the numbers are wall-clock.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import make_condition
from drlyap.regions import Region
from drlyap.simulation import initial_states, simulate
from drlyap.systems import get_system
from drlyap.training import TrainConfig, TrainSections, train


def ms_per_iteration(system_name: str, blocks: int = 5, per_block: int = 40) -> float:
    system = get_system(system_name)
    cfg = TrainConfig(system=system_name).resolved(system)
    lyapunov, controller = TrainSections.of(cfg).networks.build(system)
    xi = TrainSections.of(cfg).sampling.xi(system, cfg.seed)
    z = Region.of(system, cfg.delta).sample(cfg.n_states, torch.Generator().manual_seed(0)).float()
    cond = make_condition("dr", "pointwise", cfg.wasserstein_radius, cfg.risk_level, xi, cfg.decay_rate)
    opt = torch.optim.Adam([*lyapunov.parameters(), *controller.parameters()], lr=cfg.lr, fused=True)
    loop = ClosedLoop(system, lyapunov, controller)

    def step() -> None:
        loss = cond.loss(cond.terms(loop, z), cfg.margin)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    for _ in range(10):
        step()
    times = []
    for _ in range(blocks):
        tic = time.perf_counter()
        for _ in range(per_block):
            step()
        times.append((time.perf_counter() - tic) / per_block * 1000)
    return statistics.median(times)


def time_to_pass(system_name: str) -> tuple[float, int, bool]:
    result = train(TrainConfig(system=system_name, method="dr", seed=0), proof=None, progress=False)
    return result.metrics["train_time_s"], result.metrics["iterations"], result.metrics["passed"]


def time_to_proof(system_name: str) -> tuple[float, int, str]:
    tic = time.perf_counter()
    result = train(TrainConfig(system=system_name, method="dr", seed=0), progress=False, warn=False)
    return time.perf_counter() - tic, result.metrics["cegis"]["total_iterations"], result.metrics["certificate"]["status"]


def sim_steps_per_second(system_name: str, count: int = 1000) -> float:
    system = get_system(system_name)
    _, controller = TrainSections.of(TrainConfig(system=system_name).resolved(system)).networks.build(system)
    x0 = initial_states(system, count, torch.Generator().manual_seed(0))

    def policy(x):
        return controller(system.to_local(x).float()).double()

    steps = 200
    tic = time.perf_counter()
    simulate(system, policy, x0, torch.tensor(system.test_xi, dtype=torch.float64), horizon=steps * system.sim_dt)
    return count * steps / (time.perf_counter() - tic)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="skip the train-to-passing rows")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for name in ("pendulum", "mountain-car"):
        rows.append((f"{name}: ms per DR iteration", f"{ms_per_iteration(name):.2f}"))
        if not args.quick:
            seconds, iters, passed = time_to_pass(name)
            rows.append((f"{name}: time to DR pair (seed 0)", f"{seconds:.1f} s, {iters} it, "
                         f"{'passed' if passed else 'NOT passed'}"))
            seconds, iters, status = time_to_proof(name)
            rows.append((f"{name}: time to a proved DR pair (seed 0, default train)", f"{seconds:.1f} s, {iters} it, {status}"))
        rows.append((f"{name}: simulated trajectory-steps/s", f"{sim_steps_per_second(name):,.0f}"))
    width = max(len(r[0]) for r in rows)
    print(f"torch {torch.__version__}, {args.threads} thread(s)")
    print(f"| {'measure'.ljust(width)} | value |")
    print(f"|{'-' * (width + 2)}|-------|")
    for name, value in rows:
        print(f"| {name.ljust(width)} | {value} |")


if __name__ == "__main__":
    main()
