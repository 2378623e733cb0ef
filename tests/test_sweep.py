import json
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from drlyap.cli import main
from drlyap.runs import load_run
from drlyap.workflows.sweep import (
    Backend,
    LocalBackend,
    SweepError,
    SweepSpec,
    make_backend,
    parse_methods,
    parse_seeds,
    parse_values,
    run_sweep,
)
from drlyap.workflows.sweep.task import run_combination
from handmade import survivors_of_kill

TINY = dict(n_states=256, iters=20, check_every=20, lyapunov_hidden=[8], lyapunov_out=4, controller_hidden=[8])


class InProcess(Backend):
    """The tasks run one after another in this process: for tests of what the driver does with their rows (the
    local backend's worker processes are tested on their own)."""

    name = "in-process"

    def run(self, tasks):
        for task in tasks:
            yield run_combination(*task)


def tiny_spec(**over) -> SweepSpec:
    base = dict(system="pendulum", seeds=[0, 1], radii=[0.0, 0.02], eps=[0.1], methods=["dr"], n_init=6, horizon=2.0,
                shift_factors=[1.0, 3.0], verify_time_limit=0.3, verify=False, config=TINY)
    base.update(over)
    return SweepSpec(**base)


@pytest.fixture(scope="module")
def local_sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep") / "local"
    with LocalBackend(workers=2) as backend:
        report = run_sweep(tiny_spec(), out, backend)
    return out, report


def test_parse_grid():
    assert parse_seeds("0-3") == [0, 1, 2, 3]
    assert parse_seeds("0-2,5,1") == [0, 1, 2, 5]
    assert parse_values("0, 0.005,0.01,0.01", "--radius") == [0.0, 0.005, 0.01]
    assert parse_methods("both") == ["baseline", "dr"]
    assert parse_methods("dr") == ["dr"]


@pytest.mark.parametrize("call, message", [
    (lambda: parse_seeds("3-1"), "runs backwards"),
    (lambda: parse_seeds("a"), "not a seed or a range"),
    (lambda: parse_seeds(","), "no seed"),
    (lambda: parse_values("0,x", "--radius"), "--radius: 'x' is not a number"),
    (lambda: parse_values("nan", "--eps"), "not finite"),
    (lambda: parse_methods("ppo"), "valid: baseline, dr, both"),
    (lambda: tiny_spec(eps=[1.5]).validate(), "risk_level = 1.5"),
    (lambda: make_backend("slurm"), "valid: local, ray"),
    (lambda: make_backend("local", address="auto"), "--address is for --backend ray"),
])
def test_grid_errors_name_the_input(call, message):
    with pytest.raises(SweepError, match=message):
        call()


def test_combinations_baseline_once_per_seed():
    spec = tiny_spec(methods=["baseline", "dr"], radii=[0.0, 0.01], eps=[0.05, 0.1])
    names = [c.name for c in spec.combinations()]
    assert names[:2] == ["baseline-seed0", "baseline-seed1"]
    assert len(names) == 2 + 2 * 2 * 2 and len(set(names)) == len(names)
    assert "dr-r0.01-eps0.05-seed1" in names
    from drlyap.systems import get_system

    cfg = spec.train_config(spec.combinations()[-1], get_system("pendulum"))
    assert (cfg.method, cfg.seed, cfg.wasserstein_radius, cfg.risk_level, cfg.n_states) == ("dr", 1, 0.01, 0.1, 256)


def test_local_sweep_writes_runs_tables_and_figure(local_sweep):
    out, report = local_sweep
    names = [c.name for c in tiny_spec().combinations()]
    assert sorted(report["computed"]) == sorted(names) and report["reused"] == [] and report["failed"] == 0
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert [r["name"] for r in rows] == names
    csv_lines = (out / "results.csv").read_text().strip().splitlines()
    assert len(csv_lines) == 1 + len(names) and "success_3x" in csv_lines[0]
    for row in rows:
        run = load_run(out / row["name"])  # a complete run directory per combination
        assert run.config.wasserstein_radius == row["radius"] and run.config.seed == row["seed"]
        assert json.loads((out / row["name"] / "result.json").read_text())["name"] == row["name"]
        assert set(row["success"]) == {"1", "3"} and all(0 <= v <= 1 for v in row["success"].values())
        assert row["trained_condition"] in ("verified", "violated", "unknown")
    assert (out / "figures" / "sweep.png").stat().st_size > 0
    summary = {(s["radius"], s["eps"]): s for s in report["summary"]}
    assert set(summary) == {(0.0, 0.1), (0.02, 0.1)} and all(s["n"] == 2 for s in summary.values())


