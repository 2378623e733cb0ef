"""Certified robustness (drlyap.verification.robustness): the largest proved Wasserstein radius and shift box."""

import math

import pytest
import torch
from click.testing import CliRunner

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import DRPointwise, Nominal, TrueDecrease, decrease_terms
from drlyap.enclosures import Interval
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.verification import (
    ProofRules,
    SearchLimits,
    StartFrom,
    certified_radius,
    certified_shift_box,
    shift_box_condition,
    verify_condition,
)
from handmade import linear_pair, small_pendulum, verified_json

F64 = torch.float64
XI = torch.tensor([[0.02, 0.01], [-0.03, 0.0], [0.05, -0.02]], dtype=F64)
DELTA, TOL = 0.2, 0.01
TEN, FIVE = Budget(seconds=10, enclosure="mean-value"), Budget(seconds=5, enclosure="mean-value")  # per proof


def _linear_loop():
    """The hand-made linear pair on the small pendulum, its region and a DR pointwise condition:
    (system, V, pi, loop, region, condition)."""
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    return system, lyap, ctrl, ClosedLoop(system, lyap, ctrl), Region.of(system, DELTA), DRPointwise(1e-3, 0.1, XI, 0.05)


def _checker_confirms(folder, proof, condition, region, system, lyap, ctrl) -> None:
    """Write ``proof`` as a certificate of ``condition`` and have the independent checker confirm it."""
    from drlyap.checker.check import check_certificate
    from drlyap.runs.certificates import PairFiles, Stated, read_certificate, sha256_file, system_digest, write_certificate

    weights = {"lyapunov": lyap.state_dict(), "controller": ctrl.state_dict()}
    torch.save(weights, folder / "weights.pt")
    write_certificate(folder, "trained", proof, Stated(condition, region), system,
                      PairFiles(folder / "weights.pt", lyap.alpha_hat))
    header, arrays = read_certificate(folder, "trained")
    res = check_certificate("trained", header, arrays, system, weights, sha256_file(folder / "weights.pt"),
                            system_digest(system))
    assert res.ok, res.failures


def _dense(system, per=300):
    lo, hi = system.local_box()
    axes = [torch.linspace(float(lo[i]), float(hi[i]), per, dtype=F64) for i in range(system.n)]
    z = torch.cartesian_prod(*axes)
    return z[z.norm(dim=-1) >= DELTA]


@pytest.mark.parametrize("eps", [0.1, 0.5])  # max over the samples, and the general CVaR
def test_certified_radius_is_proved_there_and_fails_just_above(eps):
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    loop, region = ClosedLoop(system, lyap, ctrl), Region.of(system, DELTA)
    condition = DRPointwise(1e-3, eps, XI, 0.05)
    out = certified_radius(loop, condition, region, TEN, limits=SearchLimits(tol=TOL))
    r = out.radius
    assert r is not None and r > 0 and out.stopped == "tolerance"
    assert out.unproved <= r * (1 + TOL) and out.unproved_status in ("violated", "unknown")
    assert verify_condition(loop, condition.with_radius(r), region, TEN).status == "verified"
    above = verify_condition(loop, condition.with_radius(r * (1 + 2 * TOL)), region, TEN)
    assert above.status in ("violated", "unknown")
    # dense sampling: the condition holds up to eps * min_z (-rho(z, 0) / lip(z)) and fails just above it
    z = _dense(system)
    with torch.no_grad():
        terms = decrease_terms(ClosedLoop(system, lyap.double(), ctrl.double()), z, XI, 0.05)
    rho0 = condition.with_radius(0.0).residual(terms)
    sampled = eps * float((-rho0 / terms.lip).min())
    assert r <= sampled and r >= 0.95 * sampled  # sound, and not needlessly loose
    assert float(loop.exact(condition.with_radius(sampled * 1.001), z).max()) > 0


def test_radius_not_provable_at_zero_says_why():
    system = small_pendulum()
    lyap, ctrl = linear_pair(system, sign=-1.0)  # pushes away from x*
    loop, region = ClosedLoop(system, lyap, ctrl), Region.of(system, DELTA)
    out = certified_radius(loop, DRPointwise(1e-3, 0.1, XI, 0.05), region, FIVE)
    assert out.radius is None and "at 0" in out.reason
    assert out.unproved == 0.0 and out.witness["residual"] > 0


