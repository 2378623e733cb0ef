"""The independent checker (drlyap.checker) and certificate files (drlyap.runs.certificates): its arithmetic encloses
dense samples, it agrees with the verifier's proofs, and it rejects altered certificates."""

import json
import math
import shutil

import numpy as np
import pytest
import torch
from torch import Tensor

from drlyap.checker.arith import Du, Iv
from drlyap.checker.check import CertificateError, check_certificate, check_tree, rebuild_boxes
from drlyap.checker.model import Pair, Residual
from drlyap.claims.registry import claim_kind, claim_sentence
from drlyap.conditions import DRPointwise, TrueDecrease
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.runs.certificates import (
    PairFiles,
    Stated,
    condition_claim,
    read_certificate,
    sha256_file,
    system_digest,
    write_certificate,
)
from drlyap.verification import verify_condition
from handmade import linear_pair, recheck, small_pendulum

F64 = torch.float64


def random_boxes(count, seed, scale=3.0):
    g = torch.Generator().manual_seed(seed)
    a = (torch.rand(count, generator=g, dtype=F64) * 2 - 1) * scale
    w = torch.rand(count, generator=g, dtype=F64) ** 3 * scale
    return a, a + w


def samples(lo, hi, k=64, seed=1):
    g = torch.Generator().manual_seed(seed)
    t = torch.rand(k, *lo.shape, generator=g, dtype=F64)
    t[0], t[1] = 0.0, 1.0  # the end points too
    return lo + (hi - lo) * t


def assert_encloses(box: Iv, values, tol=0.0):
    assert bool(((values >= box.lo - tol) | torch.isnan(values)).all()), "lower bound above a sampled value"
    assert bool(((values <= box.hi + tol) | torch.isnan(values)).all()), "upper bound below a sampled value"


@pytest.mark.parametrize("name, fn", [
    ("sin", torch.sin), ("cos", torch.cos), ("tanh", torch.tanh), ("exp", torch.exp), ("square", torch.square),
    ("abs", torch.abs)])
def test_unary_functions_enclose_dense_samples(name, fn):
    lo, hi = random_boxes(4000, 0, scale=8.0)
    x = samples(lo, hi)
    assert_encloses(getattr(Iv(lo, hi), name)(), fn(x))


def test_sqrt_and_arithmetic_enclose_dense_samples():
    alo, ahi = random_boxes(3000, 1)
    blo, bhi = random_boxes(3000, 2)
    a, b = samples(alo, ahi, seed=3), samples(blo, bhi, seed=4)
    ia, ib = Iv(alo, ahi), Iv(blo, bhi)
    assert_encloses(ia + ib, a + b)
    assert_encloses(ia - ib, a - b)
    assert_encloses(ia * ib, a * b)
    assert_encloses(ia / ib, a / b)
    assert_encloses(ia ** 3, a ** 3)
    assert_encloses(Iv(alo.abs(), alo.abs() + (ahi - alo)).sqrt(), samples(alo.abs(), alo.abs() + (ahi - alo)).sqrt())
    assert bool((Iv(alo, ahi).sqrt().lo == -math.inf)[alo < 0].all())  # outside the domain: nothing proved


def test_tensor_operands_on_either_side():
    """A tensor met by a checker value, in either order and through torch's reflected operators."""
    iv = Iv(torch.tensor([1.0, 2.0], dtype=F64), torch.tensor([1.0, 2.0], dtype=F64))
    t = torch.tensor([3.0, 5.0], dtype=F64)
    for got, want in ((t - iv, [2.0, 3.0]), (Tensor.__rsub__(t, iv), [-2.0, -3.0]), (t / iv, [3.0, 2.5]),
                      (Tensor.__rtruediv__(t, iv), [1 / 3, 0.4]), (torch.sub(t, iv), [2.0, 3.0])):
        assert_encloses(got, torch.tensor(want, dtype=F64), tol=1e-15)
        assert float((got.hi - got.lo).max()) < 1e-14
    with pytest.raises(TypeError, match="does not support"):
        torch.sum(Iv(t[None], t[None]), -1, keepdim=True)


