"""Certificates of a region of attraction: ``roa-ball`` (V's decrease inside the delta-ball: the second-order cube and
the ring around it) and ``roa`` (the decrease outside the ball on {V <= c}), written by ``verify --roa`` and confirmed
by ``drlyap check`` with its own arithmetic."""

from __future__ import annotations

import json
import os

import pytest
import torch
from click.testing import CliRunner

from drlyap.checker.ball import hessian_negative
from drlyap.checker.model import Pair, Residual
from drlyap.cli import main
from drlyap.runs import load_run
from drlyap.runs.validate import load_weights
from handmade import linear_run_dir, small_pendulum, verified_json

SPEC = f"{os.path.dirname(__file__)}/handmade.py:small_pendulum"
XI = "0.1,0.05"


def _verify(run, *args):
    out = CliRunner().invoke(main, ["verify", str(run), "--system", SPEC, "--xi", XI, "--roa", "--json", *args])
    return verified_json(out)


def _check(run, *names):
    return CliRunner().invoke(main, ["check", str(run), "--system", SPEC, *[a for n in names for a in ("--name", n)]])


@pytest.mark.parametrize("delta, ring", [(0.1, False), (0.5, True)])
def test_verify_roa_writes_the_region_s_certificates_and_the_checker_confirms_them(tmp_path, delta, ring):
    run = linear_run_dir(tmp_path / "run", delta=delta)
    found = _verify(run)["roa"]
    assert found["certified"] and found["local"]["method"] == "second order"
    folder = run / "certificates"
    header = json.loads((folder / "roa-ball.json").read_text())
    claim = header["claim"]
    assert claim["region"]["level"] == found["level"] and claim["region"]["ball_of"] == delta
    assert claim["outer"] == "roa"  # the level search's c: the decrease on {V <= c} is proved again and written
    assert json.loads((folder / "roa.json").read_text())["claim"]["region"]["level"] == found["level"]
    assert (header["partition"] is not None) == ring == (folder / "roa-ball.npz").exists()
    if ring:  # the cube does not cover the ball: plain decrease with a decay > 0 between them
        assert max(claim["cube"]["half"]) < delta and claim["condition"]["decay_rate"] > 0
        assert claim["region"]["delta"] == min(claim["cube"]["half"])
    checked = _check(run)
    assert checked.exit_code == 0, checked.output
    assert "roa-ball: CHECKED" in checked.output and "roa: CHECKED" in checked.output
    assert "Hessian of Vdot on the cube is negative definite" in checked.output


def test_a_region_certificate_that_claims_more_than_it_proves_fails(tmp_path):
    run = linear_run_dir(tmp_path / "run", delta=0.5)
    _verify(run)
    folder = run / "certificates"
    path = folder / "roa-ball.json"
    original = path.read_text()

    def check_with(change) -> str:
        header = json.loads(original)
        change(header["claim"])
        path.write_text(json.dumps(header))
        out = _check(run, "roa-ball")
        assert out.exit_code == 1, out.output
        return out.output

    def inner_ball_wider(claim):  # the ring's inner ball no longer inside the cube
        claim["region"]["delta"] = 2 * max(claim["cube"]["half"])

    assert "inner ball" in check_with(inner_ball_wider)

    def no_decay(claim):  # the ring's decrease not strict
        claim["condition"]["decay_rate"] = 0.0

    assert "not strict" in check_with(no_decay)

    def outer_trained(claim):  # the trained condition is about X_delta, not about this model on {V <= c}
        claim["outer"] = "trained"

    assert "outer" in check_with(outer_trained)

    def other_level(claim):
        claim["region"]["level"] *= 1.5

    assert "level" in check_with(other_level)
    path.write_text(original)
    outer = json.loads((folder / "roa.json").read_text())
    outer["claim"]["condition"]["xi"] = [[0.2, 0.05]]  # the decrease outside the ball at another shift
    (folder / "roa.json").write_text(json.dumps(outer))
    assert "another shift" in _check(run, "roa-ball").output
    outer["claim"]["condition"] |= {"xi": [[0.1, 0.05]], "decay_rate": 0.0}  # Vdot <= 0 only: rest points possible
    (folder / "roa.json").write_text(json.dumps(outer))
    assert "not strict" in _check(run, "roa-ball").output
    metrics = json.loads((run / "metrics.json").read_text())
    metrics["certificate"]["roa"]["level"] *= 1.01  # a larger region than the files prove
    (run / "metrics.json").write_text(json.dumps(metrics))
    out = _check(run)
    assert out.exit_code == 1 and "roa-ball: FAILED" in out.output and "roa: FAILED" in out.output


def test_the_checker_s_hessian_bound_holds_at_sampled_states_and_refuses_a_rising_v(tmp_path):
    """Sound means sound: where the checker proves ``Vdot < 0`` on a cube by its Hessian enclosure, ``Vdot(z) <=
    bound |z|^2 / 2`` at dense states (the Taylor form it rests on); a controller that destabilises is refused."""
    run_dir = linear_run_dir(tmp_path / "run", delta=0.5)
    run = load_run(run_dir, small_pendulum())
    pair = Pair(load_weights(run_dir / "weights.pt"), float(run.config.alpha_hat), 2)
    claim = {"name": "plain", "model": "true", "xi": [[0.1, 0.05]], "decay_rate": 0.0, "exp_rate": 0.0}
    residual = Residual(claim, pair, run.system)
    half = torch.tensor([0.3, 0.5], dtype=torch.float64)
    proved, bound, why = hessian_negative(residual, half)
    assert proved and bound < 0, why
    g = torch.Generator().manual_seed(0)
    z = (2 * torch.rand(20_000, 2, generator=g, dtype=torch.float64) - 1) * half
    condition = run.true_condition([0.1, 0.05]).per_sample()
    with torch.no_grad():
        q = condition.components(condition.terms(run.loop.f64, z))[:, 0]
    assert bool((q <= bound * z.square().sum(-1) / 2 + 1e-12).all())
    too_big = torch.tensor([5.0, 5.0], dtype=torch.float64)  # where the pendulum's sin bends Vdot upward
    assert not hessian_negative(residual, too_big)[0]


