"""The V step (drlyap.training.reshape): a quadratic V's set grown by convex programs with the controller fixed."""

import dataclasses

import pytest
import torch

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import DRPointwise, Nominal, local_rates
from drlyap.regions import Region
from drlyap.sections import TrainSections
from drlyap.systems import cartpole, quadrotor2d
from drlyap.training import TrainConfig, fit
from drlyap.training.reshape import GrowthTarget, _affine_structure, grow_quadratic, quadratic_form, share


def test_the_condition_structure_is_read_from_its_own_code():
    xi = torch.randn(5, 2, dtype=torch.float64)
    c_d, c_l = _affine_structure(DRPointwise(0.05, 0.1, xi, exp_rate=0.1), 5)  # eps N = 0.5: the CVaR is the max
    assert torch.allclose(c_d, torch.ones(5, dtype=torch.float64))
    assert torch.allclose(c_l, torch.full((5,), 0.5, dtype=torch.float64))
    c_d, c_l = _affine_structure(Nominal(xi[:1]), 1)
    assert float(c_l.abs().max()) == 0.0 and float(c_d[0]) == 1.0
    assert _affine_structure(DRPointwise(0.05, 0.5, xi), 5) is None  # eps N = 2.5: a CVaR that is not the max


@pytest.fixture(scope="module")
def grown():
    """The quadrotor's default pair (a quadratic V) briefly trained for a growing set, then grown by two programs."""
    system = quadrotor2d()
    cfg = TrainConfig(system="quadrotor2d", iters=100, n_states=512, reshape_steps=2).resolved(system)
    result = fit(cfg, system, progress=False)
    return system, cfg, result


def test_quadratic_form_is_v(grown):
    system, _, result = grown
    z = torch.randn(64, system.n, dtype=torch.float64)
    p = quadratic_form(result.loop.lyapunov)
    assert torch.allclose(result.loop.f64.lyapunov(z), ((z @ p) * z).sum(-1), rtol=1e-5)


def test_the_programs_grow_the_set_within_their_constraints(grown):
    system, cfg, result = grown
    record = result.metrics["reshape"]
    assert record["steps"] == 2 and record["kept"]
    assert record["share_after"] > record["share_before"]
    p = quadratic_form(result.loop.lyapunov)  # the V kept is the grown one
    region = Region.of(system, cfg.delta)
    level = TrainSections.of(cfg).goal.level  # the trained level, (1 + level_margin) roa_level
    assert share(p / level, region) == pytest.approx(record["share_after"], rel=1e-4)
    # V at least the faces' level on every face: min over the face z_i = h_i of z'Pz is h_i^2 / (P^-1)_ii
    lo, hi = system.local_box()
    half = torch.minimum(-lo, hi)
    assert bool((half.square() / torch.linalg.inv(p).diagonal() >= 1.05 * cfg.roa_level * (1 - 1e-5)).all())
    # V's local rate at x* at least local_rate at every training sample
    assert float(local_rates(result.condition, result.loop.f64).detach().max()) <= -cfg.local_rate * (1 - 1e-4)


def test_a_v_with_hidden_layers_is_left_alone():
    system = cartpole()
    cfg = TrainConfig(system="cartpole", lyapunov_hidden=[8], controller_hidden=[8]).resolved(system)
    from drlyap.sections import TrainSections

    lyapunov, controller = TrainSections.of(cfg).networks.build(system)
    before = [t.clone() for t in lyapunov.state_dict().values()]
    loop = ClosedLoop(system, lyapunov, controller)
    condition = DRPointwise(0.05, 0.1, system.sample_xi(5, torch.Generator().manual_seed(0)))
    assert grow_quadratic(loop, condition, Region.of(system, 0.1), GrowthTarget(1.0, 1.05), 2,
                          torch.Generator().manual_seed(0)) is None
    assert all(torch.equal(a, b) for a, b in zip(before, lyapunov.state_dict().values()))


def test_negative_steps_are_refused():
    with pytest.raises(ValueError, match="reshape_steps = -1"):
        TrainConfig(system="cartpole", reshape_steps=-1).resolved(cartpole())


def test_the_training_lines_say_how_the_set_grew(grown):
    from drlyap.render import training_lines

    _, _, result = grown
    lines = "\n".join(training_lines("quadrotor2d", "dr", result.record))
    record = result.metrics["reshape"]
    assert f"grown by 2 convex program(s) with the controller fixed: {record['share_before']:.3g} -> " in lines
    assert "kept" in lines


def test_a_grown_v_that_fails_the_check_is_mixed_back_and_else_undone(monkeypatch):
    import drlyap.training.trainer as trainer

    def too_far(loop, *args, **kwargs):  # V dominated by 1e6 x^2, whose rate x xdot has no sign: every mixture fails
        bump = torch.zeros(6, 6, dtype=torch.float64)
        bump[0, 0] = 1e6
        loop.lyapunov.set_quadratic(quadratic_form(loop.lyapunov) + bump)
        return {"steps": 1, "stopped": "the steps ran out", "share_before": 0.0, "share_after": 1.0}

    seen = {}
    keep = trainer.fit

    def spy(cfg, system, **kw):
        result = keep(cfg, system, **kw)
        seen["v"] = quadratic_form(result.loop.lyapunov)
        return result

    system = quadrotor2d()
    cfg = TrainConfig(system="quadrotor2d", iters=100, n_states=512, reshape_steps=2).resolved(system)
    trained = fit(dataclasses.replace(cfg, reshape_steps=0), system, progress=False)  # the same fit, no programs
    monkeypatch.setattr(trainer, "grow_quadratic", too_far)
    result = spy(cfg, system, progress=False)
    assert result.metrics["reshape"]["kept"] is False and result.metrics["reshape"]["mix"] is None
    assert torch.allclose(seen["v"], quadratic_form(trained.loop.lyapunov))
    assert result.metrics["acceptance"]["passed"]
