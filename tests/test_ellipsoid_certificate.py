"""The closed loop's own quadratic region of attraction ``{z'Pz <= c}`` (reported where no sublevel set of V is
certified) as an ``ellipsoid`` certificate: written by ``verify --roa``, confirmed by ``drlyap check`` with the
checker's own Jacobian enclosure, and refused when it claims more than it proves."""

from __future__ import annotations

import json
import os

import pytest
import torch
from click.testing import CliRunner

from drlyap.checker.arith import F64, Du, Iv
from drlyap.checker.ellipsoid import QuadraticPair, inside_box
from drlyap.checker.model import Pair, Residual
from drlyap.claims.ellipsoid import ellipsoid_parts
from drlyap.cli import main
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.runs import load_run
from drlyap.runs.certificates import PairFiles, Stated, write_certificate
from drlyap.verification.roa import ellipsoid_proof
from drlyap.verification.roa_steps import QuadraticRegion
from handmade import linear_run_dir, recheck, run_weights, small_pendulum, verify_cli

SPEC = f"{os.path.dirname(__file__)}/handmade.py:small_pendulum"
WRONG = torch.diag(torch.tensor([1.0, 0.01], dtype=F64))  # V = theta^2 + omega^2 / 100 rises near x*


@pytest.fixture(scope="module")
def wrong_run(tmp_path_factory):
    """A run whose V certifies no sublevel set while its controller's closed loop is stable, after
    ``verify --xi 0.1,0.05 --roa``: (its folder, verify's JSON)."""
    run = linear_run_dir(tmp_path_factory.mktemp("ellipsoid") / "run", lyapunov_matrix=WRONG)
    return run, verify_cli(run, SPEC, "0.1,0.05")


def test_verify_writes_the_closed_loops_ellipsoid_and_check_confirms_it(wrong_run):
    run, found = wrong_run
    roa = found["roa"]
    assert roa["local"].get("method") != "second order" and roa["quadratic"]["proved"]
    header = json.loads((run / "certificates" / "ellipsoid.json").read_text())
    ellipsoid = header["claim"]["ellipsoid"]
    assert ellipsoid["P"] == roa["quadratic"]["P"] and ellipsoid["level"] == roa["quadratic"]["q_level"]
    assert not (run / "certificates" / "roa-ball.json").exists()
    out = CliRunner().invoke(main, ["check", str(run), "--system", SPEC, "--name", "ellipsoid"])
    assert out.exit_code == 0, out.output
    assert "ellipsoid: CHECKED" in out.output and "Jacobian's enclosure" in out.output


@pytest.mark.parametrize("change, words", [
    (lambda e, r: (e.update(level=2 * e["level"]), r.update(level=2 * r["level"])), "established on the box's faces"),
    (lambda e, r: e.update(tau=[[[1e-7 * t for t in row] for row in m] for m in e["tau"]]), "not proved negative"),
    (lambda e, r: e.update(P=[[v / 2 for v in row] for row in e["P"]]), "established on the box's faces"),
    (lambda e, r: e.update(box=[3 * h for h in e["box"]]), "does not lie in the state box"),
    (lambda e, r: e.update(P=[e["P"][0], [e["P"][1][0], -e["P"][1][1]]]), "not positive semidefinite"),
    (lambda e, r: r.update(delta=2 * max(e["box"])), "inner ball"),
    (lambda e, r: e.update(level=2 * e["level"]), "level is not the ellipsoid's"),
])
def test_an_ellipsoid_that_claims_more_than_it_proves_fails(wrong_run, change, words):
    run, _ = wrong_run
    system = small_pendulum()

    def tamper(header):
        change(header["claim"]["ellipsoid"], header["claim"]["region"])

    result = recheck(run, "ellipsoid", system, run_weights(run), tamper)
    assert not result.ok and any(words in f for f in result.failures), result.failures


