"""LQR baseline, the common run loader, and the comparison (fast: short horizons, few states)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from drlyap.cli import main
from drlyap.closed_loop import ClosedLoop
from drlyap.lqr import default_weights, linearize, lqr_design
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.runs import RunDirError, save_lqr_run, save_run, train_lqr
from drlyap.simulation import evaluate, initial_states
from drlyap.systems import get_system
from drlyap.training import TrainConfig, TrainResult, TrainSections
from drlyap.workflows.compare import CompareSettings, compare_runs, monotonicity, score_run
from drlyap.workflows.policies import load_policy_run

torch.set_num_threads(1)


@pytest.mark.parametrize("name", ["pendulum", "pendulum-u9", "mountain-car"])
def test_lqr_stabilises_linearisation(name):
    system = get_system(name)
    d = lqr_design(system)
    eig = np.linalg.eigvals((d.A - d.B @ d.K).numpy())
    assert eig.real.max() < 0
    # P solves the Riccati equation and is positive definite.
    a, b, p, q, r = (t.numpy() for t in (d.A, d.B, d.P, d.Q, d.R))
    residual = a.T @ p + p @ a - p @ b @ np.linalg.solve(r, b.T @ p) + q
    assert np.abs(residual).max() < 1e-8 * max(1.0, np.abs(p).max())
    assert np.linalg.eigvalsh(p).min() > 0


def test_linearisation_matches_pendulum_by_hand():
    a, b = linearize(get_system("pendulum"))
    assert torch.allclose(a, torch.tensor([[0.0, 1.0], [9.81, -0.13]], dtype=torch.float64))
    assert torch.allclose(b, torch.tensor([[0.0], [1.0]], dtype=torch.float64))
    # with a shift the TRUE model is linearised at the shifted parameters (mass 1.1, damping 0.18)
    a2, b2 = linearize(get_system("pendulum"), [0.1, 0.05])
    assert torch.allclose(a2, torch.tensor([[0.0, 1.0], [9.81, -0.18 / 1.1]], dtype=torch.float64))
    assert torch.allclose(b2, torch.tensor([[0.0], [1 / 1.1]], dtype=torch.float64))
    q, r = default_weights(get_system("pendulum"))
    assert torch.allclose(torch.diag(q), torch.tensor([1 / math.pi**2, 1 / 64], dtype=torch.float64))
    assert torch.allclose(r, torch.tensor([[1 / 225]], dtype=torch.float64))


def test_lqr_bad_weights():
    system = get_system("pendulum")
    with pytest.raises(ValueError, match="R must be positive definite"):
        lqr_design(system, R=[0.0])
    with pytest.raises(ValueError, match="Q must be"):
        lqr_design(system, Q=[1.0, 2.0, 3.0])


def test_lqr_controller_wraps_and_saturates():
    system = get_system("pendulum")
    d = lqr_design(system)
    x = torch.tensor([[0.3, -0.2], [0.3 + 2 * math.pi, -0.2], [3.0, 0.0], [-3.0, 0.0]], dtype=torch.float64)
    u = d.controller(x)
    assert u.shape == (4, 1) and u.dtype == torch.float64
    assert torch.allclose(u[0], u[1])  # angle wrapped into [-pi, pi)
    assert u.abs().max() <= 15.0
    assert u[2, 0] == -15.0 and u[3, 0] == 15.0  # saturated far from upright
    z = system.to_local(x)
    assert torch.allclose(d.certificate(x), torch.einsum("bi,ij,bj->b", z, d.P, z))


def test_lqr_stabilises_pendulum_small_deviations_true_model():
    system = get_system("pendulum")
    d = lqr_design(system)
    x0 = initial_states(system, 16, torch.Generator().manual_seed(1), box=((-0.3, -0.5), (0.3, 0.5)))
    for xi in (None, torch.tensor([0.1, 0.05], dtype=torch.float64)):
        result = evaluate(system, d.controller, x0, xi, lyapunov=d.certificate, horizon=6.0)
        assert result["n_success"] == 16
        # near x* the quadratic Lyapunov function decreases along the true closed loop
        assert result["worst_v_increase"] <= 1e-12


def test_lqr_run_dir_round_trip(tmp_path):
    metrics = train_lqr("pendulum", tmp_path / "lqr", evaluate_test=False)
    assert metrics["samples"] == 0
    info = json.loads((tmp_path / "lqr" / "run.json").read_text())
    assert info["kind"] == "lqr" and info["format"] == 2 and info["system"]["name"] == "pendulum"
    config = json.loads((tmp_path / "lqr" / "config.json").read_text())
    assert config["system"] == "pendulum" and len(config["Q"]) == 2 and len(config["R"]) == 1
    run = load_policy_run(tmp_path / "lqr")
    assert run.kind == "lqr" and run.system.name == "pendulum" and run.samples == 0
    d = lqr_design(get_system("pendulum"))
    x = torch.randn(32, 2, dtype=torch.float64) * 2
    assert torch.allclose(run.controller(x), d.controller(x))
    assert torch.allclose(run.certificate(x), d.certificate(x))
    with pytest.raises(RunDirError, match="already exists"):
        save_lqr_run(tmp_path / "lqr", d)
    with pytest.raises(RunDirError, match="no run.json"):
        load_policy_run(tmp_path)


def test_load_policy_run_unknown_kind(tmp_path):
    from drlyap.runs.directory import run_record

    (tmp_path / "run.json").write_text(json.dumps({**run_record("lqr", get_system("pendulum")), "kind": "mystery"}))
    with pytest.raises(RunDirError, match="run.json: kind: 'mystery' is not one of"):
        load_policy_run(tmp_path)


def _fake_lyapunov_run(path):
    """A Lyapunov run directory with untrained networks (no training: fast)."""
    system = get_system("pendulum")
    cfg = TrainConfig(system="pendulum", iters=7).resolved(system)
    torch.manual_seed(0)
    lyap, ctrl = TrainSections.of(cfg).networks.build(system)
    result = TrainResult(cfg, system, lyap, ctrl, torch.zeros(5, 2, dtype=torch.float64), None, [],
                         {"iterations": 7, "train_time_s": 1.5, "xi_samples": [[0.0, 0.0]], "xi_train": [[0.0, 0.0]]})
    return save_run(path, result)


def test_lyapunov_run_through_common_loader(tmp_path):
    from drlyap.runs import load_run

    _fake_lyapunov_run(tmp_path / "lyap")
    run = load_policy_run(tmp_path / "lyap")
    ref = load_run(tmp_path / "lyap")
    assert run.kind == "lyapunov" and run.label == "lyapunov-dr-pointwise"
    assert run.samples == 3600 * 7 and run.info["distinct_states"] == 3600 and run.train_time_s == 1.5
    x = torch.randn(8, 2, dtype=torch.float64)
    assert torch.equal(run.controller(x), ref.controller(x))
    assert torch.equal(run.certificate(x), ref.lyapunov(x))


def test_monotonicity_counts_increases():
    system = get_system("mountain-car")
    x = torch.zeros(5, 3, 2, dtype=torch.float64)
    v = torch.tensor([[4.0, 4.0, 1.0], [3.0, 5.0, 1.0], [2.0, 3.0, 1.0], [1.0, 4.0, 1.0], [0.0, 0.0, 1.0]],
                     dtype=torch.float64)
    m = monotonicity(system, x, v, torch.tensor([True, True, False]))
    assert m["counted_steps"] == 8 and m["increase_fraction"] == pytest.approx(2 / 8)
    assert m["monotone_fraction"] == pytest.approx(0.5)
    none = monotonicity(system, x, v, torch.tensor([False, False, False]))
    assert none["increase_fraction"] is None


def test_monotonicity_skips_angle_wrap():
    system = get_system("pendulum")
    x = torch.tensor([[[3.0, 1.0]], [[3.2, 1.0]], [[3.3, 1.0]]], dtype=torch.float64)  # crosses pi
    v = torch.tensor([[1.0], [0.0], [5.0]], dtype=torch.float64)
    m = monotonicity(system, x, v, torch.tensor([True]))
    assert m["counted_steps"] == 1 and m["increase_fraction"] == 1.0


def test_score_run_agrees_with_evaluate(tmp_path):
    train_lqr("pendulum-u9", tmp_path / "lqr9", evaluate_test=False)
    run = load_policy_run(tmp_path / "lqr9")
    x0 = initial_states(run.system, 12, torch.Generator().manual_seed(3))
    xi = torch.tensor([0.1, 0.05], dtype=torch.float64)
    row = score_run(run, x0, xi, horizon=8.0)
    ref = evaluate(run.system, run.controller, x0, xi, horizon=8.0)
    assert row["success"] == ref["success"] and row["n_success"] == ref["n_success"]


def test_compare_and_evaluate_cli(tmp_path):
    runner = CliRunner()
    res = runner.invoke(main, ["lqr", "pendulum", "--out", str(tmp_path / "lqr"), "--n-init", "4"])
    assert res.exit_code == 0, res.output
    assert "stabilised" in res.output
    train_lqr("pendulum-u9", tmp_path / "lqr9", evaluate_test=False)
    _fake_lyapunov_run(tmp_path / "lyap")
    res = runner.invoke(main, ["evaluate", str(tmp_path / "lqr"), "--xi", "0.1,0.05", "--n-init", "4",
                               "--horizon", "3", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["n"] == 4
    res = runner.invoke(main, ["evaluate", str(tmp_path / "lyap"), "--xi", "0.1,0.05", "--n-init", "2", "--horizon", "1"])
    assert res.exit_code == 0, res.output
    out = tmp_path / "cmp"
    res = runner.invoke(main, ["compare", str(tmp_path / "lqr"), str(tmp_path / "lqr9"), str(tmp_path / "lyap"),
                               "--xi", "0.1,0.05", "--n-init", "3", "--horizon", "2", "--certify-time", "2", "--out",
                               str(out)])
    assert res.exit_code == 0, res.output
    assert "| lqr |" in res.output and "lyapunov-dr-pointwise" in res.output
    assert "'violated' means a state of that region where it fails" in res.output  # the table's words explained
    report = json.loads((out / "compare.json").read_text())
    assert [r["samples"] for r in report["rows"]] == [0, 0, 3600 * 7]
    assert "certified radius; shift box" in res.output
    robust = [r["certified"]["robustness"] for r in report["rows"]]
    assert robust[0]["radius"] is None and robust[0]["shift_scale"] == [0.1, 0.05]  # LQR: no Wasserstein condition
    assert "radius" in robust[2] and "shift_box_s" in robust[2]
    assert len(report["figures"]) == 2 and all((out / "figures" / f"certificate_and_input_{i}.png").is_file()
                                               for i in range(2))
    assert (out / "compare.md").is_file()
    res = runner.invoke(main, ["compare", str(tmp_path / "lqr"), "--xi", "0.1"])
    assert res.exit_code != 0 and "takes 2 xi value" in res.output
    res = runner.invoke(main, ["compare", str(tmp_path / "nothing"), "--xi", "0.1,0.05"])
    assert res.exit_code != 0 and "does not exist" in res.output


def test_compare_runs_requires_runs():
    with pytest.raises(ValueError, match="at least one"):
        compare_runs([], CompareSettings(xi=[0.0]))


def test_lqr_pair_is_verifiable_and_its_region_of_attraction_is_certified():
    """The verifier takes LQR's z'Pz and clamp(-Kz) as a pair: decrease is checked soundly and a sublevel set
    is certified on the pendulum at the test shift."""
    import math

    from drlyap.conditions import TrueDecrease
    from drlyap.networks import LinearController, QuadraticLyapunov
    from drlyap.verification import certified_roa, verify_condition

    system = get_system("pendulum")
    design = lqr_design(system)
    lyapunov = QuadraticLyapunov(design.P)
    controller = LinearController(design.K, system.input_box, system.equilibrium_input)
    x = torch.tensor([[0.3, -1.0], [3.0, 5.0], [-2.0 * math.pi + 0.1, 0.0]], dtype=torch.float64)
    assert torch.allclose(controller(system.to_local(x)), design.controller(x))
    assert torch.allclose(lyapunov(system.to_local(x)), design.certificate(x))
    spec = TrueDecrease(torch.tensor([[0.1, 0.05]]), decay_rate=0.0)
    loop = ClosedLoop(system, lyapunov, controller)
    result = verify_condition(loop, spec, Region.of(system, 0.5), Budget(seconds=10, enclosure="mean-value"))
    assert result.status == "violated"  # saturation: z'Pz is not a certificate on the whole box
    cex = torch.tensor([result.counterexample], dtype=torch.float64)
    assert ClosedLoop(system, lyapunov, controller).exact(spec, system.to_local(cex)).item() > 0
    roa = certified_roa(ClosedLoop(system, lyapunov, controller), spec, Region.of(system, 0.5), Budget(seconds=10))
    assert roa.certified and 0 < roa.share_of_box < 1
    # on the certified sublevel set the decrease really holds (dense check)
    z = torch.rand(20000, 2, dtype=torch.float64) * torch.tensor([2 * math.pi, 16.0]) - torch.tensor([math.pi, 8.0])
    inside = (lyapunov(z) <= roa.level) & (z.norm(dim=-1) >= 0.5)
    assert inside.any() and (ClosedLoop(system, lyapunov, controller).exact(spec, z[inside]) <= 0).all()
