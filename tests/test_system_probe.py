"""A user's dynamics are run once when the system is loaded, through what training, the verifier and the checker will
run them on: an operation one of them cannot take is one `Error:` line naming the file, the line and the operation,
before any training (each broken system below failed today only after training, or with a traceback)."""

import dataclasses
import re
import time

import pytest
from click.testing import CliRunner

import drlyap
import drlyap.training
from drlyap.cli import main
from drlyap.systems import get_system, resolve_system, system_names
from drlyap.systems.probe import probe_system

HEAD = '''import numpy as np
import torch
from drlyap import UncertainSystem


def dynamics(x, u, p):
    (friction,) = p.unbind(-1)
'''

TAIL = '''

def make():
    return UncertainSystem(
        name="cart", state_names=("q", "v"), input_names=("f",), param_names=("friction",),
        nominal_params=(0.5,), uncertain=("friction",), dynamics=dynamics,
        state_box=((-1, -1), (1, 1)), input_box=((-2,), (2,)), equilibrium=(0.0, 0.0),
        xi_sampler=lambda n, g: 0.1 * torch.randn(n, 1, generator=g, dtype=torch.float64),
        test_xi=(-0.3,))
'''

GOOD = "    return torch.stack([x[:, 1], -friction * x[:, 1] + u[:, 0]], dim=-1)"

# (name, the body of dynamics: "# here" marks the line the error must name, "def" for the def line; what it must say)
BROKEN = [
    ("abs", "    return torch.stack([x[:, 1], -friction * torch.abs(x[:, 1]) * x[:, 1] + u[:, 0]], dim=-1)  # here",
     "torch.abs is not supported by drlyap's verifier on dual numbers"),
    ("numpy", "    return torch.stack([x[:, 1], -friction * x[:, 1] + u[:, 0] - np.sin(x[:, 0])], dim=-1)  # here",
     "np.sin is a numpy function: numpy functions cannot run on tensors that carry gradients (training) nor on "
     "drlyap's enclosures (the verifier's, the checker's); use torch.sin"),
    ("raises", "    raise RuntimeError('bug in my dynamics')  # here", "the dynamics raised RuntimeError: bug in my dynamics"),
    ("batch", "    (c,) = p.unbind(0)  # here\n    return torch.stack([x[:, 1], -c * x[:, 1] + u[:, 0]], dim=-1)",
     "ValueError: too many values to unpack (expected 1) on float64 tensors (x (6, 2)"),
    ("shape", GOOD + ".reshape(1, -1)  # def", "the dynamics returned shape (1, 12) for B = 6 states, expected (B, n)"),
    ("dtype", GOOD + ".float()  # def", "the dynamics returned torch.float32 on torch.float64 inputs"),
    ("fill", "    out = torch.zeros_like(x)  # here\n    out[:, 0] = x[:, 1]\n    out[:, 1] = -friction * x[:, 1] + u[:, 0]\n"
             "    return out", "torch.zeros_like is not supported by drlyap's verifier"),
    ("item", "    k = float(friction[0])  # here\n    return torch.stack([x[:, 1], -k * x[:, 1] + u[:, 0]], dim=-1)",
     "float()/int()/.item() fails on drlyap's verifier"),
    ("branch", "    v = x[:, 1]\n    if (v > 0).all():  # here\n        v = 2 * v\n"
               "    return torch.stack([x[:, 1], -friction * v + u[:, 0]], dim=-1)",
     "the comparison > is not supported by drlyap's verifier"),
    ("where", "    drag = torch.where(x[:, 1] > 0, x[:, 1], 2 * x[:, 1])  # here\n"
              "    return torch.stack([x[:, 1], -friction * drag + u[:, 0]], dim=-1)",
     "the comparison > is not supported by drlyap's verifier"),
    ("power", "    return torch.stack([x[:, 1], -friction * x[:, 1] * (1 + x[:, 0] ** 2) ** 0.5 + u[:, 0]], dim=-1)  # here",
     "the power ** 0.5 is not supported by drlyap's verifier"),
    ("float64-constant", "    a = torch.tensor([[0.0, 1.0], [0.0, -0.5]], dtype=torch.float64)\n"
                         "    return x @ a.T + torch.stack([0 * x[:, 0], u[:, 0] - (friction - 0.5) * x[:, 1]], -1)  # here",
     "a float64 constant meets the float32 tensors training runs on"),
    ("checker-linear", "    a = torch.tensor([[0.0, 1.0], [0.0, -0.5]])\n"
                       "    drift = torch.nn.functional.linear(x, a.to(x.dtype))  # here\n"
                       "    return drift + torch.stack([0 * x[:, 0], u[:, 0] - (friction - 0.5) * x[:, 1]], -1)",
     "torch.nn.functional.linear is not supported by drlyap's checker"),
]


