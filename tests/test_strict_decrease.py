"""A decrease ``Vdot + alpha V <= 0`` with no decay ``gamma ||z||`` is strict only where V > 0: drlyap's V is positive
away from x* by its form, an imported V is not, so before a sublevel set of an imported V is called a region of
attraction the verifier proves V > 0 outside the delta-ball, and the checker proves it again by its own bisection."""

import json
import os
import sys

import pytest
import torch
from click.testing import CliRunner
from torch import nn

from drlyap.checker.graphs import GraphPair
from drlyap.checker.levels import outside_positive
from drlyap.cli import main
from drlyap.conditions import TrueDecrease
from drlyap.networks import QuadraticLyapunov
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.runs.imported import import_pair, import_run
from drlyap.simulation import simulate
from drlyap.systems import UncertainSystem
from drlyap.verification import certified_roa
from drlyap.verification.roa.sublevel import outer_strictness, positive_lower

sys.path.insert(0, os.path.dirname(__file__))
from handmade import ConstantController, export_and_import, linear_run_dir  # noqa: E402
from test_import_onnx import _export  # noqa: E402

pytest.importorskip("onnx")
F64 = torch.float64
WELL = 0.5  # the second stable equilibrium (WELL, 0)


def _two_wells() -> UncertainSystem:
    """``q' = -(r/2) q (2q - a)(q - a)``, ``v' = -v + f``: stable rest points at q = 0 and q = a, a saddle at a/2."""

    def dyn(x, u, p):
        q, v = x[:, 0], x[:, 1]
        return torch.stack([-(p[:, 0] / 2) * q * (2 * q - WELL) * (q - WELL), -v + u[:, 0]], -1)

    return UncertainSystem(name="two-wells", state_names=("q", "v"), input_names=("f",), param_names=("rate",),
                           nominal_params=(4.0,), uncertain=("rate",), dynamics=dyn,
                           state_box=((-0.4, -1.0), (0.9, 1.0)), input_box=((-1.0,), (1.0,)), equilibrium=(0.0, 0.0))


class _WellsV(nn.Module):
    """``V = 16 q^2 (q - a)^2 + v^2 - beta exp(-|z - (a, 0)|^2 / sigma^2)``: a well of V at x*, 1/16 at the saddle, and
    a pocket below zero, 0.005 wide, at the second rest point (a, 0) (too narrow for the import's 4,096 samples)."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("e", torch.eye(2, dtype=F64))
        self.register_buffer("well", torch.tensor([WELL, 0.0], dtype=F64))

    def forward(self, x):
        q, v = x @ self.e[0], x @ self.e[1]
        d = x @ self.e - self.well
        return 16.0 * (q * (q - WELL)) ** 2 + v * v - 1e-4 * torch.exp(-(d * d).sum(-1) / 2.5e-5)


def _imported_wells(tmp_path):
    system = _two_wells()
    _export(_WellsV(), 2, tmp_path / "v.onnx")
    _export(ConstantController(), 2, tmp_path / "c.onnx")
    return system, import_pair(system, tmp_path / "c.onnx", tmp_path / "v.onnx").loop


def test_a_v_below_zero_at_another_rest_point_gets_no_region_though_its_decrease_holds(tmp_path):
    """Falsifier: V < 0 at another rest point (a, 0) of the closed loop, so ``Vdot + alpha V = alpha V < 0`` holds
    there and the decrease is proved on ``{V <= c}`` outside the ball; but a trajectory from (a, 0) stays there, so
    the set is not a region of attraction of x*, and it is not called one (nor practical stability)."""
    system, loop = _imported_wells(tmp_path)
    condition = TrueDecrease(torch.zeros(1, 1, dtype=F64), 0.0, 0.05)
    roa = certified_roa(loop, condition, Region.of(system, 0.1), Budget(seconds=30), samples_per_axis=50)
    assert 0 < roa.outer_level < 1 / 16  # the decrease is proved on {V <= c} outside the ball, both wells
    assert roa.strict.strict is False and roa.strict.lower < 0 and "V > 0" in roa.strict.reason
    assert roa.kind is None and not roa.certified
    traj = simulate(system, lambda x: torch.zeros(x.shape[0], 1, dtype=F64), torch.tensor([[WELL, 0.0]], dtype=F64),
                    torch.tensor([4.0], dtype=F64), dt=0.01, horizon=5.0)
    assert float(traj.x[-1, 0, 0]) == WELL and float(traj.x[-1, 0, 1]) == 0.0
    # the checker's own bisection finds the pocket too
    import_run(system, tmp_path / "c.onnx", tmp_path / "run", tmp_path / "v.onnx")
    pair = GraphPair(json.loads((tmp_path / "run" / "graphs.json").read_text()),
                     torch.load(tmp_path / "run" / "tensors.pt", weights_only=True), 2)
    lo, hi = system.local_box()
    holds, low, _ = outside_positive(pair, lo, hi, 0.1, max_boxes=200_000)
    assert not holds and low < 0


def test_positivity_bounds_hold_below_every_sampled_value_outside_the_ball():
    """Sound means sound: the verifier's lower bound of V outside the ball (the one its strictness proof uses) lies
    below V at 20,000 sampled states there and on the ball's rim, and proves V > 0 for a positive definite V."""
    system = _two_wells()
    p = torch.tensor([[3.0, 0.8], [0.8, 1.0]], dtype=F64)
    lyap = QuadraticLyapunov(p)
    region = Region.of(system, 0.1)
    lower, info = positive_lower(lyap, region, Budget(seconds=20))
    lo, hi = system.local_box()
    z = lo + (hi - lo) * torch.rand(20_000, 2, generator=torch.Generator().manual_seed(0), dtype=F64)
    z = z[z.norm(dim=-1) >= 0.1]
    sampled = float(lyap(z).min())
    assert 0 < lower <= sampled and info.stopped == "finished"
    circle = torch.linspace(0, 6.3, 2000, dtype=F64)
    rim = 0.1 * torch.stack([circle.cos(), circle.sin()], -1)
    assert lower <= float(lyap(rim).min())  # V's least value outside the ball is on its rim


