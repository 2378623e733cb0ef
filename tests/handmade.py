"""Hand-made certificate/controller pairs on a small pendulum box, shared by the verification tests."""

import json
from pathlib import Path

import torch
from torch import nn

from drlyap.config import PAPER_CONDITION
from drlyap.networks import Controller, Lyapunov
from drlyap.systems import UncertainSystem

F64 = torch.float64


def _pend(x, u, p):
    theta, omega = x.unbind(-1)
    m, l, b, g = p.unbind(-1)
    return torch.stack([omega, (m * g * l * torch.sin(theta) - b * omega + u[:, 0]) / (m * l * l)], dim=-1)


def small_pendulum(box=((-0.6, -1.2), (0.6, 1.2))) -> UncertainSystem:
    """A user-defined system (the pendulum on a small box) to show the verifier runs user dynamics."""
    return UncertainSystem(
        name="small-pendulum", state_names=("theta", "omega"), input_names=("torque",),
        param_names=("mass", "length", "damping", "gravity"), nominal_params=(1.0, 1.0, 0.13, 9.81),
        uncertain=("mass", "damping"), dynamics=_pend, state_box=box,
        input_box=((-15.0,), (15.0,)), equilibrium=(0.0, 0.0), angle_dims=(0,), defaults=PAPER_CONDITION)


def _offset_pend(x, u, p):
    theta, omega = x.unbind(-1)
    m, l, b, g, bias = p.unbind(-1)
    return torch.stack([omega, (m * g * l * torch.sin(theta) - b * omega + u[:, 0] + bias) / (m * l * l)], dim=-1)


def offset_pendulum() -> UncertainSystem:
    """:func:`small_pendulum` with an uncertain constant torque ``bias`` (nominal 0): a shift of it moves the closed
    loop's equilibrium away from x*, where only practical stability can be proved."""
    return UncertainSystem(
        name="offset-pendulum", state_names=("theta", "omega"), input_names=("torque",),
        param_names=("mass", "length", "damping", "gravity", "bias"), nominal_params=(1.0, 1.0, 0.13, 9.81, 0.0),
        uncertain=("mass", "damping", "bias"), dynamics=_offset_pend, state_box=((-0.6, -1.2), (0.6, 1.2)),
        input_box=((-15.0,), (15.0,)), equilibrium=(0.0, 0.0), angle_dims=(0,), defaults=PAPER_CONDITION)


def linear_pair(system, sign=1.0, eps=1e-2, p=None):
    """V ~ z^T P z (Lyapunov matrix of the LQR-like closed loop, or the ``p`` given) and pi ~ -K z, realised with
    tanh networks."""
    g, b = 9.81, 0.13
    k = torch.tensor([[g + 4.0, 4.0 - b]], dtype=F64)  # closed-loop poles at -2, -2 (nominal model)
    a_cl = torch.tensor([[0.0, 1.0], [g, -b]], dtype=F64) - torch.tensor([[0.0], [1.0]], dtype=F64) @ k
    # solve A^T P + P A = -I by vectorisation
    eye = torch.eye(2, dtype=F64)
    at = a_cl.T.contiguous()
    lhs = torch.kron(eye, at) + torch.kron(at, eye)
    if p is None:
        p = torch.linalg.solve(lhs, -eye.reshape(-1)).reshape(2, 2)
    p = (p + p.T) / 2
    lo, hi = system.local_box()
    s = ((hi - lo) / 2).float()
    alpha_hat = 1e-3
    chol = torch.linalg.cholesky(p - alpha_hat * torch.diag(1 / s.double() ** 2)).T  # P = L^T L + alpha S^-2
    lyap = Lyapunov(2, hidden=[2], out=2, alpha_hat=alpha_hat, input_scale=s.tolist())
    ctrl = Controller(2, system.input_box, system.equilibrium_input, hidden=[1], input_scale=s.tolist())
    with torch.no_grad():
        lyap.phi.layers[0].weight.copy_((eps * chol * s.double()).float())
        lyap.phi.layers[0].bias.zero_()
        lyap.phi.layers[1].weight.copy_(torch.eye(2) / eps)
        lyap.phi.layers[1].bias.zero_()
        ctrl.varphi.layers[0].weight.copy_((eps * k * s.double()).float())
        ctrl.varphi.layers[0].bias.zero_()
        ctrl.varphi.layers[1].weight.fill_(-sign / eps)
        ctrl.varphi.layers[1].bias.zero_()
    return lyap, ctrl