def test_linear_norm_and_clamp_enclose_dense_samples():
    g = torch.Generator().manual_seed(5)
    lo = torch.randn(500, 3, generator=g, dtype=F64)
    hi = lo + torch.rand(500, 3, generator=g, dtype=F64)
    w, b = torch.randn(4, 3, generator=g, dtype=F64), torch.randn(4, generator=g, dtype=F64)
    x = samples(lo, hi)
    assert_encloses(Iv(lo, hi).linear(w, b), x @ w.T + b)
    assert_encloses(Iv(lo, hi).norm(), x.norm(dim=-1))
    straddling = Iv(torch.tensor([[-1.0, -2.0]], dtype=F64), torch.tensor([[1.0, 3.0]], dtype=F64)).norm()
    assert float(straddling.lo[0]) == 0.0 and math.isfinite(float(straddling.hi[0]))  # not "outside sqrt's domain"
    low, high = torch.tensor([-0.5, -0.2, 0.0], dtype=F64), torch.tensor([0.5, 0.3, 0.1], dtype=F64)
    assert_encloses(Iv(lo, hi).clamp(low, high), torch.minimum(torch.maximum(x, low), high))


def test_dual_tangents_enclose_the_derivative_at_every_sampled_point():
    """d/dz of f(z) = tanh(W z + b) . c + ||z|| * sin(z_0) over boxes: the tangents of the dual enclose autograd's
    gradient at points of the box (the mean-value form rests on this)."""
    g = torch.Generator().manual_seed(6)
    lo = torch.randn(300, 2, generator=g, dtype=F64)
    hi = lo + 0.5 * torch.rand(300, 2, generator=g, dtype=F64)
    w, b = torch.randn(3, 2, generator=g, dtype=F64), torch.randn(3, generator=g, dtype=F64)
    c = torch.randn(3, generator=g, dtype=F64)

    def f(z):
        return (torch.tanh(z @ w.T + b) * c).sum(-1) + z.norm(dim=-1) * torch.sin(z[:, 0])

    def f_checker(z):
        return (z.linear(w, b).tanh() * c).sum(-1) + z.norm() * z[:, 0].sin()

    out = f_checker(Du.seed(Iv(lo, hi), 2, [0, 1]))
    x = samples(lo, hi, k=16).reshape(-1, 2).requires_grad_(True)
    grad = torch.autograd.grad(f(x).sum(), x)[0].reshape(16, 300, 2)
    for i in range(2):
        assert_encloses(out.d[i], grad[..., i], tol=1e-12)
    assert_encloses(out.v, f(x.detach()).reshape(16, 300), tol=1e-12)


def test_the_norms_tangent_is_enclosed_on_wide_boxes():
    """d/dz ||W z + b|| over boxes where the vector's norm ranges widely (and where it may reach 0): the tangent
    encloses autograd's at sampled points, and it is never wider than the Lipschitz bound ``||W||``-like
    ``[-||t||, ||t||]`` (the unit vector's components lie in [-1, 1])."""
    g = torch.Generator().manual_seed(8)
    lo = torch.randn(400, 2, generator=g, dtype=F64) * 2
    hi = lo + 1.5 * torch.rand(400, 2, generator=g, dtype=F64)
    w, b = torch.randn(3, 2, generator=g, dtype=F64), torch.randn(3, generator=g, dtype=F64) * 0.3
    out = Du.seed(Iv(lo, hi), 2, [0, 1]).linear(w, b).norm()
    x = samples(lo, hi, k=32).reshape(-1, 2).requires_grad_(True)
    grad = torch.autograd.grad(torch.linalg.vector_norm(x @ w.T + b, dim=-1).sum(), x)[0].reshape(32, 400, 2)
    for i in range(2):
        assert_encloses(out.d[i], grad[..., i], tol=1e-12)
        lipschitz = w[:, i].norm()
        assert bool((out.d[i].hi <= lipschitz * (1 + 1e-9)).all() and (out.d[i].lo >= -lipschitz * (1 + 1e-9)).all())


