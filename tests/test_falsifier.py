"""The falsifier's verdicts (drlyap.verification.falsifier): certain violations only, and only where a proof is unknown."""

import dataclasses
import math

import pytest
import torch

from drlyap.proof_settings import Budget, ProofConfig
from drlyap.regions import Region
from drlyap.systems import get_system
from drlyap.verification import Certificate, ConditionProof, ProofRules, prove_trained, verify_condition
from drlyap.verification.falsifier import confirmed_violations, falsifier_starts, falsify, settle_unknown
from handmade import plain_train


@pytest.fixture(scope="module")
def violating_pair():
    from drlyap.training import TrainConfig

    cfg = TrainConfig(system="pendulum", n_states=256, iters=10, check_every=10, lyapunov_hidden=[8], lyapunov_out=4,
                      controller_hidden=[8], seed=0)
    torch.set_num_threads(1)
    result = plain_train(cfg, progress=False)
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
    loop, cond = result.loop, result.condition
    z = torch.cat([region.sample(300, torch.Generator().manual_seed(3)),
                   torch.tensor([[0.01, 0.0], [0.0, -0.02]], dtype=torch.float64)])  # two inside the delta-ball
    exact = loop.exact(cond, z)
    for level in (None, 0.5):
        lower = confirmed_violations(loop, cond, region, z, level)
        certain = torch.isfinite(lower)
        assert bool((lower[certain] > 0).all() and (lower[certain] <= exact[certain] + 1e-9).all())
        assert not bool(certain[-2:].any())  # not in X_delta
        assert bool(certain[(exact > 1e-6) & (z.norm(dim=-1) >= region.delta)].all()) or level is not None
        if level is not None:
            v = loop.f64.value(z)
            assert not bool(certain[v > level].any())
    assert bool(torch.isfinite(confirmed_violations(loop, cond, region, z)).any())  # some violate


def test_settle_unknown_only_changes_unknown_proofs(violating_pair):
    result, region = violating_pair
    system, loop, cond = result.system, result.loop, result.condition
    ver = verify_condition(loop, cond, region, Budget(seconds=0.3), rules=ProofRules(keep_boxes=20))
    for status in ("verified", "violated"):
        same = dataclasses.replace(ver, status=status)
        assert settle_unknown(dataclasses.replace(same), loop, cond, region) == same
    unknown = dataclasses.replace(ver, status="unknown", counterexample=None, counterexample_local=None,
                                  counterexample_value=None)
    assert settle_unknown(dataclasses.replace(unknown), loop, cond, region, starts=0) == unknown
    out = settle_unknown(dataclasses.replace(unknown), loop, cond, region, starts=256, seed=1)
    assert out.status == "violated" and out.counterexample_source == "falsifier"
    assert out.verified_fraction == ver.verified_fraction and out.falsifier["confirmed"] >= 1
    z = torch.tensor([out.counterexample_local], dtype=torch.float64)
    assert math.isclose(float(loop.exact(cond, z)[0]), out.counterexample_value, rel_tol=1e-12)
    assert out.counterexample_value > 0 and float(z.norm()) >= region.delta
    assert torch.allclose(system.to_user(z)[0], torch.tensor(out.counterexample, dtype=torch.float64))


def test_prove_trained_reports_the_falsifier_or_the_proof(violating_pair):
    result, region = violating_pair
    loop, cond = result.loop, result.condition
    out = prove_trained(loop, cond, region, Budget(seconds=0.2))
    assert out.status == "violated"  # by the branch and bound or by the falsifier: the pair violates
    value = loop.exact(cond, torch.tensor([out.counterexample_local], dtype=torch.float64))
    assert float(value[0]) > 0
    plain = prove_trained(loop, cond, region, Budget(seconds=0.2), falsify_starts=0)
    assert plain.falsifier is None and "falsifier" not in plain.to_dict()


def test_falsify_never_loses_its_start(violating_pair):
    result, region = violating_pair
    loop, cond = result.loop, result.condition
    starts = falsifier_starts(region, 64, torch.Generator().manual_seed(2))
    found, values = falsify(loop, cond, region, starts, steps=5)
    assert bool((values >= loop.exact(cond, starts) - 1e-12).all())


def test_cegis_settles_the_returned_pairs_verdict(tiny_config, monkeypatch):
    import drlyap.training.certified as cegis
    from drlyap.render import certificate_line

    def out_of_time(*args, **kwargs):  # the branch and bound as if it had run out of time before any violation
        out = prove_trained(*args, **kwargs)
        return dataclasses.replace(out, status="unknown", counterexample=None, counterexample_local=None,
                                   counterexample_value=None)

    monkeypatch.setattr(cegis, "prove_trained", out_of_time)
    system = get_system("pendulum")
    result, rounds = cegis.train_cegis(tiny_config(iters=10, check_every=10).resolved(system), system,
                                       ProofConfig(rounds=0, time_limit=0.2).resolved(system), progress=False)
    final = result.metrics["cegis"]["final"]
    assert rounds[0].status == "unknown" and rounds[0].verification["status"] == "unknown"  # the round's own
    assert final["status"] == "violated" and final["counterexample_source"] == "falsifier"
    system = result.system
    z = system.to_local(torch.tensor([final["counterexample"]], dtype=torch.float64))
    assert float(result.loop.exact(result.condition, z)[0]) > 0
    line = certificate_line(Certificate.of(ConditionProof.from_dict(final), 0.5))
    assert "NOT VERIFIED (violated)" in line and "found by the falsifier" in line


def test_cegis_starts_near_x_star_where_training_does(violating_pair, monkeypatch):
    import drlyap.training.certified as cegis

    result, region = violating_pair
    loop, cond = result.loop, result.condition
    nothing = ConditionProof(condition=cond.label, status="unknown", verified_fraction=0.0, delta=region.delta)
    got = cegis.collect_counterexamples(loop, cond, region, nothing, torch.Generator().manual_seed(0),
                                        cegis.CounterexampleSearch(n_random=64, steps=5, near=True))
    assert got["falsifier_starts"] == 64 and bool((loop.exact(cond, got["counterexamples"]) > 0).all())
    seen = []

    def spy(loop, condition, region, verification, generator, search):
        seen.append((search.n_random, search.near))
        return {"counterexamples": torch.empty(0, 2, dtype=torch.float64), "neighbours": torch.empty(0, 2),
                "box_centres": torch.empty(0, 2, dtype=torch.float64), "open_boxes": None, "max_residual": None,
                "falsify_time_s": 0.0}

    monkeypatch.setattr(cegis, "collect_counterexamples", spy)
    from drlyap.training import TrainConfig

    for share, expected in ((0.0, (512, False)), (0.25, (2048, True))):
        cfg = TrainConfig(system="pendulum", n_states=64, iters=2, check_every=2, lyapunov_hidden=[4], lyapunov_out=2,
                          controller_hidden=[4], seed=0, near_share=share)
        system = get_system("pendulum")
        cegis.train_cegis(cfg.resolved(system), system, ProofConfig(rounds=1, time_limit=0.1, iters_per_round=1)
                          .resolved(system), progress=False)
        assert seen[-1] == expected