def test_strictness_by_decay_by_form_or_not_at_all():
    system = _two_wells()
    lyap = QuadraticLyapunov(torch.eye(2, dtype=F64))
    from drlyap.closed_loop import ClosedLoop
    from drlyap.networks import LinearController

    loop = ClosedLoop(system, lyap, LinearController(torch.zeros(1, 2, dtype=F64), system.input_box,
                                                     system.equilibrium_input))
    region, budget = Region.of(system, 0.1), Budget(seconds=5)
    xi = torch.zeros(1, 1, dtype=F64)
    assert outer_strictness(loop, TrueDecrease(xi, 0.01, 0.0), region, budget).to_dict() == {"strict": True, "by": "decay"}
    none = outer_strictness(loop, TrueDecrease(xi, 0.0, 0.0), region, budget)
    assert none.strict is False and "not strict" in none.reason
    assert outer_strictness(loop, TrueDecrease(xi, 0.0, 0.1), region, budget).to_dict() == {"strict": True, "by": "form"}
    saddle = loop.with_lyapunov(QuadraticLyapunov(torch.tensor([[1.0, 0.0], [0.0, -0.01]], dtype=F64)))
    refused = outer_strictness(saddle, TrueDecrease(xi, 0.0, 0.1), region, budget)  # not by form: bounded, and false
    assert refused.strict is False and refused.lower < 0 and "V > 0 outside the ball not proved" in refused.reason


def test_an_exported_pair_with_alpha_v_and_no_decay_is_certified_and_checked(tmp_path):
    """A drlyap pair trained with ``alpha V`` and gamma = 0, exported and imported again: its V is a graph, so its
    positivity is proved (by the verifier, then by the checker), and all three certificates are checked."""
    run = linear_run_dir(tmp_path / "run", decay_rate=0.0, exp_rate=0.05)
    spec = f"{os.path.dirname(__file__)}/handmade.py:small_pendulum"
    runner = CliRunner()
    out = export_and_import(run, spec, tmp_path)
    proved = runner.invoke(main, ["verify", str(out), "--system", spec, "--xi", "0.1,0.05", "--roa"])
    assert proved.exit_code == 0 and "CERTIFIED" in proved.output, proved.output
    assert "V > 0 outside the ball proved" in proved.output
    checked = runner.invoke(main, ["check", str(out), "--system", spec])
    assert checked.exit_code == 0 and checked.output.count(": CHECKED") == 3, checked.output
    assert "V > 0 outside the ball by the checker's bisection" in checked.output


def test_a_region_at_a_shift_asks_a_strict_decrease_and_no_more():
    """What ``verify --roa`` asks of the true model at a shift by default: the least decay that makes the decrease
    strict, never more than the run's own."""
    from drlyap.verification.roa import REGION_RATE, region_rate

    assert REGION_RATE == 0.01
    assert region_rate(0.0, 0.3) == REGION_RATE
    assert region_rate(0.0, 0.0) == REGION_RATE  # no decay at all: not strict without one
    assert region_rate(0.0, 0.003) is None  # the run's own alpha is smaller
    assert region_rate(1.0, 0.0) is None  # gamma ||z|| already makes it strict
