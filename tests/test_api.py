"""The Python API as the README shows it: a user-defined system in a few lines, trained, saved, loaded."""

import math

import pytest
import torch

import drlyap


def test_readme_user_system_round_trip(tmp_path):
    def cart(x, u, p):
        (friction,) = p.unbind(-1)
        return torch.stack([x[:, 1], -friction * x[:, 1] + u[:, 0]], -1)

    sys_ = drlyap.UncertainSystem(
        name="cart", state_names=("q", "v"), input_names=("f",), param_names=("friction",),
        nominal_params=(0.5,), uncertain=("friction",), dynamics=cart,
        state_box=((-1, -1), (1, 1)), input_box=((-2,), (2,)), equilibrium=(0.0, 0.0),
        xi_sampler=lambda n, g: 0.1 * torch.randn(n, 1, generator=g, dtype=torch.float64))
    result = drlyap.train(drlyap.TrainConfig(system="cart", iters=30, check_every=30, n_states=256), system=sys_,
                          proof=None, progress=False)
    drlyap.save_run(tmp_path / "cart", result)
    drlyap.register_system("cart", lambda: sys_)
    run = drlyap.load_run(tmp_path / "cart")
    x = torch.tensor([[0.5, -0.2], [0.0, 0.0]])
    assert run.controller(x).shape == (2, 1) and run.lyapunov(x).shape == (2,)
    assert abs(run.lyapunov(x)[1].item()) < 1e-9  # zero by construction, up to float rounding in a batch
    assert result.xi_samples.shape == (5, 1)


def test_load_run_returns_controller_and_certificate_in_user_coordinates(tmp_path, tiny_config):
    result = drlyap.train(tiny_config(system="mountain-car"), proof=None, progress=False)
    run = drlyap.load_run(drlyap.save_run(tmp_path / "mc", result))
    x_star = torch.tensor([[math.pi / 6, 0.0]], dtype=torch.float64)
    assert abs(run.lyapunov(x_star).item()) < 1e-6
    assert abs(run.controller(x_star).item()) < 1e-6
    assert run.system.name == "mountain-car"


def test_a_taken_path_is_refused_in_python_words_and_before_training(tmp_path, tiny_config):
    """The README's API block run twice: the path it saves to is checked first (drlyap.check_writable) and refused
    before any training; save_run refuses it too. The message names the path and asks for another path, not for
    a command-line option."""
    out = tmp_path / "run"
    result = drlyap.train(tiny_config(iters=2, check_every=2), proof=None, progress=False)
    drlyap.save_run(out, result)
    trained = []
    with pytest.raises(drlyap.RunDirError, match="already exists") as refused:
        drlyap.check_writable(out)
        trained.append(drlyap.train(tiny_config(iters=2, check_every=2), proof=None, progress=False))
    assert not trained
    assert str(refused.value) == f"{out} already exists; pass another path or remove it"
    with pytest.raises(drlyap.RunDirError) as again:
        drlyap.save_run(out, result)
    assert str(again.value) == str(refused.value) and "--out" not in str(again.value)


def test_train_proves_by_default_and_says_so_when_it_cannot(tiny_config):
    """drlyap.train ends with the verifier's verdict in metrics["certificate"]; an unproved run warns."""
    with pytest.warns(UserWarning, match="NOT verified"):
        result = drlyap.train(tiny_config(iters=10, check_every=10), proof=drlyap.ProofConfig(rounds=0, time_limit=1.0),
                              progress=False)
    cert = result.metrics["certificate"]
    assert cert["status"] in ("violated", "unknown") and cert["condition"] == "DR pointwise"
    assert 0 <= cert["verified_fraction"] < 1 and cert["rounds"] == 0
    plain = drlyap.train(tiny_config(iters=10, check_every=10), proof=None, progress=False)
    assert plain.metrics["certificate"]["status"] == "not checked" and "cegis" not in plain.metrics


def test_the_api_runs_on_one_thread_unless_told_otherwise():
    import subprocess
    import sys

    code = ("import torch; torch.set_num_threads(2); import drlyap; drlyap.TrainConfig; "
            "print(torch.get_num_threads()); drlyap.set_threads(2); print(torch.get_num_threads())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={k: v for k, v in __import__("os").environ.items() if k != "DRLYAP_THREADS"})
    assert out.stdout.split() == ["1", "2"]


def test_xi_samples_may_be_a_tensor_or_an_array(tmp_path, tiny_config):
    import numpy as np

    samples = torch.tensor([[0.02, 0.0], [-0.01, 0.01]], dtype=torch.float64)
    for given in (samples, samples.numpy(), np.asarray(samples)):
        result = drlyap.train(tiny_config(iters=2, check_every=2, xi_samples=given), proof=None, progress=False)
        assert result.config.xi_samples == samples.tolist()
    drlyap.save_run(tmp_path / "run", result)  # the config is plain JSON
    assert drlyap.load_run(tmp_path / "run").xi_samples.tolist() == samples.tolist()


def test_the_words_of_settings_and_results_are_string_enums_that_read_and_write_as_strings():
    import json

    from drlyap.config import TrainConfig
    from drlyap.kinds import Enclosure, Loss, Method, Status, choice
    from drlyap.proof_settings import Budget, ProofConfig
    from drlyap.systems import get_system

    system = get_system("pendulum")
    cfg = TrainConfig(system="pendulum", method="baseline", loss="pointwise").resolved(system)
    assert cfg.method is Method.BASELINE and cfg.loss is Loss.POINTWISE and cfg.method == "baseline"
    assert json.loads(json.dumps(cfg.to_dict()))["method"] == "baseline"
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))).resolved(system) == cfg
    assert Budget(enclosure="affine").enclosure is Enclosure.AFFINE
    assert ProofConfig().resolved(system).enclosure is Enclosure.MEAN_VALUE  # 2 states
    assert ProofConfig().resolved(get_system("cartpole")).enclosure is Enclosure.AFFINE
    assert Status("verified") == "verified" and f"{Status.UNKNOWN}" == "unknown"
    with pytest.raises(ValueError, match="unknown enclosure 'boxes'; valid: mean-value, affine"):
        choice(Enclosure, "boxes", "enclosure")
    with pytest.raises(ValueError, match="method 'nominal'"):
        TrainConfig(system="pendulum", method="nominal").resolved(system)