def test_every_claim_of_one_verify_on_a_user_system_has_a_certificate_the_checker_confirms(tmp_path):
    run = linear_run_dir(tmp_path / "run", delta=0.5)
    found = _verify(run, "--max-radius")
    assert found["roa"]["certified"] and found["robustness"]["radius"]["radius"] > 0.01
    assert found["robustness"]["shift_box"]["s"] > 0
    names = {p.stem for p in (run / "certificates").glob("*.json") if not p.stem.endswith(".check")}
    assert names == {"trained", "true-model", "roa", "roa-ball", "radius", "shift-box"}
    checked = _check(run)
    assert checked.exit_code == 0, checked.output
    assert sorted(line.split(":")[0] for line in checked.output.splitlines() if ": CHECKED" in line) == sorted(names)


def test_a_certified_region_without_a_certificate_file_says_so():
    from drlyap.render import unwritten_region_line
    from drlyap.verification import RegionOfAttraction
    from drlyap.verification.roa_steps import BandRegion

    band = RegionOfAttraction(level=0.04, kind="region of attraction", certified=True, local=BandRegion(proved=True))
    assert "(band route) did not all hold again" in unwritten_region_line(band, [])
    assert "(band route)" in unwritten_region_line(band, ["RUN/certificates/roa-ball.json"])  # band writes roa
    assert unwritten_region_line(band, ["RUN/certificates/roa.json"]) is None
    assert unwritten_region_line(RegionOfAttraction(level=0.0), []) is None  # nothing certified, nothing to say


def test_a_run_saved_without_a_verdict_stays_readable_after_verify(tmp_path):
    """A pair trained by ``fit`` and saved has no verdict in ``metrics.json``; ``verify --roa`` keeps its region there
    beside a "not checked" verdict on the trained condition, so the run still loads."""
    run = linear_run_dir(tmp_path / "run", delta=0.2)
    metrics_path = run / "metrics.json"
    metrics = json.loads(metrics_path.read_text())
    del metrics["certificate"]  # as `save_run` writes a `fit` result
    metrics_path.write_text(json.dumps(metrics))
    _verify(run)
    kept = json.loads(metrics_path.read_text())["certificate"]
    assert kept["status"] == "not checked" and kept["roa"]["certified"]
    assert load_run(run, system=small_pendulum()).metrics["certificate"]["roa"]["certified"]


def test_a_region_at_a_shift_may_ask_a_smaller_decay_and_its_certificates_state_it(tmp_path):
    """``--roa-rate``: the true model's decrease at the shift and its region ask ``Vdot + alpha V <= 0`` with the
    alpha given (any alpha > 0 is strict); the certificates state that alpha, metrics.json reports it, and the checker
    confirms them. Here the run's alpha 0.5 fails a little way out, and asking 0.01 certifies far more of the box."""
    run = linear_run_dir(tmp_path / "run", delta=0.1, exp_rate=0.5)
    own = _verify(run)["roa"]
    found = _verify(run, "--roa-rate", "0.01")
    assert found["roa_rate"] == 0.01 and found["roa"]["certified"]
    assert own["limited_by"] == "unverified box at minimum size" and own["share_of_box"] < 0.05
    assert found["roa"]["share_of_box"] > 0.5 and found["roa"]["level"] > 10 * own["level"]
    folder = run / "certificates"
    for name in ("true-model", "roa"):
        assert json.loads((folder / f"{name}.json").read_text())["claim"]["condition"]["exp_rate"] == 0.01
    reported = json.loads((run / "metrics.json").read_text())["certificate"]
    assert reported["roa"]["exp_rate"] == reported["true_model"]["exp_rate"] == 0.01
    checked = _check(run)
    assert checked.exit_code == 0, checked.output
    assert "roa: CHECKED" in checked.output and "true-model: CHECKED" in checked.output
    metrics = json.loads((run / "metrics.json").read_text())
    metrics["certificate"]["roa"]["exp_rate"] = 0.02  # a region reported with another decay than its certificate's
    (run / "metrics.json").write_text(json.dumps(metrics))
    refused = _check(run, "roa")
    assert refused.exit_code != 0 and "exp_rate" in refused.output


@pytest.mark.parametrize("args, message", [
    (["--roa-rate", "0.01"], "goes with --xi"),
    (["--roa", "--roa-rate", "0.01"], "goes with --xi"),
    (["--xi", XI, "--roa", "--roa-rate", "0"], "--roa-rate must be > 0"),
    (["--xi", XI, "--roa-rate", "nan"], "--roa-rate must be > 0"),
])
def test_roa_rate_is_refused_without_a_shift_or_when_not_positive(tmp_path, args, message):
    run = linear_run_dir(tmp_path / "run")
    out = CliRunner().invoke(main, ["verify", str(run), "--system", SPEC, *args])
    assert out.exit_code == 1 and message in out.output, out.output
