"""Regions of attraction of V that rest on the closed loop's own ellipsoid L = {z'Pz <= c_q} (the linearisation
route, the band proof) as certificates with a ``core``: written by ``verify --roa``, confirmed by ``drlyap check``
(every vertex of a box said to lie in L does, by the checker's interval arithmetic; L's own ``ellipsoid``
certificate is named and checked beside it), and refused when they claim more than they prove."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

from drlyap.checker.agreement import core_missing
from drlyap.checker.arith import F64
from drlyap.checker.ellipsoid import inside_core
from drlyap.conditions import PlainDecrease
from drlyap.regions import box_grid
from drlyap.runs import load_run
from drlyap.runs.certificates import certificate_partition, read_certificate
from drlyap.verification.partition import INSIDE_CORE, PROVED
from handmade import check_cli, check_without, linear_run_dir, recheck, run_weights, small_pendulum, verify_cli

SPEC = f"{os.path.dirname(__file__)}/handmade.py:small_pendulum"
WRONG = torch.diag(torch.tensor([1.0, 0.01], dtype=F64))  # V = theta^2 + omega^2 / 100 rises near x*
XI = [0.1, 0.05]


def _verified(path, **pair):
    run = linear_run_dir(path, delta=0.2, **pair)
    return run, verify_cli(run, SPEC, "0.1,0.05")


@pytest.fixture(scope="module")
def bump_run(tmp_path_factory):
    """V = the linear pair's plus a narrow bump: its Hessian test fails at x*, the linearisation route certifies."""
    return _verified(tmp_path_factory.mktemp("core") / "bump", bump=True)


@pytest.fixture(scope="module")
def band_run(tmp_path_factory):
    """V rises near x*: only the band proof outside the closed loop's ellipsoid certifies a sublevel set."""
    return _verified(tmp_path_factory.mktemp("core") / "band", lyapunov_matrix=WRONG)


def _names(run):
    return {p.stem for p in (run / "certificates").glob("*.json") if not p.stem.endswith(".check")}


def test_the_linearisation_route_is_written_around_its_ellipsoid_and_check_confirms_it(bump_run):
    run, found = bump_run
    roa = found["roa"]
    assert roa["certified"] and roa["local"]["method"] == "linearisation"
    assert _names(run) == {"trained", "true-model", "roa", "ellipsoid", "roa-ball"}
    ball = json.loads((run / "certificates" / "roa-ball.json").read_text())["claim"]
    assert "cube" not in ball and ball["core"]["certificate"] == "ellipsoid"
    assert ball["core"]["P"] == roa["local"]["P"] and ball["core"]["level"] == roa["local"]["q_level"]
    assert ball["region"]["level"] == roa["level"] and ball["region"]["delta"] == 0.0
    ellipsoid = json.loads((run / "certificates" / "ellipsoid.json").read_text())["claim"]["ellipsoid"]
    assert ellipsoid["P"] == ball["core"]["P"] and ellipsoid["level"] == ball["core"]["level"]
    out = check_cli(run, SPEC)
    assert out.exit_code == 0, out.output
    assert "roa-ball: CHECKED" in out.output and "outside the ellipsoid" in out.output
    assert "inside the core" in out.output


def test_the_band_proof_is_written_as_roa_around_its_ellipsoid_and_check_confirms_it(band_run):
    run, found = band_run
    roa = found["roa"]
    assert roa["certified"] and roa["local"]["method"] == "band"
    assert {"roa", "ellipsoid"} <= _names(run) and "roa-ball" not in _names(run)
    claim = json.loads((run / "certificates" / "roa.json").read_text())["claim"]
    assert claim["core"]["P"] == roa["local"]["P"] and claim["region"]["level"] == roa["level"]
    assert claim["condition"]["name"] == "plain" and claim["condition"]["decay_rate"] > 0
    out = check_cli(run, SPEC)
    assert out.exit_code == 0, out.output
    assert "roa: CHECKED" in out.output and "ellipsoid: CHECKED" in out.output and "inside the core" in out.output


def _relabel_proved_as_core(arrays):
    arrays["verdict"][arrays["verdict"] == PROVED] = INSIDE_CORE


