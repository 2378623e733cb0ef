"""Bring your own pair: a controller and V read from ONNX files get the same proofs as the pair of a run directory;
unsupported files are refused with one line; controllers without V get the quadratic V of their linearisation."""

import dataclasses
import json
import warnings

import pytest
import torch
from click.testing import CliRunner
from torch import nn

from drlyap.cli import main
from drlyap.conditions import TrueDecrease
from drlyap.enclosures import Affine, Dual, Interval
from drlyap.graph import read_onnx
from drlyap.proof_settings import Budget, ProofConfig
from drlyap.regions import Region
from drlyap.runs import load_run, save_run
from drlyap.runs.imported import import_pair, import_run, load_onnx_pair, quadratic_loop, rl_actor_graph
from drlyap.systems import get_system
from drlyap.training import TrainConfig, fit
from drlyap.verification import verify_condition
from drlyap.verification.roa.sublevel import TRAINED_LEVEL
from drlyap.workflows.export import export_run
from drlyap.workflows.policies import load_policy_run
from handmade import verified_json

onnx = pytest.importorskip("onnx")
F64 = torch.float64


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A tiny trained pendulum pair, saved and exported by ``drlyap export``: (run, export folder)."""
    torch.set_num_threads(1)
    system = get_system("pendulum")
    cfg = TrainConfig(system="pendulum", n_states=256, iters=60, check_every=60, lyapunov_hidden=[8], lyapunov_out=4,
                      controller_hidden=[8], seed=0).resolved(system)
    path = save_run(tmp_path_factory.mktemp("import") / "run", fit(cfg, system, progress=False))
    run = load_run(path)
    export_run(run)
    return run, path / "export"


def states(system, count=1000, seed=0):
    lo, hi = (torch.tensor(b, dtype=F64) for b in system.state_box)
    return lo + (hi - lo) * torch.rand(count, system.n, generator=torch.Generator().manual_seed(seed), dtype=F64)


def same(a, b) -> bool:
    """Two enclosures with bit-identical bounds."""
    if isinstance(a, Dual):
        return same(a.v, b.v) and (a.d is None) == (b.d is None) and (a.d is None or same(a.d, b.d))
    if isinstance(a, Affine):
        parts = [(a.c, b.c), (a.g, b.g), (a.q, b.q)]
        return all(p is None and q is None or torch.equal(p, q) for p, q in parts) and same(a.r, b.r)
    return torch.equal(a.lo, b.lo) and torch.equal(a.hi, b.hi)


def close(a, b) -> bool:
    """Two enclosures whose bounds differ by rounding only (1e-12 of their size): an imported V is pinned at x* to
    first order with enclosed ``V(0)`` and ``grad V(0)``, which pads the native V's bounds."""
    if isinstance(a, Dual):
        return close(a.v, b.v) and (a.d is None) == (b.d is None) and (a.d is None or close(a.d, b.d))
    size = torch.maximum(b.lo.abs(), b.hi.abs()).max()
    return all(bool(((p - q).abs() <= 1e-12 * size + 1e-250).all()) for p, q in ((a.lo, b.lo), (a.hi, b.hi)))


