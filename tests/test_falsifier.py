"""The falsifier's verdicts (drlyap.verification.falsifier): certain violations only, and only where a proof is unknown."""

import math

import pytest
import torch

from drlyap.regions import Region
from drlyap.systems import get_system
from drlyap.training import train
from drlyap.verification import prove_trained, verify_condition
from drlyap.verification.falsifier import confirmed_violations, falsifier_starts, falsify, settle_unknown


@pytest.fixture(scope="module")
def violating_pair():
    from drlyap.training import TrainConfig

    cfg = TrainConfig(system="pendulum", n_states=256, iters=10, check_every=10, lyapunov_hidden=[8], lyapunov_out=4,
                      controller_hidden=[8], seed=0)
    torch.set_num_threads(1)
    result = train(cfg, progress=False)
    return result, Region.of(result.system, result.config.delta)


def test_starts_reach_near_x_star_in_six_states():
    region = Region.of(get_system("quadrotor2d"), 0.1)
    z = falsifier_starts(region, 4000, torch.Generator().manual_seed(0))
    assert z.shape == (4000, 6)
    assert bool(((z >= region.lo) & (z <= region.hi)).all() and (z.norm(dim=-1) >= 0.1).all())
    scaled = (z / (region.scale / 2)).norm(dim=-1)
    uniform = (region.sample(4000, torch.Generator().manual_seed(0)) / (region.scale / 2)).norm(dim=-1)
    # a quarter of the way to the box's faces: ~1e-4 of a uniform draw in 6 states, a tenth of these starts
    assert float((scaled < 0.25).double().mean()) > 0.08 and float((uniform < 0.25).double().mean()) < 0.005


def test_confirmed_violations_are_sound_lower_bounds(violating_pair):
    result, region = violating_pair
    system, lyap, ctrl, cond = result.system, result.lyapunov, result.controller, result.condition
    z = torch.cat([region.sample(300, torch.Generator().manual_seed(3)),
                   torch.tensor([[0.01, 0.0], [0.0, -0.02]], dtype=torch.float64)])  # two inside the delta-ball
    exact = cond.exact(system, lyap, ctrl, z)
    for level in (None, 0.5):
        lower = confirmed_violations(system, lyap, ctrl, cond, region, z, level)
        certain = torch.isfinite(lower)
        assert bool((lower[certain] > 0).all() and (lower[certain] <= exact[certain] + 1e-9).all())
        assert not bool(certain[-2:].any())  # not in X_delta
        assert bool(certain[(exact > 1e-6) & (z.norm(dim=-1) >= region.delta)].all()) or level is not None
        if level is not None:
            with torch.no_grad():
                v = lyap.double()(z)
            assert not bool(certain[v > level].any())
    assert bool(torch.isfinite(confirmed_violations(system, lyap, ctrl, cond, region, z)).any())  # some violate


def test_settle_unknown_only_changes_unknown_proofs(violating_pair):
    result, region = violating_pair
    system, lyap, ctrl, cond = result.system, result.lyapunov, result.controller, result.condition
    ver = verify_condition(system, lyap, ctrl, cond, region, time_limit=0.3, keep_boxes=20).to_dict()
    for status in ("verified", "violated"):
        same = dict(ver, status=status)
        assert settle_unknown(dict(same), system, lyap, ctrl, cond, region) == same
    unknown = dict(ver, status="unknown", counterexample=None, counterexample_local=None, counterexample_value=None)
    assert settle_unknown(dict(unknown), system, lyap, ctrl, cond, region, starts=0) == unknown
    out = settle_unknown(dict(unknown), system, lyap, ctrl, cond, region, starts=256, seed=1)
    assert out["status"] == "violated" and out["counterexample_source"] == "falsifier"
    assert out["verified_fraction"] == ver["verified_fraction"] and out["falsifier"]["confirmed"] >= 1
    z = torch.tensor([out["counterexample_local"]], dtype=torch.float64)
    assert math.isclose(float(cond.exact(system, lyap, ctrl, z)[0]), out["counterexample_value"], rel_tol=1e-12)
    assert out["counterexample_value"] > 0 and float(z.norm()) >= region.delta
    assert torch.allclose(system.to_user(z)[0], torch.tensor(out["counterexample"], dtype=torch.float64))


