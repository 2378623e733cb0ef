"""Training actually learns, and ends with a proof: a fast end-to-end run (default suite) and the long ones
(`pytest -m slow`: the pendulum DR pair with the defaults, a reproduction, and mountain car's DR seed 1)."""

import json
import warnings

import pytest
import torch

import drlyap
from drlyap.simulation import evaluate, initial_states
from drlyap.training import TrainConfig


def _double_integrator() -> drlyap.UncertainSystem:
    def dynamics(x, u, p):
        (damping,) = p.unbind(-1)
        return torch.stack([x[:, 1], -damping * x[:, 1] + u[:, 0]], -1)

    return drlyap.UncertainSystem(
        name="double-integrator-e2e", state_names=("q", "v"), input_names=("f",), param_names=("damping",),
        nominal_params=(0.5,), uncertain=("damping",), dynamics=dynamics, state_box=((-1, -1), (1, 1)),
        input_box=((-2,), (2,)), equilibrium=(0.0, 0.0), test_xi=(0.3,),
        xi_sampler=lambda n, g: 0.1 * torch.randn(n, 1, generator=g, dtype=torch.float64),
        defaults={"n_states": 512, "delta": 0.1, "decay_rate": 0.1, "margin": 0.01, "lyapunov_hidden": [8, 8],
                  "controller_hidden": [8, 8]})


def test_training_learns_a_verified_pair_on_a_double_integrator(tmp_path):
    """From random networks to a pair whose DR condition is PROVED on the whole region, which also stabilises
    the true model at a shift outside the training distribution, and whose proof the verifier repeats."""
    system = _double_integrator()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an unverified run would warn
        result = drlyap.train(TrainConfig(system=system.name, iters=600, check_every=200, seed=1), system=system,
                              proof=drlyap.ProofConfig(time_limit=10), progress=False)
    assert result.metrics["certificate"]["status"] == "verified"
    assert result.metrics["passed"] and result.metrics["final_loss"] < result.history[0]["loss"]
    drlyap.register_system(system.name, lambda: system)
    run = drlyap.load_run(drlyap.save_run(tmp_path / "di", result))
    again = drlyap.verify(run, drlyap.ProofConfig(time_limit=10))
    assert again.trained.status == "verified"
    x0 = initial_states(system, 100, torch.Generator().manual_seed(0))
    scored = evaluate(system, run.controller, x0, torch.tensor(system.test_xi, dtype=torch.float64), horizon=30.0)
    assert scored["n_success"] == 100


@pytest.mark.slow
def test_default_pendulum_dr_training_ends_verified(tmp_path):
    from click.testing import CliRunner

    from drlyap.cli import main

    out = CliRunner().invoke(main, ["train", "pendulum", "--method", "dr", "--seed", "0", "--quiet",
                                    "--out", str(tmp_path / "dr0")])
    assert out.exit_code == 0, out.output
    lines = out.output.strip().splitlines()  # the verdict, then the checker's confirmation of its certificate
    assert any(line.startswith("certificate: VERIFIED") for line in lines)
    assert any(line.strip().startswith("trained: CHECKED") for line in lines)
    verified = CliRunner().invoke(main, ["verify", str(tmp_path / "dr0"), "--json"])
    assert json.loads(verified.stdout)["trained"]["status"] == "verified"


@pytest.mark.slow
def test_pendulum_reproduction_seed_0(tmp_path):
    from drlyap.workflows.reproduce import ReproduceSettings, reproduce

    report = reproduce("pendulum", ReproduceSettings(seeds=[0]), tmp_path / "rep", progress=False, log=lambda s: None)
    rows = {r["method"]: r for r in report["results"]}
    assert rows["dr"]["certificate"] == "verified" and rows["dr"]["true_model"] == "verified"
    assert rows["dr"]["roa"].endswith("%")  # a region of attraction, as a share of the box
    assert rows["dr"]["paper_10"]["n_success"] == 10 and rows["dr"]["more_200"]["n_success"] >= 195


@pytest.mark.slow
def test_default_mountain_car_dr_seed_1_is_proved_on_its_set_and_stabilises_at_the_test_shift(tmp_path):
    """The mountain car's default region-of-attraction training: the trained DR condition proved on {V <= 0.2},
    that set a certified region of attraction of the true model at the test shift, and the controller, trained on
    the rest of the box too, stabilises the test states there."""
    from drlyap.runs import load_run
    from drlyap.workflows.verify import VerifyRequest, verify

    system = drlyap.get_system("mountain-car")
    result = drlyap.train(TrainConfig(system="mountain-car", method="dr", seed=1), progress=False, warn=False)
    assert result.metrics["certificate"]["status"] == "verified" and result.metrics["certificate"]["level"] == 0.2
    drlyap.save_run(tmp_path / "dr1", result)
    run = load_run(tmp_path / "dr1")
    x0 = initial_states(system, 200, torch.Generator().manual_seed(7))
    res = evaluate(system, run.controller, x0, torch.tensor(system.test_xi, dtype=torch.float64))
    assert int(res["n_success"]) >= 195
    shift = verify(run, request=VerifyRequest(xi=system.test_xi, roa=True))
    assert shift.true_model.verified and shift.roa.certified and shift.roa.level > 0.19


@pytest.mark.slow
def test_the_checker_confirms_the_default_cartpole_certificate(tmp_path):
    """The cart-pole's default DR pair is proved on {V <= 1} with the verifier's affine forms; the independent
    checker re-proves every leaf of that certificate with its own second-order forms."""
    from click.testing import CliRunner

    from drlyap.cli import main

    out = CliRunner().invoke(main, ["train", "cartpole", "--seed", "0", "--quiet", "--out", str(tmp_path / "cp")])
    assert out.exit_code == 0, out.output
    lines = out.output.strip().splitlines()  # the verdict, then the checker's confirmation of its certificate
    assert any(line.startswith("certificate: VERIFIED") for line in lines)
    assert any(line.strip().startswith("trained: CHECKED") for line in lines)
    checked = CliRunner().invoke(main, ["check", str(tmp_path / "cp"), "--json"])
    assert checked.exit_code == 0, checked.output
    result = json.loads(checked.stdout)["certificates"][0]
    assert result["ok"] and result["proved"] > 0 and not result["failures"]