def bump_pair(system, kappa=100.0, beta=1e-3, eps=1e-2):
    """:func:`linear_pair` with a narrow bump added to V: ``V = V_linear + beta tanh(kappa z_1)^2``.

    Away from the strip ``|z_1| < 1/kappa`` the bump is flat and V decreases like the linear pair's; near x* V's
    quadratic part is ``P + beta kappa^2 e_1 e_1^T``, which is not a Lyapunov function of the closed-loop
    linearisation: V's own second-order proof fails at x* (the Hessian of Vdot is indefinite there), while the
    linearisation's ``z^T P z`` works."""
    lyap, ctrl = linear_pair(system, eps=eps)
    s1 = float(lyap.phi.input_scale[0])
    bumped = Lyapunov(2, hidden=[3], out=3, alpha_hat=lyap.alpha_hat, input_scale=lyap.phi.input_scale.tolist())
    with torch.no_grad():
        for layer in bumped.phi.layers:
            layer.weight.zero_()
            layer.bias.zero_()
        bumped.phi.layers[0].weight[:2] = lyap.phi.layers[0].weight
        bumped.phi.layers[1].weight[:2, :2] = lyap.phi.layers[1].weight
        bumped.phi.layers[0].weight[2, 0] = kappa * s1  # the first layer sees z / s
        bumped.phi.layers[1].weight[2, 2] = beta ** 0.5
    return bumped, ctrl


def plain_train(cfg, system=None, **kwargs):
    """Training alone, without the proof rounds (``drlyap.train`` with ``proof=None``)."""
    from drlyap.training import train

    return train(cfg, system, None, **kwargs)


def linear_run_dir(path, delta: float = 0.1, prove=None, lyapunov_matrix=None, bump=False, user_system=None, **overrides):
    """A saved DR run of :func:`small_pendulum` (three samples, radius 0.01, risk level 0.3, decay 0.05, ``delta``;
    ``overrides``: other config fields) whose pair is :func:`linear_pair`'s (trained for one iteration, then
    replaced; ``lyapunov_matrix``: V's P, as ``linear_pair`` takes it; ``bump``: :func:`bump_pair`'s instead; ``user_system``:
    another two-state system with the same box, e.g. :func:`offset_pendulum`, its name and samples in ``overrides``):
    its conditions prove in well under a second.
    ``prove(result)``: the trained condition's proof to keep as its certificate (None: none)."""
    from drlyap.runs import save_run
    from drlyap.training import TrainConfig

    system = user_system or small_pendulum()
    fields = dict(system="small-pendulum", method="dr", n_states=64, iters=1, check_every=1,
                  lyapunov_hidden=[3] if bump else [2], lyapunov_out=3 if bump else 2, controller_hidden=[1],
                  alpha_hat=1e-3, decay_rate=0.05, wasserstein_radius=0.01,
                  risk_level=0.3, delta=delta, xi_samples=[[0.02, 0.01], [-0.03, 0.0], [0.05, -0.02]], seed=0)
    result = plain_train(TrainConfig(**(fields | overrides)), system, progress=False)
    lyap, ctrl = bump_pair(system) if bump else linear_pair(system, p=lyapunov_matrix)
    result.lyapunov.load_state_dict(lyap.state_dict())
    result.controller.load_state_dict(ctrl.state_dict())
    if prove is not None:
        result.trained_proof = prove(result)
    return save_run(path, result)


def recheck(folder, name, system, weights, header_change=None, arrays_change=None):
    """``check_certificate`` of the certificate ``name`` in ``folder`` (its run's ``system`` and ``weights``), after
    ``header_change(header)`` and ``arrays_change(arrays)`` (on copies; it may return new arrays) where given: a
    tampered certificate, checked as ``drlyap check`` would."""
    from drlyap.checker.check import check_certificate
    from drlyap.runs.certificates import read_certificate, sha256_file, system_digest

    header, arrays = read_certificate(folder, name)
    if header_change is not None:
        header_change(header)
    if arrays_change is not None:
        arrays = {k: v.copy() for k, v in arrays.items()}
        arrays = arrays_change(arrays) or arrays
    return check_certificate(name, header, arrays, system, weights, sha256_file(folder / "weights.pt"),
                             system_digest(system))


