"""The band claim (``drlyap verify --band C1,C2``): V decreases on ``c1 <= V <= c2`` of the whole box on the true model
at a shift, and the flow enters the box wherever ``V <= c2`` on its faces. Its proof is checked against dense
sampling of the band and of the leaves it leaves below the band, its certificate by the checker (forged ones
refused), and an imported V that is not least at x* (the field's sigmoid V) is proved as its file gives it."""

import json
import os

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from torch import nn

from drlyap.cli import main
from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import TrueDecrease
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.verification.band_claim import BandProof, prove_band
from drlyap.verification.partition import BELOW_LEVEL, PROVED
from handmade import check_cli, linear_pair, linear_run_dir, recheck, run_weights, small_pendulum, verified_json

F64 = torch.float64
XI = [0.1, 0.05]
SPEC = f"{os.path.dirname(__file__)}/handmade.py:small_pendulum"
C1, C2 = 0.01, 0.35  # above V's least value on the faces (0.205): the set is cut by the box, the flow enters there


@pytest.fixture(scope="module")
def loop():
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    return ClosedLoop(system, lyap, ctrl)


def _condition(rate: float = 0.01) -> TrueDecrease:
    return TrueDecrease(torch.tensor([XI], dtype=F64), 0.0, rate)


def _dense(system, count: int, seed: int) -> torch.Tensor:
    lo, hi = system.local_box()
    return lo + (hi - lo) * torch.rand(count, system.n, generator=torch.Generator().manual_seed(seed), dtype=F64)


def test_the_band_proof_holds_on_dense_samples_of_the_band_and_below_it(loop):
    found = prove_band(loop, _condition(), Region.of(loop.system, 0.0), C1, C2, Budget(seconds=30))
    assert found.verified and found.exit_min_lower > C2
    part = found.decrease.partition
    assert int((part.verdict == BELOW_LEVEL).sum()) > 0 and int((part.verdict == PROVED).sum()) > 0
    f64 = loop.f64
    z = _dense(loop.system, 200_000, seed=3)
    with torch.no_grad():
        v = f64.lyapunov(z)
        residual = f64.exact(_condition(), z)
    band = (v >= C1) & (v <= C2)
    assert int(band.sum()) > 10_000 and float(residual[band].max()) <= 0
    from drlyap.regions import box_grid

    blo, bhi = part.boxes(*box_grid(loop.system.local_box()[0], loop.system.local_box()[1], part.grid))
    below = (part.verdict == BELOW_LEVEL).nonzero().squeeze(-1)
    t = torch.rand(len(below), 64, 2, generator=torch.Generator().manual_seed(4), dtype=F64)
    inside = blo[below][:, None] + (bhi[below] - blo[below])[:, None] * t
    with torch.no_grad():
        assert float(f64.lyapunov(inside.reshape(-1, 2)).max()) < C1  # what the proof left below the band is
    again = BandProof.from_dict(json.loads(json.dumps(found.to_dict())))
    assert again.status == found.status and again.decrease.boxes_processed == found.decrease.boxes_processed


def test_a_falsifier_finds_no_state_of_a_proved_band_where_v_rises_and_finds_one_where_it_was_refused(loop):
    from drlyap.verification import falsify

    region = Region.of(loop.system, 0.0)
    z = _dense(loop.system, 20_000, seed=5)
    with torch.no_grad():
        v = loop.f64.lyapunov(z)
    starts = z[(v >= C1) & (v <= C2)][:1024]
    for rate, band_holds in ((0.01, True), (5.0, False)):
        if rate == 0.01:
            assert prove_band(loop, _condition(rate), region, C1, C2, Budget(seconds=30)).verified
        found, residual = falsify(loop, _condition(rate), region, starts, steps=60)
        with torch.no_grad():
            on_band = (loop.f64.lyapunov(found) >= C1) & (loop.f64.lyapunov(found) <= C2)
        assert bool((residual[on_band] <= 0).all()) == band_holds


