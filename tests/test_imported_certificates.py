"""Certificates of an imported pair: ``drlyap verify`` writes the decrease it proves at a shift and its region of
attraction, naming the pair by its ``graphs.json`` and ``tensors.pt``, and ``drlyap check`` re-proves them reading those
as data with its own arithmetic."""

import json
import os

import pytest
import torch
from click.testing import CliRunner

from drlyap.checker.affine import Af
from drlyap.checker.arith import Iv
from drlyap.checker.graphs import GraphPair
from drlyap.cli import main
from drlyap.runs.imported import import_run
from drlyap.systems import get_system
from handmade import export_and_import, linear_run_dir
from test_import_onnx import Bowl, Saturated, _export, states

pytest.importorskip("onnx")
F64 = torch.float64


def test_verify_writes_an_imported_pair_s_certificate_and_the_checker_confirms_it(tmp_path):
    run = linear_run_dir(tmp_path / "run")
    spec = f"{os.path.dirname(__file__)}/handmade.py:small_pendulum"
    runner = CliRunner()
    out = export_and_import(run, spec, tmp_path)
    proved = runner.invoke(main, ["verify", str(out), "--system", spec, "--xi", "0.1,0.05", "--roa"])
    assert proved.exit_code == 0 and "VERIFIED" in proved.output and "CERTIFIED" in proved.output, proved.output
    for name in ("true-model", "roa", "roa-ball"):
        assert f"certificate: {out / 'certificates' / name}.json" in proved.output
    header = json.loads((out / "certificates" / "true-model.json").read_text())
    assert header["claim"]["condition"]["xi"] == [[0.1, 0.05]] and header["networks"]["alpha_hat"] is None
    checked = runner.invoke(main, ["check", str(out), "--system", spec])
    assert checked.exit_code == 0 and checked.output.count(": CHECKED") == 3, checked.output
    tensors = torch.load(out / "tensors.pt", weights_only=True)
    name = next(iter(tensors["controller"]))
    tensors["controller"][name] = tensors["controller"][name] * (1 + 1e-6)  # another controller
    torch.save(tensors, out / "tensors.pt")
    changed = runner.invoke(main, ["check", str(out), "--system", spec])
    assert changed.exit_code == 1 and "not the file the certificate was proved for" in changed.output


def test_the_checker_s_reading_of_an_imported_pair_holds_every_sampled_value_and_gradient(tmp_path):
    """Sound means sound: the checker's own evaluation of the import's graphs (a pinned V through products,
    quotients, exp, powers and sigmoids; a controller with ReLUs and a saturation) on intervals and second-order
    forms holds V, grad V and pi at sampled states of each box, and at a point agrees with torch's autograd."""
    system = get_system("pendulum")
    bowl = Bowl(system.n)
    _export(bowl, system.n, tmp_path / "v.onnx")
    control = Saturated(system, torch.tensor([[20.0, 5.0]], dtype=F64))
    _export(control, system.n, tmp_path / "c.onnx")
    import_run("pendulum", tmp_path / "c.onnx", tmp_path / "run", tmp_path / "v.onnx")
    graphs = json.loads((tmp_path / "run" / "graphs.json").read_text())
    pair = GraphPair(graphs, torch.load(tmp_path / "run" / "tensors.pt", weights_only=True), system.n)
    z = system.to_local(states(system, 300)).requires_grad_(True)
    expected = bowl(z) - bowl(torch.zeros(1, 2, dtype=F64))
    (grad,) = torch.autograd.grad(expected.sum(), z)
    value, ours = pair.value_and_grad(Iv.point(z.detach()))
    assert bool((value.lo <= expected).all() and (expected <= value.hi).all())
    assert bool((ours.lo <= grad).all() and (grad <= ours.hi).all())
    assert float((value.hi - value.lo).max()) < 1e-10 and float((ours.hi - ours.lo).max()) < 1e-9
    lo = z.detach()[:6]
    hi = lo + 0.2
    pts = (lo + (hi - lo) * torch.rand(50, 6, 2, generator=torch.Generator().manual_seed(3), dtype=F64)).reshape(-1, 2)
    pts.requires_grad_(True)
    pv = bowl(pts) - bowl(torch.zeros(1, 2, dtype=F64))
    (pg,) = torch.autograd.grad(pv.sum(), pts)
    with torch.no_grad():
        pu = control(system.to_user(pts))
    pv, pg, pu = (t.detach().reshape(50, 6, *t.shape[1:]) for t in (pv, pg, pu))
    for box in (Iv(lo, hi), Af.seed(lo, hi)):
        bv, bg = pair.value_and_grad(box)
        bu = pair.controller(box)
        bv, bg, bu = (e.interval(dual=True) if isinstance(e, Af) else e for e in (bv, bg, bu))
        assert bool((bv.lo <= pv).all() and (pv <= bv.hi).all())
        assert bool((bg.lo <= pg).all() and (pg <= bg.hi).all())
        assert bool((bu.lo <= pu).all() and (pu <= bu.hi).all())