def test_interval_xi_on_plain_states_is_the_max_over_the_corners():
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    loop = ClosedLoop(system, lyap, ctrl)
    z = _dense(system, 20)
    box = TrueDecrease(Interval(torch.tensor([[-0.2, -0.1]], dtype=F64), torch.tensor([[0.3, 0.1]], dtype=F64)), 0.05)
    corners = TrueDecrease(torch.tensor([[-0.2, -0.1], [-0.2, 0.1], [0.3, -0.1], [0.3, 0.1]], dtype=F64), 0.05)
    assert torch.equal(loop.exact(box, z), loop.exact(corners, z))
    with pytest.raises(ValueError, match="enclosures only"):
        loop.exact(Nominal(Interval(torch.zeros(1, 2, dtype=F64), torch.ones(1, 2, dtype=F64)), 0.05), z)


def test_certified_shift_box_is_proved_there_and_fails_just_above():
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    loop, region = ClosedLoop(system, lyap, ctrl), Region.of(system, DELTA)
    scale = torch.tensor([0.1, 0.05], dtype=F64)
    out = certified_shift_box(loop, region, scale, TEN, decay=(0.05, 0.0), limits=SearchLimits(tol=TOL))
    s = out.s
    assert s is not None and s > 0 and out.unproved <= s * (1 + TOL)
    assert out.box["mass"] == pytest.approx([-0.1 * s, 0.1 * s])
    proved = verify_condition(loop, shift_box_condition(scale, s, 0.05), region, TEN)
    assert proved.status == "verified"
    # slightly beyond: a corner shift violates at a dense state, or the proof fails
    beyond = s * (1 + 2 * TOL)
    corners = torch.tensor([[a, b] for a in (-1, 1) for b in (-1, 1)], dtype=F64) * scale * beyond
    worst = float(loop.exact(TrueDecrease(corners, 0.05), _dense(system)).max())
    status = verify_condition(loop, shift_box_condition(scale, beyond, 0.05), region, FIVE).status
    assert worst > 0 or status != "verified"
    # from the tree of another condition's proof: the same bracket
    tree = verify_condition(loop, DRPointwise(1e-3, 0.1, XI, 0.05), region, TEN).partition
    warm = certified_shift_box(loop, region, scale, TEN, decay=(0.05, 0.0), limits=SearchLimits(tol=TOL),
                               start=tree)
    assert warm.s == pytest.approx(s, rel=TOL) and warm.unproved <= warm.s * (1 + TOL)
    with pytest.raises(ValueError, match="scale must be 2"):
        certified_shift_box(loop, region, torch.tensor([0.1]), TEN, decay=(0.05, 0.0))
    with pytest.raises(ValueError, match="DRPointwise"):
        certified_radius(loop, Nominal(XI[:1], 0.05), region, TEN)


def test_cli_max_radius_on_a_baseline_run(tmp_path, tiny_config):
    from drlyap.cli import main
    from drlyap.runs import save_run
    from handmade import plain_train

    save_run(tmp_path / "run", plain_train(tiny_config(iters=5, check_every=5, method="baseline"), progress=False))
    runner = CliRunner()
    out = runner.invoke(main, ["verify", str(tmp_path / "run"), "--time-limit", "1", "--max-radius", "--json"])
    rob = verified_json(out)["robustness"]
    assert {"radius", "shift_box", "radius_training_sample"} <= set(rob)
    for res in (rob["radius"], rob["radius_training_sample"]):
        assert (res["radius"] is None and "at 0" in res["reason"]) or res["radius"] >= 0
    assert rob["shift_box"]["parameters"] == ["mass", "damping"]
    text = runner.invoke(main, ["verify", str(tmp_path / "run"), "--time-limit", "1", "--max-radius"])
    assert text.exit_code == 3 and "certified Wasserstein radius" in text.output  # five iterations: violated
    assert "certified shift box" in text.output
    bad = runner.invoke(main, ["verify", str(tmp_path / "run"), "--max-radius", "--radius-tol", "0"])
    assert bad.exit_code != 0 and "--radius-tol" in bad.output


def test_the_radius_on_a_sublevel_set_is_proved_there_and_at_least_the_whole_regions():
    """Over ``{V <= level}`` the claim asks less than over X_delta: its r* is at least as large, it is proved on
    that set, and sampled refutations come only from states inside it."""
    system, lyap, ctrl, loop, region, condition = _linear_loop()
    whole = certified_radius(loop, condition, region, TEN, limits=SearchLimits(tol=TOL))
    z = _dense(system)
    with torch.no_grad():
        level = float(loop.f64.lyapunov(z).quantile(0.3))  # a set that leaves out most of the box
    sub = certified_radius(loop, condition, region, TEN, limits=SearchLimits(tol=TOL), level=level)
    assert sub.level == level and whole.level is None
    assert sub.radius is not None and sub.radius >= whole.radius * (1 - TOL)
    assert verify_condition(loop, condition.with_radius(sub.radius), region, TEN, level=level).status == "verified"
    if sub.witness is not None and sub.unproved_by == "sampled state":
        state = system.to_local(torch.tensor([sub.witness["state"]], dtype=F64))
        assert float(loop.f64.lyapunov(state)[0]) <= level


