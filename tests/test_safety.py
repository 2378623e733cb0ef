"""Nothing lost and nothing run that the user did not ask for: crafted and damaged run directories, owned and
published directories, checks before work, one clear line for bad input."""

import errno
import json
import os
import shutil
import stat
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from drlyap.cli import main
from drlyap.runs import DirectoryLock, RunDirError, atomic_dir, check_writable, load_run, publish, save_run
from drlyap.workflows.policies import load_policy_run
from handmade import plain_train

MARKER_CODE = '''
import pathlib
pathlib.Path({marker!r}).write_text("ran")


def make():
    raise SystemExit("a crafted system file ran")
'''


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def one_line_error(result) -> str:
    """The error of a failed command: exit status not 0, one line starting with 'Error:', no traceback."""
    assert result.exit_code not in (0, None), result.output
    lines = [line for line in result.output.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.output
    assert "Traceback" not in result.output
    return lines[0]


@pytest.fixture(scope="module")
def pendulum_run(tmp_path_factory):
    from drlyap.training import TrainConfig

    tmp = tmp_path_factory.mktemp("safety")
    cfg = TrainConfig(system="pendulum", n_states=256, iters=5, check_every=5, lyapunov_hidden=[8], lyapunov_out=4,
                      controller_hidden=[8], seed=0)
    save_run(tmp / "run", plain_train(cfg, progress=False))
    return tmp / "run"


def copy_run(run: Path, tmp_path: Path) -> Path:
    out = tmp_path / "copy"
    shutil.copytree(run, out)
    return out


def edit_json(path: Path, change) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


# ------------------------------------------------------------------ 1. loading runs no code
@pytest.mark.parametrize("reload", ["file", "module"])
def test_a_crafted_run_directory_runs_no_code(pendulum_run, tmp_path, reload):
    run = copy_run(pendulum_run, tmp_path)
    marker = tmp_path / "marker"
    code = tmp_path / "evil.py"
    code.write_text(MARKER_CODE.format(marker=str(marker)))
    spec = f"{code}:make" if reload == "file" else "this:make"  # `this` prints the Zen of Python when imported
    edit_json(run / "run.json", lambda d: d.update(system_source={"kind": reload, "spec": spec, "reload": spec}))
    with pytest.raises(RunDirError, match="would run that code"):
        load_run(run)
    for command in (["evaluate", run, "--xi", "0.1,0.05", "--n-init", "2", "--horizon", "1"],
                    ["verify", run, "--time-limit", "1"],
                    ["plot", run, "--n-init", "2"]):
        result = invoke(*command)
        line = one_line_error(result)
        assert spec in line and "--trust-run" in line and "Zen of Python" not in result.output
    assert not marker.exists()


def test_an_rl_run_with_a_pickled_model_is_refused(tmp_path):
    pytest.importorskip("stable_baselines3")
    from drlyap.runs.directory import run_record
    from drlyap.systems import get_system

    run = tmp_path / "rl"
    run.mkdir()
    (run / "run.json").write_text(json.dumps(run_record("rl", get_system("pendulum"))))
    (run / "config.json").write_text(json.dumps({"system": "pendulum", "algo": "sac", "steps": 10}))
    (run / "metrics.json").write_text(json.dumps({"train_time_s": 1.0}))
    marker = tmp_path / "marker"
    with zipfile.ZipFile(run / "model.zip", "w") as zf:  # what a crafted cloudpickled lr_schedule would hold
        zf.writestr("data", json.dumps({"lr_schedule": {":serialized:": "crafted", "marker": str(marker)}}))
    with pytest.raises(RunDirError, match="model.zip is a pickled"):
        load_policy_run(run)
    line = one_line_error(invoke("evaluate", run, "--xi", "0.1,0.05", "--n-init", "2"))
    assert "--trust-run" in line and not marker.exists()


def test_rl_hyperparameters_must_be_plain_data(tmp_path):
    pytest.importorskip("stable_baselines3")
    from drlyap.rl.agents import _plain

    assert _plain({"learning_rate": 1e-3, "policy_kwargs": {"net_arch": [64, 64]}, "use_sde": True})
    assert not _plain({"learning_rate": {"x": object()}}) and not _plain({"schedule": "x" * 200})


# ------------------------------------------------------------------ 2. nothing replaced
def test_publishing_never_replaces_a_directory_that_appeared(tmp_path):
    out = tmp_path / "run"

    def fill(tmp):
        (tmp / "new.txt").write_text("second")
        out.mkdir()  # another process finished first, while this one was filling
        (out / "first.txt").write_text("first")

    with pytest.raises(RunDirError, match="created by another process"):
        atomic_dir(out, fill)
    assert [p.name for p in out.iterdir()] == ["first.txt"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".run.tmp")]  # its temporary is gone


