import json

import pytest
from click.testing import CliRunner

from drlyap.cli import main


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "run"
    result = CliRunner().invoke(main, ["train", "pendulum", "--method", "baseline", "--iters", "10", "--quiet", "--no-verify",
                                       "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "acceptance" in result.output and "V near x*: Vdot <=" in result.output
    return out


def test_every_command_has_help():
    runner = CliRunner()
    for args in ([], ["systems"], ["train"], ["evaluate"], ["reproduce"]):
        result = runner.invoke(main, [*args, "--help"])
        assert result.exit_code == 0 and "Usage" in result.output


def test_systems_lists_built_ins():
    result = CliRunner().invoke(main, ["systems", "--json"])
    names = {d["name"] for d in json.loads(result.stdout)["systems"]}  # one object, as every --json
    assert {"pendulum", "mountain-car"} <= names


def test_evaluate_json(run_dir):
    result = CliRunner().invoke(main, ["evaluate", str(run_dir), "--xi", "0.1,0.05", "--n-init", "5", "--horizon",
                                       "1", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["n"] == 5 and 0 <= data["n_success"] <= 5 and data["success_rate"] == data["n_success"] / 5


@pytest.mark.parametrize("args, message", [
    (["train", "nope", "--out", "x"], "unknown system 'nope'"),
    (["evaluate", "/nonexistent/run", "--xi", "0.1,0.05"], "does not exist"),
    (["train", "pendulum", "--eps", "2", "--iters", "1", "--out", "OUT"], "risk_level"),
    (["train", "pendulum", "--local-rate", "-1", "--iters", "1", "--out", "OUT"], "local_rate"),
    (["train", "pendulum", "--lyapunov-hidden", "40,0", "--out", "OUT"], "--lyapunov-hidden takes widths"),
])
def test_errors_name_the_problem(tmp_path, args, message):
    args = [str(tmp_path / "o") if a == "OUT" else a for a in args]
    result = CliRunner().invoke(main, args)
    assert result.exit_code != 0 and message in result.output
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("xi, message", [("0.1", "takes 2 xi value"), ("0.1,nan", "finite"), ("a,b", "numbers")])
def test_evaluate_rejects_bad_xi(run_dir, xi, message):
    result = CliRunner().invoke(main, ["evaluate", str(run_dir), "--xi", xi])
    assert result.exit_code != 0 and message in result.output


def test_train_refuses_to_overwrite(run_dir):
    result = CliRunner().invoke(main, ["train", "pendulum", "--iters", "1", "--out", str(run_dir)])
    assert result.exit_code != 0 and f"{run_dir} already exists; choose another --out or remove it" in result.output


def test_reproduce_end_to_end_writes_table_json_and_figures(tmp_path):
    from drlyap.workflows.reproduce import ReproduceSettings, reproduce

    out = tmp_path / "rep"
    settings = ReproduceSettings(seeds=[0], iters=2, n_more=4, sweep=(1, 2), verify=False, horizon=2.0)
    report = reproduce("pendulum", settings, out, progress=False, log=lambda s: None)
    assert {r["method"] for r in report["results"]} == {"baseline", "dr"}
    for r in report["results"]:
        assert r["paper_10"]["n"] == 10 and r["more_200"]["n"] == 4 and set(r["sweep_200"]) == {1, 2}
        assert (out / "seed0" / r["method"] / "run.json").is_file()
    assert (out / "report.md").is_file() and (out / "shift_sweep.png").is_file()
    assert (out / "seed0" / "figures" / "trajectories.png").is_file()
    assert (out / "seed0" / "figures" / "certificate_and_input.png").is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary leftovers
    table = (out / "report.md").read_text()
    header = next(line for line in table.splitlines() if line.startswith("| seed | method | 10 test states"))
    legend = next(line for line in table.splitlines() if line.startswith("acceptance: "))
    for column in ("acceptance", "Hurwitz", "other eq."):  # every column not defined elsewhere has its legend
        assert f"| {column} |" in header and f"{column}: " in legend
    from drlyap.kernels import describe, float_kernels

    kernels = float_kernels()  # what the digits were computed with, in the report and under its table
    assert report["float_kernels"] == kernels and f"float kernels: {describe(kernels)}" in table
    metrics = json.loads((out / "seed0" / "dr" / "metrics.json").read_text())
    assert metrics["float_kernels"] == kernels


def test_proved_shares_are_never_rounded_up_to_a_proof():
    from drlyap.io import proved_percent

    assert proved_percent(0.999996, verified=False) == "99.99%"  # rounded down: a lower bound, not "100.00%"
    assert proved_percent(0.998449, verified=False) == "99.84%"
    assert proved_percent(1.0, verified=False, decimals=4) == "> 99.9999%"  # a volume sum that reached 1.0
    assert proved_percent(1.0, verified=True) == "100.00%"


def test_a_level_is_never_printed_above_the_one_proved():
    from hypothesis import given
    from hypothesis import strategies as st

    from drlyap.wording import condition_region, level_text

    assert level_text(0.9999999999999991) == "0.999999" and level_text(1.0) == "1" and level_text(0.3) == "0.3"
    assert "{V <= 0.999999}" in condition_region(0.9999999999999991, 0.1) and "V <= 1}" not in \
        condition_region(0.9999999999999991, 0.1)

    @given(st.floats(min_value=1e-9, max_value=1e9), st.integers(min_value=3, max_value=8))
    def rounded_the_safe_way(level, digits):
        down, up = float(level_text(level, digits)), float(level_text(level, digits, up=True))
        assert down <= level <= up
        assert level - down <= 10 ** (1 - digits) * level and up - level <= 10 ** (1 - digits) * level

    rounded_the_safe_way()


def test_the_comparison_names_the_set_a_decrease_was_proved_on():
    from drlyap.render import attempt_cells
    from drlyap.verification import ProofAttempt

    on_level = ProofAttempt(status="verified", verified_fraction=1.0, level=0.9999999999999991)
    assert attempt_cells(on_level)[0] == "verified on {V <= 0.999999}"
    assert attempt_cells(ProofAttempt(status="verified", verified_fraction=1.0))[0] == "verified on X_delta"
    unknown = attempt_cells(ProofAttempt(status="unknown", verified_fraction=0.9947, level=1.0))[0]
    assert unknown.startswith("unknown on {V <= 1} (99.47% of X_delta proved")


def test_help_says_which_runs_train_for_a_region_and_which_proofs_become_certificates():
    from drlyap.config import SystemDefaults
    from drlyap.systems import get_system, system_names

    roa = {name for name in system_names() if get_system(name).defaults.roa_level is not None}
    assert roa == {name for name in system_names() if not name.startswith("pendulum")}
    assert get_system("pendulum").defaults.roa_level is None
    assert SystemDefaults().roa_level is not None  # a system of one's own trains for a region unless told otherwise
    verify_help = " ".join(CliRunner().invoke(main, ["verify", "--help"]).output.split())
    assert "the default of every built-in system but the pendulum, and of your own systems" in verify_help
    check_help = " ".join(CliRunner().invoke(main, ["check", "--help"]).output.split())
    assert "or on a sublevel set {V <= c} of it" in check_help


def test_train_with_the_local_term_saves_it_and_reports_the_rate(tmp_path):
    out = tmp_path / "run"
    result = CliRunner().invoke(main, ["train", "pendulum", "--iters", "8", "--quiet", "--no-verify", "--local-rate", "0.5",
                                       "--json", "--out", str(out)])
    assert result.exit_code == 0, result.output
    metrics = json.loads(result.stdout)["metrics"]
    assert json.loads((out / "config.json").read_text())["local_rate"] == 0.5
    rates = metrics["acceptance"]["local_rates"]
    assert len(rates) == 5 and metrics["acceptance"]["local_rate_max"] == max(rates)
    assert not metrics["passed"] or max(rates) < 0


def test_train_takes_the_networks_shapes(tmp_path):
    out = tmp_path / "run"
    result = CliRunner().invoke(main, ["train", "pendulum", "--iters", "2", "--quiet", "--no-verify", "--lyapunov-hidden",
                                       "6,5", "--controller-hidden", "", "--controller-skip", "--no-lyapunov-skip",
                                       "--json", "--out", str(out)])
    assert result.exit_code == 0, result.output
    config = json.loads((out / "config.json").read_text())
    assert (config["lyapunov_hidden"], config["controller_hidden"]) == ([6, 5], [])
    assert (config["controller_skip"], config["lyapunov_skip"]) == (True, False)


@pytest.mark.parametrize("where", ["drlyap.training.train", "drlyap.runs.directory.write_json"])
def test_ctrl_c_in_train_exits_130_saying_nothing_was_kept(tmp_path, monkeypatch, where):
    """Interrupted during training or while the run directory is being written: exit status 130, one line saying
    that nothing was saved, and nothing left at --out or beside it."""
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(where, interrupted)
    out = tmp_path / "run"
    result = CliRunner().invoke(main, ["train", "pendulum", "--iters", "2", "--quiet", "--no-verify", "--out", str(out)])
    assert result.exit_code == 130, result.output
    assert result.output.strip().splitlines() == [
        f"drlyap: interrupted; nothing was saved ({out} is written only when training and its proofs end)"]
    assert list(tmp_path.iterdir()) == []


def test_ctrl_c_in_check_exits_130_saying_nothing_changed(tmp_path, monkeypatch):
    """Interrupted while checking: exit 130 and one line, as train and verify
    (tests/test_parallel.py::test_an_interrupted_verify_resumes_its_proof_and_clears_its_checkpoints)."""
    from pathlib import Path

    from handmade import linear_run_dir

    run = linear_run_dir(tmp_path / "run")
    spec = f"{Path(__file__).parent / 'handmade.py'}:small_pendulum"
    assert CliRunner().invoke(main, ["verify", str(run), "--system", spec]).exit_code == 0

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("drlyap.checker.check_run", stop)
    result = CliRunner().invoke(main, ["check", str(run), "--system", spec])
    assert result.exit_code == 130 and "interrupted; nothing was changed" in result.output


def test_a_mistyped_system_name_gets_a_suggestion(tmp_path):
    result = CliRunner().invoke(main, ["train", "pendullum", "--out", str(tmp_path / "x")])
    assert result.exit_code != 0
    assert "unknown system 'pendullum' (did you mean 'pendulum'?); valid: cartpole" in result.output


def test_a_slow_start_says_what_it_loads(tmp_path):
    """Where importing torch takes longer than the threshold (here 0 s), one line on stderr says what is loading;
    a bad argument, refused before torch loads, prints none."""
    import subprocess
    import sys

    code = ("import drlyap.cli.startup as s; s.SLOW = 0.0\nfrom drlyap.cli import main\nimport sys\n"
            "try:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n")
    slow = subprocess.run([sys.executable, "-c", code, "systems"], capture_output=True, text=True, timeout=120)
    assert slow.stderr.count("drlyap: loading torch and the numerical code") == 1, slow.stderr
    refused = subprocess.run([sys.executable, "-c", code, "verify", str(tmp_path / "none")], capture_output=True,
                             text=True, timeout=120)
    assert "loading torch" not in refused.stderr and "does not exist" in refused.stderr


def test_an_unknown_claim_is_refused_with_the_kinds_proved_by_name(tmp_path):
    from drlyap.claims.registry import KINDS

    out = CliRunner().invoke(main, ["verify", str(tmp_path), "--claim", "trained"])
    assert out.exit_code == 2 and "'trained' is no claim proved by name; valid: " in out.output, out.output
    assert all(k.name in out.output for k in KINDS if k.provable)