def test_nested_duals_give_the_design_models_w_and_its_gradient():
    """The pendulum's W = dF/dp in (mass, damping) and its derivative in the state, from nested duals."""
    system = small_pendulum()
    lo = torch.tensor([[0.1, -0.3]], dtype=F64)
    hi = lo + 1e-9
    z = Du.seed(Iv(lo, hi), 2, [0, 1])
    p0 = torch.tensor([[1.0, 1.0, 0.13, 9.81]], dtype=F64)
    tangents = []
    for i in system.uncertain_index:
        e = torch.zeros(1, 4, dtype=F64)
        e[0, i] = 1.0
        tangents.append(Du(Iv.point(e), [Iv.point(torch.zeros(1, 4, dtype=F64))] * 2))
    p = Du(Du(Iv.point(p0), [Iv.point(torch.zeros(1, 4, dtype=F64))] * 2), tangents)
    u = torch.tensor([[0.7]], dtype=F64)
    out = system.dynamics(z, u, p)  # (1, 2): value, d/dmass, d/ddamping, each with d/dz
    theta, omega = float(lo[0, 0]), float(lo[0, 1])
    dmass = -(0.7 - 0.13 * omega) / 1.0  # d/dm of (m g sin - b w + u) / m at m = 1: -(u - b w)
    assert abs(float(out.d[0].v.lo[0, 1]) - dmass) < 1e-6
    assert abs(float(out.d[1].v.lo[0, 1]) + omega) < 1e-6  # d/db = -omega
    assert abs(float(out.d[1].d[1].lo[0, 1]) + 1.0) < 1e-6  # d/domega of d/db = -1
    assert abs(float(out.v.d[0].lo[0, 1]) - 9.81 * math.cos(theta)) < 1e-6


# --------------------------------------------------------------------------- certificates
@pytest.fixture(scope="module")
def proved(tmp_path_factory):
    """A verified DR pointwise proof of the hand-made linear pair on the small pendulum, as a certificate file."""
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    from drlyap.closed_loop import ClosedLoop

    loop = ClosedLoop(system, lyap, ctrl)
    xi = torch.tensor([[0.02, 0.01], [-0.03, 0.0], [0.05, -0.02]], dtype=F64)
    condition = DRPointwise(0.01, 0.3, xi, decay_rate=0.05)
    region = Region.of(system, 0.1)
    proof = verify_condition(loop, condition, region, Budget(seconds=1e9, boxes=200_000, enclosure="mean-value"))
    assert proof.status == "verified" and proof.partition is not None
    folder = tmp_path_factory.mktemp("cert")
    weights = {"lyapunov": lyap.state_dict(), "controller": ctrl.state_dict()}
    torch.save(weights, folder / "weights.pt")
    write_certificate(folder, "trained", proof, Stated(condition, region), system,
                      PairFiles(folder / "weights.pt", lyap.alpha_hat))
    return {"system": system, "folder": folder, "weights": weights, "proof": proof, "loop": loop,
            "condition": condition, "region": region}


def run_check(proved, folder=None, weights=None, header_change=None, arrays_change=None):
    return recheck(folder or proved["folder"], "trained", proved["system"], weights or proved["weights"],
                   header_change, arrays_change)


def test_the_checker_re_proves_the_verifiers_certificate(proved):
    result = run_check(proved)
    assert result.ok, result.failures
    counts = proved["proof"].partition.counts()
    assert result.proved == counts["proved"] and result.inside_ball == counts["inside ball"]
    assert "DR pointwise condition (r = 0.01, eps = 0.3, 3 samples of xi" in result.claim


