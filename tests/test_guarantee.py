"""The probability behind the guarantee and the Lipschitz covering check (drlyap.guarantee)."""

import json
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from drlyap import systems
from drlyap.conditions import wasserstein_radius_guarantee
from drlyap.io import jsonable
from drlyap.runs import Run
from drlyap.training import TrainConfig
from drlyap.workflows.guarantee import Draws, clopper_pearson, guarantee, parse_distribution, wilson
from drlyap.workflows.verify import run_covering
from handmade import linear_pair, small_pendulum

F64 = torch.float64
XI = torch.tensor([[0.02, 0.01], [-0.03, 0.0], [0.05, -0.02]], dtype=F64)


def hand_run(sign=1.0, loss="pointwise") -> Run:
    system = small_pendulum()
    lyap, ctrl = linear_pair(system, sign)
    cfg = TrainConfig(system=system.name, method="dr", loss=loss, wasserstein_radius=1e-3, risk_level=0.1,
                      decay_rate=0.05, delta=0.2, lyapunov_hidden=[2], lyapunov_out=2, controller_hidden=[1]).resolved(system)
    metrics = {"xi_samples": XI.tolist(), "xi_train": XI.tolist()}
    return Run(Path("hand-made"), system, cfg, metrics, lyap, ctrl)


# ------------------------------------------------------------------ distributions and intervals
def test_distribution_specs_parse_and_draw():
    gen = torch.Generator().manual_seed(0)
    pend = systems.pendulum()
    sample, desc = parse_distribution("train", 2, pend)
    assert desc["kind"] == "train" and sample(7, gen).shape == (7, 2)
    sample, desc = parse_distribution("point:0.1,-0.05", 2)
    assert torch.equal(sample(3, gen), torch.tensor([[0.1, -0.05]] * 3, dtype=F64))
    sample, desc = parse_distribution("normal:1,2;0.1,0", 2)
    draws = sample(4000, gen)
    assert abs(float(draws[:, 0].mean()) - 1) < 0.02 and abs(float(draws[:, 0].std()) - 0.1) < 0.01
    assert bool((draws[:, 1] == 2).all()) and desc == {"kind": "normal", "mean": [1.0, 2.0], "std": [0.1, 0.0]}
    sample, desc = parse_distribution(" uniform:-1,0;1,0.5 ", 2)
    draws = sample(2000, gen)
    assert bool((draws[:, 0] >= -1).all() and (draws[:, 0] <= 1).all() and (draws[:, 1] <= 0.5).all())
    assert float(draws[:, 0].min()) < -0.9 and float(draws[:, 0].max()) > 0.9


@pytest.mark.parametrize("spec,match", [
    ("gamma:1,2", "unknown distribution"), ("point:1", "needs 2 value"), ("point:1,2;3,4", "one vector"),
    ("normal:1,2", "two vectors"), ("normal:0,0;-1,1", ">= 0"), ("uniform:1,1;0,2", "low <= high"),
    ("point:a,b", "comma-separated numbers"), ("point:1,inf", "finite"), ("train:1", "no parameters"),
    ("train", "declares its xi distribution"),
])
def test_distribution_spec_errors(spec, match):
    with pytest.raises(ValueError, match=match):
        parse_distribution(spec, 2, small_pendulum())


def test_binomial_intervals_contain_the_fraction():
    for k, n in [(0, 10), (10, 10), (3, 10), (950, 1000)]:
        for lo, hi in (clopper_pearson(k, n), wilson(k, n)):
            assert 0 <= lo <= k / n <= hi <= 1
    assert clopper_pearson(0, 10)[0] == 0 and clopper_pearson(10, 10)[1] == 1
    assert clopper_pearson(10, 10)[0] == pytest.approx(0.025 ** (1 / 10), rel=1e-6)  # (alpha/2)^(1/n)


# ------------------------------------------------------------------ the probability
@pytest.mark.parametrize("method", ["sampling", "verifier"])
def test_stable_pair_holds_at_a_point_and_broken_pair_fails(method):
    good = guarantee(hand_run(), Draws("point:0.1,0.05", 30), method, time_limit=10)
    assert good["holds"] == 30 and good["fraction"] == 1.0 and good["n_distinct"] == 1
    for key in ("interval_clopper_pearson", "interval_wilson"):
        lo, hi = good[key]
        assert lo <= good["fraction"] <= hi and lo > 0.8
    assert good["bound"] == pytest.approx((1 - 0.1) * (1 - 0.05))
    assert not good["bound_applies"]  # the lemma needs the uniform condition (sup over x inside the probability)
    if method == "sampling":
        assert guarantee(hand_run(loss="uniform"), Draws("point:0.1,0.05", 5), method)["bound_applies"]
    assert good["worst_sup_residual"] <= 0
    bad = guarantee(hand_run(sign=-1.0), Draws("point:0.1,0.05", 30), method, time_limit=10)
    assert bad["holds"] == 0 and bad["fraction"] == 0.0 and bad["worst_sup_residual"] > 0
    lo, hi = bad["interval_clopper_pearson"]
    assert lo == 0.0 <= hi < 0.2
    json.dumps(jsonable(good), allow_nan=False)


