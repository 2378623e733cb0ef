"""Soundness and behaviour of the interval / branch-and-bound verifier (drlyap.verification)."""

import copy
import json
import math

import pytest
import torch
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from drlyap import systems
from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import DRPointwise, DRUniform, Nominal, TrueDecrease, decrease_terms
from drlyap.enclosures import Dual, Interval
from drlyap.networks import TanhMLP
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.systems import UncertainSystem
from drlyap.training import TrainConfig, TrainSections
from drlyap.verification import (
    ProofRules,
    box_bounds,
    certified_roa,
    combine_lower,
    combine_upper,
    condition_objective,
    uniform_margin,
    verify_condition,
)
from handmade import linear_pair, plain_train, small_pendulum, verified_json

F64 = torch.float64


def _boxes(n, count, lo, hi, max_width, seed):
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.as_tensor(lo, dtype=F64), torch.as_tensor(hi, dtype=F64)
    centre = lo + (hi - lo) * torch.rand(count, n, generator=g, dtype=F64)
    half = max_width * (hi - lo) * torch.rand(count, n, generator=g, dtype=F64) / 2
    return torch.maximum(centre - half, lo), torch.minimum(centre + half, hi), g


def _samples(lo, hi, g, k=16):
    return lo + (hi - lo) * torch.rand(k, *lo.shape, generator=g, dtype=F64)


def _encloses(enc, values, atol=0.0):
    return bool(((enc.lo - atol <= values) & (values <= enc.hi + atol)).all())


def _dual_box(lo, hi):
    n = lo.shape[-1]
    eye = torch.eye(n, dtype=F64).expand(lo.shape[0], n, n)
    return Dual(Interval(lo, hi), Interval(eye, eye))


# ------------------------------------------------------------------ (a) elementary enclosures
_interval = st.tuples(st.floats(-5, 5), st.floats(0, 3)).map(lambda t: (t[0], t[0] + t[1]))


@settings(max_examples=150, deadline=None)
@given(a=_interval, b=_interval, frac=st.lists(st.floats(0, 1), min_size=2, max_size=2))
def test_interval_arithmetic_encloses_point_results(a, b, frac):
    x = a[0] + frac[0] * (a[1] - a[0])
    y = b[0] + frac[1] * (b[1] - b[0])
    ia = Interval(torch.tensor([a[0]], dtype=F64), torch.tensor([a[1]], dtype=F64))
    ib = Interval(torch.tensor([b[0]], dtype=F64), torch.tensor([b[1]], dtype=F64))
    tx, ty = torch.tensor([x], dtype=F64), torch.tensor([y], dtype=F64)
    checks = [(ia + ib, tx + ty), (ia - ib, tx - ty), (ia * ib, tx * ty), (-ia, -tx), (ia.square(), tx * tx),
              (ia ** 3, tx ** 3), (ia ** 4, tx ** 4), (torch.sin(ia), torch.sin(tx)), (torch.cos(ia), torch.cos(tx)),
              (torch.tanh(ia), torch.tanh(tx)), (torch.exp(ia), torch.exp(tx)), (2.5 * ia - 1.0, 2.5 * tx - 1.0),
              (ia.abs().sqrt(), tx.abs().sqrt()), (ty * ia, ty * tx), (ty - ia, ty - tx), (torch.mul(ia, ty), tx * ty),
              (torch.stack([ia, ib], dim=-1), torch.stack([tx, ty], dim=-1))]
    if b[0] > 0.01:
        checks.append((ia / ib, tx / ty))
        checks.append((1.0 / ib, 1.0 / ty))
    for enc, value in checks:
        assert _encloses(enc, value), (enc, value)
        assert bool((enc.lo <= enc.hi).all())


def test_sin_cos_enclose_extrema_and_division_by_zero_interval_raises():
    iv = Interval(torch.tensor([1.0, -4.0, 3.0]), torch.tensor([2.0, -1.0, 3.2])).lo.to(F64)
    box = Interval(iv, torch.tensor([2.0, -1.0, 3.2], dtype=F64))
    s, c = box.sin(), box.cos()
    assert s.hi[0] == 1.0 and s.lo[1] == -1.0 and c.lo[2] == -1.0
    with pytest.raises(ValueError, match="contains 0"):
        box / Interval(torch.tensor([-1.0], dtype=F64), torch.tensor([1.0], dtype=F64))


