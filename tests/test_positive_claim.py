"""The ``positive`` claim (``drlyap verify RUN --claim positive``): V > 0 on X_delta, proved by name through its kind
module alone. Its bound is checked against dense sampling, a V that is negative somewhere is found violated and gets
no certificate, and the checker re-proves the certificate and refuses forged ones."""

import dataclasses
import json
import os

import torch

from drlyap.claims.registry import CERTIFICATES, claim_sentence
from drlyap.networks import QuadraticLyapunov
from drlyap.proof_settings import ProofConfig
from drlyap.runs import load_run
from drlyap.workflows.claim import provable_claims, prove_claim
from handmade import check_cli, linear_run_dir, small_pendulum

SPEC = f"{os.path.dirname(__file__)}/handmade.py:small_pendulum"
PROOF = ProofConfig(max_boxes=20_000, time_limit=600.0)


def _proved(tmp_path):
    run = load_run(linear_run_dir(tmp_path / "run"), system=small_pendulum())
    return run, prove_claim(run, "positive", PROOF)


def test_positive_is_proved_by_name_and_its_bound_holds_on_dense_samples(tmp_path):
    assert "positive" in CERTIFICATES and provable_claims() == ("positive",)
    run, found = _proved(tmp_path)
    assert found.status == "verified" and found.certificate is not None
    lower = found.numbers["lower"]
    assert 0 < lower <= found.numbers["least_sampled"]
    lo, hi = run.system.local_box()
    z = lo + (hi - lo) * torch.rand(200_000, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    z = z[z.norm(dim=-1) >= run.config.delta]
    with torch.no_grad():
        v = run.loop.lyapunov(z.to(torch.float32)).double()
    assert float(v.min()) >= lower * (1 - 1e-5), (float(v.min()), lower)
    header = json.loads(open(found.certificate).read())
    assert header["partition"] is None and header["claim"]["condition"] is None
    assert header["claim"]["statement"] == claim_sentence(header["claim"]) == found.sentence
    assert "V > 0 at every state of the state box minus the open ball ||x - x*|| < 0.1" in found.sentence


def test_the_checker_re_proves_it_and_refuses_forged_ones(tmp_path):
    run, found = _proved(tmp_path)
    out = check_cli(run.path, SPEC, "positive")
    assert out.exit_code == 0 and "positive: CHECKED - V > 0 at every state" in out.output, out.output
    path = run.path / "certificates" / "positive.json"
    header = json.loads(path.read_text())
    for forge, why in ((lambda c: c["region"].update(level=1.0), "states no level or condition"),
                       (lambda c: c.update(condition={"name": "plain", "xi": [[0.0, 0.0]]}), "states no level or"),
                       (lambda c: c["region"].update(ball_of=0.1), "make no kind of claim")):
        forged = json.loads(json.dumps(header))
        forge(forged["claim"])
        path.write_text(json.dumps(forged))
        out = check_cli(run.path, SPEC, "positive")
        assert out.exit_code != 0 and why in out.output, out.output


def test_a_v_negative_somewhere_is_violated_and_gets_no_certificate(tmp_path):
    run = load_run(linear_run_dir(tmp_path / "run"), system=small_pendulum())
    saddle = dataclasses.replace(run, lyapunov_net=QuadraticLyapunov(torch.diag(torch.tensor([1.0, -0.5]))))
    found = prove_claim(saddle, "positive", PROOF)
    assert found.status == "violated" and found.certificate is None and found.numbers["least_sampled"] <= 0
    assert not (run.path / "certificates" / "positive.json").exists()


def test_an_imported_pair_s_v_is_proved_positive_and_checked(tmp_path):
    from drlyap.runs import load_imported_run
    from handmade import export_and_import

    imported = export_and_import(linear_run_dir(tmp_path / "run"), SPEC, tmp_path)
    found = prove_claim(load_imported_run(imported, small_pendulum()), "positive", PROOF)
    assert found.status == "verified", found
    out = check_cli(imported, SPEC, "positive")
    assert out.exit_code == 0 and "positive: CHECKED" in out.output, out.output


def test_the_command_proves_it_and_says_so(tmp_path):
    from click.testing import CliRunner

    from drlyap.cli import main

    run = linear_run_dir(tmp_path / "run")
    out = CliRunner().invoke(main, ["verify", str(run), "--system", SPEC, "--claim", "positive", "--json"])
    data = json.loads(out.stdout)
    assert out.exit_code == 0 and data["outcome"] == "verified", out.output
    assert data["claims"]["positive"]["numbers"]["lower"] > 0
    out = CliRunner().invoke(main, ["verify", str(run), "--system", SPEC, "--claim", "positive", "--roa"])
    assert out.exit_code == 1 and "--claim proves that claim alone" in out.output, out.output