def test_guarantee_under_a_spread_distribution_and_radius_constants():
    run = hand_run()
    out = guarantee(run, Draws("normal:0,0;0.05,0.05", 40, seed=3), eps_bar=0.1, radius_constants=(2.0, 1.0, 2.0))
    assert out["n_distinct"] == 40 and 0 <= out["holds"] <= 40 and out["eps_bar"] == 0.1
    rg = out["radius_guarantee"]
    assert rg["r_N"] == pytest.approx(wasserstein_radius_guarantee(2.0, 1.0, 2.0, 2, 3, 0.1))
    assert rg["radius_sufficient"] == (1e-3 >= rg["r_N"])
    with pytest.raises(ValueError, match="eps_bar"):
        guarantee(run, Draws("point:0,0", 5), eps_bar=1.5)
    with pytest.raises(ValueError, match="c1 > 0"):
        guarantee(run, Draws("point:0,0", 5), radius_constants=(-1.0, 1.0, 2.0))
    with pytest.raises(ValueError, match="unknown method"):
        guarantee(run, Draws("point:0,0", 5), method="mc")


# ------------------------------------------------------------------ Lipschitz covering
def test_lipschitz_covering_finite_and_never_certified_when_violated():
    good = run_covering(hand_run(), spacing=0.02, compare_seconds=10).to_dict()
    for key in ("max_residual", "lipschitz_sound", "lipschitz_sampled", "covering_radius", "required_max_residual"):
        assert isinstance(good[key], float) and torch.isfinite(torch.tensor(good[key])), key
    assert good["lipschitz_sampled"] <= good["lipschitz_sound"] + 1e-9
    assert good["max_residual"] < 0 and good["verifier"]["status"] == "verified"
    assert good["covering_radius"] == pytest.approx(0.02 * 2 ** 0.5 / 2, rel=0.05)
    assert good["certified"] == (good["max_residual"] <= -good["lipschitz_sound"] * good["covering_radius"])
    assert not good["certified"] and 0 < good["spacing_needed"] < 0.02  # L rho is too large at this spacing
    finer = run_covering(hand_run(), spacing=0.005).to_dict()  # about 1e5 cells where the branch and bound needed ~500 boxes
    assert finer["certified"] and finer["max_residual"] <= finer["required_max_residual"]
    bad = run_covering(hand_run(sign=-1.0), spacing=0.05, compare_seconds=10).to_dict()
    assert bad["verifier"]["status"] == "violated" and not bad["certified"] and bad["max_residual"] > 0
    assert bad["spacing_needed"] is None
    json.dumps(jsonable(good), allow_nan=False)


# ------------------------------------------------------------------ CLI
def test_cli_guarantee_and_lipschitz(tmp_path, tiny_config):
    from drlyap.cli import main
    from drlyap.runs import save_run
    from handmade import plain_train

    save_run(tmp_path / "run", plain_train(tiny_config(iters=5, check_every=5), progress=False))
    runner = CliRunner()
    out = runner.invoke(main, ["guarantee", str(tmp_path / "run"), "--dist", "normal:0.1,0.05;0.02,0.01", "--n", "20",
                               "--radius-constants", "2,1,2", "--json"])
    assert out.exit_code == 0, out.output
    data = json.loads(out.stdout)
    assert data["n"] == 20 and 0 <= data["fraction"] <= 1 and "radius_guarantee" in data
    text = runner.invoke(main, ["guarantee", str(tmp_path / "run"), "--dist", "train", "--n", "10"])
    assert text.exit_code == 0 and "lemma bound" in text.output and "r = r_N(eps_bar)" in text.output
    bad = runner.invoke(main, ["guarantee", str(tmp_path / "run"), "--dist", "normal:1;2"])
    assert bad.exit_code != 0 and "needs 2 value" in bad.output
    lip = runner.invoke(main, ["lipschitz", str(tmp_path / "run"), "--spacing", "0.2", "--verify-time", "1", "--json"])
    assert lip.exit_code == 0, lip.output
    data = json.loads(lip.stdout)
    assert data["verifier"] is not None and not (data["certified"] and data["verifier"]["status"] == "violated")
    text = runner.invoke(main, ["lipschitz", str(tmp_path / "run"), "--spacing", "0.2", "--verify-time", "0"])
    assert text.exit_code == 0 and "covering certificate" in text.output
    missing = runner.invoke(main, ["lipschitz", str(tmp_path / "nope")])
    assert missing.exit_code != 0 and "does not exist" in missing.output