def test_the_radius_search_starts_at_a_radius_already_proved():
    system, lyap, ctrl, loop, region, condition = _linear_loop()
    plain = certified_radius(loop, condition, region, TEN, limits=SearchLimits(tol=TOL))
    known = 0.5 * plain.radius
    assert verify_condition(loop, condition.with_radius(known), region, TEN).status == "verified"
    started = certified_radius(loop, condition, region, TEN, limits=SearchLimits(tol=TOL), proved=known)
    assert started.probes[0] == {"value": known, "status": "verified", "by": "an earlier proof", "time_s": None}
    assert all(p["value"] > 0 for p in started.probes)  # r = 0 was not proved again
    assert started.radius >= known and started.unproved <= started.radius * (1 + TOL)
    assert abs(started.radius - plain.radius) <= TOL * plain.radius


def test_a_proof_starts_from_the_partition_of_a_weaker_one_and_its_tree_is_checked(tmp_path):
    system, lyap, ctrl, loop, region, condition = _linear_loop()
    radius = certified_radius(loop, condition, region, TEN, limits=SearchLimits(tol=TOL)).radius
    weak = verify_condition(loop, condition.with_radius(0.3 * radius), region, TEN)
    fresh = verify_condition(loop, condition.with_radius(0.9 * radius), region, TEN)
    warm = verify_condition(loop, condition.with_radius(0.9 * radius), region, TEN, start=StartFrom(weak.partition))
    assert weak.verified and fresh.verified and warm.verified
    assert warm.boxes_processed < fresh.boxes_processed  # the weaker proof's splits are not bounded again
    assert warm.partition.size >= weak.partition.size
    _checker_confirms(tmp_path, warm, condition.with_radius(0.9 * radius), region, system, lyap, ctrl)
    with pytest.raises(ValueError, match="its own grid and enclosure"):
        verify_condition(loop, condition, region, Budget(seconds=10, enclosure="affine"), start=StartFrom(weak.partition))


