"""A run's certificates, its ``metrics.json`` and the ``drlyap check`` line ``drlyap verify`` prints stay consistent
under any sequence of ``verify`` calls: at other shifts, with and without ``--roa``, ``--roa-rate``, ``--delta``,
``--uniform`` and ``--max-radius``. After each call the check line it printed (``drlyap check RUN --system SPEC``
where it printed none) confirms every certificate the run holds, and ``metrics.json`` reports what they state: the
shift of the ``true-model`` certificate, and the region (and its shift) of the region's certificates."""

import json
import re
import shlex
from pathlib import Path

import pytest
from click.testing import CliRunner

from drlyap.cli import main
from drlyap.cli.verify import EXIT_CODES
from handmade import linear_run_dir

SPEC = f"{Path(__file__).parent / 'handmade.py'}:small_pendulum"
A, B = "0.1,0.05", "0.05,0.02"
BAD = "0.0,-3"  # a shift at which the decrease on the true model is violated
REGION = ("roa-ball", "roa", "ellipsoid", "practical")
TRAINED = "trained"  # a region about the trained condition (no shift)

# (verify's arguments, the shift of the true-model certificate after it, the region's shift: A, B, TRAINED or None
# for no region certificate)
STEPS = [
    (["--xi", A, "--roa"], A, A),
    (["--xi", A], A, A),  # the same shift: the region at it stands
    (["--xi", B], B, None),  # another shift: the region at A (and what rests on true-model) goes
    (["--roa"], B, TRAINED),
    (["--xi", A], A, TRAINED),  # a region about the trained condition stays
    (["--xi", B, "--roa"], B, B),
    (["--xi", B, "--roa", "--roa-rate", "0.5"], B, B),
    (["--xi", B], B, None),  # the default decay, not the region's 0.5
    (["--delta", "0.3", "--xi", A, "--roa"], B, None),  # a region at another delta has no certificate
    (["--xi", A, "--roa", "--uniform"], A, A),
    (["--max-radius"], A, A),
    (["--xi", B, "--delta", "0.3"], A, A),  # another delta, no region: nothing of the run's changes
    (["--xi", BAD], None, None),  # violated: no true-model certificate, and no region resting on the last one
    (["--xi", A, "--roa"], A, A),
]


def _present(run: Path) -> list[str]:
    return sorted(p.stem for p in (run / "certificates").glob("*.json") if not p.name.endswith(".check.json"))


def _claim(run: Path, name: str) -> dict:
    return json.loads((run / "certificates" / f"{name}.json").read_text())["claim"]


def _check_as_printed(run: Path, output: str) -> None:
    """Run the ``drlyap check`` line ``verify`` printed (the default one where it printed none): every certificate
    the run holds must be CHECKED."""
    hints = set(re.findall(r"re-check it with `drlyap (check [^`]*)`", output))
    assert len(hints) <= 1, output
    args = shlex.split(hints.pop()) if hints else ["check", str(run), "--system", SPEC]
    out = CliRunner().invoke(main, args)
    assert out.exit_code == 0, out.output
    assert sorted(re.findall(r"^([\w-]+): CHECKED", out.output, re.M)) == _present(run), out.output