def test_an_exported_pair_imports_and_is_proved_the_same(exported):
    run, folder = exported
    system = run.system
    loop = load_onnx_pair(system, folder / "controller.onnx", folder / "lyapunov.onnx")
    x = states(system)
    z = system.to_local(x)
    with torch.no_grad():  # float64 graphs vs the run's float32 networks
        u, v = loop.controller(z), loop.lyapunov(z)
    assert float((u - run.controller(x)).abs().max()) <= 1e-5 * float(u.abs().max())
    assert float((v - run.lyapunov(x)).abs().max()) <= 1e-5 * float(v.abs().max())
    native = run.loop.f64
    assert torch.equal(u, native.controller(z)) and torch.equal(v, native.lyapunov(z))  # the same float64 reading
    lo = z[:4]
    boxes = [Interval(lo, lo + 0.05), Affine.box(lo, lo + 0.05),
             Dual(Interval(lo, lo + 0.05), Interval(torch.eye(2, dtype=F64).expand(4, 2, 2).clone()))]
    for box in boxes:  # the controller's enclosures bit for bit as the built-in networks give, V's up to rounding
        assert same(loop.controller(box), native.controller(box))
        assert all(close(a, b) for a, b in zip(loop.lyapunov.value_and_grad(box), native.lyapunov.value_and_grad(box)))
    xi = torch.tensor(system.test_xi, dtype=F64)
    condition = TrueDecrease(xi[None], decay_rate=run.config.decay_rate, exp_rate=run.config.exp_rate)
    region, budget = Region.of(system, run.config.delta), Budget(boxes=4000, seconds=1e9)
    ours, theirs = verify_condition(loop, condition, region, budget), verify_condition(run.loop, condition, region, budget)
    mine, other = ours.to_dict(), theirs.to_dict()
    bounds = [d.pop("sup_bounds") for d in (mine, other)]  # V's bounds move by rounding (close, above)
    for d in (mine, other):
        d.pop("time_s")
    assert mine == other and ours.boxes_processed > 1000
    assert bounds[0] == pytest.approx(bounds[1], rel=1e-12)
    print(f"native and imported: {ours.status}, {100 * ours.verified_fraction:.2f}% proved, "
          f"{ours.boxes_processed} boxes ({ours.boxes_verified} verified)")


def test_import_writes_a_run_that_loads_and_compares(exported, tmp_path):
    run, folder = exported
    out = tmp_path / "imported"
    result = CliRunner().invoke(main, ["import", "pendulum", "--controller", str(folder / "controller.onnx"),
                                       "--lyapunov", str(folder / "lyapunov.onnx"), "--out", str(out), "--json"])
    assert result.exit_code == 0, result.output
    record = json.loads(result.stdout)
    assert record["certificate"] == "onnx" and record["checks"]["pi_minus_u_star"] == [0.0]
    assert any("angle wrap" in note for note in record["notes"]["controller"])
    loaded = load_policy_run(out)
    assert loaded.kind == "imported" and (out / "source" / "controller.onnx").is_file()
    x = states(run.system, 200)
    assert torch.equal(loaded.controller(x), run.loop.f64.controller(run.system.to_local(x)))
    assert torch.equal(loaded.certificate(x), run.loop.f64.lyapunov(run.system.to_local(x)))
    again = CliRunner().invoke(main, ["import", "pendulum", "--controller", str(folder / "controller.onnx"),
                                      "--out", str(out)])
    assert again.exit_code != 0 and "already exists" in again.output
    # drlyap verify proves the imported pair as the run itself: the same proof of decrease at the shift
    args = ["--xi", "0.1,0.05", "--time-limit", "1e9", "--json"]
    own = CliRunner().invoke(main, ["verify", str(exported[0].path), *args])
    imported = CliRunner().invoke(main, ["verify", str(out), *args])
    own, imported = verified_json(own)["true_model"], verified_json(imported)["true_model"]
    for key in ("status", "verified_fraction", "boxes_processed", "boxes_verified", "counterexample"):
        assert own[key] == imported[key], key
    shown = CliRunner().invoke(main, ["compare", str(out), "--xi", "0.1,0.05", "--n-init", "4", "--certify-time", "0.5",
                                      "--json"])
    assert shown.exit_code == 0, shown.output
    attempt = json.loads(shown.stdout)["rows"][0]["certified"]
    assert attempt["status"] in ("verified", "violated", "unknown") and attempt["verified_fraction"] is not None


def _export(module: nn.Module, n: int, path, input_dim: int | None = None) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module.double(), (torch.zeros(2, input_dim or n, dtype=F64),), str(path), dynamo=False,
                          opset_version=17, input_names=["x"], output_names=["u"],
                          dynamic_axes={"x": {0: "batch"}, "u": {0: "batch"}})


