"""drlyap export: the ONNX and TorchScript models do what the run's controller and V do, on 10,000 states."""

import json

import pytest
import torch
from click.testing import CliRunner

from drlyap.cli import main
from drlyap.runs import load_run, save_run
from drlyap.systems import get_system
from drlyap.training import TrainConfig, TrainResult, TrainSections

ort = pytest.importorskip("onnxruntime")


def untrained_run(path, name):
    """A run directory of untrained (random) networks for a built-in system: export does not care how they were
    trained, and random weights exercise every input direction."""
    system = get_system(name)
    cfg = TrainConfig(system=name, iters=1).resolved(system)
    torch.manual_seed(0)
    lyap, ctrl = TrainSections.of(cfg).networks.build(system)
    zeros = [[0.0] * system.k]
    result = TrainResult(cfg, system, lyap, ctrl, torch.zeros(1, system.k, dtype=torch.float64), None, [],
                         {"iterations": 1, "train_time_s": 0.1, "xi_samples": zeros, "xi_train": zeros})
    return save_run(path, result)


def states(system, count=10_000, seed=0):
    """``count`` states of the box, a tenth of them beyond it and around the angle wrap (x* +- pi)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = (torch.tensor(b, dtype=torch.float64) for b in system.state_box)
    x = lo + (hi - lo) * torch.rand(count, system.n, generator=g, dtype=torch.float64)
    x[: count // 10] = x[: count // 10] * 1.5
    return x


def close(a, b, rtol=1e-6):
    """Largest difference relative to the output's range over the states (float32 networks: onnxruntime's
    tanh and matrix products round differently from torch's)."""
    return float((a - b).abs().max() / b.abs().max()) <= rtol


@pytest.mark.parametrize("name", ["pendulum", "cartpole", "quadrotor2d"])
def test_onnx_models_match_the_run_on_10000_states(tmp_path, name):
    run = load_run(untrained_run(tmp_path / "run", name))
    result = CliRunner().invoke(main, ["export", str(tmp_path / "run"), "--json"])
    assert result.exit_code == 0, result.output
    record = json.loads(result.stdout)
    folder = tmp_path / "run" / "export"
    assert json.loads((folder / "export.json").read_text()) == record
    assert record["weights_sha256"] and record["inputs"]["x"]["order"] == list(run.system.state_names)
    x = states(run.system)
    u = ort.InferenceSession(str(folder / "controller.onnx")).run(["u"], {"x": x.numpy()})[0]
    v = ort.InferenceSession(str(folder / "lyapunov.onnx")).run(["V"], {"x": x.numpy()})[0]
    u, v = torch.from_numpy(u), torch.from_numpy(v)
    assert u.shape == (x.shape[0], run.system.m) and v.shape == (x.shape[0],)
    assert close(u, run.controller(x)) and close(v, run.lyapunov(x))
    lo, hi = (torch.tensor(b, dtype=torch.float64) for b in run.system.input_box)
    assert bool(((u >= lo) & (u <= hi)).all())  # the saturation is part of the model
    import onnx

    meta = {p.key: p.value for p in onnx.load(str(folder / "controller.onnx")).metadata_props}
    assert json.loads(meta["drlyap"])["weights_sha256"] == record["weights_sha256"]


def test_torchscript_export_and_refusals(tmp_path):
    run = load_run(untrained_run(tmp_path / "run", "pendulum"))
    result = CliRunner().invoke(main, ["export", str(tmp_path / "run"), "--format", "torchscript",
                                       "--out", str(tmp_path / "ts")])
    assert result.exit_code == 0 and "controller.pt" in result.output, result.output
    x = states(run.system, 1000)
    controller = torch.jit.load(str(tmp_path / "ts" / "controller.pt"))
    assert torch.allclose(controller(x), run.controller(x), rtol=1e-6, atol=1e-9)
    again = CliRunner().invoke(main, ["export", str(tmp_path / "run"), "--format", "torchscript",
                                      "--out", str(tmp_path / "ts")])
    assert again.exit_code != 0 and "already exists" in again.output


def test_the_exported_controller_gives_u_star_exactly_at_x_star(tmp_path):
    run = load_run(untrained_run(tmp_path / "run", "quadrotor2d"))  # u* = m g / 2 is not a float32 number
    result = CliRunner().invoke(main, ["export", str(tmp_path / "run")])
    assert result.exit_code == 0, result.output
    x_star = torch.tensor([run.system.equilibrium], dtype=torch.float64)
    u = ort.InferenceSession(str(tmp_path / "run" / "export" / "controller.onnx")).run(["u"], {"x": x_star.numpy()})[0]
    assert u.tolist() == [list(run.system.equilibrium_input)]
    assert float(torch.tensor(run.system.equilibrium_input[0]).float()) != run.system.equilibrium_input[0]
