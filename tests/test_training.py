import json
import math

import pytest
import torch

from drlyap.closed_loop import ClosedLoop
from drlyap.records import AcceptanceCheck
from drlyap.regions import Region
from drlyap.runs import RunDirError, load_run, save_run
from drlyap.systems import cartpole, mountain_car, pendulum
from drlyap.training import TrainConfig, TrainSections
from drlyap.training.acceptance import SetAsked, acceptance_check, find_equilibria, jacobian_check
from handmade import plain_train


def test_training_states_avoid_the_delta_ball_and_fill_the_box():
    p = pendulum()
    z = Region.of(p, 0.5).sample(2000, torch.Generator().manual_seed(0))
    lo, hi = p.local_box()
    assert z.shape == (2000, 2) and (z.norm(dim=-1) >= 0.5).all()
    assert (z >= lo).all() and (z <= hi).all()


def test_near_states_spread_over_the_distance_from_x_star_in_four_states():
    """A uniform batch in 4 states holds almost no states near x* (where local stability is decided):
    the near draw gives every distance the same share, inside the box and outside the delta-ball."""
    cp = cartpole()
    region = Region.of(cp, 0.1)
    gen = torch.Generator().manual_seed(0)
    uniform, near = region.sample(20000, gen), region.sample_near(20000, gen)
    lo, hi = cp.local_box()
    assert near.shape == (20000, 4) and (near.norm(dim=-1) >= 0.1).all()
    assert (near >= lo).all() and (near <= hi).all()
    half = (hi - lo) / 2  # distances in box-scaled coordinates (cartpole's box is not a cube)
    assert float(((uniform / half).norm(dim=-1) < 0.3).double().mean()) < 0.01
    assert float(((near / half).norm(dim=-1) < 0.3).double().mean()) > 0.15
    assert (near / half).mean(0).abs().max() < 0.02  # no preferred direction


def test_the_validation_set_in_four_states_covers_the_neighbourhood_of_x_star():
    cp = cartpole()
    z = Region.of(cp, 0.1).grid()
    lo, hi = cp.local_box()
    near = ((z / ((hi - lo) / 2)).norm(dim=-1) < 0.3).sum()
    assert z.shape[0] >= 45000 and (z.norm(dim=-1) >= 0.1).all() and near > 1000  # uniform alone: about 100


def test_a_share_of_near_states_enters_every_batch(tiny_config):
    result = plain_train(tiny_config(near_share=0.5), progress=False)
    assert result.config.near_share == 0.5
    assert plain_train(tiny_config(), progress=False).config.near_share == 0.0  # off by default
    with pytest.raises(ValueError, match="near_share"):
        plain_train(tiny_config(near_share=1.5), progress=False)


def test_tiny_training_run_round_trips_through_a_run_directory(tmp_path, tiny_config):
    result = plain_train(tiny_config(), progress=False)
    m = result.metrics
    assert m["iterations"] == 20 and "acceptance" in m and isinstance(m["passed"], bool)
    assert set(m["acceptance"]) >= {"max_violation", "violating_fraction", "jacobian", "other_equilibria"}
    out = save_run(tmp_path / "run", result)
    run = load_run(out)
    x = torch.tensor([[0.3, -1.0], [2.0, 4.0]], dtype=torch.float64)
    with torch.no_grad():
        z = run.system.to_local(x).float()
        assert torch.allclose(run.controller(x), result.controller(z).double())
        assert torch.allclose(run.lyapunov(x), result.lyapunov(z).double())
    # user coordinates: the angle branch does not matter, V(x*) = 0 and pi(x*) = u*
    assert torch.allclose(run.controller(x + torch.tensor([2 * math.pi, 0.0], dtype=torch.float64)), run.controller(x),
                          atol=1e-5)
    star = torch.zeros(1, 2, dtype=torch.float64)
    assert run.lyapunov(star).item() == 0.0 and run.controller(star).item() == 0.0
    saved = json.loads((out / "config.json").read_text())
    assert saved["wasserstein_radius"] == 0.01 and saved["n_states"] == 256
    with pytest.raises(ValueError, match="shape"):
        run.controller(torch.zeros(3))


def test_interrupted_save_leaves_no_run_directory(tmp_path, tiny_config):
    result = plain_train(tiny_config(iters=2, check_every=2), progress=False)

    def boom(tmp):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        save_run(tmp_path / "run", result, extra=boom)
    assert list(tmp_path.iterdir()) == []