def test_the_checkers_residual_is_the_conditions(proved):
    loop, condition = proved["loop"], proved["condition"]
    pair = Pair(proved["weights"], loop.lyapunov.alpha_hat, 2)
    residual = Residual(condition_claim(condition), pair, proved["system"])
    z = proved["region"].sample(200, torch.Generator().manual_seed(0))
    mine = residual.components(Iv.point(z))
    theirs = condition.components(condition.terms(loop.f64, z)).detach()
    assert_encloses(mine, theirs, tol=1e-12)
    assert float((mine.hi - mine.lo).max()) < 1e-9


def test_the_checker_reads_networks_with_a_linear_path():
    from drlyap.networks import Controller, Lyapunov

    torch.manual_seed(4)
    lyap = Lyapunov(2, (4,), 3, 0.5, skip=True).double()
    ctrl = Controller(2, ((-2.0,), (3.0,)), (0.5,), (8,), skip=True).double()
    with torch.no_grad():
        ctrl.varphi.skip.weight.copy_(torch.tensor([[-1.5, -0.7]]))
        lyap.phi.skip.weight.copy_(torch.tensor([[0.8, 0.1], [0.0, 1.2], [0.3, -0.4]]))
    pair = Pair({"lyapunov": lyap.state_dict(), "controller": ctrl.state_dict()}, 0.5, 2)
    z = torch.randn(100, 2, dtype=F64)
    assert_encloses(pair.controller(Iv.point(z)), ctrl(z).detach(), tol=1e-12)
    value, grad = pair.value_and_grad(Iv.point(z))
    theirs_value, theirs_grad = lyap.value_and_grad(z)
    assert_encloses(value, theirs_value.detach(), tol=1e-12)
    assert_encloses(grad, theirs_grad.detach(), tol=1e-12)


def test_the_boxes_cover_the_state_box(proved):
    header, arrays = read_certificate(proved["folder"], "trained")
    region = proved["region"]
    blo, bhi = rebuild_boxes(region.lo, region.hi, header["partition"]["grid"], arrays)
    leaves = arrays["verdict"] != 0
    volume = float((bhi[leaves] - blo[leaves]).prod(-1).sum())
    assert volume == pytest.approx(float(region.scale.prod()), rel=1e-12)


def test_a_weight_changed_by_1e_6_is_rejected(proved, tmp_path):
    folder = tmp_path / "changed"
    shutil.copytree(proved["folder"], folder)
    weights = {k: {n: t.clone() for n, t in v.items()} for k, v in proved["weights"].items()}
    weights["controller"]["varphi.layers.0.weight"][0, 0] += 1e-6
    torch.save(weights, folder / "weights.pt")
    result = run_check(proved, folder=folder, weights=weights)
    assert not result.ok and "weights.pt" in result.failures[0]


def test_a_removed_box_is_rejected(proved):
    def drop_last(arrays):
        return {k: v[:-1] for k, v in arrays.items()}

    result = run_check(proved, arrays_change=drop_last)
    assert not result.ok and "exactly one lower and one upper half" in result.failures[0]


def test_a_lowered_bound_is_rejected(proved):
    def lower_one(arrays):
        i = int(np.flatnonzero(arrays["verdict"] == 1)[0])
        arrays["bound"][i] = -1e6

    result = run_check(proved, arrays_change=lower_one)
    assert not result.ok and "recorded bounds lie below" in result.failures[-1]


def test_a_stronger_claim_than_proved_is_rejected(proved):
    """The same partition claimed for a far larger decay rate: the checker's own bounds refuse the boxes."""
    def stronger(header):
        header["claim"]["condition"]["decay_rate"] = 50.0

    result = run_check(proved, header_change=stronger)
    assert not result.ok and "not proved by the checker's bounds" in result.failures[0]