def test_a_band_where_v_rises_is_violated_at_a_state_of_the_band(loop):
    found = prove_band(loop, _condition(rate=5.0), Region.of(loop.system, 0.0), C1, 0.2, Budget(seconds=30))
    assert found.status == "violated" and found.counterexample is not None
    z = loop.system.to_local(torch.tensor([found.counterexample], dtype=F64))
    with torch.no_grad():
        v = float(loop.f64.lyapunov(z)[0])
        assert float(loop.f64.exact(_condition(rate=5.0), z)[0]) > 0
    assert C1 <= v <= 0.2


def test_the_falsifier_of_an_unknown_band_confirms_only_rises_on_the_band(loop):
    from drlyap.verification.falsifier import confirmed_violations

    z = _dense(loop.system, 20_000, seed=6)
    with torch.no_grad():
        v, residual = loop.f64.lyapunov(z), loop.f64.exact(_condition(rate=5.0), z)
    region = Region.of(loop.system, 0.0)
    below, band = (v < C1) & (residual > 0), (v >= C1) & (v <= 0.2) & (residual > 0)
    assert int(below.sum()) > 100 and int(band.sum()) > 100
    assert bool(torch.isfinite(confirmed_violations(loop, _condition(5.0), region, z[below], 0.2)).all())
    assert not bool(torch.isfinite(confirmed_violations(loop, _condition(5.0), region, z[below], 0.2, C1)).any())
    assert bool(torch.isfinite(confirmed_violations(loop, _condition(5.0), region, z[band], 0.2, C1)).all())


def test_a_band_whose_set_the_flow_leaves_is_violated_on_the_faces(loop):
    found = prove_band(loop, _condition(), Region.of(loop.system, 0.0), C1, 1.0, Budget(seconds=30))
    assert found.status == "violated" and "leaves the box" in found.reason and found.exit_min_upper <= 1.0


def test_bad_levels_are_refused(loop):
    for low, high in ((0.2, 0.1), (0.0, 1.0), (0.1, float("nan"))):
        with pytest.raises(ValueError, match="0 < C1 < C2"):
            prove_band(loop, _condition(), Region.of(loop.system, 0.0), low, high)
    with pytest.raises(ValueError, match="alpha > 0"):
        prove_band(loop, _condition(rate=0.0), Region.of(loop.system, 0.0), C1, C2)


@pytest.fixture(scope="module")
def band_run(tmp_path_factory):
    """A small pendulum run with its band proved through the CLI: (run directory, the verify JSON)."""
    run = linear_run_dir(tmp_path_factory.mktemp("band") / "run")
    out = CliRunner().invoke(main, ["verify", str(run), "--system", SPEC, "--xi", ",".join(map(str, XI)),
                                    "--band", f"{C1},{C2}", "--json"])
    return run, verified_json(out)


def test_the_cli_band_is_written_as_a_certificate_the_checker_confirms(band_run):
    run, found = band_run
    assert found["band"]["status"] == "verified" and found["band"]["time_s"] > 0 and found["outcome"] == "verified"
    assert found["band"]["xi"] == XI and found["band"]["exp_rate"] == 0.01 and "true_model" not in found
    header = json.loads((run / "certificates" / "band.json").read_text())
    assert header["claim"]["band"] == {"low": C1} and header["claim"]["region"]["level"] == C2
    assert header["claim"]["region"]["delta"] == 0 and header["claim"]["faces"] == "inward"
    assert "reach {V <= 0.01}" in header["claim"]["statement"]
    out = check_cli(run, SPEC, "band")
    assert out.exit_code == 0 and "band: CHECKED" in out.output, out.output


def _recheck(run, header_change=None, arrays_change=None):
    return recheck(run, "band", small_pendulum(), run_weights(run), header_change, arrays_change)


def test_a_forged_band_certificate_is_not_confirmed(band_run):
    run, _ = band_run
    assert _recheck(run).ok

    def lower_floor(header):  # a wider band than was proved: the leaves below it are not below the new floor
        header["claim"]["band"]["low"] = 1e-4

    def no_decay(header):  # a decrease that is not strict on the band
        header["claim"]["condition"]["exp_rate"] = 0.0

    def not_inward(header):
        del header["claim"]["faces"]

    def proved_as_below(arrays):  # a proved leaf said to lie below the band
        verdict = arrays["verdict"].copy()
        verdict[np.flatnonzero(verdict == PROVED)[-1]] = BELOW_LEVEL
        return arrays | {"verdict": verdict}

    assert any("not established on the leaves below the band" in f for f in _recheck(run, lower_floor).failures)
    assert any("alpha > 0" in f for f in _recheck(run, no_decay).failures)
    assert any("flow entering the box" in f for f in _recheck(run, not_inward).failures)
    assert not _recheck(run, arrays_change=proved_as_below).ok