def test_dual_gradient_encloses_autograd():
    lo, hi, g = _boxes(2, 64, [-2, -2], [2, 2], 0.3, 0)
    z = _dual_box(lo, hi)
    a, b = z.unbind(-1)
    out = torch.sin(a) * b ** 2 / (2.0 + torch.cos(b)) - torch.tanh(a * b) + torch.exp(-a)
    for p in _samples(lo, hi, g):
        p = p.requires_grad_(True)
        x, y = p.unbind(-1)
        val = torch.sin(x) * y ** 2 / (2.0 + torch.cos(y)) - torch.tanh(x * y) + torch.exp(-x)
        (grad,) = torch.autograd.grad(val.sum(), p)
        assert _encloses(out.v, val.detach()) and _encloses(out.d, grad)


def test_mlp_value_and_jacobian_enclosures():
    torch.manual_seed(0)
    net = TanhMLP([3, 16, 16, 4], input_scale=[1.0, 2.0, 0.5])  # float32 weights, read as float64 by the bounds
    lo, hi, g = _boxes(3, 50, [-1, -2, -0.5], [1, 2, 0.5], 0.2, 1)
    out = net(_dual_box(lo, hi))  # the network's own forward code, run on enclosures
    net = net.double()
    for p in _samples(lo, hi, g, 8):
        jac = torch.autograd.functional.jacobian(lambda q: net(q).sum(0), p)  # (4, B, 3)
        assert _encloses(out.v, net(p).detach())
        assert _encloses(out.d, jac.permute(1, 0, 2))


def _random_pair(system, gain=10.0, seed=0):
    torch.manual_seed(seed)
    cfg = TrainConfig(system=system.name, lyapunov_hidden=[16], lyapunov_out=4, controller_hidden=[16],
                      init_gain=gain).resolved(system)
    return TrainSections.of(cfg).networks.build(system)


@pytest.mark.parametrize("make", [systems.pendulum, systems.mountain_car])
def test_pair_and_dynamics_enclosures(make):
    """V, grad V, its Hessian, the clamped controller, the design-model and true-model Vdot, computed by the
    networks' and the conditions' own code on enclosures, enclose sampled values."""
    system = make()
    lyap, ctrl = _random_pair(system, gain=300.0)  # large gain: the clamp is active on much of the box
    l64, c64 = copy.deepcopy(lyap).double(), copy.deepcopy(ctrl).double()
    box_lo, box_hi = system.local_box()
    lo, hi, g = _boxes(system.n, 80, box_lo, box_hi, 0.05, 2)
    z = _dual_box(lo, hi)
    value, grad = lyap.value_and_grad(z)
    u = ctrl(z)
    xi = torch.tensor([system.test_xi], dtype=F64)
    design = decrease_terms(ClosedLoop(system, lyap, ctrl), z, xi, 0.0)
    true = decrease_terms(ClosedLoop(system, lyap, ctrl), z, xi, 0.0, model="true")
    saturated = 0
    for p in _samples(lo, hi, g, 8):
        p = p.requires_grad_(True)
        v, gv = l64.value_and_grad(p)
        hess = torch.stack([torch.autograd.grad(gv[:, i].sum(), p, retain_graph=True)[0] for i in range(system.n)], 1)
        raw = c64.raw(p)
        uu = c64.u_star + torch.clamp(raw, c64.room_low, c64.room_high)  # the real clamp, with its real derivative
        du = torch.autograd.grad(uu.sum(), p)[0]
        saturated += int(((raw <= c64.room_low) | (raw >= c64.room_high)).sum())
        x = system.to_user(p.detach())
        f_design, w_design = system.design_model(x, uu.detach())
        vdot_design = (gv.detach() * (f_design + (w_design @ xi[0]))).sum(-1)
        vdot_true = (gv.detach() * system.true_dynamics(x, uu.detach(), xi[0])).sum(-1)
        assert _encloses(value.v, v.detach()) and _encloses(grad.v, gv.detach()) and _encloses(grad.d, hess)
        assert _encloses(u.v, uu.detach()) and _encloses(u.d[:, 0], du)
        assert _encloses(design.vdot.v[:, 0], vdot_design) and _encloses(true.vdot.v[:, 0], vdot_true)
    assert saturated > 0