def test_an_ellipsoid_inside_its_jacobian_box_needs_no_partition_and_a_larger_one_fails(wrong_run, tmp_path):
    """At the level the Jacobian test proves on its own (the ellipsoid inside the box), the certificate has no
    partition and the checker asks the ellipsoid to lie in the box: 1.5x that level is refused."""
    run, found = wrong_run
    system = small_pendulum()
    loaded = load_run(run, system=system)
    ellipsoid = QuadraticRegion.from_dict(found["roa"]["quadratic"]).ellipsoid()
    ellipsoid.q_level = ellipsoid.box_level
    condition = loaded.true_condition([0.1, 0.05])
    region = Region.of(system, float(loaded.config.delta))
    proof = ellipsoid_proof(loaded.loop, condition, region, ellipsoid, Budget(seconds=5))
    assert proof is not None and proof.ring is None
    folder = tmp_path / "copy"
    folder.mkdir()
    (folder / "weights.pt").write_bytes((run / "weights.pt").read_bytes())
    parts = ellipsoid_parts(proof.p.tolist(), proof.level, proof.box.tolist(), proof.tau.tolist(), False)
    write_certificate(folder, "ellipsoid", None, Stated(proof.condition, proof.region, level=proof.level, parts=parts),
                      system, PairFiles(folder / "weights.pt", float(loaded.config.alpha_hat)))
    assert recheck(folder, "ellipsoid", system, run_weights(run)).ok

    def larger(header):
        header["claim"]["ellipsoid"]["level"] *= 1.5
        header["claim"]["region"]["level"] *= 1.5

    result = recheck(folder, "ellipsoid", system, run_weights(run), larger)
    assert not result.ok and any("not proved to lie in" in f for f in result.failures), result.failures


def test_the_checkers_jacobian_enclosure_holds_every_sampled_jacobian(wrong_run):
    """Dense sampling: the Jacobian of the true closed loop at 2,000 states of the certificate's box (autograd on
    the library's dynamics) lies in the checker's enclosure over that box (its own dual numbers)."""
    run, _ = wrong_run
    system = small_pendulum()
    header = json.loads((run / "certificates" / "ellipsoid.json").read_text())
    claim = header["claim"]
    h = torch.as_tensor(claim["ellipsoid"]["box"], dtype=F64)
    residual = Residual(claim["condition"], QuadraticPair(Pair(run_weights(run), 1e-3, 2), torch.eye(2, dtype=F64)),
                        system)
    (field,) = residual.fields(Du.seed(Iv((-h)[None], h[None]), 2, [0, 1]))
    lo = torch.stack([field.d[i].lo[0] for i in range(2)], -1)
    hi = torch.stack([field.d[i].hi[0] for i in range(2)], -1)
    loaded = load_run(run, system=system)
    ctrl = loaded.loop.f64.controller
    xi = torch.tensor([0.1, 0.05], dtype=F64)
    z = (2 * torch.rand(2000, 2, generator=torch.Generator().manual_seed(0), dtype=F64) - 1) * h

    def closed_loop(point):
        point = point[None]
        return system.true_dynamics(system.to_user(point), ctrl(point), xi[None])[0]

    jac = torch.stack([torch.autograd.functional.jacobian(closed_loop, p) for p in z[:200]])
    assert bool(((jac >= lo - 1e-12) & (jac <= hi + 1e-12)).all())
    assert bool((hi - lo).max() < 50)  # an enclosure, not the whole line


def test_inside_box_is_the_ellipsoids_extent():
    """{z'Pz <= c} lies in |z_i| <= h_i exactly when h_i^2 >= c (P^-1)_ii: a hair above passes, a hair below not."""
    p = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=F64)
    c = 0.7
    extent = (c * torch.linalg.inv(p).diagonal()).sqrt()
    assert inside_box(p, c, extent * (1 + 1e-9))
    assert not inside_box(p, c, extent * (1 - 1e-6))