def test_a_box_moved_into_the_ball_is_rejected(proved):
    def into_ball(arrays):
        i = int(np.flatnonzero(arrays["verdict"] == 1)[0])
        arrays["verdict"][i] = 2

    result = run_check(proved, arrays_change=into_ball)
    assert not result.ok and "open ball" in result.failures[0]


def test_a_claim_proved_on_the_balls_box_alone_is_not_confirmed_for_the_whole_box(proved, tmp_path):
    """A plain claim whose region names the delta-ball's box (``ball_of``, which only a ``roa-ball`` or ``practical``
    claim states) was checked on that box while its sentence claimed the state box minus the ball."""
    system, loop, condition = proved["system"], proved["loop"], proved["condition"]
    ball = 0.3
    lo, hi = system.local_box()
    inside = Region(torch.clamp(lo, min=-ball), torch.clamp(hi, max=ball), proved["region"].delta)
    proof = verify_condition(loop, condition, inside, Budget(seconds=1e9, boxes=200_000, enclosure="mean-value"))
    assert proof.verified
    folder = tmp_path / "run"
    folder.mkdir()
    shutil.copy(proved["folder"] / "weights.pt", folder / "weights.pt")
    write_certificate(folder, "trained", proof, Stated(condition, inside, parts={"ball_of": ball}), system,
                      PairFiles(folder / "weights.pt", loop.lyapunov.alpha_hat))
    result = recheck(folder, "trained", system, proved["weights"])
    assert not result.ok and result.claim == "(an unreadable claim)"
    assert any("make no kind of claim" in f for f in result.failures), result.failures


@pytest.mark.parametrize("parts, ball, kind", [
    ({}, False, "condition"), ({"ellipsoid": {}}, False, "ellipsoid"), ({"practical": {}}, True, "practical"),
    ({"band": {}}, False, "band"), ({"cube": {}}, True, "roa-ball"), ({"core": {}}, True, "roa-ball"),
    ({"core": {}}, False, "core"), ({}, True, None), ({"cube": {}}, False, None), ({"band": {}, "core": {}}, False, None),
    ({"ellipsoid": {}, "practical": {}}, True, None)])
def test_a_claims_parts_make_one_kind_or_none(parts, ball, kind):
    claim = {"condition": {"name": "true"}, "region": {"delta": 0.1, **({"ball_of": 0.1} if ball else {})}, **parts}
    if kind is None:
        with pytest.raises(ValueError, match="no kind of claim"):
            claim_kind(claim)
        assert claim_sentence(claim) == "(an unreadable claim)"
    else:
        assert claim_kind(claim) == kind
    assert claim_kind({"condition": {"name": "uniform"}, "region": {}}) == "uniform"
    with pytest.raises(ValueError, match="no level"):  # its sentence would state V > c on the faces, never checked
        claim_kind({"condition": {"name": "uniform"}, "region": {"level": 1.0}})


def test_what_the_checker_reads_of_a_claim_is_what_its_sentence_says(proved):
    """Hand-edited headers whose sentence would state more than the checker re-proves are refused."""
    def edit(change):
        return run_check(proved, header_change=change)

    cases = [
        (lambda h: h["claim"].update(band={"low": 0.1}), "a 'trained' certificate does not state a band claim"),
        (lambda h: h["claim"]["region"].update(delta=-0.1), "not a finite number"),
        (lambda h: h["claim"]["region"].update(level=float("nan")), "not a finite number"),
        (lambda h: h["claim"]["condition"].update(xi=[0.02, 0.01, -0.03]), "is not (N, 2)"),  # flat: read as 3 rows
        (lambda h: h["claim"]["condition"].update(xi_box={"low": [[0.0, 0.0]], "high": [[0.0, 0.0]]}),
         "box of shifts is stated by the true model's condition alone"),
        (lambda h: h["claim"]["condition"].update(risk_level=0.0), "risk level"),
        (lambda h: h["claim"]["condition"].update(exp_rate=-1000.0), "decay (gamma, alpha >= 0)"),  # no decrease
        (lambda h: h["claim"]["condition"].pop("wasserstein_radius"), "cannot be put in words"),
    ]
    for change, says in cases:
        result = edit(change)
        assert not result.ok and any(says in f for f in result.failures), (says, result.failures)