# ------------------------------------------------------------------ hand-made pairs on a small pendulum box
XI = torch.tensor([[0.02, 0.01], [-0.03, 0.0], [0.05, -0.02]], dtype=F64)


def _specs():
    return [Nominal(XI.mean(0, keepdim=True), 0.05),
            DRPointwise(1e-3, 0.1, XI, 0.05),
            DRPointwise(1e-3, 0.5, XI, 0.05, 0.1),  # general-eps CVaR and the exponential term
            TrueDecrease(torch.tensor([[0.1, 0.05]], dtype=F64), 0.05)]


def _ids(c):
    return f"{c.name}-{c.eps}" if hasattr(c, "eps") else c.name


@pytest.mark.parametrize("spec", _specs(), ids=_ids)
def test_box_bounds_enclose_the_residual(spec):
    """The combined bound over random boxes encloses the residual sampled by the ordinary code path."""
    for system, (lyap, ctrl) in [(small_pendulum(), linear_pair(small_pendulum())),
                                 (systems.pendulum(), _random_pair(systems.pendulum(), 30.0, 3))]:
        box_lo, box_hi = system.local_box()
        lo, hi, g = _boxes(2, 60, box_lo, box_hi, 0.1, 4)
        lb, ub, _ = box_bounds(condition_objective(ClosedLoop(system, lyap, ctrl), spec), lo, hi)
        upper, lower = combine_upper(spec, ub), combine_lower(spec, lb)
        for p in _samples(lo, hi, g, 8):
            res = ClosedLoop(system, lyap, ctrl).exact(spec, p)
            assert bool((lower <= res).all() and (res <= upper).all())


@pytest.mark.parametrize("spec", _specs(), ids=_ids)
def test_one_condition_object_on_points_and_on_enclosures(spec):
    """The condition that training evaluates on tensors, run on degenerate intervals at the same states,
    encloses the tensor value (one formula, two number types)."""
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    z = torch.tensor([[0.3, -0.5], [-0.2, 0.9], [0.55, 1.1]], dtype=F64)
    on_points = ClosedLoop(system, lyap, ctrl).exact(spec, z)
    enclosure = condition_objective(ClosedLoop(system, lyap, ctrl), spec)(Interval(z, z))
    assert bool((combine_lower(spec, enclosure.lo) <= on_points).all() and (on_points <= combine_upper(spec, enclosure.hi)).all())
    assert float((combine_upper(spec, enclosure.hi) - combine_lower(spec, enclosure.lo)).max()) < 1e-9


# ------------------------------------------------------------------ (b), (c), (d) branch and bound
def _dense_region(system, delta, per=200):
    lo, hi = system.local_box()
    axes = [lo[i] + (hi[i] - lo[i]) * (torch.arange(per, dtype=F64) + 0.5) / per for i in range(system.n)]
    z = torch.cartesian_prod(*axes)
    g = torch.Generator().manual_seed(7)
    z = torch.cat([z, lo + (hi - lo) * torch.rand(20000, system.n, generator=g, dtype=F64)])
    return z[z.norm(dim=-1) >= delta]


@pytest.mark.parametrize("spec", _specs(), ids=_ids)
def test_hand_made_pair_verifies_and_dense_sampling_agrees(spec):
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    result = verify_condition(ClosedLoop(system, lyap, ctrl), spec, Region.of(system, 0.2), Budget(seconds=20))
    assert result.status == "verified", result
    assert result.verified_fraction == 1.0 and result.counterexample is None
    assert result.sup_bounds[1] <= 0
    res = ClosedLoop(system, lyap, ctrl).exact(spec, _dense_region(system, 0.2))
    assert float(res.max()) <= 0
    assert result.sup_bounds[0] <= float(res.max()) + 1e-9  # the reported lower end is attained


