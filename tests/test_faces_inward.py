"""Regions of attraction cut by the state box: ``{z in box : V(z) <= c}`` where the true model's flow enters the box
wherever the set meets a face. The verifier's bound of V where the flow may leave is checked against dense sampling,
the certified set by simulation on the true model, and the checker's face rule against a level where the flow leaves."""

import json
import os

import pytest
import torch

from drlyap.checker.agreement import outer_missing
from drlyap.checker.levels import faces_inward
from drlyap.checker.model import Pair, Residual
from drlyap.claims.registry import claim_sentence
from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import TrueDecrease
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.simulation import simulate
from drlyap.verification import certified_roa
from drlyap.verification.roa.sublevel import EXIT_ROOM
from drlyap.verification.sublevel import boundary_minimum, exit_minimum, outward_bounds
from handmade import check_cli, linear_pair, linear_run_dir, small_pendulum, verify_cli

F64 = torch.float64
XI = [0.1, 0.05]


@pytest.fixture(scope="module")
def loop():
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    return ClosedLoop(system, lyap, ctrl)


def _condition():
    return TrueDecrease(torch.tensor([XI], dtype=F64), 0.05)


def _face_points(system, per_face: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniform points on every face of the local box ``(F, n)`` and each one's outward unit vector's axis and sign."""
    lo, hi = system.local_box()
    g = torch.Generator().manual_seed(seed)
    points, outward = [], []
    for i in range(system.n):
        for side, sign in ((lo[i], -1.0), (hi[i], 1.0)):
            z = lo + (hi - lo) * torch.rand(per_face, system.n, generator=g, dtype=F64)
            z[:, i] = side
            points.append(z)
            out = torch.zeros(per_face, system.n, dtype=F64)
            out[:, i] = sign
            outward.append(out)
    return torch.cat(points), torch.cat(outward)


def test_exit_minimum_bounds_v_where_the_sampled_flow_leaves(loop):
    region = Region.of(loop.system, 0.2)
    found = exit_minimum(loop, _condition(), region)
    lower, upper = found.lower, found.upper
    z, out = _face_points(loop.system, 50_000, seed=1)
    f64 = loop.f64
    with torch.no_grad():
        leaving = (f64.rhs(z, torch.tensor(XI, dtype=F64)) * out).sum(-1) >= 0
        v = f64.lyapunov(z)
    sampled = float(v[leaving].min())
    assert lower <= sampled <= upper * (1 + 1e-6) + 1e-12
    assert upper - lower <= 1e-3 * upper + 1e-9
    assert lower > boundary_minimum(loop.lyapunov, region).upper  # where the flow enters, V is lower: the rule adds


def test_outward_bounds_hold_the_sampled_flow(loop):
    region = Region.of(loop.system, 0.2)
    lo, hi = region.lo, region.hi
    a = torch.stack([lo, torch.tensor([hi[0], -0.3], dtype=F64)])
    b = torch.stack([torch.tensor([lo[0], 0.5], dtype=F64), torch.tensor([hi[0], 0.4], dtype=F64)])
    a[0, 0] = b[0, 0] = lo[0]
    low, up = outward_bounds(loop, _condition(), region, a, b, "mean-value")
    t = torch.linspace(0, 1, 1001, dtype=F64)[:, None]
    for row, sign in ((0, -1.0), (1, 1.0)):
        z = a[row] + (b[row] - a[row]) * t
        with torch.no_grad():
            flow = sign * loop.f64.rhs(z, torch.tensor(XI, dtype=F64))[:, 0]
        assert float(low[row, 0]) <= float(flow.min()) and float(flow.max()) <= float(up[row, 0])


def test_a_set_cut_by_the_box_is_certified_and_no_trajectory_leaves_it(loop):
    system = loop.system
    region = Region.of(system, 0.2)
    roa = certified_roa(loop, _condition(), region, Budget(seconds=10), samples_per_axis=100)
    assert roa.certified and roa.faces == "inward" and roa.level > roa.boundary_min_lower
    assert roa.level <= (1 - EXIT_ROOM) * roa.exit_min_lower and "flow leaves" in roa.limited_by
    lo, hi = system.local_box()
    g = torch.Generator().manual_seed(3)
    inner = lo + (hi - lo) * torch.rand(4_000, system.n, generator=g, dtype=F64)
    faces = _face_points(system, 1_000, seed=4)[0]
    z0 = torch.cat([inner, faces])
    with torch.no_grad():
        z0 = z0[loop.f64.lyapunov(z0) <= roa.level]  # about 5,700 states, 2,100 of them on the faces
    assert int(((z0 == lo) | (z0 == hi)).any(-1).sum()) >= 100  # states on the faces are part of the set
    ctrl = loop.f64.controller
    traj = simulate(system, lambda x: ctrl(system.to_local(x)), system.to_user(z0), torch.tensor(XI, dtype=F64),
                    dt=0.005, horizon=12.0)
    z = system.to_local(traj.x.reshape(-1, system.n)).reshape(traj.x.shape)
    assert bool(((z >= lo - 1e-9) & (z <= hi + 1e-9)).all()), "a trajectory left the box"
    assert float(z[-1].norm(dim=-1).max()) < 1e-3


def test_above_the_exit_minimum_a_trajectory_leaves_the_box(loop):
    """Falsifier of the rule's need: from face states with V just above the exit minimum, where the flow points out,
    trajectories leave the box at once."""
    region = Region.of(loop.system, 0.2)
    upper = exit_minimum(loop, _condition(), region).upper
    z, out = _face_points(loop.system, 50_000, seed=1)
    with torch.no_grad():
        flow = (loop.f64.rhs(z, torch.tensor(XI, dtype=F64)) * out).sum(-1)
        v = loop.f64.lyapunov(z)
    leaving = (flow > 0) & (v <= upper * 1.01)
    assert bool(leaving.any())


def _residual(loop, model="true"):
    system = loop.system
    state = {"lyapunov": loop.lyapunov.state_dict(), "controller": loop.controller.state_dict()}
    pair = Pair(state, float(loop.lyapunov.alpha_hat), system.n)
    claim = {"name": "true" if model == "true" else "plain", "model": model, "xi": [XI], "decay_rate": 0.05}
    return Residual(claim, pair, system)


def test_the_checker_refutes_the_rule_above_the_exit_minimum(loop):
    region = Region.of(loop.system, 0.2)
    found = exit_minimum(loop, _condition(), region)
    lower, upper = found.lower, found.upper
    residual = _residual(loop)
    holds, _, boxes = faces_inward(residual, region.lo, region.hi, 0.999 * lower)
    assert holds and boxes > 0
    holds, _, _ = faces_inward(residual, region.lo, region.hi, 1.01 * upper)
    assert not holds
    with pytest.raises(ValueError, match="true model"):
        faces_inward(_residual(loop, "design"), region.lo, region.hi, 0.999 * lower)


def test_the_claim_says_the_set_is_cut_by_the_box():
    claim = {"condition": {"name": "true", "xi": [XI], "decay_rate": 0.05},
             "region": {"level": 0.4, "delta": 0.2}, "faces": "inward"}
    text = claim_sentence(claim)
    assert "{V <= 0.4} in the state box" in text and "the flow entering the box" in text
    assert "V > 0.4 on the box's faces" in claim_sentence({k: v for k, v in claim.items() if k != "faces"})


SPEC = f"{os.path.dirname(__file__)}/handmade.py:small_pendulum"


def test_verify_writes_the_rule_and_check_holds_a_certificate_to_it(tmp_path):
    """End to end: `verify --roa` at a shift writes a `roa` certificate with the inward rule, `drlyap check` confirms it,
    and the same partition claimed with V above the level on the faces (false here), or with a rule the checker does
    not know, fails."""
    run = linear_run_dir(tmp_path / "run", delta=0.2)
    found = verify_cli(run, SPEC, ",".join(map(str, XI)))
    assert found["roa"]["certified"] and found["roa"]["faces"] == "inward"
    path = run / "certificates" / "roa.json"
    header = json.loads(path.read_text())
    assert header["claim"]["faces"] == "inward" and "the flow entering the box" in header["claim"]["statement"]
    out = check_cli(run, SPEC, "roa", "roa-ball")
    assert out.exit_code == 0, out.output
    for rule, words in (("above", "is not established on the box's faces"), ("sideways", "not one the checker takes")):
        header["claim"]["faces"] = rule
        path.write_text(json.dumps(header))
        out = check_cli(run, SPEC, "roa")
        assert out.exit_code != 0 and words in out.output, out.output
    header["claim"]["faces"] = "inward"
    path.write_text(json.dumps(header))
    metrics_path = run / "metrics.json"
    metrics = json.loads(metrics_path.read_text())
    metrics["certificate"]["roa"]["faces"] = "above"  # the run's report no longer says the set is cut by the box
    metrics_path.write_text(json.dumps(metrics))
    out = check_cli(run, SPEC, "roa")
    assert out.exit_code != 0 and "faces (not the rule" in out.output, out.output


def test_a_claim_resting_on_another_certificate_states_its_rule_for_the_faces(tmp_path):
    """A `practical` claim's rule for the faces is its outer certificate's: another rule, or none where the outer
    states one, is a failure (the outer's boxes and faces are checked on their own)."""
    folder = tmp_path / "certificates"
    folder.mkdir()
    condition = {"name": "plain", "xi": [[0.1, 0.05]], "decay_rate": 0.1}
    outer = {"claim": {"region": {"delta": 0.2, "level": 2.0}, "condition": condition, "faces": "inward"}}
    (folder / "roa.json").write_text(json.dumps(outer))
    practical = {"claim": {"region": {"ball_of": 0.2, "level": 2.0}, "condition": condition, "outer": "roa",
                           "practical": {"level": 0.5}}}
    assert outer_missing(tmp_path, practical | {"claim": practical["claim"] | {"faces": "inward"}}) == []
    for claim in (practical["claim"] | {"faces": "above"}, practical["claim"] | {"faces": "sideways"}):
        problems = outer_missing(tmp_path, {"claim": claim})
        assert len(problems) == 1 and "rule for the box's faces" in problems[0], problems
    assert outer_missing(tmp_path, practical) != []  # no rule stated: V above the level on the faces, not the outer's
    ball = {"claim": {k: v for k, v in practical["claim"].items() if k != "practical"}}
    assert outer_missing(tmp_path, ball) == []  # a roa-ball's claim leaves the set's faces to its outer


def test_the_region_search_reports_each_long_step_on_stderr(loop, monkeypatch):
    """A region search with ``compute.progress`` prints a line of boxes for the exits' bound and the level search
    (the quadrotor's went ten minutes without a word); without it nothing."""
    import io

    from drlyap import progress as progress_module
    from drlyap.compute import Compute

    stream = io.StringIO()

    def every_step(total, desc, enabled=True, **_):
        return progress_module.progress(total, desc, enabled, stream=stream, every=0.0)

    for module in ("drlyap.verification.branch_and_bound", "drlyap.verification.roa.levels"):
        monkeypatch.setattr(f"{module}.show_progress", every_step)
    region = Region.of(loop.system, 0.2)
    quiet = certified_roa(loop, _condition(), region, Budget(seconds=10), samples_per_axis=20)
    assert stream.getvalue() == ""
    shown = certified_roa(loop, _condition(), region, Budget(seconds=10, compute=Compute(progress=True)),
                          samples_per_axis=20)
    assert shown.level == quiet.level
    lines = stream.getvalue().splitlines()
    assert any(line.startswith("V's least value where the flow may leave the box: boxes: ") for line in lines)
    search = [line for line in lines if line.startswith("region of attraction: level search, boxes: ")]
    assert search and "level=" in search[-1] and "queued=" in search[-1]