class Saturated(nn.Module):
    """``clamp(u* - K z + 0.05 (relu(W z + b) - relu(b)) . w + 0.05 (sigmoid(a . z) - 1/2), U)`` on user states."""

    def __init__(self, system, gain, relu=True) -> None:
        super().__init__()
        g = torch.Generator().manual_seed(1)
        self.register_buffer("x_star", torch.tensor([system.equilibrium], dtype=F64))
        self.register_buffer("gain", gain)
        self.register_buffer("w1", torch.randn(4, system.n, generator=g, dtype=F64))
        self.register_buffer("b1", torch.rand(4, generator=g, dtype=F64) + 0.5)
        self.register_buffer("w2", torch.randn(system.m, 4, generator=g, dtype=F64))
        self.register_buffer("a", torch.randn(system.n, system.m, generator=g, dtype=F64) * 0.3)
        self.low, self.high = system.input_box[0][0], system.input_box[1][0]
        self.relu = relu

    def forward(self, x):
        z = x - self.x_star
        u = -z @ self.gain.T
        if self.relu:
            u = u + 0.05 * ((torch.relu(z @ self.w1.T + self.b1) - torch.relu(self.b1)) @ self.w2.T)
            u = u + 0.05 * (torch.sigmoid(z @ self.a) - 0.5)
        return torch.clamp(u, self.low, self.high)


def test_a_controller_without_v_gets_the_quadratic_certificate_of_its_linearisation(tmp_path):
    from drlyap.lqr import lqr_design

    system = get_system("pendulum")
    design = lqr_design(system)
    _export(Saturated(system, design.K), system.n, tmp_path / "c.onnx")
    pair = import_pair(system, tmp_path / "c.onnx")
    assert pair.certificate == "quadratic" and pair.exp_rate > 0
    assert any("clamp to U" in n or "lies in U" in n for n in pair.notes["controller"])
    z = system.to_local(states(system, 500))
    expected = Saturated(system, design.K)(system.to_user(z))
    with torch.no_grad():
        assert torch.allclose(pair.loop.controller(z), expected, rtol=1e-12, atol=1e-12)
    import_run("pendulum", tmp_path / "c.onnx", tmp_path / "run")
    saved = load_policy_run(tmp_path / "run")
    with torch.no_grad():  # saved and loaded again: the same graph (the relu's one-sided bound, inf, kept)
        assert torch.equal(saved.controller(system.to_user(z)), pair.loop.controller(z))
    assert torch.equal(saved.info["loop"].lyapunov.P, pair.loop.lyapunov.P)
    a = torch.tensor(pair.checks["A"], dtype=F64)
    p = pair.loop.lyapunov.P
    s = (torch.tensor(system.state_box[1], dtype=F64) - torch.tensor(system.state_box[0], dtype=F64)) / 2
    assert torch.allclose(a.T @ p + p @ a, -torch.diag(1 / s**2), atol=1e-9)  # A'P + PA = -S^-2
    # the graph's ReLU and sigmoid run on enclosures; x* needs V's proof only outside the delta-ball
    result = verify_condition(pair.loop, TrueDecrease(torch.zeros(1, system.k, dtype=F64), 0.0, pair.exp_rate),
                              Region.of(system, 0.5), Budget(boxes=2000, seconds=1e9))
    assert result.boxes_processed > 0 and result.status in ("verified", "violated", "unknown")
    # a controller that does not hold x*: refused, one line
    shifted = Saturated(system, design.K, relu=False)
    shifted.x_star += torch.tensor([[0.0, 0.1]], dtype=F64)
    _export(shifted, system.n, tmp_path / "off.onnx")
    with pytest.raises(ValueError, match="equilibrium") as err:
        import_pair(system, tmp_path / "off.onnx")
    assert "\n" not in str(err.value)


def _graph_model(path, ops: list[str], n_in: int = 2, hidden: int = 3):
    """An ONNX model x (batch, n_in) -> Gemm -> ops... -> Gemm -> u (batch, 1)."""
    from onnx import TensorProto, helper, numpy_helper

    g = torch.Generator().manual_seed(0)
    inits = [numpy_helper.from_array(torch.randn(hidden, n_in, generator=g, dtype=F64).numpy(), "w1"),
             numpy_helper.from_array(torch.randn(1, hidden, generator=g, dtype=F64).numpy(), "w2")]
    nodes, last = [helper.make_node("Gemm", ["x", "w1"], ["h0"], transB=1)], "h0"
    for i, op in enumerate(ops):
        nodes.append(helper.make_node(op, [last], [f"a{i}"]))
        last = f"a{i}"
    nodes.append(helper.make_node("Gemm", [last, "w2"], ["u"], transB=1))
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.DOUBLE, ["batch", n_in])],
                              [helper.make_tensor_value_info("u", TensorProto.DOUBLE, ["batch", 1])], inits)
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), str(path))


