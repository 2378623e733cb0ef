"""Counterexample-guided training (drlyap.cegis)."""

import json

import pytest
import torch
from click.testing import CliRunner

from drlyap.cegis import collect_counterexamples, falsify, train_cegis
from drlyap.regions import Region
from drlyap.systems import get_system
from drlyap.training import train
from drlyap.verification import verify_condition


def test_projection_lands_in_x_delta():
    system = get_system("pendulum")
    z = torch.tensor([[0.0, 0.1], [10.0, -20.0], [0.01, 0.0], [-3.0, 0.2]], dtype=torch.float64)
    p = Region.of(system, 0.5).project(z)
    lo, hi = system.local_box()
    assert bool((p >= lo).all() and (p <= hi).all() and (p.norm(dim=-1) >= 0.5).all())
    assert torch.equal(p[3], z[3])


def test_falsifier_and_collected_states_really_violate(tiny_config):
    result = train(tiny_config(iters=10, check_every=10), progress=False)
    system, lyap, ctrl, cond = result.system, result.lyapunov, result.controller, result.condition
    cfg = result.config
    region = Region.of(system, cfg.delta)
    starts = region.sample(64, torch.Generator().manual_seed(1))
    before = cond.exact(system, lyap, ctrl, starts)
    found, values = falsify(system, lyap, ctrl, cond, region, starts, steps=10)
    assert bool((values >= before - 1e-12).all())  # never worse than the start
    assert torch.allclose(values, cond.exact(system, lyap, ctrl, found))
    assert bool((found.norm(dim=-1) >= cfg.delta).all())
    ver = verify_condition(system, lyap, ctrl, cond, region, time_limit=1.0, keep_boxes=50).to_dict()
    assert ver["status"] != "verified"
    got = collect_counterexamples(system, lyap, ctrl, cond, region, ver, torch.Generator().manual_seed(0),
                                  n_random=64, steps=5)
    cex = got["counterexamples"]
    assert cex.shape[0] > 0
    assert bool((cond.exact(system, lyap, ctrl, cex) > 0).all())  # one condition object: training's and the verifier's
    assert got["neighbours"].shape[0] == 3 * cex.shape[0]


def test_tiny_cegis_run_records_rounds_and_saves_metrics(tmp_path, tiny_config):
    from drlyap.rundir import load_run, save_run

    cfg = tiny_config(iters=20, check_every=20)
    result, rounds = train_cegis(cfg, rounds=2, verify_time_limit=1.5, progress=False, iters_per_round=10,
                                 n_random=64, falsifier_steps=5, max_extra=300)
    assert 1 <= len(rounds) <= 3 and [r["round"] for r in rounds] == list(range(len(rounds)))
    first = rounds[0]
    if not first["verified"]:  # a 20-iteration pair is never verified in practice
        assert first["counterexamples_added"] > 0 and first["extra_states"] <= 300
        # the counterexamples violate the condition of the pair they were found for (training is deterministic)
        again = train(cfg, progress=False)
        res = again.condition.exact(again.system, again.lyapunov, again.controller, first["counterexamples"])
        assert bool((res > 0).all())
    cegis = result.metrics["cegis"]
    assert len(cegis["rounds"]) == len(rounds) and cegis["final"]["status"] in ("verified", "violated", "unknown")
    assert cegis["verified"] == (cegis["final"]["status"] == "verified")
    assert result.config.iters == 20 and result.config.xi_samples is None  # the first run's config
    its = [h["iteration"] for h in result.history]
    assert its == sorted(set(its)) and its[-1] <= cegis["total_iterations"]
    save_run(tmp_path / "run", result)
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert saved["cegis"]["rounds"][0]["round"] == 0 and "counterexamples" not in saved["cegis"]["rounds"][0]
    run = load_run(tmp_path / "run")
    assert torch.allclose(run.xi_samples, result.xi_samples)


def test_cegis_rejects_bad_arguments_before_training(tiny_config):
    with pytest.raises(ValueError, match="per-state"):
        train_cegis(tiny_config(iters=5, check_every=5, loss="uniform"), rounds=1, progress=False)
    with pytest.raises(ValueError, match="iters_per_round"):
        train_cegis(tiny_config(iters=5, check_every=5), rounds=1, progress=False, iters_per_round=0)
    with pytest.raises(ValueError, match="rounds"):
        train_cegis(tiny_config(iters=5, check_every=5), rounds=-1, progress=False)


def test_cli_train_proves_by_default(tmp_path):
    from drlyap.cli import main

    runner = CliRunner()
    out = runner.invoke(main, ["train", "pendulum", "--iters", "4", "--quiet", "--verify-rounds", "1",
                               "--verify-time", "1", "--out", str(tmp_path / "run")])
    assert out.exit_code == 0, out.output
    assert "proof round 0:" in out.output and "proof round 1:" in out.output
    last = out.output.strip().splitlines()[-1]
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert "cegis" in metrics and metrics["cegis"]["max_rounds"] == 1
    status = metrics["certificate"]["status"]
    assert last.startswith("certificate: ") and (("NOT VERIFIED (" + status + ")") in last or status == "verified")
    plain = runner.invoke(main, ["train", "pendulum", "--iters", "4", "--quiet", "--no-verify", "--out", str(tmp_path / "p")])
    assert plain.exit_code == 0 and plain.output.strip().splitlines()[-1].startswith("certificate: NOT CHECKED")
    assert "cegis" not in json.loads((tmp_path / "p" / "metrics.json").read_text())
    bad = runner.invoke(main, ["train", "pendulum", "--verify-rounds", "-1", "--out", str(tmp_path / "x")])
    assert bad.exit_code != 0 and "verify_rounds" in bad.output