def test_a_claims_sentence_never_prints_the_files_own_words_and_rounds_towards_less():
    claim = {"condition": {"name": "nominal", "label": "DR pointwise (r = 1, eps = 0.01)", "xi": [[0.1, 0.0]],
                           "decay_rate": 0.05},
             "region": {"delta": 0.1 + 1e-12, "level": None}}
    words = claim_sentence(claim)
    assert "DR pointwise" not in words and "the nominal (baseline) condition" in words
    assert repr(0.1 + 1e-12) in words  # a ball printed as 0.1 would claim the states between
    cube = {"condition": {"name": "plain", "model": "true", "xi": [[0.0]]}, "cube": {"half": [0.00390625, 0.0573999]},
            "outer": "roa", "region": {"delta": 0.1, "ball_of": 0.1, "level": 1.0}}
    assert "[0.0039, 0.0573]" in claim_sentence(cube)  # rounded down: a smaller cube is proved too
    core = {"condition": {"name": "true", "xi": [[0.2, 0.0]]}, "core": {"P": [[1.0]], "level": 0.5,
            "certificate": "ellipsoid"}, "faces": "inward", "region": {"delta": 0.0, "level": 2.0}}
    assert "V > 2 on the box's faces" not in claim_sentence(core)  # the rule checked is the flow entering the box
    assert "the flow entering the box at every point of its faces with V <= 2" in claim_sentence(core)
    shifts = {"condition": {"name": "true", "xi": None, "xi_box": {"low": [[-0.123456]], "high": [[0.123456]]}},
              "region": {"delta": 0.1, "level": None}}
    assert "[-0.1234, 0.1234]" in claim_sentence(shifts)  # a narrower box of shifts than proved


def test_a_dr_condition_stated_on_the_true_model_is_not_checked_as_a_plain_decrease(proved):
    def true_model(header):  # the checker's residual would drop the Wasserstein term; the sentence would not say so
        header["claim"]["condition"]["model"] = "true"

    result = run_check(proved, header_change=true_model)
    assert not result.ok
    assert any("on the 'true' model is not one drlyap states" in f for f in result.failures), result.failures


def test_tree_checks_name_the_problem():
    arrays = {"parent": np.array([-1, -1, 0]), "side": np.zeros(3, np.int8), "axis": np.array([0, -1, -1], np.int8),
              "verdict": np.array([0, 1, 1], np.int8), "bound": np.zeros(3)}
    with pytest.raises(CertificateError, match="exactly one lower and one upper half"):
        check_tree(arrays, 2, 2, None)
    arrays["verdict"][1] = 4
    with pytest.raises(CertificateError, match="not proved"):
        check_tree({**arrays, "parent": np.array([-1, -1]), "side": np.zeros(2, np.int8),
                    "axis": np.array([-1, -1], np.int8), "verdict": np.array([1, 4], np.int8),
                    "bound": np.zeros(2)}, 2, 2, None)


def test_a_changed_partition_file_is_named(proved, tmp_path):
    folder = tmp_path / "changed"
    shutil.copytree(proved["folder"], folder)
    data = bytearray((folder / "certificates" / "trained.npz").read_bytes())
    data[-40] ^= 0xFF
    (folder / "certificates" / "trained.npz").write_bytes(bytes(data))
    with pytest.raises(ValueError, match="does not match the sha256"):
        read_certificate(folder, "trained")
    header = json.loads((folder / "certificates" / "trained.json").read_text())
    header["version"] = 99
    (folder / "certificates" / "trained.json").write_text(json.dumps(header))
    with pytest.raises(ValueError, match="version 99"):
        read_certificate(folder, "trained")


