"""The region-of-attraction search is budgeted by work (boxes), not seconds: the same search certifies the same region
on an idle and on a busy machine (a clock running 100x faster stands for a machine 100x slower), its seconds are only
a cap that says when it is reached, and a box budget that runs out says so."""

import os
import time

import pytest
import torch
from click.testing import CliRunner

from drlyap.cli import main
from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import TrueDecrease
from drlyap.io import jsonable
from drlyap.proof_settings import ROA_TIME_CAP, Budget, ProofConfig
from drlyap.regions import Region
from drlyap.runs import load_run
from drlyap.verification import certified_roa
from drlyap.verification.roa.levels import BOX_BUDGET, TIME_LIMIT
from drlyap.workflows.verify import VerifyRequest, verify
from handmade import linear_pair, linear_run_dir, small_pendulum, verify_cli

F64 = torch.float64
SPEC = f"{os.path.dirname(__file__)}/handmade.py:small_pendulum"
SHIFT = [0.1, 0.05]
WRONG = torch.diag(torch.tensor([1.0, 0.01], dtype=F64))  # V rises near x*: the route of the closed loop's ellipsoid


def _loop(p=None) -> ClosedLoop:
    system = small_pendulum()
    return ClosedLoop(system, *linear_pair(system, p=p))


def _condition() -> TrueDecrease:
    return TrueDecrease(torch.tensor([SHIFT], dtype=F64), 0.05)


def _timeless(value):
    """A result's JSON without its timings (the only part that may differ between two machines)."""
    if isinstance(value, dict):
        return {k: _timeless(v) for k, v in value.items() if k != "time_s"}
    if isinstance(value, list):
        return [_timeless(v) for v in value]
    return value


def _same(a, b) -> bool:
    return _timeless(jsonable(a.to_dict())) == _timeless(jsonable(b.to_dict()))


def _slow_clock(monkeypatch, factor: float = 100.0) -> None:
    """Every ``time.perf_counter`` from now on runs ``factor`` times faster: a machine ``factor`` times slower."""
    real = time.perf_counter
    start = real()
    monkeypatch.setattr(time, "perf_counter", lambda: start + factor * (real() - start))


@pytest.mark.parametrize("p, route", [(None, "second order"), (WRONG, "band")])
def test_the_search_certifies_the_same_region_on_a_slow_machine(p, route, monkeypatch):
    """V's own proofs (the linear pair), and where they fail the linearisation, the closed loop's ellipsoid and the
    band proof (V rising near x*: the route of ``verify --roa`` in tests/test_ellipsoid_certificate.py): with a box
    budget the result is the same, bit for bit but its timings, under a clock 100x faster, where a search budgeted by
    seconds stops early and says so."""
    loop, condition = _loop(p), _condition()
    region = Region.of(loop.system, 0.1)
    by_work = Budget(seconds=1e5, boxes=200_000)
    fast = certified_roa(loop, condition, region, by_work, samples_per_axis=50)
    _slow_clock(monkeypatch)
    slow = certified_roa(loop, condition, region, by_work, samples_per_axis=50)
    by_seconds = certified_roa(loop, condition, region, Budget(seconds=0.5, boxes=200_000), samples_per_axis=50)
    monkeypatch.undo()
    assert fast.certified and fast.method == route and "time limit" not in fast.limited_by, fast
    assert (slow.level, slow.limited_by, slow.boxes_processed) == (fast.level, fast.limited_by, fast.boxes_processed)
    assert _same(fast, slow)
    assert TIME_LIMIT in by_seconds.limited_by, by_seconds  # the clock did slow the search down, and the cap says so


def test_a_box_budget_that_runs_out_limits_the_level_and_says_so():
    loop, condition = _loop(), _condition()
    region = Region.of(loop.system, 0.1)
    full = certified_roa(loop, condition, region, Budget(seconds=1e5, boxes=200_000), samples_per_axis=50)
    short = certified_roa(loop, condition, region, Budget(seconds=1e5, boxes=300, batch=16), samples_per_axis=50)
    assert full.limited_by != BOX_BUDGET and full.boxes_processed > 300
    assert short.limited_by == BOX_BUDGET and short.level < full.level, short
    assert short.boxes_processed < 0.6 * 300 + 16  # the level search's share: 60%, a batch at most beyond it
    again = certified_roa(loop, condition, region, Budget(seconds=1e5, boxes=300, batch=16), samples_per_axis=50)
    assert _same(short, again)


def test_the_proof_settings_budget_the_region_by_boxes_with_seconds_as_a_cap():
    system = small_pendulum()
    resolved = ProofConfig().resolved(system)
    assert resolved.roa_boxes == system.defaults.verify_boxes
    budget = resolved.roa_budget()
    assert budget.boxes == resolved.roa_boxes and budget.seconds == ROA_TIME_CAP * resolved.time_limit
    mine = ProofConfig(roa_boxes=1234, roa_time=7.0).resolved(system).roa_budget()
    assert (mine.boxes, mine.seconds) == (1234, 7.0)
    assert ProofConfig.from_dict({"rounds": 1}).roa_boxes is None  # settings recorded before the field
    with pytest.raises(ValueError, match="roa_boxes"):
        ProofConfig(roa_boxes=0).validate()


def test_verify_gives_the_same_region_on_a_slow_machine_and_names_its_box_budget(tmp_path, monkeypatch):
    run = load_run(linear_run_dir(tmp_path / "run"), system=small_pendulum())
    settings = ProofConfig(time_limit=1e5)
    fast = verify(run, settings, VerifyRequest(xi=SHIFT, roa=True), reprove=True).roa
    _slow_clock(monkeypatch)
    slow = verify(run, settings, VerifyRequest(xi=SHIFT, roa=True), reprove=True).roa
    monkeypatch.undo()
    assert fast.certified and _same(fast, slow)
    found = verify_cli(linear_run_dir(tmp_path / "other"), SPEC, ",".join(map(str, SHIFT)), "--roa-boxes", "200")
    assert found["roa"]["limited_by"] == BOX_BUDGET and found["roa"]["level"] < fast.level
    out = CliRunner().invoke(main, ["verify", str(tmp_path / "other"), "--system", SPEC, "--roa", "--roa-boxes", "0"])
    assert out.exit_code != 0 and "--roa-boxes must be >= 1" in out.output