def test_ray_backend_gives_the_same_table(local_sweep, tmp_path):
    pytest.importorskip("ray")
    out, local = local_sweep
    with make_backend("ray", workers=2) as backend:  # the combinations of seed 0: one per worker
        remote = run_sweep(tiny_spec(seeds=[0]), tmp_path / "ray", backend)
    assert remote["backend"] == "ray" and remote["failed"] == 0
    same = [r for r in local["rows"] if r["seed"] == 0]
    assert [r["name"] for r in remote["rows"]] == [r["name"] for r in same] and len(same) == 2
    for a, b in zip(same, remote["rows"]):
        # training (without proof rounds) and simulation are deterministic given the seed; the branch and bound
        # stops on a time limit, so its verified fractions may differ, its verdicts may not
        for key in ("status", "iterations", "passed_acceptance", "trained_condition", "test_decrease", "roa_certified"):
            assert a[key] == b[key], (a["name"], key)
        assert a["violating_fraction"] == pytest.approx(b["violating_fraction"], abs=1e-9)
        assert a["success"] == pytest.approx(b["success"], abs=1e-12)


def test_resume_redoes_only_missing_and_incomplete(local_sweep, tmp_path):
    src, _ = local_sweep
    out = tmp_path / "resumed"
    shutil.copytree(src, out)
    names = [c.name for c in tiny_spec().combinations()]
    gone, incomplete, kept = names[0], names[1], names[2:]
    shutil.rmtree(out / gone)
    (out / incomplete / "run.json").unlink()  # as if interrupted before the directory was complete
    (out / ".staging" / "junk").mkdir(parents=True)
    before = {n: (out / n / "result.json").stat().st_mtime_ns for n in kept}
    report = run_sweep(tiny_spec(), out, InProcess())
    assert sorted(report["computed"]) == sorted([gone, incomplete])
    assert sorted(report["reused"]) == sorted(kept)
    assert {n: (out / n / "result.json").stat().st_mtime_ns for n in kept} == before
    assert not (out / ".staging").exists() and len(report["rows"]) == len(names)
    load_run(out / incomplete)


def test_resume_refuses_a_different_grid(local_sweep):
    out, _ = local_sweep
    with pytest.raises(SweepError, match="radii"):
        run_sweep(tiny_spec(radii=[0.0, 0.05]), out)


def test_failing_combination_is_recorded_and_retried(tmp_path):
    spec = tiny_spec(seeds=[0], radii=[-1.0, 0.02])  # r = -1 is an invalid training config
    report = run_sweep(spec, tmp_path / "s", InProcess())
    rows = {r["name"]: r for r in report["rows"]}
    bad, good = "dr-r-1-eps0.1-seed0", "dr-r0.02-eps0.1-seed0"
    assert rows[bad]["status"] == "failed" and "wasserstein_radius = -1" in rows[bad]["error"]
    assert rows[bad]["traceback"] and rows[good]["status"] == "ok" and report["failed"] == 1
    assert not (tmp_path / "s" / bad).exists()
    assert "failed" in (tmp_path / "s" / "results.csv").read_text()
    again = run_sweep(spec, tmp_path / "s", InProcess(), figures=False)
    assert again["computed"] == [bad] and again["reused"] == [good]


def test_cli_sweep_help_and_bad_input(tmp_path):
    runner = CliRunner()
    assert "--backend" in runner.invoke(main, ["sweep", "--help"]).output
    result = runner.invoke(main, ["sweep", "pendulum", "--seeds", "0-1", "--eps", "0.1,2", "--out", str(tmp_path / "x")])
    assert result.exit_code != 0 and "risk_level = 2.0" in result.output
    result = runner.invoke(main, ["sweep", "pendulum", "--radius", "0,abc", "--out", str(tmp_path / "x")])
    assert result.exit_code != 0 and "--radius: 'abc' is not a number" in result.output
    assert not (tmp_path / "x").exists()


KILLED_SWEEP = """
import sys
from pathlib import Path
sys.path.insert(0, sys.argv[2])
from test_sweep import tiny_spec
from drlyap.workflows.sweep import LocalBackend, run_sweep
with LocalBackend(workers=2) as backend:
    run_sweep(tiny_spec(seeds=[0]), Path(sys.argv[1]), backend)
"""


