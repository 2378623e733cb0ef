"""Counterexample-guided training (drlyap.training.certified)."""

import json

import pytest
import torch
from click.testing import CliRunner

from drlyap.proof_settings import Budget, ProofConfig
from drlyap.records import ProofRound
from drlyap.regions import Region
from drlyap.systems import get_system
from drlyap.training.certified import CounterexampleSearch, collect_counterexamples, train_cegis
from drlyap.verification import ProofRules, falsify, verify_condition
from handmade import plain_train


def test_projection_lands_in_x_delta():
    system = get_system("pendulum")
    z = torch.tensor([[0.0, 0.1], [10.0, -20.0], [0.01, 0.0], [-3.0, 0.2]], dtype=torch.float64)
    p = Region.of(system, 0.5).project(z)
    lo, hi = system.local_box()
    assert bool((p >= lo).all() and (p <= hi).all() and (p.norm(dim=-1) >= 0.5).all())
    assert torch.equal(p[3], z[3])


def test_falsifier_and_collected_states_really_violate(tiny_config):
    result = plain_train(tiny_config(iters=10, check_every=10), progress=False)
    loop, cond = result.loop, result.condition
    cfg = result.config
    region = Region.of(result.system, cfg.delta)
    starts = region.sample(64, torch.Generator().manual_seed(1))
    before = loop.exact(cond, starts)
    found, values = falsify(loop, cond, region, starts, steps=10)
    assert bool((values >= before - 1e-12).all())  # never worse than the start
    assert torch.allclose(values, loop.exact(cond, found))
    assert bool((found.norm(dim=-1) >= cfg.delta).all())
    ver = verify_condition(loop, cond, region, Budget(seconds=1.0), rules=ProofRules(keep_boxes=50))
    assert ver.status != "verified"
    got = collect_counterexamples(loop, cond, region, ver, torch.Generator().manual_seed(0),
                                  CounterexampleSearch(n_random=64, steps=5))
    cex = got["counterexamples"]
    assert cex.shape[0] > 0
    assert bool((loop.exact(cond, cex) > 0).all())  # one condition object: training's and the verifier's
    assert got["neighbours"].shape[0] == 3 * cex.shape[0]


def test_tiny_cegis_run_records_rounds_and_saves_metrics(tmp_path, tiny_config):
    from drlyap.runs import load_run, save_run

    system = get_system("pendulum")
    cfg = tiny_config(iters=20, check_every=20).resolved(system)
    proof = ProofConfig(rounds=2, time_limit=1.5, iters_per_round=10, falsifier_starts=64, falsifier_steps=5,
                        max_extra=300).resolved(system)
    result, rounds = train_cegis(cfg, system, proof, progress=False)
    assert 1 <= len(rounds) <= 3 and [r.round for r in rounds] == list(range(len(rounds)))
    assert result.metrics["cegis"]["rounds"] == [r.to_dict() for r in rounds]
    assert [ProofRound.from_dict(r.to_dict()).to_dict() for r in rounds] == [r.to_dict() for r in rounds]
    first = rounds[0]
    if not first.verified:  # a 20-iteration pair is never verified in practice
        assert first.added["counterexamples_added"] > 0 and first.added["extra_states"] <= 300
        # the counterexamples violate the condition of the pair they were found for (training is deterministic)
        again = plain_train(cfg, progress=False)
        res = again.loop.exact(again.condition, first.counterexamples)
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
    # the training's record, typed: the same from the result and from the run directory, rounds included
    record = run.record
    assert record == result.record and record.proved_in_rounds
    assert [r.to_dict() for r in record.rounds] == [r.to_dict() for r in rounds]  # kept without counterexamples
    assert (record.total_iterations, record.returned_round) == (cegis["total_iterations"], cegis["returned_round"])
    assert record.iterations == saved["iterations"] and record.final_proof == saved["cegis"]["final"]
    run.keep({"sweep": {"success": 1.0}})
    run.keep({"roa": {"level": 1.0}}, certificate=True)
    again = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert again["sweep"] == {"success": 1.0} and again["certificate"]["roa"] == {"level": 1.0}


