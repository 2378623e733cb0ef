"""Figures: units on axes, input limits on u(t), what the drawn certified set is called, and `drlyap plot`."""

import dataclasses
import json

import matplotlib.pyplot as plt
import pytest
import torch
from click.testing import CliRunner

from drlyap import plotting
from drlyap.cli import main
from drlyap.render import region_label
from drlyap.simulation import simulate
from drlyap.systems import get_system, pendulum
from drlyap.verification import RegionOfAttraction

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("plot") / "run"
    result = CliRunner().invoke(main, ["train", "pendulum", "--method", "dr", "--iters", "10", "--quiet",
                                       "--verify-rounds", "0", "--verify-time", "2", "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


def test_units_are_validated_and_described():
    sys_ = pendulum()
    assert sys_.describe()["state_units"] == ["rad", "rad/s"] and sys_.describe()["time_unit"] == "s"
    assert plotting.state_label(sys_, 0) == "theta [rad]" and plotting.time_label(sys_) == "t [s]"
    assert get_system("mountain-car").state_units == ("u.", "u./step")
    with pytest.raises(ValueError, match="state_units must be empty or 2"):
        dataclasses.replace(sys_, state_units=("rad",))
    with pytest.raises(ValueError, match="input_units"):
        dataclasses.replace(sys_, input_units="N m")  # a string, not one unit per input


def test_region_label_names_a_region_of_attraction_only_when_certified():
    where = "xi = (mass +0.1)"
    yes = region_label(RegionOfAttraction(level=2.5, certified=True, ball_max_upper=0.3), where)
    assert yes == "certified region of attraction {V <= 2.5} at xi = (mass +0.1)"
    no = region_label(RegionOfAttraction(level=0.2, certified=False, ball_max_upper=0.3), where)
    assert "region of attraction" not in no and no.startswith("not certified") and "{V <= 0.2}" in no
    practical = region_label(RegionOfAttraction(level=2.0, certified=True, kind="practical stability",
                                                ball_max_upper=0.5), where)
    assert "region of attraction" not in practical and "practical stability" in practical
    assert "converges to {V <= 0.5}" in practical
    assert region_label(RegionOfAttraction(level=0.0, certified=False), where) == ""
    assert region_label(None, where) == ""


def test_input_limits_drawn_on_u_plot():
    sys_ = pendulum()
    t = torch.linspace(0, 1, 11)
    series = {"a": (t, torch.exp(-t), 3 * torch.ones(11)), "b": (t, torch.exp(-2 * t), -torch.ones(11))}
    fig = plotting.time_series_figure(series, input_label=plotting.input_label(sys_),
                                      time_label=plotting.time_label(sys_), limits=plotting.input_limits(sys_))
    labels = [line.get_label() for line in fig.axes[1].lines]
    assert "u_max = 15 N m" in labels and "u_min = -15 N m" in labels
    ymin, ymax = fig.axes[1].get_ylim()
    assert ymin < -15 and ymax > 15  # both limits visible
    assert fig.axes[1].get_ylabel() == "u(t) = torque [N m]" and fig.axes[0].get_xlabel() == "t [s]"
    plt.close(fig)
    nine = plotting.input_limits_of([pendulum(), pendulum(9.0)])
    assert [v for v, _ in nine] == [15.0, -15.0, 9.0, -9.0] and nine[2][1] == "pendulum-u9: u_max = 9 N m"


def test_phase_panel_has_units_contour_labels_and_region():
    sys_ = pendulum()
    lyap = lambda x: (sys_.to_local(x) ** 2).sum(-1)  # noqa: E731
    policy = lambda x: -20 * sys_.to_local(x)[:, :1] - 5 * x[:, 1:]  # noqa: E731
    traj = simulate(sys_, policy, torch.tensor([[0.5, 0.0], [-1.0, 1.0]], dtype=torch.float64), None, horizon=1.0)
    fig, ax = plt.subplots()
    region = {"level": 4.0, "certified": True, "label": region_label(RegionOfAttraction(level=4.0, certified=True), "x")}
    plotting.draw_phase(ax, sys_, traj, [True, False], plotting.lyapunov_grid(sys_, lyap, 40), region, delta=0.5)
    assert ax.get_xlabel() == "theta [rad]" and ax.get_ylabel() == "theta_dot [rad/s]"
    labels = ax.get_legend_handles_labels()[1]
    assert region["label"] in labels
    assert "stabilised (1 of 2)" in labels and "not stabilised (1 of 2)" in labels  # one entry per colour
    assert any(text.get_text().startswith("V=") for text in ax.texts)  # labelled level sets
    plt.close(fig)


def test_sweep_plot_shows_every_seed(tmp_path):
    rows = [{"method": m, "more_200": {"n": 10}, "sweep_200": {1: 10, 2: s}} for m in ("baseline", "dr")
            for s in (3, 7, 9)]
    path = plotting.sweep_plot("pendulum", (1, 2), rows, tmp_path / "s.png", [0.1, 0.05])
    assert path.read_bytes()[:8] == PNG


def test_plot_command_writes_figures(run_dir, tmp_path):
    out = tmp_path / "figs"
    result = CliRunner().invoke(main, ["plot", str(run_dir), "--n-init", "3", "--horizon", "2", "--out", str(out), "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["xi"] == [0.1, 0.05] and data["region"] is None and len(data["figures"]) == 4
    assert any(path.endswith("states.png") for path in data["figures"])
    for path in data["figures"]:
        assert path.startswith(str(out)) and open(path, "rb").read(8) == PNG


def test_plot_uses_a_stored_certificate(run_dir, tmp_path):
    metrics_path = run_dir / "metrics.json"
    original = metrics_path.read_text()
    metrics = json.loads(original)
    metrics["certificate"] = {"status": "verified", "condition": "DR pointwise", "true_model": {"xi": [0.1, 0.05]},
                              "roa": {"level": 1.5, "certified": False, "ball_max_upper": 2.0}}
    metrics_path.write_text(json.dumps(metrics))
    try:
        result = CliRunner().invoke(main, ["plot", str(run_dir), "--n-init", "2", "--horizon", "1", "--out", str(tmp_path)])
    finally:
        metrics_path.write_text(original)
    assert result.exit_code == 0, result.output
    assert "not certified at xi = (mass +0.1, damping +0.05)" in result.output
    assert "phase_portrait.png" in result.output


def test_plot_rejects_bad_xi(run_dir, tmp_path):
    result = CliRunner().invoke(main, ["plot", str(run_dir), "--xi", "0.1", "--out", str(tmp_path)])
    assert result.exit_code != 0 and "takes 2 xi value" in result.output


def test_plot_roa_computes_the_set_now(run_dir, tmp_path):
    result = CliRunner().invoke(main, ["plot", str(run_dir), "--n-init", "1", "--horizon", "1", "--roa", "--time-limit", "2",
                                       "--out", str(tmp_path), "--json"])
    assert result.exit_code == 0, result.output
    region = json.loads(result.stdout)["region"]
    if region is not None:  # a 10-iteration pair may certify nothing
        assert ("region of attraction" in region["label"]) == region["certified"]


def test_plots_of_a_six_state_two_input_system(tmp_path):
    quad = get_system("quadrotor2d")
    assert quad.plot_dims == (0, 1) and get_system("cartpole").plot_dims == (1, 3)
    with pytest.raises(ValueError, match="plot_dims"):
        dataclasses.replace(quad, plot_dims=(2, 2))
    u_star = torch.tensor(quad.equilibrium_input, dtype=torch.float64)
    hover = lambda x: u_star.expand(x.shape[0], -1)  # noqa: E731
    traj = simulate(quad, hover, torch.zeros(1, 6, dtype=torch.float64) + 0.1, torch.zeros(2), horizon=0.5)
    assert traj.u.shape[-1] == 2
    limits = plotting.input_limits(quad)
    assert [v for v, _ in limits] == [5.96, 0.0] and "thrust_1, thrust_2" in limits[0][1]  # one shared pair
    fig = plotting.time_series_figure({"hover": (traj.t, torch.ones_like(traj.t), traj.u[:, 0])},
                                      input_names=quad.input_names, limits=limits)
    assert len(fig.axes[1].lines) >= 2 + 2  # both inputs, both limits
    plt.close(fig)
    path = plotting.states_over_time(quad, {"hover": (traj.t, traj.x[:, 0])}, tmp_path / "x.png")
    assert path.read_bytes()[:8] == PNG
    fig, ax = plt.subplots()
    grid = plotting.lyapunov_grid(quad, lambda x: (x ** 2).sum(-1), per_axis=9)
    plotting.draw_phase(ax, quad, traj, [True], grid)
    assert ax.get_xlabel().startswith("x") and ax.get_ylabel().startswith("y")
    assert any("slice" in t.get_text() for t in ax.texts)  # says the V contours are a slice through x*
    plt.close(fig)