def test_leftover_temporaries_of_dead_processes_are_cleaned(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = tmp_path / f".old.tmp-{dead.stdout.strip()}-abc"
    stale.mkdir()
    live = tmp_path / f".other.tmp-{os.getppid()}-abc"  # a live process's: kept
    live.mkdir()
    atomic_dir(tmp_path / "run", lambda tmp: (tmp / "a").write_text("x"))
    assert not stale.exists() and live.exists()


def test_run_directories_follow_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        atomic_dir(tmp_path / "run", lambda tmp: (tmp / "a").write_text("x"))
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "run").stat().st_mode) == 0o755


LOCK_HOLDER = """
import sys, time
from pathlib import Path
from drlyap.runs import DirectoryLock
with DirectoryLock(Path(sys.argv[1]), "a sweep"):
    print("locked", flush=True)
    time.sleep(60)
"""


def test_a_locked_directory_refuses_a_second_owner_and_runs_written_into_it(tmp_path):
    sweep = tmp_path / "sweep"
    holder = subprocess.Popen([sys.executable, "-c", LOCK_HOLDER, str(sweep)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(RunDirError, match="in use by another drlyap process"):
            DirectoryLock(sweep).__enter__()
        line = one_line_error(invoke("train", "pendulum", "--iters", "1", "--out", sweep / "dr-r0.01-eps0.1-seed0"))
        assert "in use by another drlyap process" in line
        with pytest.raises(RunDirError, match="in use"):
            atomic_dir(sweep / "x", lambda tmp: None)
        assert not (sweep / "dr-r0.01-eps0.1-seed0").exists()
    finally:
        holder.kill()
        holder.wait()
    with DirectoryLock(sweep):  # released when its process ended, however it ended
        pass


# ------------------------------------------------------------------ 3. checks before work
def test_a_read_only_or_full_out_fails_before_training(tmp_path, monkeypatch):
    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    with pytest.raises(RunDirError, match="Read-only file system"):
        check_writable(tmp_path / "run")
    result = invoke("train", "pendulum", "--out", tmp_path / "run")
    assert "Read-only file system" in one_line_error(result) and "iteration" not in result.output
    monkeypatch.undo()
    monkeypatch.setattr(publish, "MIN_FREE_BYTES", 2**62)
    for command in (["train", "pendulum"], ["reproduce", "pendulum", "--seeds", "0"], ["lqr", "pendulum"]):
        result = invoke(*command, "--out", tmp_path / "run")
        assert "MB free" in one_line_error(result), command
    assert not (tmp_path / "run").exists()


def test_xi_samples_as_tensor_or_array_are_saved(tmp_path, tiny_config):
    import numpy as np

    for i, samples in enumerate([torch.tensor([[0.1, 0.0], [0.0, 0.1]]), np.array([[0.1, 0.0], [0.0, 0.1]])]):
        result = plain_train(tiny_config(iters=2, check_every=2, xi_samples=samples), progress=False)
        save_run(tmp_path / f"run{i}", result)
        assert load_run(tmp_path / f"run{i}").xi_samples.shape == (2, 2)


# ------------------------------------------------------------------ 4. bad input: one clear line
NAN_SYSTEM = '''
import torch
from drlyap import UncertainSystem


def dynamics(x, u, p):
    (c,) = p.unbind(-1)
    v = torch.where(x[:, 0] > 0.7, torch.full_like(x[:, 1], float("nan")), x[:, 1])
    return torch.stack([v, -c * x[:, 1] + u[:, 0]], dim=-1)


def make():
    return UncertainSystem(
        name="nan-dint", state_names=("q", "v"), input_names=("f",), param_names=("damping",), nominal_params=(0.5,),
        uncertain=("damping",), dynamics=dynamics, state_box=((-1.0, -1.0), (1.0, 1.0)), input_box=((-2.0,), (2.0,)),
        equilibrium=(0.0, 0.0), test_xi=(-0.2,),
        xi_sampler=lambda n, g: 0.05 * torch.randn(n, 1, generator=g, dtype=torch.float64))
'''


def test_dynamics_that_are_not_finite_are_named_before_training(tmp_path):
    file = tmp_path / "nan_system.py"
    file.write_text(NAN_SYSTEM)
    for command in (["train", f"{file}:make", "--iters", "2"], ["lqr", f"{file}:make"]):
        result = invoke(*command, "--out", tmp_path / "run")
        line = one_line_error(result)
        assert "nan-dint: the dynamics are not finite" in line and "at x = [" in line, line
    assert not (tmp_path / "run").exists()


def test_a_system_file_with_a_syntax_error_names_its_line(tmp_path):
    file = tmp_path / "broken.py"
    file.write_text("import torch\n\ndef make(:\n    pass\n")
    line = one_line_error(invoke("train", f"{file}:make", "--out", tmp_path / "run"))
    assert f"{file}:3:" in line and "SyntaxError" not in line.split(":")[0]


def test_warm_start_from_nan_networks_is_refused(pendulum_run, tmp_path):
    run = copy_run(pendulum_run, tmp_path)
    weights = torch.load(run / "weights.pt", weights_only=True)
    weights["lyapunov"][next(iter(weights["lyapunov"]))].fill_(float("nan"))
    torch.save(weights, run / "weights.pt")
    with pytest.raises(RunDirError, match="NaN or inf"):
        load_run(run)
    for command in (["evaluate", run, "--xi", "0.1,0.05", "--n-init", "2"], ["verify", run, "--time-limit", "1"], ["plot", run],
                    ["train", "pendulum", "--iters", "2", "--warm-start", run, "--out", tmp_path / "new"]):
        assert "holds NaN or inf in lyapunov." in one_line_error(invoke(*command)), command


@pytest.mark.parametrize("content, message", [(b"", "is damaged"), (os.urandom(512), "is damaged"),
                                              (None, "is missing")])
def test_damaged_weights_are_named(pendulum_run, tmp_path, content, message):
    run = copy_run(pendulum_run, tmp_path)
    if content is None:
        (run / "weights.pt").unlink()
    else:
        (run / "weights.pt").write_bytes(content)
    for command in (["evaluate", run, "--xi", "0.1,0.05", "--n-init", "2"], ["verify", run, "--time-limit", "1"]):
        result = invoke(*command)
        line = one_line_error(result)
        assert "weights.pt" in line and message in line and "Aborted" not in result.output
        assert "weights_only=False" not in line


@pytest.mark.parametrize("change, message", [
    (lambda c: c.pop("delta"), "delta"),
    (lambda c: c.update(delta=None), "delta is missing"),
    (lambda c: c.update(delta="0.5"), "delta"),
    (lambda c: c.update(seed="zero"), "seed"),
    (lambda c: c.update(iters=2.5), "iters"),
    (lambda c: c.pop("method"), "missing method"),  # never defaulted: a baseline would be proved as a DR run
    (lambda c: c.pop("roa_level"), "missing roa_level"),
])
def test_config_json_is_validated(pendulum_run, tmp_path, change, message):
    run = copy_run(pendulum_run, tmp_path)
    edit_json(run / "config.json", change)
    with pytest.raises(RunDirError, match=message):
        load_run(run)
    assert "config.json" in one_line_error(invoke("verify", run, "--time-limit", "1"))


def test_a_run_saved_before_a_later_field_loads_with_the_value_it_was_trained_with(pendulum_run, tmp_path):
    run = copy_run(pendulum_run, tmp_path)
    edit_json(run / "config.json", lambda c: (c.pop("outside_weight"), c.pop("controller_skip")))  # saved before them
    loaded = load_run(run)
    assert loaded.config.outside_weight == 0.0 and loaded.config.controller_skip is False
    edit_json(run / "config.json", lambda c: c.update(outside_weight=None))
    with pytest.raises(RunDirError, match="outside_weight is missing"):
        load_run(run)


def test_metrics_json_is_validated(pendulum_run, tmp_path):
    run = copy_run(pendulum_run, tmp_path)
    edit_json(run / "metrics.json", lambda m: m.update(xi_samples=[[0.1, 0.0, 0.2]] * 3))
    for command in (["verify", run, "--time-limit", "1"],
                    ["compare", run, "--xi", "0.1,0.05", "--n-init", "2", "--out", tmp_path / "c"]):
        line = one_line_error(invoke(*command))
        assert "xi_samples must have 2 value(s) per sample" in line
    edit_json(run / "metrics.json", lambda m: m.pop("xi_train"))
    assert "xi_train" in one_line_error(invoke("evaluate", run, "--xi", "0.1,0.05", "--n-init", "2"))
    (run / "run.json").write_text("{not json")
    assert "run.json is not valid JSON" in one_line_error(invoke("evaluate", run, "--xi", "0.1,0.05", "--n-init", "2"))


# ------------------------------------------------------------------ 5. work, not seconds
def test_proof_rounds_give_the_same_pair_on_a_slow_machine(tiny_config, monkeypatch):
    """The rounds are budgeted by boxes: a clock running 100x faster (a machine 100x slower) gives the same pair,
    where a proof limited by seconds stops early under the same clock."""
    import drlyap
    from drlyap.verification import ProofConfig

    cfg = tiny_config(iters=20, check_every=10)
    by_work = ProofConfig(rounds=1, max_boxes=3000, iters_per_round=10, round_time=1e5)

    def weights(result):
        return [p.detach().clone() for p in (*result.lyapunov.parameters(), *result.controller.parameters())]

    def rounds(result):
        return [(r["verification"]["boxes_processed"], r["verification"]["stopped"])
                for r in result.metrics["cegis"]["rounds"]]

    fast = drlyap.train(cfg, proof=by_work, progress=False, warn=False)
    real = time.perf_counter
    start = real()
    monkeypatch.setattr(time, "perf_counter", lambda: start + 100 * (real() - start))
    slow = drlyap.train(cfg, proof=by_work, progress=False, warn=False)
    by_seconds = drlyap.train(cfg, proof=ProofConfig(rounds=0, max_boxes=3000, time_limit=0.5), progress=False,
                              warn=False)
    monkeypatch.undo()
    assert rounds(fast) == rounds(slow) and all(stop != "time limit" for _, stop in rounds(fast))
    assert all(torch.equal(a, b) for a, b in zip(weights(fast), weights(slow)))
    assert rounds(by_seconds)[0][1] == "time limit"  # the clock did slow the proofs down


def test_plot_into_an_unwritable_folder_is_one_line(pendulum_run, tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    line = one_line_error(invoke("plot", pendulum_run, "--out", blocker / "figures"))
    assert "cannot write the figures to" in line and "a-file" in line