def test_true_model_certificate_of_a_shift(proved, tmp_path):
    """Decrease on the true model at a shift: proved, written and re-checked."""
    loop, region, system = proved["loop"], proved["region"], proved["system"]
    condition = TrueDecrease(torch.tensor([[0.1, 0.05]], dtype=F64), decay_rate=0.05)
    proof = verify_condition(loop, condition, region, Budget(seconds=1e9, boxes=200_000, enclosure="mean-value"))
    assert proof.verified
    folder = tmp_path / "shift"
    shutil.copytree(proved["folder"], folder)
    write_certificate(folder, "true-model", proof, Stated(condition, region), system,
                      PairFiles(folder / "weights.pt", 1e-3))
    header, arrays = read_certificate(folder, "true-model")
    result = check_certificate("true-model", header, arrays, system, proved["weights"],
                               sha256_file(folder / "weights.pt"), system_digest(system))
    assert result.ok, result.failures
    assert "true model at xi = [0.1, 0.05]" in result.claim


def test_verify_writes_and_check_re_checks_a_run(tmp_path):
    """`drlyap verify RUN --xi` writes certificates of the proofs that end verified; `drlyap check RUN` re-checks
    them (exit 0) and fails (exit 1) once the weights changed."""
    from pathlib import Path

    from click.testing import CliRunner

    from drlyap.cli import main
    from handmade import linear_run_dir

    run = linear_run_dir(tmp_path / "run")
    spec = f"{Path(__file__).parent / 'handmade.py'}:small_pendulum"
    runner = CliRunner()
    out = runner.invoke(main, ["verify", str(run), "--system", spec, "--xi", "0.1,0.05"])
    assert out.exit_code == 0, out.output
    assert "certificates/trained.json" in out.output and "certificates/true-model.json" in out.output
    out = runner.invoke(main, ["check", str(run), "--system", spec])
    assert out.exit_code == 0, out.output
    assert out.output.count("CHECKED") == 2 and "the boxes cover the region" in out.output
    header = json.loads((run / "certificates" / "trained.json").read_text())
    header["claim"]["condition"]["wasserstein_radius"] = 0.0  # a weaker condition than the run was trained on
    (run / "certificates" / "trained.json").write_text(json.dumps(header))
    out = runner.invoke(main, ["check", str(run), "--system", spec, "--name", "trained"])
    assert out.exit_code == 1 and "not the run's trained condition (wasserstein_radius" in out.output
    weights = torch.load(run / "weights.pt", weights_only=True)
    weights["lyapunov"]["phi.layers.0.weight"][0, 0] += 1e-6
    torch.save(weights, run / "weights.pt")
    out = runner.invoke(main, ["check", str(run), "--system", spec])
    assert out.exit_code == 1 and "FAILED" in out.output and "sha256 differs" in out.output
    out = runner.invoke(main, ["check", str(tmp_path / "nothing")])
    assert out.exit_code != 0 and "does not exist" in out.output


def test_a_sublevel_set_certificate_is_checked_with_its_faces(proved, tmp_path):
    """The condition on {V <= c} minus the ball, with V > c on the faces: written, re-checked; the same partition
    claimed for a level above V's minimum on the faces fails there."""
    from drlyap.verification.sublevel import boundary_minimum, verify_sublevel

    loop, region, system, condition = proved["loop"], proved["region"], proved["system"], proved["condition"]
    faces_low = boundary_minimum(loop.f64.lyapunov, region).lower
    level = 0.5 * faces_low
    proof = verify_sublevel(loop, condition, region, level, Budget(seconds=1e9, boxes=200_000, enclosure="mean-value"))
    assert proof.verified and proof.partition is not None and proof.partition.counts()["above level"] > 0
    folder = tmp_path / "level"
    shutil.copytree(proved["folder"], folder)
    write_certificate(folder, "trained", proof, Stated(condition, region), system,
                      PairFiles(folder / "weights.pt", 1e-3))
    result = run_check(proved, folder=folder)
    assert result.ok, result.failures
    assert result.faces_min > level and "{V <= " in result.claim

    def too_high(header):
        header["claim"]["region"]["level"] = 1.5 * faces_low

    result = run_check(proved, folder=folder, header_change=too_high)
    assert not result.ok and any("faces" in f for f in result.failures)


