"""A training config's sections: every field in exactly one, each building what it is about."""

import dataclasses

import pytest
import torch

from drlyap.conditions import DRPointwise, Nominal, TrueDecrease
from drlyap.config import TrainConfig
from drlyap.regions import Region
from drlyap.sections import GROW_FACES_MARGIN, SECTIONS, TrainSections
from drlyap.systems import pendulum


def test_every_field_of_the_config_is_in_exactly_one_section():
    names = [f.name for kind in SECTIONS for f in dataclasses.fields(kind)]
    assert len(names) == len(set(names))
    assert sorted(names + ["system"]) == sorted(f.name for f in dataclasses.fields(TrainConfig))


def test_an_unresolved_config_has_no_sections():
    with pytest.raises(ValueError, match="resolve it first"):
        TrainSections.of(TrainConfig())


def test_the_sections_build_what_the_config_describes():
    system = pendulum()
    cfg = TrainConfig(roa_level=2.0, level_margin=0.1, grow_weight=0.3, lyapunov_hidden=[5], lyapunov_out=3,
                      controller_hidden=[4], n_xi=7, seed=3).resolved(system)
    plan = TrainSections.of(cfg)
    assert plan.goal.level == pytest.approx(2.2)
    assert plan.goal.faces_level == pytest.approx(2.2 * (1 + GROW_FACES_MARGIN))
    lyapunov, controller = plan.networks.build(system)
    assert lyapunov.phi.sizes == [2, 5, 3] and controller.varphi.sizes == [2, 4, 1]
    xi = plan.sampling.xi(system, plan.schedule.seed)
    assert xi.shape == (7, system.k) and torch.equal(xi, plan.sampling.xi(system, plan.schedule.seed))
    trained = plan.condition.build(plan.condition.training_samples(xi))
    assert isinstance(trained, DRPointwise) and trained.r == pytest.approx(cfg.wasserstein_radius)
    assert isinstance(plan.condition.build(xi[:1], "true"), TrueDecrease)
    region = plan.sampling.region(system)
    assert region.delta == pytest.approx(cfg.delta)


def test_the_baseline_trains_at_the_samples_mean():
    system = pendulum()
    plan = TrainSections.of(TrainConfig(method="baseline").resolved(system))
    xi = torch.tensor([[0.0, 1.0], [2.0, 3.0]], dtype=torch.float64)
    mean = plan.condition.training_samples(xi)
    assert torch.equal(mean, torch.tensor([[1.0, 2.0]], dtype=torch.float64))
    assert isinstance(plan.condition.build(mean), Nominal)


def test_a_training_box_moves_where_states_are_drawn_only():
    system = pendulum()
    box = [[-0.5, -0.5], [0.5, 0.5]]
    sampling = TrainSections.of(TrainConfig(train_box=box).resolved(system)).sampling
    drawn = sampling.sampling_region(system).sample(2000, torch.Generator().manual_seed(0))
    assert float(drawn.abs().max()) <= 0.5 + 1e-12
    assert sampling.region(system).hi.tolist() == Region.of(system, sampling.delta).hi.tolist()


def test_distinct_keeps_the_first_of_states_that_agree_to_the_resolution():
    region = Region.of(pendulum(), 0.1)
    z = torch.tensor([[0.5, 0.5], [0.3, 0.1], [0.5, 0.5 + 1e-12], [0.3, 0.1]], dtype=torch.float64)
    assert torch.equal(region.distinct(z), z[:2])
    assert region.distinct(z[:0]).shape == (0, 2)