def test_unsupported_ops_and_other_dimensions_are_refused(tmp_path):
    system = get_system("pendulum")
    _graph_model(tmp_path / "softplus.onnx", ["Tanh", "Softplus"])
    with pytest.raises(ValueError) as err:
        import_pair(system, tmp_path / "softplus.onnx")
    message = str(err.value)
    assert "Softplus" in message and "softplus.onnx" in message and "\n" not in message
    _graph_model(tmp_path / "three.onnx", ["Tanh"], n_in=3)
    with pytest.raises(ValueError, match=r"\(batch, 3\).*n = 2") as err:
        import_pair(system, tmp_path / "three.onnx")
    assert "\n" not in str(err.value)
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(ValueError, match="junk.onnx"):
        import_pair(system, tmp_path / "junk.onnx")


def _one_extra_node(path, node_maker):
    """x (batch, 2) -> Gemm -> (a node from ``node_maker(last)``, with its own inits) -> Gemm -> u (batch, 1)."""
    from onnx import TensorProto, helper, numpy_helper

    g = torch.Generator().manual_seed(0)
    inits = [numpy_helper.from_array(torch.randn(3, 2, generator=g, dtype=F64).numpy(), "w1"),
             numpy_helper.from_array(torch.randn(1, 3, generator=g, dtype=F64).numpy(), "w2")]
    extra_nodes, extra_inits = node_maker("h0", "h1")
    graph = helper.make_graph([helper.make_node("Gemm", ["x", "w1"], ["h0"], transB=1), *extra_nodes,
                               helper.make_node("Gemm", ["h1", "w2"], ["u"], transB=1)], "g",
                              [helper.make_tensor_value_info("x", TensorProto.DOUBLE, ["batch", 2])],
                              [helper.make_tensor_value_info("u", TensorProto.DOUBLE, ["batch", 1])],
                              inits + extra_inits)
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), str(path))


def test_files_that_would_read_elsewhere_or_be_read_unsoundly_are_refused(tmp_path):
    from onnx import TensorProto, helper, numpy_helper

    system = get_system("pendulum")
    secret = tmp_path / "secret.bin"
    secret.write_bytes(b"\x00" * 24)

    def external_constant(last, out):  # a Constant whose value names a file beside the model
        t = helper.make_tensor("c", TensorProto.DOUBLE, [3], [0.0, 0.0, 0.0])
        t.ClearField("double_data")
        t.data_location = TensorProto.EXTERNAL
        entry = t.external_data.add()
        entry.key, entry.value = "location", "secret.bin"
        return [helper.make_node("Constant", [], ["c"], value=t), helper.make_node("Add", [last, "c"], [out])], []

    _one_extra_node(tmp_path / "external.onnx", external_constant)
    with pytest.raises(ValueError, match="stored outside the file") as err:
        import_pair(system, tmp_path / "external.onnx")
    assert "\n" not in str(err.value)

    def inverted_clip(last, out):  # min > max: ONNX outputs max everywhere; no rewrite may read it as a range
        return [helper.make_node("Clip", [last, "low", "high"], [out])], [
            numpy_helper.from_array(torch.tensor(1.0, dtype=F64).numpy(), "low"),
            numpy_helper.from_array(torch.tensor(0.5, dtype=F64).numpy(), "high")]

    _one_extra_node(tmp_path / "inverted.onnx", inverted_clip)
    with pytest.raises(ValueError, match="min > max"):
        import_pair(system, tmp_path / "inverted.onnx")

    def scaled(last, out):  # a product with a constant vector is read (no ambiguous comparison of arrays)
        return [helper.make_node("Mul", [last, "s"], [out])], [
            numpy_helper.from_array(torch.tensor([0.5, 2.0, -1.0], dtype=F64).numpy(), "s")]

    _one_extra_node(tmp_path / "scaled.onnx", scaled)
    graph, _ = read_onnx(tmp_path / "scaled.onnx", system, "controller")
    assert graph.n == 2


