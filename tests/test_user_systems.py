"""A user's own system, defined in a Python file, through every command; reloads that refuse other dynamics."""

import io
import json
import math
import re
import shlex

import pytest
import torch
from click.testing import CliRunner

import drlyap
from drlyap.cli import main
from drlyap.progress import progress
from drlyap.runs import RunDirError, load_run
from drlyap.systems import UncertainSystem, get_system, resolve_system
from drlyap.workflows.policies import load_policy_run

SYSTEM_FILE = '''
import torch
from drlyap import UncertainSystem


def dynamics(x, u, p):
    (c,) = p.unbind(-1)
    return torch.stack([x[:, 1], -c * x[:, 1] + u[:, 0]], dim=-1)   # damped double integrator


def make():
    return UncertainSystem(
        name=NAME, state_names=("q", "v"), input_names=("f",), param_names=("damping",),
        nominal_params=(DAMPING,), uncertain=("damping",), dynamics=dynamics,
        state_box=((-1.0, -1.0), (1.0, 1.0)), input_box=((-2.0,), (2.0,)), equilibrium=(0.0, 0.0),
        xi_sampler=lambda n, g: 0.05 * torch.randn(n, 1, generator=g, dtype=torch.float64),
        test_xi=(-0.2,), reference_states=((-0.8, 0.5),), horizon=5.0,
        defaults={"n_states": 128, "lyapunov_hidden": [8, 8], "controller_hidden": [8, 8]},
    )
'''


def write_system(path, name="user-dint", damping=0.5):
    path.write_text(SYSTEM_FILE.replace("NAME", repr(name)).replace("DAMPING", repr(damping)))
    return path


def invoke(*args):
    result = CliRunner().invoke(main, [str(a) for a in args])
    return result


@pytest.fixture(scope="module")
def user_runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("user")
    file = write_system(tmp / "dint.py")
    train = invoke("train", f"{file}:make", "--iters", "20", "--quiet", "--json", "--verify-rounds", "1",
                   "--verify-time", "2", "--out", tmp / "run")
    assert train.exit_code == 0, train.output
    lqr = invoke("lqr", f"{file}:make", "--n-init", "5", "--json", "--out", tmp / "lqr")
    assert lqr.exit_code == 0, lqr.output
    return tmp, file, json.loads(train.stdout), json.loads(lqr.stdout)


def test_user_file_system_trains_evaluates_verifies_and_compares(user_runs):
    tmp, file, trained, lqr = user_runs
    assert trained["system"] == "user-dint" and trained["metrics"]["cegis"]["total_iterations"] >= 20
    assert trained["metrics"]["certificate"]["status"] in {"verified", "violated", "unknown"}
    assert lqr["system"] == "user-dint" and len(lqr["gains"]["K"][0]) == 2
    with pytest.raises(ValueError, match="unknown system"):
        get_system("user-dint")  # nothing registered it: every command below is given it or trusts run.json
    source = json.loads((tmp / "run" / "run.json").read_text())["system_source"]
    assert source["path"] == str(file.resolve()) and source["reload"] == f"{file.resolve()}:make"

    ev = invoke("evaluate", tmp / "run", "--system", f"{file}:make", "--xi", "-0.2", "--n-init", "4", "--horizon", "1",
                "--json")
    assert ev.exit_code == 0, ev.output
    assert json.loads(ev.stdout)["n"] == 4
    ver = invoke("verify", tmp / "run", "--trust-run", "--time-limit", "1", "--json")
    assert ver.exit_code == 0, ver.output
    assert json.loads(ver.stdout)["trained"]["status"] in {"verified", "violated", "unknown"}
    cmp_ = invoke("compare", tmp / "run", tmp / "lqr", "--trust-run", "--xi", "-0.2", "--n-init", "4", "--horizon", "1",
                  "--certify-time", "0.5", "--json", "--out", tmp / "cmp")
    assert cmp_.exit_code == 0, cmp_.output
    rows = json.loads(cmp_.stdout)["rows"]
    assert [r["kind"] for r in rows] == ["lyapunov", "lqr"] and all(r["system"] == "user-dint" for r in rows)
    assert (tmp / "cmp" / "figures" / "certificate_and_input_0.png").is_file()  # from the declared reference state
    # the pair trained for {V <= 1} is proved on that set, the LQR pair on X_delta: each row names its set
    assert rows[0]["certified"]["level"] == 1.0 and "level" not in rows[1]["certified"]
    table = (tmp / "cmp" / "compare.md").read_text().splitlines()
    lyap, lqr = (next(line for line in table if line.startswith(f"| {tmp / name} |")) for name in ("run", "lqr"))
    assert f"| {rows[0]['certified']['status']} on {{V <= 1}}" in lyap and "X_delta" in lqr