def write(path, body: str):
    path.write_text(HEAD + body + "\n" + TAIL)
    return path


def named_line(path) -> int:
    lines = path.read_text().splitlines()
    marker = next(i for i, text in enumerate(lines) if text.rstrip().endswith(("# here", "# def")))
    if lines[marker].rstrip().endswith("# def"):
        marker = next(i for i, text in enumerate(lines) if text.startswith("def dynamics"))
    return marker + 1


@pytest.fixture
def no_training(monkeypatch):
    """``drlyap train`` must stop before it reaches training."""
    def refuse(*args, **kwargs):
        raise AssertionError("training started")

    monkeypatch.setattr(drlyap.training, "train", refuse)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # numpy's, on the tensor the numpy system hands it
@pytest.mark.parametrize("name, body, says", BROKEN, ids=[b[0] for b in BROKEN])
def test_a_broken_system_is_one_error_line_before_training(tmp_path, no_training, name, body, says):
    file = write(tmp_path / f"user_{name}.py", body)  # (not numpy.py: it would shadow numpy where cwd is on the path)
    start = time.perf_counter()
    result = CliRunner().invoke(main, ["train", f"{file}:make", "--iters", "1", "--out", str(tmp_path / "out")])
    seconds = time.perf_counter() - start
    assert result.exit_code == 1, result.output
    assert not isinstance(result.exception, AssertionError), result.output  # not the training stand-in's
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.output
    assert f"{file.name}:{named_line(file)}" in lines[0], lines[0]
    assert says in lines[0], lines[0]
    assert "checked when loaded, before any training or proof" in lines[0]
    assert not (tmp_path / "out").exists() and seconds < 10


def test_the_python_api_checks_a_system_object_where_training_takes_it(tmp_path):
    file = write(tmp_path / "abs_api.py", BROKEN[0][1])
    module: dict = {}
    exec(compile(file.read_text(), str(file), "exec"), module)
    system = module["make"]()  # an object, never resolved: x* alone is no reason to refuse it
    with pytest.raises(ValueError, match=r"abs_api\.py:8: torch\.abs is not supported by drlyap's verifier"):
        drlyap.train(drlyap.TrainConfig(system="cart", iters=1), system=system, progress=False)


def test_the_checker_alone_takes_abs(tmp_path):
    """``verifier=False`` (a command that runs only the checker): the checker's duals take abs (the Clarke gradient),
    the verifier's do not."""
    file = write(tmp_path / "abs_checker.py", BROKEN[0][1])
    assert resolve_system(f"{file}:make", verifier=False).name == "cart"
    with pytest.raises(ValueError, match="torch.abs is not supported by drlyap's verifier on dual numbers"):
        resolve_system(f"{file}:make", verifier=True)


def test_built_in_and_readme_systems_pass_and_are_probed_once(tmp_path):
    for name in system_names():
        probe_system(get_system(name))
    system = resolve_system(f"{write(tmp_path / 'cart.py', GOOD)}:make", verifier=True)
    calls = []

    def counted(x, u, p):
        calls.append(1)
        return system.dynamics(x, u, p)

    counting = dataclasses.replace(system, dynamics=counted)
    calls.clear()
    probe_system(counting)
    assert len(calls) > 20  # tensors with autograd, every enclosure of the verifier and of the checker
    calls.clear()
    probe_system(counting)
    probe_system(dataclasses.replace(counting))  # another object, the same dynamics, boxes and parameters
    assert calls == [1]  # F at x* when the copy is built; the probe not again


def test_a_system_that_raises_when_built_names_its_line(tmp_path):
    file = write(tmp_path / "at_rest.py", "    raise ValueError('bug in my dynamics')  # here")
    with pytest.raises(ValueError, match=re.escape(f"at_rest.py:{named_line(file)}: the dynamics raised ValueError: "
                                                   "bug in my dynamics on float64 tensors at x* = [0.0, 0.0]")):
        resolve_system(f"{file}:make")