def test_run_directory_errors(tmp_path, tiny_config):
    with pytest.raises(RunDirError, match="does not exist"):
        load_run(tmp_path / "missing")
    (tmp_path / "half").mkdir()
    with pytest.raises(RunDirError, match="not a complete"):
        load_run(tmp_path / "half")
    out = save_run(tmp_path / "run", plain_train(tiny_config(iters=2, check_every=2), progress=False))
    with pytest.raises(RunDirError, match="already exists"):
        save_run(out, plain_train(tiny_config(iters=2, check_every=2), progress=False))
    from drlyap.systems import mountain_car

    with pytest.raises(RunDirError, match="made for system 'pendulum'"):
        load_run(out, mountain_car())


def test_divergence_stops_with_last_good_weights(tiny_config):
    result = plain_train(tiny_config(lr=1e30, iters=40, check_every=40), progress=False)
    assert result.metrics["status"].startswith("diverged")
    assert all(torch.isfinite(p).all() for p in result.controller.parameters())


@pytest.mark.parametrize("field, value, message", [
    ("method", "magic", "method"), ("risk_level", 1.5, "risk_level"), ("n_states", 0, "n_states"),
    ("xi_samples", [[0.1]], "xi_samples must be"), ("xi_samples", [[0.1, float("nan")]], "NaN"),
    ("decay_rate", -1.0, "decay_rate"), ("device", "tpu", "device"), ("local_rate", -0.5, "local_rate"),
    ("local_rate", float("nan"), "local_rate"),
])
def test_bad_config_is_rejected_before_training(tiny_config, field, value, message):
    with pytest.raises(ValueError, match=message):
        plain_train(tiny_config(**{field: value}), progress=False)


def test_acceptance_checks_flag_a_bad_controller():
    """A zero controller: x* is unstable (not Hurwitz) and the hanging state is another equilibrium."""
    p = pendulum()
    _, controller = TrainSections.of(TrainConfig(lyapunov_hidden=[4], controller_hidden=[4]).resolved(p)).networks.build(p)
    with torch.no_grad():
        for param in controller.parameters():
            param.zero_()
    xi = torch.zeros(1, 2)
    loop = ClosedLoop(p, None, controller)
    assert not jacobian_check(loop, xi)["hurwitz"]
    found = find_equilibria(loop, xi, delta=0.5)
    assert found and all(abs(abs(e["state"][0]) - math.pi) < 1e-3 for e in found)


def test_a_pd_like_controller_passes_the_jacobian_and_equilibrium_checks():
    p = pendulum()
    _, controller = TrainSections.of(TrainConfig(lyapunov_hidden=[4], controller_hidden=[2]).resolved(p)).networks.build(p)
    with torch.no_grad():  # varphi(z) ~ -K z through a nearly linear tanh layer
        first, last = controller.varphi.layers
        first.weight.copy_(torch.tensor([[0.01 * math.pi, 0.0], [0.0, 0.01 * 8.0]]))
        first.bias.zero_()
        last.weight.copy_(torch.tensor([[-30.0 / 0.01, -8.0 / 0.01]]))
        last.bias.zero_()
    xi = torch.tensor([[0.1, 0.05], [0.0, 0.0]])
    loop = ClosedLoop(p, None, controller)
    assert jacobian_check(loop, xi)["hurwitz"]
    assert find_equilibria(loop, xi, delta=0.5) == []


def test_training_states_can_be_drawn_from_a_box_wider_than_x():
    car = mountain_car()
    region = car.with_state_box([[-3.2, -0.4], [3.2, 0.4]])
    z = Region.of(region, 0.1).sample(4000, torch.Generator().manual_seed(0))
    x = car.to_user(z)
    assert (x[:, 0] >= -3.2).all() and (x[:, 0] <= 3.2).all() and (x[:, 0].abs() > 2.0).any()
    assert region.state_box[0] == (-3.2, -0.4) and car.state_box[0] == (-2.0, -0.4)  # X itself is untouched
    sampling = TrainSections.of(TrainConfig(system="mountain-car").resolved(car)).sampling  # no training box: X
    assert sampling.sampling_region(car).hi.tolist() == sampling.region(car).hi.tolist()


def test_a_train_box_without_the_equilibrium_is_rejected(tiny_config):
    with pytest.raises(ValueError, match="train_box"):
        plain_train(tiny_config(train_box=[[1.0, -1.0], [2.0, 1.0]]), progress=False)


def test_a_saved_config_with_an_unknown_key_is_refused_by_name():
    with pytest.raises(ValueError, match=r"unknown config keys \['iterz'\]"):
        TrainConfig.from_dict({"system": "pendulum", "iterz": 10})