def test_cegis_rejects_bad_arguments_before_training(tiny_config):
    system = get_system("pendulum")
    proof = ProofConfig(rounds=1).resolved(system)
    with pytest.raises(ValueError, match="per-state"):
        train_cegis(tiny_config(iters=5, check_every=5, loss="uniform").resolved(system), system, proof, progress=False)
    with pytest.raises(ValueError, match="iters_per_round"):
        ProofConfig(rounds=1, iters_per_round=0).resolved(system)
    with pytest.raises(ValueError, match="rounds"):
        ProofConfig(rounds=-1).resolved(system)
    with pytest.raises(ValueError, match="resolve"):
        train_cegis(tiny_config(iters=5, check_every=5).resolved(system), system, ProofConfig(), progress=False)


def test_cli_train_proves_by_default(tmp_path):
    from drlyap.cli import main

    runner = CliRunner()
    out = runner.invoke(main, ["train", "pendulum", "--iters", "4", "--quiet", "--verify-rounds", "1",
                               "--verify-time", "1", "--out", str(tmp_path / "run")])
    assert out.exit_code == 0, out.output
    assert "proof round 0:" in out.output and "proof round 1:" in out.output
    assert "; retraining round 1 of at most 1 (2 iterations from this pair) on " in out.output  # the next phase named
    if "proof round 1: VERIFIED" not in out.output:
        assert "no more retraining: its 1 retraining round(s) are spent" in out.output
    last = out.output.strip().splitlines()[-1]
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert "cegis" in metrics and metrics["cegis"]["max_rounds"] == 1
    status = metrics["certificate"]["status"]
    assert last.startswith("certificate: ") and (("NOT VERIFIED (" + status + ")") in last or status == "verified")
    plain = runner.invoke(main, ["train", "pendulum", "--iters", "4", "--quiet", "--no-verify", "--out", str(tmp_path / "p")])
    assert plain.exit_code == 0 and plain.output.strip().splitlines()[-1].startswith("certificate: NOT CHECKED")
    assert "cegis" not in json.loads((tmp_path / "p" / "metrics.json").read_text())
    bad = runner.invoke(main, ["train", "pendulum", "--verify-rounds", "-1", "--out", str(tmp_path / "x")])
    assert bad.exit_code != 0 and "--verify-rounds must be >= 0" in bad.output


def test_proof_rounds_can_end_at_their_first_violation(tiny_config):
    system = get_system("pendulum")
    cfg = tiny_config(iters=10, check_every=10).resolved(system)
    assert ProofConfig().resolved(system).stop_at_counterexample is False  # the system's default
    runs = {}
    for stop in (False, True):
        proof = ProofConfig(rounds=0, time_limit=30.0, max_boxes=20_000, stop_at_counterexample=stop).resolved(system)
        assert proof.stop_at_counterexample is stop
        _, rounds = train_cegis(cfg, system, proof, progress=False)
        runs[stop] = rounds[0].verification
    assert runs[False]["status"] == runs[True]["status"] == "violated"  # a 10-iteration pair
    assert runs[True]["stopped"] == "counterexample" and runs[False]["stopped"] != "counterexample"
    assert runs[True]["boxes_processed"] < runs[False]["boxes_processed"]
    assert runs[True]["verified_fraction"] <= runs[False]["verified_fraction"]


