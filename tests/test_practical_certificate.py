"""Practical stability (a shift moves the closed loop's equilibrium off x*: trajectories from {V <= c} end up in
{V <= c0}) as a ``practical`` certificate: V at most c0 on the delta-ball, bisected by the checker itself, beside the
decrease outside the ball on {V <= c} that it names. Written by ``verify --roa``, confirmed by ``drlyap check``,
refused when it claims more."""

from __future__ import annotations

import json
import os

import pytest
import torch

from drlyap.checker.agreement import claim_mismatch
from drlyap.checker.arith import F64
from drlyap.checker.levels import ball_below
from drlyap.checker.model import Pair
from drlyap.runs import load_run
from drlyap.runs.certificates import read_certificate
from drlyap.simulation import simulate
from handmade import check_cli, check_without, linear_run_dir, offset_pendulum, recheck, run_weights, verify_cli

SPEC = f"{os.path.dirname(__file__)}/handmade.py:offset_pendulum"
XI = [0.1, 0.05, 0.06]  # a constant torque of 0.06 moves the equilibrium off x*


@pytest.fixture(scope="module")
def practical_run(tmp_path_factory):
    run = linear_run_dir(tmp_path_factory.mktemp("practical") / "run", delta=0.2, user_system=offset_pendulum(),
                         system="offset-pendulum",
                         xi_samples=[[0.02, 0.01, 0.0], [-0.03, 0.0, 0.01], [0.05, -0.02, -0.01]])
    return run, verify_cli(run, SPEC, ",".join(map(str, XI)))


def test_verify_writes_practical_stability_and_check_confirms_it(practical_run):
    run, found = practical_run
    roa = found["roa"]
    assert roa["kind"] == "practical stability" and not roa["certified"]
    header = json.loads((run / "certificates" / "practical.json").read_text())
    claim = header["claim"]
    assert claim["practical"]["level"] == roa["practical_level"] and claim["region"]["level"] == roa["level"]
    assert claim["outer"] == "roa" and header["partition"] is None
    out = check_cli(run, SPEC)
    assert out.exit_code == 0, out.output
    assert "practical: CHECKED" in out.output and "roa: CHECKED" in out.output
    assert "end up in {V <= " in out.output and "checker's bisection" in out.output


@pytest.mark.parametrize("change, words", [
    (lambda c: c["practical"].update(level=0.9 * c["practical"]["level"]), "not established on the ball"),
    (lambda c: c["practical"].update(level=c["region"]["level"]), "is not below the set's"),
    (lambda c: c["region"].update(ball_of=0.3), "delta-ball's box"),
])
def test_a_practical_claim_that_claims_more_than_it_proves_fails(practical_run, change, words):
    run, _ = practical_run
    result = recheck(run, "practical", offset_pendulum(), run_weights(run), lambda h: change(h["claim"]))
    assert not result.ok and any(words in f for f in result.failures), result.failures


def test_the_practical_claim_must_be_the_runs_and_name_its_outer_proof(practical_run, tmp_path):
    run, _ = practical_run
    header, _ = read_certificate(run, "practical")
    config = json.loads((run / "config.json").read_text())
    metrics = json.loads((run / "metrics.json").read_text())
    assert claim_mismatch("practical", header, config, metrics) == []
    header["claim"]["practical"]["level"] /= 2
    assert any("end up in" in f for f in claim_mismatch("practical", header, config, metrics))
    out = check_without(run, tmp_path / "copy", SPEC, "roa", "practical")
    assert out.exit_code != 0 and "outside the ball" in out.output


def test_the_balls_bound_holds_dense_samples_and_trajectories_end_up_in_the_set(practical_run):
    """V at 20,000 states of the ball lies below the checked level, ball_below refuses a level under the sampled
    maximum, and trajectories of the true model from {V <= c} end up in {V <= c0} (and away from x*)."""
    run, found = practical_run
    system = offset_pendulum()
    roa = found["roa"]
    c, c0 = roa["level"], roa["practical_level"]
    loaded = load_run(run, system=system)
    lyap = loaded.loop.f64.lyapunov
    g = torch.Generator().manual_seed(5)
    z = (2 * torch.rand(60_000, 2, generator=g, dtype=F64) - 1) * 0.2
    z = z[z.norm(dim=-1) < 0.2][:20_000]
    with torch.no_grad():
        v = lyap(z)
    assert float(v.max()) <= c0
    pair = Pair(run_weights(run), float(loaded.config.alpha_hat), 2)
    lo, hi = torch.full((2,), -0.2, dtype=F64), torch.full((2,), 0.2, dtype=F64)
    assert ball_below(pair, lo, hi, 0.2, c0)[0]
    assert not ball_below(pair, lo, hi, 0.2, 0.99 * float(v.max()))[0]
    box_lo, box_hi = system.local_box()
    z0 = box_lo + (box_hi - box_lo) * torch.rand(4000, 2, generator=g, dtype=F64)
    with torch.no_grad():
        z0 = z0[lyap(z0) <= c][:100]
    ctrl = loaded.loop.f64.controller
    traj = simulate(system, lambda x: ctrl(system.to_local(x)), system.to_user(z0), torch.tensor(XI, dtype=F64),
                    dt=0.005, horizon=15.0)
    with torch.no_grad():
        values = lyap(system.to_local(traj.x.reshape(-1, 2))).reshape(traj.x.shape[:2])
        end = lyap(system.to_local(traj.x[-1]))
    assert z0.shape[0] == 100 and float(values.max()) <= c * (1 + 1e-9) and float(end.max()) <= c0
    assert float(system.to_local(traj.x[-1]).norm(dim=-1).min()) > 1e-3  # the equilibrium has moved off x*