def test_an_export_made_for_another_equilibrium_is_refused(exported, tmp_path):
    run, folder = exported
    model = onnx.load(str(folder / "controller.onnx"))
    for t in model.graph.initializer:
        if t.name == "x_star":
            t.CopyFrom(onnx.numpy_helper.from_array(onnx.numpy_helper.to_array(t) + 0.25, "x_star"))
    onnx.save(model, str(tmp_path / "moved.onnx"))
    with pytest.raises(ValueError, match="another equilibrium"):
        load_onnx_pair(run.system, tmp_path / "moved.onnx", folder / "lyapunov.onnx")


@pytest.mark.parametrize("algo", ["sac", "ppo"])
def test_rl_actors_read_as_graphs(algo):
    pytest.importorskip("stable_baselines3")
    from drlyap.rl.agents import DEFAULT_HYPER, RLPolicy, _algo_class
    from drlyap.rl.envs import UncertainSystemEnv
    from drlyap.runs import PolicyRun
    from drlyap.workflows.compare import certify

    system = get_system("pendulum")
    hyper = dict(DEFAULT_HYPER[algo]) | ({"buffer_size": 1} if algo == "sac" else {})
    model = _algo_class(algo)("MlpPolicy", UncertainSystemEnv(system), seed=0, device="cpu", verbose=0, **hyper)
    agent = RLPolicy(system, algo, model)
    actor = rl_actor_graph(system, algo, model.policy)
    x = states(system)
    with torch.no_grad():
        u = actor(system.to_local(x))
    expected = agent.controller(x)
    assert float((u - expected).abs().max()) <= 1e-5 * max(float(expected.abs().max()), 1.0)
    lo, hi = system.input_box
    assert bool(((u >= lo[0]) & (u <= hi[0])).all())
    box = Interval(system.to_local(x[:8]), system.to_local(x[:8]) + 0.01)
    out = actor(box)  # runs on enclosures
    assert bool((out.lo <= u[:8]).all() and (out.hi >= u[:8]).all())
    offset = float(actor(torch.zeros(1, 2, dtype=F64))[0, 0])
    run = PolicyRun(None, "rl", system, agent.controller, agent.certificate, 0, 0.0, f"rl-{algo}", {"algo": algo}, {},
                    {"agent": agent})
    # an untrained actor does not hold x* (SAC) or does not stabilise its linearisation (PPO's zero action net):
    # the attempt says why and proves nothing
    why = "not an equilibrium" if abs(offset) > 1e-5 else "not Hurwitz"
    attempt = certify(run, torch.tensor(system.test_xi, dtype=F64), 1.0)
    assert attempt.status == "none" and why in attempt.note and "\n" not in attempt.note
    with pytest.raises(ValueError, match=why):
        quadratic_loop(system, actor)


class Bowl(nn.Module):
    """``V(z) = |tanh(W z + b) - tanh(b)|^2 + (z.z + sum z^4 / 100) exp(a.z / 10) / (1 + sigmoid(c.z)) + offset``:
    the reverse mode through products and quotients of state-dependent values, exp, powers and sigmoids."""

    def __init__(self, n: int, offset: float = 0.5, tilt: float = 0.0) -> None:
        super().__init__()
        g = torch.Generator().manual_seed(2)
        for name, shape in (("w", (3, n)), ("b", (3,)), ("a", (n,)), ("c", (n,))):
            self.register_buffer(name, torch.randn(*shape, generator=g, dtype=F64))
        self.offset, self.tilt = offset, tilt

    def forward(self, x):
        z = x - torch.zeros(1, x.shape[1], dtype=x.dtype)
        d = torch.tanh(z @ self.w.T + self.b) - torch.tanh(self.b)
        bowl = (z * z).sum(-1) + (z**4).sum(-1) / 100
        scale = torch.exp((z @ self.a) / 10) / (1 + torch.sigmoid(z @ self.c))
        return (d * d).sum(-1) + bowl * scale + self.offset + self.tilt * z[:, 0]


