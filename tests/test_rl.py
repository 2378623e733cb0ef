"""RL baselines with tiny budgets (only when stable-baselines3 is installed)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

pytest.importorskip("stable_baselines3")

from drlyap.cli import main  # noqa: E402
from drlyap.rl import train_rl  # noqa: E402
from drlyap.rl.envs import observe  # noqa: E402
from drlyap.runs import RunDirError  # noqa: E402
from drlyap.workflows.policies import load_policy_run  # noqa: E402

torch.set_num_threads(1)

TINY = {
    "ppo": {"n_steps": 64, "batch_size": 32, "n_epochs": 2, "policy_kwargs": {"net_arch": [16]}},
    "sac": {"learning_starts": 50, "batch_size": 32, "buffer_size": 1000, "policy_kwargs": {"net_arch": [16]}},
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    import tempfile

    root = tmp_path_factory.mktemp("rl")
    before = {p.name for p in Path(tempfile.gettempdir()).glob("SB3-*")}
    for algo in ("ppo", "sac"):
        train_rl("pendulum", algo, 200, 0, root / algo, TINY[algo])
    left = {p.name for p in Path(tempfile.gettempdir()).glob("SB3-*")} - before
    assert not left, f"training an agent left {sorted(left)} in the temp dir"
    return root


@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_rl_run_dir_round_trip(runs, algo):
    path = runs / algo
    assert json.loads((path / "run.json").read_text())["kind"] == "rl"
    config = json.loads((path / "config.json").read_text())
    assert config["algo"] == algo and config["steps"] == 200 and config["seed"] == 0 and config["wall_time_s"] > 0
    metrics = json.loads((path / "metrics.json").read_text())
    assert metrics["samples"] == 200 and (path / "policy.pt").is_file() and not (path / "model.zip").exists()
    run = load_policy_run(path)
    assert run.kind == "rl" and run.samples == 200 and run.label == f"rl-{algo}"
    x = torch.tensor([[3.0, 0.0], [0.1, -0.3], [0.1 + 6.283185307179586, -0.3], [0.0, 30.0]], dtype=torch.float64)
    u = run.controller(x)
    assert u.shape == (4, 1) and u.dtype == torch.float64 and u.abs().max() <= 15.0
    assert torch.allclose(u[1], u[2])
    # the controller is the deterministic SB3 prediction on the env's observation
    model = run.info["agent"].model
    ref, _ = model.predict(observe(run.system, x), deterministic=True)
    assert torch.allclose(u, torch.from_numpy(ref).double().clamp(-15, 15), atol=1e-5)
    v = run.certificate(x)
    assert v.shape == (4,) and torch.isfinite(v).all()
    obs, _ = model.policy.obs_to_tensor(observe(run.system, x))
    with torch.no_grad():
        if algo == "sac":
            q = torch.cat(model.policy.critic(obs, model.policy.actor(obs, deterministic=True)), dim=1).min(1).values
        else:
            q = model.policy.predict_values(obs).reshape(-1)
    assert torch.allclose(v, -q.double(), atol=1e-6)


def test_rl_refuses_existing_and_bad_algo(runs, tmp_path):
    with pytest.raises(RunDirError, match="already exists"):
        train_rl("pendulum", "ppo", 10, 0, runs / "ppo")
    with pytest.raises(ValueError, match="unknown algorithm"):
        train_rl("pendulum", "dqn", 10, 0, tmp_path / "x")


def test_cli_accepts_rl_runs(runs, tmp_path):
    runner = CliRunner()
    res = runner.invoke(main, ["evaluate", str(runs / "sac"), "--xi", "0.1,0.05", "--n-init", "3", "--horizon", "1",
                               "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["n"] == 3
    res = runner.invoke(main, ["compare", str(runs / "ppo"), str(runs / "sac"), "--xi", "0.1,0.05", "--n-init", "3",
                               "--horizon", "1", "--json"])
    assert res.exit_code == 0, res.output
    rows = json.loads(res.stdout)["rows"]
    assert [r["label"] for r in rows] == ["rl-ppo", "rl-sac"] and [r["samples"] for r in rows] == [200, 200]
    res = runner.invoke(main, ["rl", "train", "pendulum", "--algo", "sac", "--steps", "60", "--json", "--out",
                               str(tmp_path / "cli_sac")])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["metrics"]["samples"] == 60
    assert load_policy_run(tmp_path / "cli_sac").samples == 60
    res = runner.invoke(main, ["rl", "train", "pendulum", "--algo", "sac", "--steps", "0", "--out", str(tmp_path / "z")])
    assert res.exit_code != 0 and "steps must be >= 1" in res.output