def test_prove_trained_reports_the_falsifier_or_the_proof(violating_pair):
    result, region = violating_pair
    system, lyap, ctrl, cond = result.system, result.lyapunov, result.controller, result.condition
    out = prove_trained(system, lyap, ctrl, cond, region, time_limit=0.2)
    assert out["status"] == "violated"  # by the branch and bound or by the falsifier: the pair violates
    value = cond.exact(system, lyap, ctrl, torch.tensor([out["counterexample_local"]], dtype=torch.float64))
    assert float(value[0]) > 0
    plain = prove_trained(system, lyap, ctrl, cond, region, time_limit=0.2, falsify_starts=0)
    assert "falsifier" not in plain


def test_falsify_never_loses_its_start(violating_pair):
    result, region = violating_pair
    system, lyap, ctrl, cond = result.system, result.lyapunov, result.controller, result.condition
    starts = falsifier_starts(region, 64, torch.Generator().manual_seed(2))
    found, values = falsify(system, lyap, ctrl, cond, region, starts, steps=5)
    assert bool((values >= cond.exact(system, lyap, ctrl, starts) - 1e-12).all())


def test_cegis_settles_the_returned_pairs_verdict(tiny_config, monkeypatch):
    import drlyap.cegis as cegis
    from drlyap.cli import certificate_line

    def out_of_time(*args, **kwargs):  # the branch and bound as if it had run out of time before any violation
        out = prove_trained(*args, **kwargs)
        return dict(out, status="unknown", counterexample=None, counterexample_local=None, counterexample_value=None)

    monkeypatch.setattr(cegis, "prove_trained", out_of_time)
    result, rounds = cegis.train_cegis(tiny_config(iters=10, check_every=10), rounds=0, verify_time_limit=0.2,
                                       progress=False)
    final = result.metrics["cegis"]["final"]
    assert rounds[0]["status"] == "unknown" and rounds[0]["verification"]["status"] == "unknown"  # the round's own
    assert final["status"] == "violated" and final["counterexample_source"] == "falsifier"
    system = result.system
    z = system.to_local(torch.tensor([final["counterexample"]], dtype=torch.float64))
    assert float(result.condition.exact(system, result.lyapunov, result.controller, z)[0]) > 0
    line = certificate_line(cegis.certificate_summary(final, result.condition.label, 0.5))
    assert "NOT VERIFIED (violated)" in line and "found by the falsifier" in line


def test_cegis_starts_near_x_star_where_training_does(violating_pair, monkeypatch):
    import drlyap.cegis as cegis

    result, region = violating_pair
    system, lyap, ctrl, cond = result.system, result.lyapunov, result.controller, result.condition
    got = cegis.collect_counterexamples(system, lyap, ctrl, cond, region, {}, torch.Generator().manual_seed(0),
                                        n_random=64, steps=5, near=True)
    assert got["falsifier_starts"] == 64 and bool((cond.exact(system, lyap, ctrl, got["counterexamples"]) > 0).all())
    seen = []

    def spy(*args, **kwargs):
        seen.append((kwargs["n_random"], kwargs["near"]))
        return {"counterexamples": torch.empty(0, 2, dtype=torch.float64), "neighbours": torch.empty(0, 2),
                "box_centres": torch.empty(0, 2, dtype=torch.float64), "max_residual": None, "falsify_time_s": 0.0}

    monkeypatch.setattr(cegis, "collect_counterexamples", spy)
    from drlyap.training import TrainConfig

    for share, expected in ((0.0, (512, False)), (0.25, (2048, True))):
        cfg = TrainConfig(system="pendulum", n_states=64, iters=2, check_every=2, lyapunov_hidden=[4], lyapunov_out=2,
                          controller_hidden=[4], seed=0, near_share=share)
        cegis.train_cegis(cfg, rounds=1, verify_time_limit=0.1, progress=False, iters_per_round=1)
        assert seen[-1] == expected