def test_an_imported_v_has_sound_values_and_gradients(tmp_path):
    system = get_system("pendulum")
    bowl = Bowl(system.n)
    _export(bowl, system.n, tmp_path / "v.onnx")
    _export(Saturated(system, torch.tensor([[20.0, 5.0]], dtype=F64), relu=False), system.n, tmp_path / "c.onnx")
    pair = import_pair(system, tmp_path / "c.onnx", tmp_path / "v.onnx")
    v_net = pair.loop.lyapunov
    assert pair.certificate == "onnx" and pair.checks["V_at_equilibrium"] == 0.5  # pinned: V - V(x*)
    z = system.to_local(states(system, 500)).requires_grad_(True)
    expected = bowl(z) - bowl(torch.zeros(1, 2, dtype=F64))
    (grad,) = torch.autograd.grad(expected.sum(), z)
    value, ours = v_net.value_and_grad(z.detach())
    assert torch.allclose(value, expected.detach(), rtol=1e-12, atol=1e-12)
    assert torch.allclose(ours, grad, rtol=1e-10, atol=1e-12)
    lo = z.detach()[:6]
    hi = lo + 0.2
    pts = lo + (hi - lo) * torch.rand(50, 6, 2, generator=torch.Generator().manual_seed(3), dtype=F64)
    pv, pg = zip(*[v_net.value_and_grad(p) for p in pts])
    pv, pg = torch.stack(pv), torch.stack(pg)
    for box in (Interval(lo, hi), Affine.box(lo, hi)):  # the enclosures contain every sampled value and gradient
        bv, bg = v_net.value_and_grad(box)
        bv, bg = (e.to_interval() if isinstance(e, Affine) else e for e in (bv, bg))
        assert bool((bv.lo <= pv).all() and (pv <= bv.hi).all() and (bg.lo <= pg).all() and (pg <= bg.hi).all())
    _export(Bowl(system.n, tilt=0.3), system.n, tmp_path / "tilted.onnx")
    tilted = import_pair(system, tmp_path / "c.onnx", tmp_path / "tilted.onnx")  # taken as given, for a band claim
    assert not tilted.pinned and tilted.loop.lyapunov is tilted.given_loop.lyapunov
    assert any("not a minimum of V" in note and "--band" in note for note in tilted.notes["lyapunov"])


