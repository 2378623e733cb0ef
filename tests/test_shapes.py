"""Shapes that verify and adversarial training states: networks without hidden layers (a quadratic V, a saturated
linear controller) set exactly to an LQR pair; states drawn inside a sublevel set; one step of the adversary."""

import pytest
import torch

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import DRPointwise
from drlyap.lqr import lqr_design
from drlyap.regions import Region
from drlyap.systems import cartpole, quadrotor2d
from drlyap.training import TrainConfig, TrainSections
from drlyap.training.states import ascend, radial_states
from drlyap.training.warm_start import Regression, warm_start_pair
from handmade import plain_train, small_pendulum

F64 = torch.float64


def linear_loop(system, **overrides):
    """A closed loop of networks without hidden layers, warm-started from the system's LQR (exactly)."""
    cfg = TrainConfig(system=system.name, lyapunov_hidden=[], controller_hidden=[], controller_skip=False,
                      **overrides).resolved(system)
    plan = TrainSections.of(cfg)
    lyapunov, controller = plan.networks.build(system)
    region = Region.of(system, cfg.delta)
    warm = warm_start_pair(ClosedLoop(system, lyapunov, controller), plan.networks, plan.goal.level, region,
                           torch.Generator().manual_seed(0), torch.zeros(0, 2), 0.0, Regression(cfg.lr))
    return cfg, ClosedLoop(system, lyapunov, controller), region, warm


def test_networks_without_hidden_layers_take_the_lqr_pair_exactly():
    system = cartpole()
    cfg, loop, region, warm = linear_loop(system, alpha_hat=1e-3)
    design = lqr_design(system, *cfg.lqr_weights)
    assert warm["iterations"] == 0 and warm["v_relative_error"] < 1e-10 and warm["u_relative_error"] < 1e-10
    z = region.sample(2000, torch.Generator().manual_seed(1))
    f64 = loop.f64
    with torch.no_grad():
        v = f64.lyapunov(z)
        assert torch.allclose(v, warm["P_scale"] * ((z @ design.P) * z).sum(-1), rtol=1e-5)  # float32 weights
        assert torch.allclose(f64.controller.raw(z), -(z @ design.K.T), rtol=1e-5, atol=1e-6)
    # V's minimum on the faces sits at 1.2 roa_level, as for the regression warm start
    with torch.no_grad():
        faces = region.sample_faces(20000, torch.Generator().manual_seed(2))
        assert float(f64.lyapunov(faces).min()) == pytest.approx(1.2 * cfg.roa_level, rel=0.05)


def test_a_linear_v_above_alpha_hat_keeps_the_floor_where_the_lqr_form_lies_below_it():
    """alpha_hat ||z/s||^2 is V's floor: where s P s has eigenvalues below alpha_hat, V lies above the LQR form."""
    system = cartpole()
    cfg, loop, region, _ = linear_loop(system, alpha_hat=100.0)
    z = region.sample(500, torch.Generator().manual_seed(3))
    with torch.no_grad():
        v = loop.f64.lyapunov(z)
        floor = 100.0 * (z / loop.lyapunov.phi.input_scale.double()).square().sum(-1)
    assert bool((v >= floor * (1 - 1e-9)).all())


def test_radial_states_lie_in_the_set_and_spread_to_its_edge():
    system = quadrotor2d()
    cfg, loop, region, _ = linear_loop(system)
    z = radial_states(loop.lyapunov, region, 1.0, 4096, torch.Generator().manual_seed(4))
    with torch.no_grad():
        v = loop.f64.lyapunov(z)
    assert z.shape[0] > 0.9 * 4096  # a quadratic V: nearly every draw is kept (the rest fall in the delta-ball)
    assert bool(region.contains(z).all()) and float(v.max()) <= 1.0
    assert float(v.max()) > 0.95 and float((v > 0.5).double().mean()) > 0.5  # most of a 6-D set's volume is near its edge
    uniform = region.sample(4096, torch.Generator().manual_seed(4))
    with torch.no_grad():
        assert int((loop.f64.lyapunov(uniform) <= 1.0).sum()) < 50  # what rejection would have kept


def test_one_adversarial_step_raises_the_residual_and_stays_in_the_set():
    system = quadrotor2d()
    cfg, loop, region, _ = linear_loop(system)
    condition = DRPointwise(0.05, 0.1, system.sample_xi(5, torch.Generator().manual_seed(5)).float(), exp_rate=1.0)
    z = radial_states(loop.lyapunov, region, 1.0, 1024, torch.Generator().manual_seed(6)).float()
    with torch.no_grad():
        before = condition.residual(condition.terms(loop, z))
    moved = ascend(loop, condition, z, region, 1.0)
    with torch.no_grad():
        after = condition.residual(condition.terms(loop, moved))
        value = loop.lyapunov(moved)
    assert float((after - before).mean()) > 0 and float((after > before).double().mean()) > 0.8
    inside_box = ((moved.double() >= region.lo) & (moved.double() <= region.hi)).all(-1)
    outside_ball = moved.double().norm(dim=-1) >= region.delta * (1 - 1e-6)  # float32 states on the ball's sphere
    assert bool((inside_box & outside_ball).all()) and float(value.max()) <= 1.0 + 1e-5
    assert all(p.grad is None for p in [*loop.lyapunov.parameters(), *loop.controller.parameters()])


def test_training_with_adversarial_states_runs_and_they_are_validated():
    system = small_pendulum()
    cfg = TrainConfig(system=system.name, roa_level=1.0, warm_start="lqr", decay_rate=0.0, exp_rate=0.3, iters=10,
                      check_every=10, n_states=256, lyapunov_hidden=[], controller_hidden=[4], seed=0,
                      adversarial_share=0.25, xi_samples=[[0.0, 0.0], [0.05, 0.01]])
    result = plain_train(cfg, system, progress=False)
    assert result.config.adversarial_share == 0.25 and result.metrics["iterations"] == 10
    for bad in ({"adversarial_share": 1.5}, {"adversarial_share": -0.1}, {"adversarial_share": 0.8, "near_share": 0.5},
                {"adversarial_share": 0.2, "loss": "uniform"}):
        with pytest.raises(ValueError, match="adversarial_share"):
            TrainConfig(system="cartpole", **bad).resolved(cartpole())


def test_retraining_rounds_do_not_grow_the_set():
    """``fit(grow=False)`` (the proof rounds) drops the growth term but keeps V above 1.05 level on the faces."""
    from drlyap.sections import GROW_FACES_MARGIN
    from drlyap.training.trainer import fit

    system = small_pendulum(((-0.6, -1.2), (0.6, 1.2)))
    cfg = TrainConfig(system=system.name, roa_level=1.0, warm_start="lqr", decay_rate=0.0, exp_rate=0.3, iters=60,
                      check_every=60, n_states=512, lyapunov_hidden=[8], controller_hidden=[8], seed=0, grow_weight=0.3,
                      xi_samples=[[0.0, 0.0], [0.05, 0.01]]).resolved(system)
    grid = Region.of(system, 0.1).grid().float()
    faces = Region.of(system, 0.1).sample_faces(4000, torch.Generator().manual_seed(1)).float()
    shares = []
    for grow in (True, False):
        result = fit(cfg, system, progress=False, grow=grow)
        with torch.no_grad():
            shares.append(float((result.lyapunov(grid) <= 1.0).double().mean()))
            assert float(result.lyapunov(faces).min()) > 1.0 + GROW_FACES_MARGIN / 2
    assert shares[0] > shares[1] + 0.05, shares