def test_refining_a_false_certificate_costs_at_most_about_as_many_pieces_as_it_has_boxes(proved):
    from drlyap.checker.leaves import MIN_PIECES

    def stricter(header):
        header["claim"]["condition"]["decay_rate"] = 5.0  # far more decay than the pair has: most boxes fail

    result = run_check(proved, header_change=stricter)
    assert not result.ok and result.refined > 0
    assert result.pieces <= max(MIN_PIECES, result.boxes)


def test_leaves_a_crowded_chunk_left_unproved_get_the_pieces_the_others_did_not_spend(monkeypatch):
    import drlyap.checker.leaves as leaves

    class Job:  # a hard leaf (lo < 0) is proved by 4 pieces of bisection, where its chunk's budget allows them all
        def on(self, device):
            return self

        def __call__(self, lo, hi, above, allowance):
            budget = int(allowance.sum())
            hard = lo[:, 0] < 0
            pieces = 4 * int(hard.sum()) if 4 * int(hard.sum()) <= budget else 0
            ok = ~hard | torch.tensor(pieces > 0)
            return {"ok": ok, "centre_low": torch.zeros(len(lo), dtype=torch.float64),
                    "refined": torch.tensor([int(hard.sum())]), "pieces": torch.tensor([pieces])}

    monkeypatch.setattr(leaves, "LEAF_CHUNK", 8)
    lo = torch.ones(64, 1, dtype=torch.float64)
    lo[:8] = -1.0  # every hard leaf in the first chunk: its own budget of 8 pieces cannot prove them
    ok, _, _, pieces = leaves.prove_leaves(Job(), lo, lo + 1, torch.zeros(64, dtype=torch.bool))
    assert bool(ok.all()) and pieces <= 64
    lo[:40] = -1.0  # too many hard leaves for one piece per leaf in all: refused, within the same budget
    ok, _, _, pieces = leaves.prove_leaves(Job(), lo, lo + 1, torch.zeros(64, dtype=torch.bool))
    assert not bool(ok[:40].any()) and bool(ok[40:].all()) and pieces <= 64
    # with 6 pieces per leaf (`drlyap check --pieces 6`) every chunk affords its hard leaves' 4 pieces each
    ok, _, _, pieces = leaves.prove_leaves(Job(), lo, lo + 1, torch.zeros(64, dtype=torch.bool), pieces_per_leaf=6.0)
    assert bool(ok.all()) and pieces == 4 * 40 <= 7 * 64
    with pytest.raises(ValueError, match="pieces per leaf must be >= 1"):
        leaves.prove_leaves(Job(), lo, lo + 1, torch.zeros(64, dtype=torch.bool), pieces_per_leaf=0.5)


@pytest.mark.parametrize("value, says", [("0.5", "0.5 is not in the range x>=1.0"),
                                         ("nan", "--pieces must be a finite number >= 1, got nan")])
def test_check_refuses_a_piece_budget_below_one_per_leaf_before_reading_the_run(tmp_path, value, says):
    from click.testing import CliRunner

    from drlyap.cli import main

    result = CliRunner().invoke(main, ["check", str(tmp_path / "missing"), "--pieces", value])
    assert result.exit_code != 0 and says in result.output


def test_the_check_command_bisects_as_deep_as_the_checker_by_default():
    """`drlyap check`'s --refine (written out there: its help loads no torch) is the checker's own default."""
    from drlyap.checker.leaves import REFINE
    from drlyap.cli.check import check

    refine = next(p for p in check.params if p.name == "refine")
    assert refine.default == REFINE == 30