def test_an_exported_region_of_attraction_pair_imports_with_its_run_s_claim_and_certifies_the_same(tmp_path):
    """The export of a run trained for a region of attraction carries its claim (decay, level, delta): the imported
    pair is proved on the same {V <= level} and certifies the same region; above that level (the default), both
    certify the same larger one."""
    from drlyap.workflows.verify import VerifyRequest, verify, verify_imported

    system = get_system("pendulum")
    cfg = TrainConfig(system="pendulum", roa_level=1.0, warm_start="lqr", decay_rate=0.0, exp_rate=0.3, n_states=256,
                      iters=400, check_every=400, lyapunov_hidden=[8], controller_hidden=[8], seed=0).resolved(system)
    path = save_run(tmp_path / "run", fit(cfg, system, progress=False))
    run = load_run(path)
    record = export_run(run)
    assert record["claim"] == {"decay_rate": 0.0, "exp_rate": 0.3, "level": 1.0, "delta": run.config.delta}
    folder = path / "export"
    out = tmp_path / "imported"
    result = CliRunner().invoke(main, ["import", "pendulum", "--controller", str(folder / "controller.onnx"),
                                       "--lyapunov", str(folder / "lyapunov.onnx"), "--out", str(out)])
    assert result.exit_code == 0, result.output
    pair = load_policy_run(out).info["pair"]
    assert (pair.level, pair.delta, pair.decay_rate, pair.exp_rate) == (1.0, run.config.delta, 0.0, 0.3)
    xi = torch.tensor(system.test_xi, dtype=F64)
    proof = dataclasses.replace(run.proof or ProofConfig(), time_limit=20.0)
    mine = verify(run, proof, VerifyRequest(xi=xi, roa=True, above_level=False), reprove=True)
    theirs = verify_imported(pair, str(out), proof, request=VerifyRequest(xi=xi, roa=True, above_level=False))
    assert theirs.true_model.level == mine.true_model.level == 1.0
    assert theirs.true_model.status == mine.true_model.status
    assert theirs.true_model.boxes_processed == mine.true_model.boxes_processed
    assert mine.true_model.verified and mine.roa.limited_by == TRAINED_LEVEL and 0.99 < mine.roa.level <= 1.0
    assert theirs.roa.level == mine.roa.level and theirs.roa.share_of_box == mine.roa.share_of_box
    above = verify_imported(pair, str(out), proof, request=VerifyRequest(xi=xi, roa=True))
    run_above = verify(run, proof, VerifyRequest(xi=xi, roa=True))
    assert above.roa.level == pytest.approx(run_above.roa.level, rel=1e-9)  # V's bounds move by rounding
    assert above.roa.level > mine.roa.level  # this pair's decrease reaches past its level
    assert above.roa.share_of_box == pytest.approx(run_above.roa.share_of_box, rel=1e-6)
    assert above.roa.share_of_box > mine.roa.share_of_box
    print(f"run and import: level {mine.roa.level}, {mine.roa.share_of_box}; above it: {above.roa.level}, "
          f"{above.roa.share_of_box}")
    refused = CliRunner().invoke(main, ["verify", str(path), "--roa-at-level"])
    assert refused.exit_code == 1 and "--roa-at-level goes with --roa" in refused.output


def test_a_damaged_claim_in_an_export_is_refused_in_one_line():
    from drlyap.runs.imported import claim_of

    good = {"decay_rate": 0.0, "exp_rate": 0.3, "level": 1.0, "delta": 0.1}
    assert claim_of({"claim": good}) == good
    assert claim_of({"claim": good | {"level": None}})["level"] is None
    for bad, words in (({"level": 0.0}, "level must be a finite number > 0"),
                       ({"exp_rate": float("nan")}, "exp_rate must be a finite number >= 0"),
                       ({"delta": "0.1"}, "delta must be a finite number >= 0")):
        with pytest.raises(ValueError, match=words):
            claim_of({"claim": good | bad})
    with pytest.raises(ValueError, match="no 'claim' object"):
        claim_of({})