def test_dense_violations_lie_in_unverified_boxes_of_a_mixed_case():
    """The linear pair on a larger box holds near x* only: every densely sampled violating state lies in a
    box left unverified, so no verified box contains a violation."""
    system = small_pendulum(((-1.5, -3.0), (1.5, 3.0)))
    lyap, ctrl = linear_pair(system)
    spec = DRPointwise(1e-3, 0.1, XI, 0.05)
    loop = ClosedLoop(system, lyap, ctrl)
    result = verify_condition(loop, spec, Region.of(system, 0.2), Budget(seconds=20, min_width=1e-2),
                              rules=ProofRules(keep_boxes=10**6))
    z = _dense_region(system, 0.2, per=150)
    res = loop.exact(spec, z)
    bad = z[res > 0]
    assert result.status == ("violated" if bad.shape[0] else "verified")
    assert result.n_unverified == len(result.unverified_boxes)
    x_star = torch.tensor(system.equilibrium, dtype=F64)
    lo = torch.tensor([b["lo"] for b in result.unverified_boxes], dtype=F64).reshape(-1, 2) - x_star
    hi = torch.tensor([b["hi"] for b in result.unverified_boxes], dtype=F64).reshape(-1, 2) - x_star
    covered = ((lo[None] <= bad[:, None]) & (bad[:, None] <= hi[None])).all(-1).any(-1)
    assert bool(covered.all()), bad[~covered]
    assert 0 < result.verified_fraction < 1 and result.counterexample_value > 0


def test_wrong_way_controller_is_violated_with_a_real_counterexample():
    system = small_pendulum()
    lyap, ctrl = linear_pair(system, sign=-1.0)  # pushes away from the equilibrium
    spec = DRPointwise(1e-3, 0.1, XI, 0.05)
    result = verify_condition(ClosedLoop(system, lyap, ctrl), spec, Region.of(system, 0.2), Budget(seconds=20))
    assert result.status == "violated"
    z = torch.tensor([result.counterexample_local], dtype=F64)
    assert math.hypot(*result.counterexample_local) >= 0.2
    assert torch.allclose(system.to_user(z), torch.tensor([result.counterexample], dtype=F64))
    terms = decrease_terms(ClosedLoop(system, lyap.double(), ctrl.double()), z, XI, 0.05)
    assert float(DRPointwise(1e-3, 0.1).residual(terms)[0].detach()) > 0  # recomputed from the formula's pieces
    assert result.counterexample_value > 0 and result.verified_fraction < 1


def test_budget_exhaustion_is_unknown_not_verified():
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    spec = Nominal(XI[:1], 0.05)
    result = verify_condition(ClosedLoop(system, lyap, ctrl), spec, Region.of(system, 0.2), Budget(boxes=10),
                              rules=ProofRules(grid=[2, 2]))
    assert result.status == "unknown" and result.stopped == "box budget" and result.verified_fraction < 1


def test_uniform_margin_brackets_sampled_value():
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    r, eps = 1e-3, 0.1
    out = uniform_margin(ClosedLoop(system, lyap, ctrl), DRUniform(r, eps, XI, 0.05), Region.of(system, 0.2),
                         Budget(seconds=5))
    z = _dense_region(system, 0.2, per=100)
    with torch.no_grad():
        terms = decrease_terms(ClosedLoop(system, lyap.double(), ctrl.double()), z, XI, 0.05)
    sampled = r / eps * float(terms.lip.max()) + float((terms.vdot + terms.decay[:, None]).max())
    assert out.margin_lower <= out.margin_upper
    assert sampled <= out.margin_upper + 1e-12
    assert out.status in ("verified", "unknown", "violated")


def test_certified_roa_is_a_sublevel_set_inside_the_box_where_the_condition_holds():
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    spec = DRPointwise(1e-3, 0.1, XI, 0.05)
    loop = ClosedLoop(system, lyap, ctrl)
    roa = certified_roa(loop, spec, Region.of(system, 0.2), Budget(seconds=10), samples_per_axis=100)
    assert roa.certified and roa.kind == "region of attraction" and 0 < roa.share_of_box < 1
    assert roa.local.proved
    l64 = copy.deepcopy(lyap).double()
    lo, hi = system.local_box()
    t = torch.linspace(0, 1, 400, dtype=F64)
    edges = torch.cat([torch.stack([lo[0] + (hi[0] - lo[0]) * t, torch.full_like(t, float(s))], -1) for s in (lo[1], hi[1])]
                      + [torch.stack([torch.full_like(t, float(s)), lo[1] + (hi[1] - lo[1]) * t], -1) for s in (lo[0], hi[0])])
    with torch.no_grad():
        assert float(l64(edges).min()) > roa.level
        z = _dense_region(system, 0.2)
        inside = z[l64(z) <= roa.level]
    assert inside.shape[0] > 0 and float(loop.exact(spec, inside).max()) <= 0