def test_the_local_term_makes_v_decay_near_x_star_and_the_acceptance_check_asks_for_it(tiny_config):
    """Same seed with and without the local term: it lowers V's worst second-order rate at x* (it starts well
    above 0 here), and with the term asked the acceptance check fails while any rate is >= 0."""
    plain = plain_train(tiny_config(iters=200, check_every=200), progress=False).metrics
    local = plain_train(tiny_config(iters=200, check_every=200, local_rate=1.0), progress=False).metrics
    assert plain["acceptance"]["local_rate_max"] > 0
    assert local["acceptance"]["local_rate_max"] < plain["acceptance"]["local_rate_max"] - 1.0
    assert local["checks"][-1]["local_rate_max"] == pytest.approx(local["acceptance"]["local_rate_max"])
    if local["acceptance"]["local_rate_max"] >= 0:
        assert not local["passed"]


def test_the_acceptance_check_is_a_typed_record_that_reads_back_as_it_was_written(tmp_path, tiny_config):
    """Training keeps its acceptance check as ``metrics["acceptance"]`` and everything else reads it through
    :class:`~drlyap.records.AcceptanceCheck`: the same keys, read back equal, and a run written before the local rates
    were kept still reads (without them)."""
    import json

    from drlyap.records import AcceptanceCheck
    from drlyap.runs import load_run, save_run
    from handmade import plain_train

    result = plain_train(tiny_config())
    check = result.acceptance
    assert isinstance(check, AcceptanceCheck) and check.iteration == result.metrics["best_iteration"]
    assert check.to_dict() == result.metrics["acceptance"]
    assert check.stability() == (check.passed, bool(check.jacobian["hurwitz"]), not check.other_equilibria)
    assert result.metrics["checks"][-1].keys() == check.summary().keys()
    run = load_run(save_run(tmp_path / "run", result), result.system)
    assert run.acceptance == AcceptanceCheck.from_dict(json.loads((tmp_path / "run" / "metrics.json").read_text())[
        "acceptance"])
    old = {k: v for k, v in result.metrics["acceptance"].items() if k not in ("local_rates", "local_rate_max")}
    older = AcceptanceCheck.from_dict(old | {"written_by": "an older drlyap"})
    assert older.local_rates == [] and older.local_rate_max is None and older.to_dict()["written_by"] == "an older drlyap"
    # a training without proof rounds: its record counts its own iterations and seconds
    record = run.record
    assert not record.proved_in_rounds and record.rounds == () and record.acceptance == check
    assert (record.total_iterations, record.total_time_s) == (record.iterations, record.train_time_s)
    assert record.iterations == result.metrics["iterations"] and record.status == result.metrics["status"]


def test_an_equilibrium_outside_the_trained_set_does_not_count_against_the_pair():
    """A zero controller leaves the pendulum its hanging equilibria (theta = +-pi). For a pair trained for
    {V <= level} only the equilibria inside the set count against it (each found one recorded with V there); without
    a level every one does, as before."""
    p = pendulum()
    lyapunov, controller = TrainSections.of(TrainConfig(lyapunov_hidden=[4], controller_hidden=[4]).resolved(p)
                                            ).networks.build(p)
    with torch.no_grad():
        for param in controller.parameters():
            param.zero_()
    loop, xi = ClosedLoop(p, lyapunov, controller), torch.zeros(1, 2)
    condition = TrainSections.of(TrainConfig().resolved(p)).condition.build(xi)
    region = Region.of(p, 0.5)
    found = find_equilibria(loop, xi, delta=0.5)
    assert found and all(abs(abs(e["state"][0]) - math.pi) < 1e-3 for e in found)
    values = loop.value(torch.tensor([e["local"] for e in found]))
    below, above = 0.5 * float(values.min()), 2.0 * float(values.max())
    outside = acceptance_check(loop, condition, xi, region, asked=SetAsked(below))
    inside = acceptance_check(loop, condition, xi, region, asked=SetAsked(above))
    whole = acceptance_check(loop, condition, xi, region)
    assert len(outside.other_equilibria) == len(found) and outside.blocking_equilibria == []
    assert all(e["in_set"] is False and e["value"] > below for e in outside.other_equilibria)
    assert outside.stability()[2] and not inside.stability()[2] and not whole.stability()[2]
    assert len(inside.blocking_equilibria) == len(whole.blocking_equilibria) == len(found)
    assert AcceptanceCheck.from_dict(outside.to_dict()).blocking_equilibria == []
