"""The proofs near x* rest on two facts there. ``grad V(x*) = 0`` exactly: with a linear term ``g . z`` left in V,
however small, ``Vdot`` is positive on states a little way from x* that the cube's Hessian test calls decreasing.
drlyap's V has no linear term by its form; an imported graph V is pinned to first order at x* (``V(z) - V(0) -
grad V(0) . z``, both terms computed by the graph itself), in the verifier and in the checker alike. And x* must be an
equilibrium: a controller with ``pi(x*) = u* + 1e-12`` moves the rest point off x*, and the enclosure of ``F(x*)``
proves it, so no trajectory is said to converge to x*."""

import json
import os
import sys

import pytest
import torch
from torch import nn

from drlyap.checker.arith import Du, Iv
from drlyap.checker.graphs import GraphPair
from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import PlainDecrease, TrueDecrease
from drlyap.kinds import Model
from drlyap.networks import Controller, QuadraticLyapunov
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.runs.imported import PinnedLyapunov, import_pair, import_run
from drlyap.systems import UncertainSystem, get_system
from drlyap.verification import certified_roa
from drlyap.verification.roa.local import _hessian_negative, local_decrease, not_equilibrium

sys.path.insert(0, os.path.dirname(__file__))
from handmade import ConstantController  # noqa: E402
from test_import_onnx import _export  # noqa: E402

pytest.importorskip("onnx")
F64 = torch.float64
A = torch.tensor([[0.0, 1.0], [-1.0, -1.0]], dtype=F64)  # a damped oscillator, the controller 0
P = torch.tensor([[1.5, 0.5], [0.5, 1.0]], dtype=F64)  # A^T P + P A = -I
G = torch.tensor([3e-11, -2e-11], dtype=F64)  # V's slope at x*: 1e-11 of V's size, inside the import's tolerance


def _oscillator() -> UncertainSystem:
    def dyn(x, u, p):
        return torch.stack([x[:, 1], -x[:, 0] - p[:, 0] * x[:, 1] + u[:, 0]], -1)

    return UncertainSystem(name="oscillator", state_names=("q", "v"), input_names=("f",), param_names=("damping",),
                           nominal_params=(1.0,), uncertain=("damping",), dynamics=dyn,
                           state_box=((-1.0, -1.0), (1.0, 1.0)), input_box=((-1.0,), (1.0,)), equilibrium=(0.0, 0.0))