def test_a_proof_that_cannot_finish_within_its_budget_gives_up_early():
    system, lyap, ctrl, loop, region, condition = _linear_loop()
    full = verify_condition(loop, condition, region, TEN)
    small = Budget(seconds=10, boxes=full.boxes_processed // 2, enclosure="mean-value", batch=64)
    out = verify_condition(loop, condition, region, small, rules=ProofRules(give_up=True))
    assert out.status == "unknown" and out.stopped == "more boxes queued than the budget has left"
    assert out.boxes_processed < full.boxes_processed // 2


def test_the_radius_search_from_a_proved_partition_brackets_the_same_radius():
    system, lyap, ctrl, loop, region, condition = _linear_loop()
    plain = certified_radius(loop, condition, region, TEN, limits=SearchLimits(tol=TOL))
    known = 0.5 * plain.radius
    proof = verify_condition(loop, condition.with_radius(known), region, TEN)
    warm = certified_radius(loop, condition, region, TEN, limits=SearchLimits(tol=TOL), proved=known,
                            start=proof.partition)
    assert abs(warm.radius - plain.radius) <= TOL * plain.radius
    assert verify_condition(loop, condition.with_radius(warm.radius), region, TEN).status == "verified"


def test_a_proof_keeps_the_leaves_a_stronger_proof_left_proved_and_its_tree_is_checked(tmp_path):
    from drlyap.verification.partition import OPEN, PROVED

    system, lyap, ctrl, loop, region, condition = _linear_loop()
    radius = certified_radius(loop, condition, region, TEN, limits=SearchLimits(tol=TOL)).radius
    # fails, but proves much of the region at the larger radius
    strong = verify_condition(loop, condition.with_radius(1.5 * radius), region, TEN,
                              rules=ProofRules(stop_at_counterexample=True, keep_partition=True))
    assert strong.status == "violated" and strong.partition is not None
    tree = strong.partition
    assert int((tree.verdict == PROVED).sum()) > 0 and int((tree.verdict == OPEN).sum()) > 0
    weaker = condition.with_radius(0.9 * radius)
    fresh = verify_condition(loop, weaker, region, TEN)
    warm = verify_condition(loop, weaker, region, TEN, start=StartFrom(tree, tree.verdict == PROVED))
    assert fresh.verified and warm.verified
    assert warm.boxes_processed < fresh.boxes_processed  # what stood was not bounded again
    # every leaf that stood is proved at the smaller radius by the checker's own bounds
    _checker_confirms(tmp_path, warm, weaker, region, system, lyap, ctrl)
    with pytest.raises(ValueError, match="standing must mark"):
        verify_condition(loop, weaker, region, TEN, start=StartFrom(tree, torch.ones(3, dtype=torch.bool)))


def test_a_node_inherits_the_largest_value_of_its_ancestors():
    from drlyap.verification.partition import INTERNAL, OPEN, PROVED, Partition

    # a cell split twice down one branch: 0 -> (1, 2), 2 -> (3, 4), 4 -> (5, 6)
    parent = torch.tensor([-1, 0, 0, 2, 2, 4, 4])
    side = torch.tensor([0, 0, 1, 0, 1, 0, 1], dtype=torch.int8)
    axis = torch.tensor([0, -1, 1, -1, 0, -1, -1], dtype=torch.int8)
    verdict = torch.tensor([INTERNAL, PROVED, INTERNAL, OPEN, INTERNAL, PROVED, OPEN], dtype=torch.int8)
    tree = Partition([1, 1], parent, side, axis, verdict, torch.full((7,), float("nan"), dtype=F64), "mean-value")
    inf = float("inf")
    values = torch.tensor([-inf, 0.5, 0.2, -inf, -inf, 0.1, -inf], dtype=F64)
    assert tree.inherit_max(values).tolist() == [-inf, 0.5, 0.2, 0.2, 0.2, 0.2, 0.2]
    values[0] = 0.3
    assert tree.inherit_max(values).tolist() == [0.3, 0.5, 0.3, 0.3, 0.3, 0.3, 0.3]


def test_a_proof_names_its_radius_or_its_box_of_shifts_in_its_progress_line():
    from drlyap.verification.branch_and_bound import proof_label

    scale = torch.tensor([0.1, 0.05], dtype=F64)
    assert proof_label(DRPointwise(0.0123456, 0.1, XI, 0.05), 0.8) == "DR pointwise, r = 0.01235, on {V <= 0.8}"
    box = proof_label(shift_box_condition(scale, 0.5, 0.05))
    assert box.endswith(", xi within +-(0.05, 0.025)") and box.startswith("true model")
    assert proof_label(TrueDecrease(XI[:1], 0.05)) == TrueDecrease(XI[:1], 0.05).label


def test_a_narrow_bracket_is_closed_by_one_proof_just_below_its_unproved_end(monkeypatch):
    """Where a budget's edge sits just below the value a proof gave up at (the quadrotor's searches), the search
    bisects while the bracket is wide and then proves ``unproved / (1 + tol)``, which ends it; where that proof fails
    it bisects below it, and its bracket is always within the tolerance and proved at its lower end."""
    from drlyap.verification.robustness import _largest_proved

    def search(edge: float, proved: float | None, guess: float):
        tried = []

        def prove(v: float) -> dict:
            tried.append(v)
            return {"status": "verified" if v <= edge else "unknown", "time_s": 1.0}

        found = _largest_proved(prove, lambda v: None, guess, 1.0, SearchLimits(total_time=1e9, cap=1e6), None, proved)
        return found, tried

    found, tried = search(0.0884, 0.05, 0.2355)
    assert found["certified"] <= 0.0884 < found["unproved"] and found["relative_gap"] <= 0.01
    assert found["proofs"] == 6 and tried[-1] == pytest.approx(found["unproved"] / 1.00999)
    with monkeypatch.context() as patch:  # bisection alone
        patch.setattr("drlyap.verification.robustness.NEAR", 0)
        assert search(0.0884, 0.05, 0.2355)[0]["proofs"] == 9
    found, tried = search(0.0805, 0.05, 0.2355)  # the probe below the end fails: bisection below it
    assert found["certified"] <= 0.0805 < found["unproved"] and found["relative_gap"] <= 0.01
    found, tried = search(0.03, 0.05, 0.2355)  # nothing above the proved start: no probe near the end at all
    assert found["certified"] == 0.05 and all(not math.isclose(v, w * 1.00999) for v, w in zip(tried, tried[1:]))
