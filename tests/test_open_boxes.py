"""Certified training on the boxes a proof left open: the bound trained on is the verifier's, sound, differentiable in
the weights only where asked, and training on it lowers it."""

import math

import pytest
import torch

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import DRPointwise
from drlyap.config import TrainConfig
from drlyap.kinds import Enclosure
from drlyap.networks import Controller, Lyapunov
from drlyap.proof_settings import ProofConfig
from drlyap.training.boxes import OpenBoxes
from drlyap.training.trainer import fit
from drlyap.verification.bounding import ConditionJob
from handmade import linear_pair, small_pendulum

F64 = torch.float64
XI = torch.tensor([[0.02, 0.01], [-0.03, 0.0], [0.05, -0.02]], dtype=F64)
CONDITION = DRPointwise(1e-3, 0.1, XI, 0.05)


def _random_pair(system, seed=0):
    torch.manual_seed(seed)
    lo, hi = system.local_box()
    scale = ((hi - lo) / 2).tolist()
    lyap = Lyapunov(2, hidden=[4], out=3, alpha_hat=0.05, input_scale=scale)
    ctrl = Controller(2, system.input_box, system.equilibrium_input, hidden=[4], input_scale=scale, init_gain=2.0)
    return lyap, ctrl


def _boxes(system, count=48, width=0.15, seed=1):
    g = torch.Generator().manual_seed(seed)
    lo, hi = system.local_box()
    centre = lo + (hi - lo) * torch.rand(count, 2, generator=g, dtype=F64)
    half = width * (hi - lo) / 2 * torch.rand(count, 2, generator=g, dtype=F64)
    return (centre - half).clamp(lo, hi), (centre + half).clamp(lo, hi)


@pytest.mark.parametrize("enclosure,level", [(Enclosure.MEAN_VALUE, None), (Enclosure.AFFINE, None),
                                             (Enclosure.AFFINE, 0.5)])
def test_the_trained_bound_is_the_verifiers_and_encloses_the_residual(enclosure, level):
    """On the live float32 networks the bound equals the verifier's on their float64 copy (up to the order of float64
    sums), lies above the residual at dense samples of every box, and has finite weight gradients."""
    system = small_pendulum()
    lyap, ctrl = _random_pair(system)
    loop = ClosedLoop(system, lyap, ctrl)
    lo, hi = _boxes(system)
    boxes = OpenBoxes(lo, hi, level, enclosure)
    upper = boxes.upper(loop, CONDITION)
    verifier = ConditionJob(loop.f64, CONDITION, level, enclosure)(lo, hi)["upper"]
    assert torch.allclose(upper.detach(), verifier, rtol=1e-12, atol=1e-12)
    g = torch.Generator().manual_seed(2)
    points = lo[:, None] + (hi - lo)[:, None] * torch.rand(lo.shape[0], 200, 2, generator=g, dtype=F64)
    residual = loop.exact(CONDITION, points.reshape(-1, 2)).reshape(lo.shape[0], 200)
    if level is not None:  # the claim is about {V <= level} only
        inside = loop.f64.value(points.reshape(-1, 2)).reshape(lo.shape[0], 200) <= level
        residual = torch.where(inside, residual, -math.inf)
    assert bool((residual.amax(1) <= upper.detach()).all())
    finite = torch.isfinite(upper)
    torch.relu(upper[finite]).sum().backward()
    grads = [p.grad for p in [*lyap.parameters(), *ctrl.parameters()]]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)
    assert any(float(g.abs().max()) > 0 for g in grads)


def test_the_verifier_builds_no_graph_on_live_networks():
    """Outside certified training the bridge detaches the weights: a bound of live networks carries no graph."""
    system = small_pendulum()
    loop = ClosedLoop(system, *_random_pair(system))
    lo, hi = _boxes(system, count=4)
    assert not ConditionJob(loop, CONDITION, None, Enclosure.AFFINE)(lo, hi)["upper"].requires_grad


def test_training_on_open_boxes_lowers_their_bound():
    """A pair whose sampled loss is 0 on every state keeps its bound over the boxes without the term and lowers it
    with it (the same fit otherwise)."""
    system = small_pendulum()
    lo, hi = _boxes(system, count=64, width=0.5)
    cfg = TrainConfig(system="small-pendulum", method="dr", n_states=64, iters=30, check_every=1000,
                      lyapunov_hidden=[2], lyapunov_out=2, controller_hidden=[1], alpha_hat=1e-3, decay_rate=0.05,
                      wasserstein_radius=1e-3, risk_level=0.1, delta=0.2, xi_samples=XI.tolist(), lr=3e-4,
                      seed=0).resolved(system)
    hinge = {}
    for weight in (0.0, 10.0):
        pair = linear_pair(system)
        boxes = OpenBoxes(lo, hi, None, Enclosure.AFFINE, weight=weight, batch=64)
        before = torch.relu(boxes.upper(ClosedLoop(system, *pair), CONDITION).detach()).mean()
        result = fit(cfg, system, progress=False, init=pair, boxes=boxes)
        hinge[weight] = float(torch.relu(boxes.upper(result.loop, result.condition).detach()).mean())
    assert float(before) > 0
    assert hinge[0.0] == pytest.approx(float(before), rel=1e-9)
    assert hinge[10.0] < 0.8 * float(before)


@pytest.mark.parametrize("lo,hi,message", [
    (torch.zeros(3, 2), torch.ones(3, 3), "one shape"),
    (torch.zeros(3), torch.ones(3), "one shape"),
    (torch.tensor([[0.0, math.nan]]), torch.ones(1, 2), "finite"),
    (torch.ones(2, 2), torch.zeros(2, 2), "lo <= hi"),
])
def test_bad_open_boxes_are_refused(lo, hi, message):
    with pytest.raises(ValueError, match=message):
        OpenBoxes(lo, hi, None, Enclosure.AFFINE)


@pytest.mark.parametrize("field,value", [("box_weight", -1.0), ("box_weight", math.nan), ("train_boxes", -1)])
def test_bad_box_settings_are_named(field, value):
    with pytest.raises(ValueError, match=field):
        ProofConfig(**{field: value}).validate()


def test_a_retraining_round_trains_on_the_boxes_its_proof_left():
    """A round after a proof that left boxes open trains on them (counted in its record) and moves a pair whose
    sampled loss is 0 (the same start, on the states alone, is returned unchanged: tests/test_cegis.py)."""
    from drlyap.render import proof_round_line
    from drlyap.training import train

    system = small_pendulum()
    fields = dict(system="small-pendulum", method="dr", n_states=64, iters=20, check_every=10, lyapunov_hidden=[2],
                  lyapunov_out=2, controller_hidden=[1], alpha_hat=1e-3, decay_rate=0.05, wasserstein_radius=0.01,
                  risk_level=0.3, delta=0.2, xi_samples=XI.tolist(), seed=0)
    lines: list[str] = []
    result = train(TrainConfig(**fields), system, ProofConfig(rounds=1, max_boxes=10, train_boxes=8), progress=False,
                   init=linear_pair(system), warn=False, log=lambda entry: lines.append(proof_round_line(entry)))
    first, last = result.metrics["cegis"]["rounds"]
    assert 0 < first["open_boxes"] <= 8
    assert f"the verifier's bound over {first['open_boxes']} open boxes" in lines[0]
    assert last["round"] == 1 and not last.get("unchanged", False)