def test_a_changed_system_file_is_refused(user_runs, tmp_path):
    tmp, file, _, _ = user_runs
    original = file.read_text()
    try:
        write_system(file, damping=0.7)
        for path in (tmp / "run", tmp / "lqr"):
            with pytest.raises(RunDirError, match="other dynamics.*damping"):
                load_policy_run(path, trust=True)
        result = invoke("evaluate", tmp / "run", "--trust-run", "--xi", "-0.2", "--n-init", "2")
        assert result.exit_code != 0 and "other dynamics" in result.output
    finally:
        file.write_text(original)
    assert load_run(tmp / "run", trust=True).system.nominal_params == (0.5,)


def test_config_and_run_json_must_name_the_same_system(user_runs, tmp_path):
    import shutil

    tmp, _, _, _ = user_runs
    shutil.copytree(tmp / "run", tmp_path / "run")
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    info["system"]["name"] = "pendulum"
    (tmp_path / "run" / "run.json").write_text(json.dumps(info))
    with pytest.raises(RunDirError, match="inconsistent"):
        load_run(tmp_path / "run")


def test_train_refuses_a_config_naming_another_system(tmp_path):
    system = resolve_system(f"{write_system(tmp_path / 'd.py', name='other')}:make")
    with pytest.raises(ValueError, match="names another system"):
        drlyap.train(drlyap.TrainConfig(system="pendulum", iters=1), system=system, progress=False)


def test_resolve_system_forms_and_errors(tmp_path):
    assert resolve_system("pendulum").name == "pendulum"
    assert resolve_system("drlyap.systems:mountain_car").name == "mountain-car"
    file = write_system(tmp_path / "s.py")
    for spec, message in [("nope", "unknown system 'nope'"), (str(file), "add ':factory'"),
                          (f"{file}:missing", "no attribute 'missing'"), (f"{tmp_path}/none.py:make", "does not exist"),
                          ("no_such_module_xyz:make", "cannot import module"), (f"{file}:torch", "not an UncertainSystem")]:
        with pytest.raises(ValueError, match=message):
            resolve_system(spec)


def _kwargs(**over):
    base = dict(name="bad", state_names=("q", "v"), input_names=("f",), param_names=("c",), nominal_params=(0.5,),
                uncertain=("c",), dynamics=lambda x, u, p: torch.stack([x[:, 1], -p[:, 0] * x[:, 1] + u[:, 0]], -1),
                state_box=((-1, -1), (1, 1)), input_box=((-1,), (1,)), equilibrium=(0.0, 0.0))
    return base | over


@pytest.mark.parametrize("over, message", [
    ({"nominal_params": (math.nan,)}, "nominal_params must be finite, got c=nan"),
    ({"equilibrium": (0.0, math.inf)}, "equilibrium must be finite"),
    ({"equilibrium_input": (math.nan,)}, "equilibrium_input must be finite"),
    ({"test_xi": (math.inf,)}, "test_xi must be finite"),
    ({"reference_states": ((0.1,),)}, r"reference_states\[0\] has 1 entries, state has 2"),
    ({"xi_sampler": lambda n, g: torch.zeros(n, 2)}, r"xi_sampler\(N, generator\) must return shape \(N, 1\).*got \(4, 2\)"),
    ({"xi_sampler": lambda n, g: torch.full((n, 1), math.nan)}, "xi_sampler returned non-finite"),
])
def test_bad_systems_are_refused_when_built(over, message):
    with pytest.raises(ValueError, match=f"bad: {message}"):
        UncertainSystem(**_kwargs(**over))