def test_a_retraining_that_returns_its_starting_pair_is_said_so():
    """A retraining round whose loss is 0 on every state it draws (a pair holding the condition with its margin) returns
    the pair it started from: its round is marked ``unchanged`` and its line says so; a retraining that moves the
    weights is not marked."""
    from drlyap.config import TrainConfig
    from drlyap.render import proof_round_line
    from drlyap.training import train
    from handmade import linear_pair, small_pendulum

    system = small_pendulum()
    fields = dict(system="small-pendulum", method="dr", n_states=64, iters=20, check_every=10, lyapunov_hidden=[2],
                  lyapunov_out=2, controller_hidden=[1], alpha_hat=1e-3, decay_rate=0.05, wasserstein_radius=0.01,
                  risk_level=0.3, delta=0.2, xi_samples=[[0.02, 0.01], [-0.03, 0.0], [0.05, -0.02]], seed=0)
    # too few boxes to prove: a retraining round follows; on the states alone (the open boxes' bound would move it)
    proof = ProofConfig(rounds=1, max_boxes=10, box_weight=0.0)
    for init, unchanged in ((linear_pair(system), True), (None, False)):
        lines: list[str] = []
        result = train(TrainConfig(**fields), system, proof, progress=False, init=init, warn=False,
                       log=lambda entry, lines=lines: lines.append(proof_round_line(entry)))
        last = result.metrics["cegis"]["rounds"][-1]
        assert last["round"] == 1 and last.get("unchanged", False) is unchanged
        assert ("left the pair unchanged" in lines[-1]) is unchanged
        assert ProofRound.from_dict(last).unchanged is unchanged and ProofRound.from_dict(last).to_dict() == last


def test_retraining_the_controller_only_keeps_v(tiny_config):
    """``retrain="controller"``: every retraining round keeps V as the first fit left it (so its sets stay where that
    fit put them) and trains the controller; ``"pair"`` trains both. A bad value is refused when resolved."""
    system = get_system("pendulum")
    cfg = tiny_config(iters=20, check_every=20).resolved(system)
    first = plain_train(cfg, progress=False)
    assert ProofConfig().resolved(system).retrain == "pair"  # the system's default
    pairs = {}
    for retrain in ("pair", "controller"):
        proof = ProofConfig(rounds=1, time_limit=1.0, max_boxes=2_000, iters_per_round=10, falsifier_starts=64,
                            falsifier_steps=5, retrain=retrain).resolved(system)
        result, rounds = train_cegis(cfg, system, proof, progress=False)
        assert len(rounds) == 2 and not rounds[1].unchanged  # a retraining round ran and moved the weights
        pairs[retrain] = result
    for retrain, result in pairs.items():
        assert result.metrics["cegis"]["returned_round"] == 1  # the retrained pair (ranked above round 0's here)
        v_same = all(torch.equal(a, b) for a, b in zip(first.lyapunov.state_dict().values(),
                                                         result.lyapunov.state_dict().values()))
        assert v_same is (retrain == "controller")
        assert all(p.requires_grad for p in result.lyapunov.parameters())  # V trainable again afterwards
    with pytest.raises(ValueError, match="retrain = 'v'"):
        ProofConfig(retrain="v").resolved(system)


def test_an_interrupted_train_resumes_without_training_again(tmp_path, monkeypatch):
    """Ctrl-C in the second round's proof, then the same command: the fits already done are taken from the checkpoints
    (the command says so), the proof resumes, and the run is bit for bit the uninterrupted one's."""
    import drlyap.verification.bounding as bounding
    from drlyap.cli import main

    args = ["train", "pendulum", "--iters", "4", "--verify-rounds", "1", "--verify-time", "600", "--verify-boxes",
            "6000"]
    whole = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "whole")])
    assert whole.exit_code == 0, whole.output
    assert "proof round 1:" in whole.output
    calls = {"n": 0}
    bound = bounding.ConditionJob.__call__

    def interrupted(self, lo, hi):
        calls["n"] += 1
        if calls["n"] == 4:  # the first proof takes two batches at most of these 6,000 boxes: this is round 1's
            raise KeyboardInterrupt
        return bound(self, lo, hi)

    monkeypatch.setattr(bounding.ConditionJob, "__call__", interrupted)
    out = tmp_path / "run"
    first = CliRunner().invoke(main, [*args, "--out", str(out)])
    assert first.exit_code == 130, first.output
    monkeypatch.setattr(bounding.ConditionJob, "__call__", bound)
    again = CliRunner().invoke(main, [*args, "--out", str(out)])
    assert again.exit_code == 0, again.output
    assert again.output.count("taken from the checkpoint, not trained again") >= 1
    assert (out / "weights.pt").read_bytes() == (tmp_path / "whole" / "weights.pt").read_bytes()