class _SlopedV(nn.Module):
    """``z^T P z + g . z``."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("p", P.clone())
        self.register_buffer("g", G.clone())

    def forward(self, x):
        return ((x @ self.p) * x).sum(-1) + x @ self.g


class _QuadraticV(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("p", P.clone())

    def forward(self, x):
        return ((x @ self.p) * x).sum(-1)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sloped")
    _export(_SlopedV(), 2, folder / "v.onnx")
    _export(ConstantController(), 2, folder / "c.onnx")
    _export(ConstantController(1e-12), 2, folder / "off.onnx")
    _export(_QuadraticV(), 2, folder / "q.onnx")
    return folder


def _vdot(lyapunov: nn.Module, z: torch.Tensor) -> torch.Tensor:
    _, grad = lyapunov.value_and_grad(z)
    return (grad * (z @ A.T)).sum(-1)


def test_a_linear_term_left_in_v_breaks_the_second_order_proof_and_the_pin_mends_it(files):
    system = _oscillator()
    pair = import_pair(system, files / "c.onnx", files / "v.onnx")
    pinned = pair.loop.lyapunov
    assert isinstance(pinned, PinnedLyapunov)
    raw = ClosedLoop(system, pinned.graph, pair.loop.controller)
    plain = TrueDecrease(torch.zeros(1, 1, dtype=F64)).per_sample()
    cube = torch.full((2,), 0.05, dtype=F64)
    # the cube's Hessian test does not see the linear term: it passes for the raw graph too ...
    assert _hessian_negative(raw, plain, cube)[0]
    # ... yet the raw graph's Vdot = (2 P z + g) . A z is positive a little way from x* along A^-1 g
    z = 1e-12 * torch.linalg.solve(A, G / G.norm())[None]
    assert float(_vdot(pinned.graph, z)[0]) > 0
    # pinned, V's gradient at x* is 0 and Vdot < 0 there, as the proof says
    zero = torch.zeros(1, 2, dtype=F64)
    assert torch.equal(pinned.value_and_grad(zero)[1], zero)
    assert float(_vdot(pinned, z)[0]) < 0
    out = local_decrease(pair.loop, TrueDecrease(torch.zeros(1, 1, dtype=F64)), Region.of(system, 0.1))
    assert out.proved, out
    # and on samples of the cube the pinned V moves from the graph by no more than its slope allows
    states = 0.05 * (2 * torch.rand(500, 2, generator=torch.Generator().manual_seed(0), dtype=F64) - 1)
    assert float((pinned(states) - pinned.graph(states)).abs().max()) <= float((G.abs() * 0.05).sum()) * 1.01


def test_the_checker_pins_the_imported_v_to_first_order_too(files, tmp_path):
    system = _oscillator()
    out = tmp_path / "imported"
    import_run(system, files / "c.onnx", out, files / "v.onnx")
    graphs = json.loads((out / "graphs.json").read_text())
    assert graphs["lyapunov"]["pinned"] == "first order"
    tensors = torch.load(out / "tensors.pt", weights_only=True)
    pair = GraphPair(graphs, tensors, 2)
    at = pair.value(Du.seed(Iv.point(torch.zeros(1, 2, dtype=F64)), 2, [0, 1]))
    for t in at.d:  # the gradient's enclosure at x*: around 0, rounding wide, though the graph's slope is 1e-11
        assert bool((t.lo <= 0).all() and (t.hi >= 0).all()) and float((t.hi - t.lo).max()) < 1e-20
    z = torch.tensor([[0.3, -0.2], [0.01, 0.02]], dtype=F64)
    box = pair.value(Iv.point(z))
    expected = ((z @ P) * z).sum(-1)
    assert bool(((box.lo <= expected + 1e-15) & (box.hi >= expected - 1e-15)).all())


def test_a_rest_point_moved_off_x_star_by_1e_12_gets_no_region_of_attraction(files):
    """``pi(x*) = 1e-12`` passes the import (1e-6 of U) and x* is within 1e-9 of an equilibrium, but the closed loop
    rests at (1e-12, 0): the verifier's enclosure of ``F(x*)`` excludes 0, so only practical stability is claimed."""
    system = _oscillator()
    condition = TrueDecrease(torch.zeros(1, 1, dtype=F64), decay_rate=0.0, exp_rate=0.1)
    region = Region.of(system, 0.1)
    at_rest = certified_roa(import_pair(system, files / "c.onnx", files / "q.onnx").loop, condition, region,
                            Budget(seconds=20.0))
    assert at_rest.certified and at_rest.kind == "region of attraction"
    moved = import_pair(system, files / "off.onnx", files / "q.onnx")
    assert moved.checks["pi_minus_u_star"] == [1e-12]
    roa = certified_roa(moved.loop, condition, region, Budget(seconds=20.0))
    assert not roa.certified and roa.kind == "practical stability", roa
    assert "F(x*) proved nonzero" in roa.local.reason


@pytest.mark.parametrize("name", ["pendulum", "pendulum-u9", "cartpole", "mountain-car", "quadrotor2d"])
def test_every_built_in_system_rests_at_x_star_by_the_verifier_s_enclosure(name):
    """drlyap's controller gives ``pi(x*) = u*`` by its form; the enclosure of ``F(x*, u*)`` holds 0 on the true and
    design models at the test shift, at no shift and at -2x it, so the proofs near x* are not refused."""
    system = get_system(name)
    controller = Controller(system.n, system.input_box, system.equilibrium_input, hidden=(4,))
    loop = ClosedLoop(system, QuadraticLyapunov(torch.eye(system.n, dtype=F64)), controller).f64
    xi = torch.tensor(system.test_xi, dtype=F64)
    for model in (Model.TRUE, Model.DESIGN):
        for shift in (xi, 0 * xi, -2 * xi):
            assert not_equilibrium(loop, PlainDecrease(shift[None], 0.0, 0.0, model), Region.of(system, 0.1)) == ""