def test_band_options_are_checked_before_any_proof(tmp_path):
    run = linear_run_dir(tmp_path / "run")
    for args, words in ((["--band", "0.2,0.1"], "0 < C1 < C2"), (["--band", "0.1"], "two levels"),
                        (["--band", "0.1,0.2", "--roa"], "proved apart")):
        out = CliRunner().invoke(main, ["verify", str(run), "--system", SPEC, *args])
        assert out.exit_code == 1 and words in out.output and "trained condition" not in out.output, out.output


class _Controller(nn.Module):
    def __init__(self):
        super().__init__()
        self.gain = nn.Linear(2, 1, bias=False)
        with torch.no_grad():
            self.gain.weight.copy_(torch.tensor([[-13.81, -3.87]]))

    def forward(self, x):
        return torch.clamp(self.gain(x), -15.0, 15.0)


class _SigmoidLyapunov(nn.Module):
    """V = sigmoid(10 x'Px + b.x - 4), P the closed loop's Lyapunov matrix: about 0.018 at x*, least beside it (b
    moves the minimum), as the field's pairs."""

    def __init__(self):
        super().__init__()
        self.root = nn.Linear(2, 2, bias=False)
        self.slope = nn.Linear(2, 1, bias=False)
        with torch.no_grad():
            self.root.weight.copy_(torch.linalg.cholesky(10 * torch.tensor([[1.125, 0.125], [0.125, 0.15625]])).T)
            self.slope.weight.copy_(torch.tensor([[0.05, 0.0]]))

    def forward(self, x):
        return torch.sigmoid((self.root(x) ** 2).sum(-1) + self.slope(x)[:, 0] - 4.0)


def _onnx(module, path):
    torch.onnx.export(module.eval(), (torch.zeros(1, 2),), str(path), dynamo=False, input_names=["x"],
                      output_names=["y"], dynamic_axes={"x": {0: "batch"}, "y": {0: "batch"}})


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_an_imported_v_not_least_at_x_star_is_taken_as_given_for_a_band(tmp_path):
    pytest.importorskip("onnx")
    _onnx(_Controller(), tmp_path / "controller.onnx")
    _onnx(_SigmoidLyapunov(), tmp_path / "lyapunov.onnx")
    runner, out = CliRunner(), tmp_path / "imported"
    done = runner.invoke(main, ["import", SPEC, "--controller", str(tmp_path / "controller.onnx"),
                                "--lyapunov", str(tmp_path / "lyapunov.onnx"), "--out", str(out)])
    assert done.exit_code == 0 and "not pinned at x*" in done.output and "--band" in done.output, done.output
    refused = runner.invoke(main, ["verify", str(out), "--system", SPEC, "--xi", "0.1,0.05"])
    assert refused.exit_code == 1 and "--band C1,C2" in refused.output, refused.output
    found = verified_json(runner.invoke(main, ["verify", str(out), "--system", SPEC, "--xi", "0.1,0.05", "--band",
                                               "0.03,0.1", "--json"]))
    assert found["band"]["status"] == "verified", found["band"]
    checked = check_cli(out, SPEC)
    assert checked.exit_code == 0 and "band: CHECKED" in checked.output, checked.output
    header = json.loads((out / "certificates" / "band.json").read_text())
    del header["claim"]["band"]  # the same boxes as a claim on {V <= c2}: nothing of it is checked for such a V
    (out / "certificates" / "band.json").write_text(json.dumps(header))
    refused = check_cli(out, SPEC)
    assert refused.exit_code != 0 and "a 'band' certificate does not state a condition claim" in refused.output
    (out / "certificates" / "band.json").rename(out / "certificates" / "true-model.json")  # named as such a claim
    refused = check_cli(out, SPEC, "true-model")
    assert refused.exit_code != 0 and "only a band claim is checked" in refused.output, refused.output