def test_user_dynamics_with_unsupported_ops_fail_clearly():
    def weird(x, u, p):
        return torch.stack([torch.atan(x[:, 0]), x[:, 1] * p[:, 0] + u[:, 0]], dim=-1)

    system = UncertainSystem(name="weird", state_names=("a", "b"), input_names=("u",), param_names=("k",),
                             nominal_params=(1.0,), uncertain=("k",), dynamics=weird,
                             state_box=((-1.0, -1.0), (1.0, 1.0)), input_box=((-1.0,), (1.0,)), equilibrium=(0.0, 0.0))
    lyap, ctrl = _random_pair(system)
    with pytest.raises(TypeError, match="does not support"):
        verify_condition(ClosedLoop(system, lyap, ctrl), Nominal(torch.zeros(1, 1), 0.0), Region.of(system, 0.1))


# ------------------------------------------------------------------ runs and CLI
def test_cli_verify_on_a_run_directory(tmp_path, tiny_config):
    from drlyap.cli import main
    from drlyap.runs import save_run
    result = plain_train(tiny_config(iters=5, check_every=5), progress=False)
    save_run(tmp_path / "run", result)
    runner = CliRunner()
    out = runner.invoke(main, ["verify", str(tmp_path / "run"), "--time-limit", "2", "--xi", "0.1,0.05", "--uniform",
                               "--json"])
    data = verified_json(out)
    assert data["status"] in ("verified", "violated", "unknown")
    assert {"trained", "uniform", "true_model", "roa"} <= set(data)
    assert data["uniform"]["margin_lower"] <= data["uniform"]["margin_upper"]
    if data["counterexample"] is not None:
        assert data["counterexample_value"] > 0
    text = runner.invoke(main, ["verify", str(tmp_path / "run"), "--time-limit", "1", "--roa"])
    assert text.exit_code in (3, 4) and "uniform DR condition" not in text.output  # five iterations: not proved
    assert "region of attraction" in text.output
    assert f"drawn by `drlyap plot {tmp_path / 'run'}`" in text.output  # verify --roa keeps its region for plot
    assert "roa" in json.loads((tmp_path / "run" / "metrics.json").read_text())["certificate"]
    bad = runner.invoke(main, ["verify", str(tmp_path / "run"), "--xi", "1"])
    assert bad.exit_code != 0 and "takes 2 xi" in bad.output
    missing = runner.invoke(main, ["verify", str(tmp_path / "nope")])
    assert missing.exit_code != 0 and "does not exist" in missing.output
    affine = runner.invoke(main, ["verify", str(tmp_path / "run"), "--time-limit", "2", "--enclosure", "affine", "--json"])
    both = verified_json(affine)
    assert both["enclosure"] == "affine" and both["trained"]["status"] in ("verified", "violated", "unknown")
    if both["trained"]["status"] == "verified" or data["trained"]["status"] == "verified":  # sound: never contradict
        assert "violated" not in (both["trained"]["status"], data["trained"]["status"])


def test_verify_on_a_uniform_run_reports_the_margin(tmp_path, tiny_config):
    from drlyap.io import jsonable
    from drlyap.runs import load_run, save_run
    from drlyap.verification import ProofConfig, UniformMargin
    from drlyap.workflows.verify import VerifyRequest, verify

    # eps N = 2.5 > 1: the uniform condition's CVaR is not the samples' maximum, so it implies no decrease at each
    # sample and no region of attraction rests on it
    result = plain_train(tiny_config(iters=5, check_every=5, loss="uniform", risk_level=0.5), progress=False)
    save_run(tmp_path / "uni", result)
    out = verify(load_run(tmp_path / "uni"), ProofConfig(time_limit=2, uniform_time=1), VerifyRequest(roa=True))
    assert out.trained == out.uniform and isinstance(out.trained, UniformMargin)
    assert out.trained.margin_lower <= out.trained.margin_upper
    assert "implies no decrease at each sample" in out.roa.error and out.status in ("verified", "violated", "unknown")
    data = out.to_dict()
    assert "margin_upper" in data["trained"] and "error" in data["roa"]
    json.dumps(jsonable(data), allow_nan=False)