def test_reproduce_needs_a_test_shift(tmp_path):
    system = UncertainSystem(**_kwargs(name="no-test", xi_sampler=lambda n, g: torch.zeros(n, 1)))
    from drlyap.workflows.reproduce import ReproduceSettings, reproduce

    with pytest.raises(ValueError, match="declares no test_xi"):
        reproduce(system, ReproduceSettings(seeds=[0]), tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_progress_lines_when_piped_and_nothing_when_disabled():
    stream = io.StringIO()
    bar = progress(3, "work", stream=stream, every=0.0)
    bar.set_postfix(loss="1e-3")
    bar.update(2)
    bar.close()
    assert "work: 2/3 (67%) loss=1e-3" in stream.getvalue()
    count = io.StringIO()
    bar = progress(None, "search", stream=count, every=0.0)  # no known end: a count
    bar.update(5)
    assert count.getvalue().startswith("search: 5, ")
    quiet = io.StringIO()
    bar = progress(3, "work", enabled=False, stream=quiet)
    bar.update(3)
    bar.close()
    assert quiet.getvalue() == ""


def test_reproduce_takes_a_user_file(user_runs):
    tmp, file, _, _ = user_runs
    result = invoke("reproduce", f"{file}:make", "--iters", "2", "--seeds", "0", "--verify-rounds", "0", "--verify-time",
                    "1", "--horizon", "2", "--json", "--out", tmp / "rep")
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["system"] == "user-dint" and report["test_xi"] == [-0.2]
    assert load_run(tmp / "rep" / "seed0" / "dr", trust=True).system.name == "user-dint"


def test_sweep_takes_a_user_file(user_runs):
    tmp, file, _, _ = user_runs
    result = invoke("sweep", f"{file}:make", "--seeds", "0", "--radius", "0.01", "--iters", "10", "--verify-rounds",
                    "0", "--verify-time-limit", "1", "--n-init", "4", "--shifts", "1", "--json", "--out", tmp / "sw")
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["failed"] == 0 and len(report["rows"]) == 1
    run = load_run(tmp / "sw" / report["rows"][0]["name"], trust=True)
    assert run.system.name == "user-dint" and run.metrics["certificate"]["status"] in ("verified", "violated", "unknown")


def test_run_kind_loaders_are_one_table():
    from drlyap.workflows.policies import LOADERS

    assert {"lyapunov", "lqr", "rl"} <= set(LOADERS)


def _run_printed(output: str, pattern: str, codes: tuple[int, ...] = (0,)) -> str:
    """The command a previous one printed (``pattern``'s group), run through the command line exactly as printed;
    ``codes``: the exit statuses it may end with (a verify whose claim is violated or unknown ends with 3 or 4)."""
    found = re.search(pattern, output)
    assert found, (pattern, output)
    words = shlex.split(found.group(1))
    assert words[0] == "drlyap", words
    result = CliRunner().invoke(main, words[1:])
    assert result.exit_code in codes, (found.group(1), result.output)
    return result.output


def test_printed_commands_run_as_printed(tmp_path):
    """The next steps train, verify and import print for a system from a file carry --system with the run's
    recorded spec, and run as printed."""
    file = write_system(tmp_path / "dint.py")
    train = invoke("train", f"{file}:make", "--iters", "20", "--quiet", "--no-verify", "--out", tmp_path / "run")
    assert train.exit_code == 0, train.output
    assert f"--system {file.resolve()}:make" in train.output
    verified = _run_printed(train.output, r"certificate: NOT CHECKED .*; run `([^`]*)`")
    checked = _run_printed(verified, r"re-check it with `([^`]*)`")
    assert "trained: CHECKED" in checked
    region = invoke("verify", tmp_path / "run", "--system", f"{file}:make", "--xi", "-0.2", "--roa", "--time-limit", "2")
    assert region.exit_code == 0, region.output
    assert re.search(r"drawn by `drlyap plot \S+ --xi -0.2 --system ", region.output)  # at the shift it was proved
    drawn = _run_printed(region.output, r"drawn by `([^`]*)`")
    assert "trajectories stabilised" in drawn and "phase_portrait.png" in drawn
    exported = invoke("export", tmp_path / "run", "--system", f"{file}:make")
    assert exported.exit_code == 0, exported.output
    imported = invoke("import", f"{file}:make", "--controller", tmp_path / "run" / "export" / "controller.onnx",
                      "--out", tmp_path / "imported")
    assert imported.exit_code == 0, imported.output
    proved = _run_printed(imported.output, r"prove it: (.*)", codes=(0, 3, 4))
    assert "true model at xi = [-0.2]" in proved


def test_a_printed_command_quotes_what_the_shell_would_split(tmp_path):
    from drlyap.cli.common import command_hint

    source = {"spec": "my dir/s.py:make", "reload": "/home/me/my dir/s.py:make", "path": "/home/me/my dir/s.py"}
    hint = command_hint("check", tmp_path / "a run", source=source)
    assert shlex.split(hint) == ["drlyap", "check", str(tmp_path / "a run"), "--system", "/home/me/my dir/s.py:make"]
    assert command_hint("check", "runs/p", source={"spec": "pendulum", "reload": "pendulum", "path": None}) == \
        "drlyap check runs/p"


def test_compare_figures_start_from_the_test_box_without_reference_states(tmp_path, monkeypatch):
    """A system that declares no reference states: compare's figures start from states drawn from its test box
    with --seed (not from its centre, x* here, where V and u are flat lines)."""
    from drlyap import plotting

    file = write_system(tmp_path / "plain.py")
    file.write_text(file.read_text().replace("reference_states=((-0.8, 0.5),), ", ""))
    system = resolve_system(f"{file}:make")
    assert system.reference_states == ()
    train = invoke("train", f"{file}:make", "--iters", "20", "--quiet", "--no-verify", "--out", tmp_path / "run")
    assert train.exit_code == 0, train.output
    drawn = []
    real = plotting.time_series

    def record(series, path, title, **kwargs):
        drawn.append((title, series))
        return real(series, path, title, **kwargs)

    monkeypatch.setattr(plotting, "time_series", record)
    result = invoke("compare", tmp_path / "run", "--system", f"{file}:make", "--xi", "-0.2", "--n-init", "4",
                    "--seed", "3", "--horizon", "1", "--certify-time", "0", "--out", tmp_path / "cmp")
    assert result.exit_code == 0, result.output
    starts = system.figure_starts(3)
    assert len(drawn) == len(starts) == 2 and starts != system.figure_starts(4)
    (lo, hi), x_star = system.test_box, system.equilibrium
    for (title, series), start in zip(drawn, starts):
        assert all(a <= v <= b for a, v, b in zip(lo, start, hi)) and tuple(start) != tuple(x_star)
        assert f"from ({', '.join(f'{v:.3g}' for v in start)})" in title
        (_, value, u), = series.values()
        assert float(value.max() - value.min()) > 1e-3 and float(u.max() - u.min()) > 0  # not flat lines


def test_a_growing_set_says_how_many_iterations_grew_it(tmp_path):
    """A system of one's own trains a growing set {V <= 1}: the growth term acts on the first two thirds of the
    iterations (GROW_SHARE), the rest repair the condition, and the training status says so."""
    from drlyap.training.trainer import GROW_SHARE, growth_words

    system = resolve_system(f"{write_system(tmp_path / 'g.py')}:make")
    result = drlyap.train(drlyap.TrainConfig(system=system.name, iters=20), system=system, proof=None, progress=False)
    grown = math.floor(GROW_SHARE * 20)
    assert grown == 13 and result.config.grow_weight > 0 and result.config.roa_level == 1.0
    assert result.metrics["passed"]
    assert result.metrics["status"] == ("grew the set for 13 of 20 iterations, then repaired the condition on it; kept "
                                        "the latest pair passing the acceptance check")
    assert growth_words(20, 20) == "grew the set for all 20 iterations"