@pytest.mark.parametrize("header_change, arrays_change, words", [
    (None, _relabel_proved_as_core, "said to lie in the core"),
    (lambda h: h["claim"]["core"].update(level=h["claim"]["core"]["level"] / 4), None, "said to lie in the core"),
    (lambda h: h["claim"]["region"].update(delta=0.1), None, "no inner ball"),
    (lambda h: h["claim"]["condition"].update(decay_rate=0.0), None, "not strict"),
    (lambda h: h["claim"]["core"].update(P=[[-v for v in row] for row in h["claim"]["core"]["P"]]), None,
     "not positive semidefinite"),
    (lambda h: h["claim"].pop("core"), None, "not proved"),  # without a core, its leaves prove nothing
])
def test_a_core_that_claims_more_than_it_proves_fails(band_run, header_change, arrays_change, words):
    run, _ = band_run
    result = recheck(run, "roa", small_pendulum(), run_weights(run), header_change, arrays_change)
    assert not result.ok and any(words in f for f in result.failures), result.failures


def test_the_core_must_be_the_ellipsoid_its_certificate_states(band_run):
    run, _ = band_run
    header, _ = read_certificate(run, "roa")
    assert core_missing(run, header) == []
    header["claim"]["core"]["level"] *= 2
    assert any("another ellipsoid" in f for f in core_missing(run, header))
    header, _ = read_certificate(run, "roa")
    header["claim"]["condition"]["xi"] = [[0.0, 0.0]]
    assert any("other samples" in f for f in core_missing(run, header))
    header["claim"]["core"]["certificate"] = "nothing"  # a core rests on the ellipsoid's own certificate alone
    assert any("is not one of ellipsoid" in f for f in core_missing(run, header))


def test_check_refuses_a_region_whose_ellipsoid_certificate_is_gone(band_run, tmp_path):
    run, _ = band_run
    out = check_without(run, tmp_path / "copy", SPEC, "ellipsoid", "roa")
    assert out.exit_code != 0 and "cannot be read" in out.output


def test_the_core_leaves_hold_dense_samples_and_the_rest_decreases_at_sampled_states(band_run):
    """Dense sampling of the written partition: states drawn in the leaves said to lie in L have z'Pz <= c_q (and the
    checker's vertex test agrees with the verifier's on every leaf); states drawn in the proved leaves with
    V <= c decrease strictly on the true model."""
    run, _ = band_run
    system = small_pendulum()
    header, arrays = read_certificate(run, "roa")
    claim = header["claim"]
    p, c_q = torch.tensor(claim["core"]["P"], dtype=F64), float(claim["core"]["level"])
    level = float(claim["region"]["level"])
    loaded = load_run(run, system=system)
    part = certificate_partition(run, "roa")
    lo, hi = system.local_box()
    clo, chi = box_grid(lo.to(F64), hi.to(F64), part.grid)
    blo, bhi = part.boxes(clo, chi)
    verdict = torch.as_tensor(arrays["verdict"].astype(np.int64))
    core = verdict == INSIDE_CORE
    assert bool(inside_core(p, c_q, blo[core], bhi[core]).all())
    g = torch.Generator().manual_seed(3)
    for mask, count in ((core, 20), (verdict == PROVED, 20)):
        a, b = blo[mask], bhi[mask]
        z = (a[:, None] + (b - a)[:, None] * torch.rand(a.shape[0], count, 2, generator=g, dtype=F64)).reshape(-1, 2)
        if mask is core:
            assert float(((z @ p) * z).sum(-1).max()) <= c_q
        else:
            with torch.no_grad():
                v = loaded.loop.f64.lyapunov(z)
            z = z[v <= level]
            plain = loaded.true_condition(XI).per_sample()
            strict = PlainDecrease(plain.xi, float(claim["condition"]["decay_rate"]), 0.0, plain.model)
            rate = loaded.loop.exact(strict, z)
            assert z.shape[0] > 100 and float(rate.max()) <= 0


def test_the_printed_recheck_runs_as_printed_for_a_run_saved_from_python(bump_run):
    """A run saved from Python records no system source: the check ``verify`` prints carries the --system it was
    given, and runs as printed."""
    import re
    import shlex

    from click.testing import CliRunner

    from drlyap.cli import main

    run, _ = bump_run
    out = CliRunner().invoke(main, ["verify", str(run), "--system", SPEC, "--xi", "0.1,0.05", "--reprove"])
    assert out.exit_code == 0, out.output
    hint = re.search(r"re-check it with `([^`]*)`", out.output).group(1)
    assert shlex.split(hint)[-2:] == ["--system", SPEC]
    checked = CliRunner().invoke(main, shlex.split(hint)[1:])
    assert checked.exit_code == 0 and "true-model: CHECKED" in checked.output, checked.output