def _assert_described(run: Path, shift: str | None, region_shift: str | None) -> None:
    """``metrics.json`` reports exactly what the certificates present state (and the step's expectations hold)."""
    config = json.loads((run / "config.json").read_text())
    metrics = json.loads((run / "metrics.json").read_text())
    reported = metrics.get("certificate") or {}
    present = _present(run)
    true_model = reported.get("true_model")
    if shift is None:
        assert "true-model" not in present
        assert true_model is None or true_model["status"] != "verified"
    else:
        assert "true-model" in present and true_model is not None and true_model["status"] == "verified"
        claim = _claim(run, "true-model")["condition"]
        assert claim["xi"] == [true_model["xi"]] == [[float(v) for v in shift.split(",")]]
        assert claim["exp_rate"] == true_model.get("exp_rate", float(config.get("exp_rate") or 0.0))
        # --roa-rate asks alpha V in place of the run's decay terms: no gamma ||z|| beside it
        assert claim["decay_rate"] == (0.0 if "exp_rate" in true_model else float(config.get("decay_rate") or 0.0))
    region = reported.get("roa")
    mine = [n for n in REGION if n in present]
    if region_shift is None:
        assert not mine
        assert region is None or region.get("delta") != config["delta"] or not region.get("certified")
        return
    assert "roa-ball" in mine and region is not None and region["certified"] and region["delta"] == config["delta"]
    if region_shift == TRAINED:
        assert region["xi"] is None
        samples = metrics["xi_train"]
    else:
        assert region["xi"] == true_model["xi"] == [float(v) for v in region_shift.split(",")]
        assert region.get("exp_rate") == true_model.get("exp_rate")  # the region rests on the true model's decay
        samples = [region["xi"]]
    for name in mine:
        claim = _claim(run, name)
        if name != "ellipsoid":
            assert claim["condition"]["xi"] == samples and claim["region"]["level"] == region["level"]
        if claim.get("outer") is not None:
            assert claim["outer"] in present
            assert _claim(run, claim["outer"])["condition"]["xi"] == samples


@pytest.mark.parametrize("overrides, at_level, outers_named", [
    ({}, False, {"roa"}), ({"roa_level": 0.2}, True, {"trained", "true-model"}), ({"roa_level": 0.2}, False, {"roa"}),
    ({"decay_rate": 0.0, "exp_rate": 0.3}, False, {"roa"})],
    ids=["own-proof", "trained-for-a-region", "above-the-trained-level", "alpha-v"])
def test_certificates_and_metrics_agree_after_every_verify(tmp_path, overrides, at_level, outers_named):
    """Without a level the region's decrease outside the ball is its own ``roa``; a run trained for a region searched
    at its level (``--roa-at-level``) has it proved by ``trained`` / ``true-model`` on ``{V <= 0.2}``, which
    ``roa-ball`` names; searched above it (the default), by its own ``roa`` again."""
    run = linear_run_dir(tmp_path / "run", delta=0.5, **overrides)
    outers = set()
    for args, shift, region_shift in STEPS:
        args = [*args, "--roa-at-level"] if at_level and "--roa" in args else args
        out = CliRunner().invoke(main, ["verify", str(run), "--system", SPEC, *args])
        assert out.exit_code in EXIT_CODES.values(), out.output
        _check_as_printed(run, out.output)
        _assert_described(run, shift, region_shift)
        if shift is not None and "exp_rate" in overrides:  # at a shift a strict decrease, 0.01 V, unless asked
            assert _claim(run, "true-model")["condition"]["exp_rate"] == (0.5 if "--roa-rate" in args else 0.01)
        if (run / "certificates" / "roa-ball.json").is_file():
            outers.add(_claim(run, "roa-ball")["outer"])
    assert outers == outers_named
    assert {"radius", "shift-box"} <= set(_present(run))


IMPORTED_STEPS = [
    (["--xi", A, "--roa"], A, A),
    (["--xi", B], B, None),
    (["--xi", B, "--roa"], B, B),
    (["--xi", B], B, B),  # the same shift, proved again: the region at it stands
    (["--delta", "0.3", "--xi", A, "--roa"], B, None),  # not the pair's delta: a region kept, no certificate
    (["--xi", BAD], None, None),
]


def test_an_imported_pair_s_certificates_and_metrics_agree_after_every_verify(tmp_path):
    pytest.importorskip("onnx")
    from handmade import export_and_import

    run = export_and_import(linear_run_dir(tmp_path / "run", delta=0.5), SPEC, tmp_path)
    for args, shift, region_shift in IMPORTED_STEPS:
        out = CliRunner().invoke(main, ["verify", str(run), "--system", SPEC, *args])
        assert out.exit_code in EXIT_CODES.values(), out.output
        if (run / "certificates").is_dir() and _present(run):
            _check_as_printed(run, out.output)
        _assert_described(run, shift, region_shift)