def _children(pid: int) -> set[int]:
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.add(int(stat.parent.name))
    return found


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table from /proc")
def test_kill_9_of_a_sweep_leaves_no_process_and_a_rerun_gives_the_same_table(local_sweep, tmp_path):
    import subprocess
    import sys
    import time

    out = tmp_path / "killed"
    main_proc = subprocess.Popen([sys.executable, "-c", KILLED_SWEEP, str(out), str(Path(__file__).parent)])
    workers: set[int] = set()
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not list((out / ".staging").glob("*")):
        workers |= _children(main_proc.pid)
        time.sleep(0.05)
    workers |= _children(main_proc.pid)
    assert workers, "the sweep started no worker"
    assert not survivors_of_kill(main_proc, workers, 2.0), "workers outlived the killed sweep by 2 s"
    rerun = run_sweep(tiny_spec(seeds=[0]), out, InProcess(), figures=False)
    same = [r for r in local_sweep[1]["rows"] if r["seed"] == 0]
    assert rerun["failed"] == 0 and [r["name"] for r in rerun["rows"]] == [r["name"] for r in same]
    for a, b in zip(same, rerun["rows"]):
        for key in ("status", "iterations", "passed_acceptance", "violating_fraction", "success", "weights_sha256"):
            assert a[key] == b[key], (a["name"], key)


def test_a_second_sweep_into_a_running_one_is_refused(tmp_path):
    from drlyap.runs import DirectoryLock, RunDirError

    with DirectoryLock(tmp_path / "s", "a sweep"):
        with pytest.raises(RunDirError, match="in use by another drlyap process"):
            run_sweep(tiny_spec(seeds=[0], radii=[0.0]), tmp_path / "s")
    assert not (tmp_path / "s" / "sweep.json").exists()


def test_damaged_combinations_are_redone_and_a_garbled_sweep_json_rebuilt(local_sweep, tmp_path):
    src, clean = local_sweep
    out = tmp_path / "damaged"
    shutil.copytree(src, out)
    names = [c.name for c in tiny_spec().combinations()]
    weights = out / names[0] / "weights.pt"
    weights.write_bytes(weights.read_bytes()[:100])  # truncated
    (out / "sweep.json").write_text("{garbled")
    report = run_sweep(tiny_spec(), out, InProcess(), figures=False)
    assert report["damaged"] == [names[0]] and report["computed"] == [names[0]]
    assert sorted(report["reused"]) == sorted(names[1:]) and report["failed"] == 0
    assert json.loads((out / "sweep.json").read_text()) == json.loads((src / "sweep.json").read_text())
    redone = {r["name"]: r for r in report["rows"]}[names[0]]
    assert redone["weights_sha256"] == {r["name"]: r for r in clean["rows"]}[names[0]]["weights_sha256"]
    (out / "sweep.json").write_text("{garbled")
    with pytest.raises(SweepError, match="do not record this grid"):
        run_sweep(tiny_spec(radii=[0.0, 0.05]), out)


def test_cli_sweep_exits_non_zero_when_a_combination_failed(tmp_path, monkeypatch):
    from drlyap.workflows import sweep as sw

    monkeypatch.setattr(sw.SweepSpec, "validate", lambda self: None)  # let an invalid combination reach a worker
    result = CliRunner().invoke(main, ["sweep", "pendulum", "--seeds", "0", "--radius", "-1", "--iters", "2",
                                       "--no-verify", "--n-init", "2", "--shifts", "1", "--out", str(tmp_path / "s")])
    assert result.exit_code == 1 and "1 of 1 combination(s) failed" in result.output
    assert "sweep.png" not in result.output and not (tmp_path / "s" / "figures" / "sweep.png").exists()
    result = CliRunner().invoke(main, ["sweep", "pendulum", "--seeds", "0", "--device", "cuda:7", "--out",
                                       str(tmp_path / "c")])
    assert result.exit_code != 0 and "cuda" in result.output and not (tmp_path / "c").exists()


def test_a_folder_the_sweep_did_not_write_is_never_removed(tmp_path):
    """A run a user put at a combination's name (no result.json) stops the sweep with one line; nothing is deleted."""
    from drlyap.workflows.sweep.driver import finished_row
    from drlyap.workflows.sweep.grid import Combination, SweepError

    combo = Combination("dr", 1, 0.01, 0.1)
    folder = tmp_path / combo.name
    folder.mkdir()
    (folder / "run.json").write_text("{}")
    with pytest.raises(SweepError, match="not written by this sweep"):
        finished_row(tmp_path, combo)
    assert (folder / "run.json").is_file()
    (folder / "result.json").write_text("{not json")  # the sweep's own, damaged: redone
    assert finished_row(tmp_path, combo) is None and not folder.exists()