def test_a_users_system_pair_exported_and_imported_again_certifies_the_same_region(tmp_path):
    """The same through the command line for a system of the user's own file (trained for {V <= 1})."""
    import os

    from handmade import plain_train, small_pendulum

    spec = f"{os.path.dirname(__file__)}/handmade.py:small_pendulum"
    system = small_pendulum()
    cfg = TrainConfig(system=system.name, roa_level=1.0, warm_start="lqr", decay_rate=0.0, exp_rate=0.3, iters=60,
                      check_every=60, n_states=512, lyapunov_hidden=[8], controller_hidden=[8], seed=0,
                      xi_samples=[[0.0, 0.0], [0.05, 0.01]])
    run_dir = save_run(tmp_path / "run", plain_train(cfg, system, progress=False))
    runner = CliRunner()
    done = runner.invoke(main, ["export", str(run_dir), "--system", spec])
    assert done.exit_code == 0, done.output
    folder, out = run_dir / "export", tmp_path / "imported"
    done = runner.invoke(main, ["import", spec, "--controller", str(folder / "controller.onnx"),
                                "--lyapunov", str(folder / "lyapunov.onnx"), "--out", str(out)])
    assert done.exit_code == 0 and "its run's claim is taken" in done.output, done.output

    def verify(path, *more):
        res = runner.invoke(main, ["verify", str(path), "--system", spec, "--xi", "0.02,0.01", "--roa", "--json",
                                   "--time-limit", "10", *more])
        assert res.exit_code == 0, res.output
        return json.loads(res.stdout)

    mine, theirs = verify(run_dir, "--roa-at-level"), verify(out, "--roa-at-level")  # the run's claimed level
    assert theirs["roa_rate"] == mine["roa_rate"] == 0.01  # the strict decrease a region needs, by default
    assert theirs["true_model"]["level"] == mine["true_model"]["level"] == 1.0
    assert theirs["true_model"]["boxes_processed"] == mine["true_model"]["boxes_processed"]
    assert theirs["roa"]["level"] == mine["roa"]["level"] and theirs["roa"]["share_of_box"] == mine["roa"]["share_of_box"]
    print(f"run and import: {mine['true_model']['status']}, level {mine['roa']['level']}, {mine['roa']['share_of_box']}")
    # a slower decay asked at the shift (--roa-rate): the same proof and region for the pair and its import, and the
    # imported pair's certificates state that decay and are checked against it
    slow_mine, slow_theirs = (verify(path, "--roa-rate", "0.05", "--roa-at-level") for path in (run_dir, out))
    assert slow_theirs["roa_rate"] == slow_mine["roa_rate"] == 0.05
    assert slow_theirs["true_model"]["boxes_processed"] == slow_mine["true_model"]["boxes_processed"]
    assert slow_theirs["roa"]["level"] == slow_mine["roa"]["level"]
    assert slow_theirs["roa"]["share_of_box"] == slow_mine["roa"]["share_of_box"]
    claim = json.loads((out / "certificates" / "true-model.json").read_text())["claim"]["condition"]
    assert claim["exp_rate"] == 0.05
    checked = runner.invoke(main, ["check", str(out), "--system", spec])
    assert checked.exit_code == 0 and "FAILED" not in checked.output, checked.output


def test_a_graph_whose_reverse_mode_or_clamp_would_read_otherwise_is_refused():
    """Hand-made graphs the interpreter's reverse mode or the enclosures would read unlike plain torch: a squeeze of
    a last axis wider than 1 (its cotangent went to every column), a state-dependent input widened by broadcasting,
    and a clamp whose lower bound lies above its upper one (torch and the enclosures then disagree)."""
    import torch

    from drlyap.graph.interpreter import Graph, Node

    w = torch.tensor([[1.0, -1.0], [1.0, -1.0]], dtype=torch.float64)
    wide = [Node("linear", ("z", "w"), "a", {}), Node("square", ("a",), "b", {}), Node("squeeze", ("b",), "v", {})]
    with pytest.raises(ValueError, match="squeezes a last axis of 1 only"):
        Graph(wide, {"w": w}, "v", 2)
    row = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    widened = [Node("linear", ("z", "r"), "a", {}), Node("mul", ("a", "z"), "b", {}), Node("sum", ("b",), "v", {})]
    with pytest.raises(ValueError, match="broadcasts an input that depends on the state"):
        Graph(widened, {"r": row}, "v", 2)
    low, high = torch.tensor([5.0], dtype=torch.float64), torch.tensor([0.0], dtype=torch.float64)
    swapped = [Node("linear", ("z", "r"), "a", {}), Node("clamp", ("a", "lo", "hi"), "u", {})]
    with pytest.raises(ValueError, match="lower bounds must not exceed"):
        Graph(swapped, {"r": row, "lo": low, "hi": high}, "u", 2)
    from drlyap.checker.graphs import GraphNet  # the checker's own reading refuses the same clamp, and a pow of 2.5

    spec = {"input": "z", "output": "u", "constants": ["r", "lo", "hi"],
            "nodes": [{"op": "linear", "inputs": ["z", "r"], "output": "a"},
                      {"op": "clamp", "inputs": ["a", "lo", "hi"], "output": "u"}]}
    with pytest.raises(ValueError, match="lower bounds above its upper ones"):
        GraphNet(spec, {"r": row, "lo": low, "hi": high})
    spec["nodes"][1] = {"op": "pow", "inputs": ["a"], "output": "u", "attrs": {"n": 2.5}}
    with pytest.raises(ValueError, match="integer exponent"):
        GraphNet(spec, {"r": row, "lo": low, "hi": high})