def verified_json(out) -> dict:
    """The JSON of a ``drlyap verify --json`` run through click's test runner, whose exit status must be the one its
    outcome documents (0 verified, 3 violated, 4 unknown)."""
    from drlyap.cli.verify import EXIT_CODES

    assert out.exit_code in EXIT_CODES.values(), out.output
    data = json.loads(out.stdout)
    assert out.exit_code == EXIT_CODES[data["outcome"]], out.output
    return data


def verify_cli(run, spec: str, xi: str, *args: str) -> dict:
    """``drlyap verify RUN --system SPEC --xi XI --roa --json ARGS``'s JSON (the command must run to its end, with the
    exit status of its outcome)."""
    from click.testing import CliRunner

    from drlyap.cli import main

    out = CliRunner().invoke(main, ["verify", str(run), "--system", spec, "--xi", xi, "--roa", "--json", *args])
    return verified_json(out)


def export_and_import(run, spec: str, folder) -> Path:
    """``drlyap export RUN`` into ``folder/export``, then ``drlyap import SPEC`` of its two ONNX files into
    ``folder/imported`` (both commands must succeed); returns the imported run's directory."""
    from click.testing import CliRunner

    from drlyap.cli import main

    runner, export = CliRunner(), Path(folder) / "export"
    done = runner.invoke(main, ["export", str(run), "--system", spec, "--out", str(export)])
    assert done.exit_code == 0, done.output
    out = Path(folder) / "imported"
    done = runner.invoke(main, ["import", spec, "--controller", str(export / "controller.onnx"),
                                "--lyapunov", str(export / "lyapunov.onnx"), "--out", str(out)])
    assert done.exit_code == 0, done.output
    return out


def check_cli(run, spec: str, *names: str):
    """``drlyap check RUN --system SPEC [--name N ...]``'s click result."""
    from click.testing import CliRunner

    from drlyap.cli import main

    return CliRunner().invoke(main, ["check", str(run), "--system", spec, *[a for n in names for a in ("--name", n)]])


def run_weights(run) -> dict:
    """A run's two state dicts as the checker reads them from ``weights.pt``."""
    from drlyap.runs.validate import load_weights

    return load_weights(run / "weights.pt", (run / "weights.pt").read_bytes())


def check_without(run, copy, spec: str, gone: str, name: str):
    """``drlyap check`` of certificate ``name`` on a copy (at ``copy``) of ``run`` whose certificate ``gone`` was
    removed."""
    import shutil

    shutil.copytree(run, copy)
    (copy / "certificates" / f"{gone}.json").unlink()
    return check_cli(copy, spec, name)


class ConstantController(nn.Module):
    """``u = b`` for 2 states and 1 input, as a module to export to ONNX (u* = 0 at ``b = 0``)."""

    def __init__(self, b: float = 0.0) -> None:
        super().__init__()
        self.register_buffer("k", torch.zeros(2, 1, dtype=F64))
        self.register_buffer("b", torch.full((1,), b, dtype=F64))

    def forward(self, x):
        return x @ self.k + self.b


def survivors_of_kill(driver, workers, seconds: float = 2.0) -> list[int]:
    """``kill -9`` the process ``driver`` (a Popen), then the ``workers`` (pids) still running ``seconds`` later."""
    import os
    import signal
    import time

    os.kill(driver.pid, signal.SIGKILL)
    driver.wait()
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and any(alive(p) for p in workers):
        time.sleep(0.05)
    return [p for p in workers if alive(p)]


def alive(pid: int) -> bool:
    """Whether process ``pid`` runs (read from /proc; a zombie waiting to be reaped counts as ended)."""
    from pathlib import Path

    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def doc_quotes():
    """docs/quotes.py (the script that produces the outputs README and docs quote) as a module."""
    import importlib.util
    import sys
    from pathlib import Path

    if "doc_quotes" not in sys.modules:
        spec = importlib.util.spec_from_file_location("doc_quotes", Path(__file__).resolve().parents[1] / "docs" / "quotes.py")
        sys.modules["doc_quotes"] = module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    return sys.modules["doc_quotes"]
