"""The DR uniform condition's certificate: the verifier keeps the boxes its margin was bounded on, the checker
bounds every component's supremum over them with its own arithmetic, and a claim that does not hold is refused."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from drlyap.checker.arith import Iv
from drlyap.checker.model import Pair, Residual
from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import DRUniform
from drlyap.regions import Region
from drlyap.runs.certificates import PairFiles, Stated, condition_claim, write_certificate
from drlyap.verification import Budget, uniform_margin
from handmade import linear_pair, linear_run_dir, recheck, small_pendulum

F64 = torch.float64
XI = torch.tensor([[0.0, 0.0], [0.05, 0.01], [-0.03, 0.02]], dtype=F64)


@pytest.fixture(scope="module")
def margin(tmp_path_factory):
    """A verified uniform margin of the hand-made linear pair, written as a certificate."""
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    loop = ClosedLoop(system, lyap, ctrl)
    condition = DRUniform(1e-4, 0.1, XI, decay_rate=0.05)
    region = Region.of(system, 0.2)
    found = uniform_margin(loop, condition, region, Budget(seconds=1e9, boxes=200_000), keep_partition=True)
    assert found.verified and found.partition is not None
    folder = tmp_path_factory.mktemp("uniform")
    weights = {"lyapunov": lyap.state_dict(), "controller": ctrl.state_dict()}
    torch.save(weights, folder / "weights.pt")
    write_certificate(folder, "uniform", found, Stated(condition, region), system,
                      PairFiles(folder / "weights.pt", lyap.alpha_hat))
    return {"system": system, "folder": folder, "weights": weights, "margin": found, "loop": loop,
            "condition": condition, "region": region}


def check(m, header_change=None, arrays_change=None):
    return recheck(m["folder"], "uniform", m["system"], m["weights"], header_change, arrays_change)


def test_an_unverified_margin_keeps_no_boxes(margin):
    strong = DRUniform(0.05, 0.1, XI, decay_rate=0.05)
    found = uniform_margin(margin["loop"], strong, margin["region"], Budget(seconds=1e9, boxes=50_000),
                           keep_partition=True)
    assert found.status == "violated" and found.partition is None


def test_the_checker_confirms_the_margin_on_every_leaf(margin):
    result = check(margin)
    assert result.ok, result.failures
    counts = margin["margin"].partition.counts()
    assert result.proved == counts["proved"] and result.inside_ball == counts["inside ball"]
    assert "DR uniform condition (r = 0.0001, eps = 0.1, 3 samples of xi" in result.claim
    assert "as one inequality" in result.claim


def test_the_checkers_components_enclose_the_conditions(margin):
    loop, condition = margin["loop"], margin["condition"]
    residual = Residual(condition_claim(condition), Pair(margin["weights"], loop.lyapunov.alpha_hat, 2),
                        margin["system"])
    z = margin["region"].sample(300, torch.Generator().manual_seed(0))
    mine = residual.components(Iv.point(z))
    theirs = condition.components(condition.terms(loop.f64, z)).detach()
    assert bool((mine.lo <= theirs + 1e-12).all() and (theirs <= mine.hi + 1e-12).all())


def test_the_margins_bounds_hold_at_dense_samples(margin):
    """The verifier's margin bound lies above the margin of the components' maxima over 20,000 states."""
    loop, condition = margin["loop"], margin["condition"]
    z = margin["region"].sample(20_000, torch.Generator().manual_seed(1))
    sampled = float(condition.margin(condition.components(condition.terms(loop.f64, z)).detach().amax(0)))
    found = margin["margin"]
    assert found.margin_lower <= found.margin_upper and sampled <= found.margin_upper
    assert sampled >= found.margin_upper - 1e-3


def test_a_larger_radius_than_proved_is_refused(margin):
    def stronger(header):
        header["claim"]["condition"]["wasserstein_radius"] = 0.05

    result = check(margin, header_change=stronger)
    assert not result.ok and "bound of the uniform margin" in result.failures[0]


def test_a_lowered_bound_and_a_leaf_moved_into_the_ball_are_refused(margin):
    def lower_one(arrays):
        arrays["bound"][int(np.flatnonzero(arrays["verdict"] == 1)[0])] = -1e6

    def into_ball(arrays):
        arrays["verdict"][int(np.flatnonzero(arrays["verdict"] == 1)[-1])] = 2

    result = check(margin, arrays_change=lower_one)
    assert not result.ok and "recorded bounds lie below" in result.failures[-1]
    result = check(margin, arrays_change=into_ball)
    assert not result.ok and "do not" in result.failures[0]


def test_verify_uniform_writes_a_certificate_that_check_confirms(tmp_path):
    from click.testing import CliRunner

    from drlyap.cli import main

    run = linear_run_dir(tmp_path / "run", delta=0.2, wasserstein_radius=1e-4, risk_level=0.1, xi_samples=XI.tolist())
    spec = f"{Path(__file__).parent / 'handmade.py'}:small_pendulum"
    runner = CliRunner()
    out = runner.invoke(main, ["verify", str(run), "--system", spec, "--uniform"])
    assert out.exit_code == 0, out.output
    assert "certificates/uniform.json" in out.output
    out = runner.invoke(main, ["check", str(run), "--system", spec, "--name", "uniform"])
    assert out.exit_code == 0 and "CHECKED" in out.output, out.output
    header = json.loads((run / "certificates" / "uniform.json").read_text())
    header["claim"]["condition"]["xi"] = header["claim"]["condition"]["xi"][:1]  # fewer samples than the run's
    (run / "certificates" / "uniform.json").write_text(json.dumps(header))
    out = runner.invoke(main, ["check", str(run), "--system", spec, "--name", "uniform"])
    assert out.exit_code == 1 and "not the run's uniform condition (xi" in out.output


def test_a_run_trained_on_the_uniform_condition_keeps_its_margin_as_the_trained_certificate(tmp_path):
    from click.testing import CliRunner

    from drlyap.checker import check_run
    from drlyap.cli import main

    system = small_pendulum()

    def prove(result):
        return uniform_margin(ClosedLoop(system, result.lyapunov, result.controller), result.condition,
                              Region.of(system, 0.2), Budget(seconds=1e9, boxes=200_000), keep_partition=True)

    run = linear_run_dir(tmp_path / "run", delta=0.2, prove=prove, loss="uniform", wasserstein_radius=1e-4,
                         risk_level=0.1, xi_samples=XI.tolist())
    assert (run / "certificates" / "trained.json").is_file()
    [checked] = check_run(run, system, names=["trained"])
    assert checked.ok, checked.failures
    spec = f"{Path(__file__).parent / 'handmade.py'}:small_pendulum"
    out = CliRunner().invoke(main, ["verify", str(run), "--system", spec])
    assert out.exit_code == 0, out.output
    assert "trained condition (DR uniform): VERIFIED; margin in [" in out.output
    assert "certificates/trained.json" in out.output


def test_the_margin_says_where_its_suprema_lie(margin):
    """``attained_at``: the states at which each component's lower bound was found; the components there are those
    lower bounds."""
    loop, condition, found = margin["loop"], margin["condition"], margin["margin"]
    at = torch.tensor(found.attained_at, dtype=F64)
    assert at.shape == (1 + XI.shape[0], 2) and bool(margin["region"].in_region(at).all())
    values = condition.components(condition.terms(loop.f64, at)).detach().diagonal()
    lower = torch.tensor([found.lipschitz_sup[0]] + [h[0] for h in found.h_sup], dtype=F64)
    assert torch.allclose(values, lower, rtol=1e-9, atol=1e-12)


def test_training_on_the_uniform_condition_has_proof_rounds_on_its_suprema(tiny_config):
    """A uniform run's rounds bound its margin and retrain on the states where the suprema lie; the returned pair's
    verdict is its round's margin, and every round's line reads."""
    import drlyap
    from drlyap.proof_settings import ProofConfig
    from drlyap.records import TrainingRecord
    from drlyap.render import proof_round_line

    lines = []
    result = drlyap.train(tiny_config(loss="uniform", iters=10, check_every=10),
                          proof=ProofConfig(rounds=1, time_limit=2.0, iters_per_round=5), progress=False, warn=False,
                          log=lambda entry: lines.append(proof_round_line(entry)))
    record = TrainingRecord.from_metrics(result.metrics)
    first = record.rounds[0]
    assert first.verification["condition"] == "DR uniform" and first.verified_fraction is None
    assert lines[0].startswith("  proof round 0: ") and "margin in [" in lines[0]
    assert not first.verified and len(record.rounds) == 2  # ten iterations do not prove it: one retraining round
    assert first.added["peaks_added"] == 1 + len(result.metrics["xi_train"])
    assert "states where its suprema lie" in lines[0]
    assert record.final_proof["condition"] == "DR uniform"
    assert result.metrics["certificate"]["status"] == record.final_proof["status"]


def test_a_uniform_run_certifies_a_region_on_the_decrease_at_each_sample_it_implies(tmp_path):
    """With eps N <= 1 the uniform condition implies plain decrease at every sample: `verify --roa` certifies a
    sublevel set of V on it, writes its certificates, and `check` confirms them as the run's."""
    from click.testing import CliRunner

    from drlyap.cli import main

    run = linear_run_dir(tmp_path / "run", delta=0.2, loss="uniform", wasserstein_radius=1e-4, risk_level=0.1,
                         xi_samples=XI.tolist())
    spec = f"{Path(__file__).parent / 'handmade.py'}:small_pendulum"
    runner = CliRunner()
    out = runner.invoke(main, ["verify", str(run), "--system", spec, "--roa"])
    assert out.exit_code == 0, out.output
    assert "region of attraction: CERTIFIED {V <=" in out.output and "design model at each training sample" in out.output
    assert "certificates/roa-ball.json" in out.output and "certificates/roa.json" in out.output
    out = runner.invoke(main, ["check", str(run), "--system", spec])
    assert out.exit_code == 0, out.output
    assert out.output.count("CHECKED") == 3  # trained (the margin), roa, roa-ball
