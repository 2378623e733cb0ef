"""Proofs on worker processes, on Ray and from checkpoints: the same verdict, the same partition and a certificate the
checker accepts, for any number of workers; a proof killed half way resumes where it was."""

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest
import torch

from drlyap.checker.check import LeafSettings, check_certificate
from drlyap.compute import Compute
from drlyap.conditions import DRPointwise
from drlyap.networks import Controller, Lyapunov
from drlyap.parallel import WorkerError, close_pools, pool_for
from drlyap.proof_settings import Budget, ProofConfig
from drlyap.regions import Region
from drlyap.runs.certificates import PairFiles, Stated, read_certificate, sha256_file, system_digest, write_certificate
from drlyap.systems import resolve_system
from drlyap.verification import ProofRules, verify_condition
from handmade import linear_pair, small_pendulum

F64 = torch.float64
XI = torch.tensor([[0.02, 0.01], [-0.01, 0.0], [0.05, -0.02]], dtype=F64)


@pytest.fixture(scope="module")
def pendulum_loop():
    from drlyap.closed_loop import ClosedLoop

    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    yield ClosedLoop(system, lyap, ctrl), DRPointwise(0.01, 0.3, XI, decay_rate=0.05), Region.of(system, 0.1)
    close_pools()


@pytest.fixture(scope="module")
def wide_loop():
    """:func:`linear_pair`'s closed loop with 16 tanh units in each network's hidden layer (the pair's own, and others
    with random weights whose output weights are small): it still proves, and its float64 matrix products are wide
    enough for their last bits to depend on the number of boxes bounded together."""
    from drlyap.closed_loop import ClosedLoop

    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    scale = lyap.phi.input_scale.tolist()
    wide_lyap = Lyapunov(2, hidden=[16], out=2, alpha_hat=lyap.alpha_hat, input_scale=scale)
    wide_ctrl = Controller(2, system.input_box, system.equilibrium_input, hidden=[16], input_scale=scale)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for wide, narrow in ((wide_lyap.phi, lyap.phi), (wide_ctrl.varphi, ctrl.varphi)):
            (first, last), units = wide.layers, narrow.layers[0].weight.shape[0]
            first.weight.copy_(torch.randn(first.weight.shape, generator=gen))
            first.bias.copy_(0.1 * torch.randn(first.bias.shape, generator=gen))
            last.weight.copy_(1e-3 * torch.randn(last.weight.shape, generator=gen))
            last.bias.zero_()
            first.weight[:units], first.bias[:units] = narrow.layers[0].weight, 0.0
            last.weight[:, :units] = narrow.layers[1].weight
    yield ClosedLoop(system, wide_lyap, wide_ctrl), DRPointwise(0.01, 0.3, XI, decay_rate=0.05), Region.of(system, 0.1)
    close_pools()


def _up(workers: int, **settings) -> Compute:
    """A Compute of ``workers`` local workers whose pool is up, so that the workers bound every batch (until it is,
    this process bounds them: the same bits, but not what these tests are about)."""
    compute = Compute(workers=workers, **settings)
    pool_for(compute).wait_up()
    return compute


def _same(a, b) -> None:
    assert (a.status, a.boxes_processed, a.boxes_verified, a.verified_fraction) == \
        (b.status, b.boxes_processed, b.boxes_verified, b.verified_fraction)
    assert a.sup_bounds == b.sup_bounds
    if a.partition is not None:
        for name in ("parent", "side", "axis", "verdict"):
            assert torch.equal(getattr(a.partition, name), getattr(b.partition, name)), name
        bits_a, bits_b = a.partition.bound.view(torch.int64), b.partition.bound.view(torch.int64)  # bit for bit
        differ = bits_a != bits_b
        assert not differ.any(), (f"{int(differ.sum())} of {differ.numel()} bounds differ, by up to "
                                  f"{float((a.partition.bound - b.partition.bound)[differ].abs().nan_to_num(0).max()):.3g}")


def test_two_workers_prove_the_same_partition_as_one(pendulum_loop):
    loop, condition, region = pendulum_loop
    budget = Budget(seconds=600, batch=64)
    one = verify_condition(loop, condition, region, budget)
    two = verify_condition(loop, condition, region, Budget(seconds=600, batch=64, compute=_up(2)))
    assert one.status == "verified" and one.boxes_processed > 4 * 64  # several batches, prefetched
    _same(one, two)
    # a budget that runs out part way: the same boxes, the same unknown verdict and share
    part = Budget(seconds=600, batch=64, boxes=500)
    _same(verify_condition(loop, condition, region, part),
          verify_condition(loop, condition, region, Budget(seconds=600, batch=64, boxes=500,
                                                           compute=_up(2))))


def test_a_violation_stops_the_workers_and_they_go_on_with_the_next_proof(pendulum_loop):
    loop, _, region = pendulum_loop
    strict = DRPointwise(0.01, 0.3, XI, decay_rate=50.0)  # far more decay than the pair has
    kwargs = dict(rules=ProofRules(stop_at_counterexample=True))
    one = verify_condition(loop, strict, region, Budget(seconds=600, batch=64), **kwargs)
    two = verify_condition(loop, strict, region, Budget(seconds=600, batch=64, compute=_up(2)), **kwargs)
    assert one.status == two.status == "violated"
    assert one.counterexample == two.counterexample
    _same(one, two)
    assert one.n_unverified == two.n_unverified
    _, condition, _ = pendulum_loop  # the pool is still usable: nothing of the stopped proof is left in flight
    assert verify_condition(loop, condition, region,
                            Budget(seconds=600, batch=64, compute=_up(2))).status == "verified"


def test_the_checker_accepts_a_certificate_proved_by_workers_and_checks_with_workers(pendulum_loop, tmp_path,
                                                                                   monkeypatch):
    import drlyap.checker.leaves as leaves

    monkeypatch.setattr(leaves, "LEAF_CHUNK", 256)  # several chunks, each with its own bisection budget
    loop, condition, region = pendulum_loop
    proof = verify_condition(loop, condition, region, Budget(seconds=600, batch=64, compute=_up(2)))
    torch.save({"lyapunov": loop.lyapunov.state_dict(), "controller": loop.controller.state_dict()},
               tmp_path / "weights.pt")
    write_certificate(tmp_path, "trained", proof, Stated(condition, region), loop.system,
                      PairFiles(tmp_path / "weights.pt", loop.lyapunov.alpha_hat))
    header, arrays = read_certificate(tmp_path, "trained")
    weights = torch.load(tmp_path / "weights.pt", weights_only=True)
    results = []
    for compute in (Compute(), _up(2)):
        res = check_certificate("trained", header, arrays, loop.system, weights,
                                sha256_file(tmp_path / "weights.pt"), system_digest(loop.system), LeafSettings(compute=compute))
        assert res.ok, res.failures
        assert res.proved == int((torch.as_tensor(arrays["verdict"]) == 1).sum())
        results.append((res.proved, res.refined, res.pieces))
    assert results[0] == results[1]  # the same chunks, the same bisections, wherever they are bounded


def test_a_batch_is_cut_into_as_few_chunks_of_about_equal_size():
    from drlyap.verification.bounding import CHUNK, chunk_sizes

    for boxes in (1, 300, CHUNK, CHUNK + 1, 1134, 4 * CHUNK - 1, 4 * CHUNK, 5000):
        sizes = chunk_sizes(boxes)
        assert sum(sizes) == boxes and len(sizes) == -(-boxes // CHUNK) and max(sizes) - min(sizes) <= 1


def test_a_worker_failure_is_an_error_that_names_it(pendulum_loop):
    pool = pool_for(Compute(workers=2))
    pool.wait_up()

    def broken(lo, hi):
        raise RuntimeError("no bounds here")

    with pytest.raises(WorkerError, match="no bounds here"):
        pool.submit(broken, torch.zeros(4, 2), torch.ones(4, 2)).result()


def test_the_bounds_are_the_same_bits_for_any_number_of_workers(wide_loop, monkeypatch):
    import drlyap.verification.bounding as bounding

    loop, condition, region = wide_loop
    proofs = {}
    for workers in (1, 2, 3):
        for chunk in (512, 96):  # one or two chunks a batch; up to eleven (of about equal size), dealt in turn
            monkeypatch.setattr(bounding, "CHUNK", chunk)
            proofs[chunk, workers] = verify_condition(loop, condition, region, Budget(
                seconds=600, batch=1000, compute=_up(workers) if workers > 1 else Compute()))
    for (chunk, _), proof in proofs.items():
        assert proof.status == "verified" and proof.partition.bound.isfinite().sum() > 500
        _same(proofs[chunk, 1], proof)  # every bound bit for bit (a chunk per worker differed in the last bits)


def test_a_system_from_a_users_file_travels_to_the_workers(tmp_path):
    path = tmp_path / "mysys.py"
    path.write_text(textwrap.dedent('''
        import torch
        from drlyap import UncertainSystem

        def dynamics(x, u, p):
            (friction,) = p.unbind(-1)
            return torch.stack([x[:, 1], -friction * x[:, 1] + u[:, 0]], dim=-1)

        def make():
            return UncertainSystem(
                name="mycart", state_names=("q", "v"), input_names=("f",), param_names=("friction",),
                nominal_params=(0.5,), uncertain=("friction",), dynamics=dynamics,
                state_box=((-1, -1), (1, 1)), input_box=((-2,), (2,)), equilibrium=(0.0, 0.0))
        '''))
    from drlyap.closed_loop import ClosedLoop
    from drlyap.conditions import TrueDecrease
    from drlyap.networks import LinearController, QuadraticLyapunov

    system = resolve_system(f"{path}:make")
    k = torch.tensor([[1.0, 1.5]], dtype=F64)
    p = torch.tensor([[1.25, 0.5], [0.5, 1.0]], dtype=F64)  # a Lyapunov matrix of the closed loop
    loop = ClosedLoop(system, QuadraticLyapunov(p), LinearController(k, system.input_box, system.equilibrium_input))
    condition, region = TrueDecrease(torch.tensor([[0.1]], dtype=F64)), Region.of(system, 0.05)
    one = verify_condition(loop, condition, region, Budget(seconds=600, batch=128), level=0.5)
    two = verify_condition(loop, condition, region, Budget(seconds=600, batch=128, compute=_up(2)),
                           level=0.5)
    assert one.status == "verified"
    _same(one, two)
    close_pools()


def test_compute_settings_are_checked_and_not_recorded_in_a_run():
    with pytest.raises(ValueError, match="workers = 0"):
        Compute(workers=0)
    with pytest.raises(ValueError, match="backend 'mpi'"):
        Compute(backend="mpi")
    with pytest.raises(ValueError, match="workers = 1 and the local backend"):
        Compute(workers=2, device="cuda")
    with pytest.raises(ValueError, match="compute must be a Compute"):
        ProofConfig(compute={"workers": 2}).validate()
    record = ProofConfig(compute=Compute(workers=4, checkpoint_dir="/tmp/x")).to_dict()
    assert "compute" not in record and "workers" not in record  # where proofs ran is not recorded
    assert ProofConfig.from_dict(record).compute == Compute()


# --------------------------------------------------------------------------- checkpoints
_SCRIPT = '''
import sys, json, time, torch
sys.path.insert(0, {tests!r})
torch.set_num_threads(1)
import drlyap.verification.bounding as bounding
bound = bounding.ConditionJob.__call__
bounding.ConditionJob.__call__ = lambda self, lo, hi: (time.sleep(0.03), bound(self, lo, hi))[1]  # slow: kill it half way
from handmade import linear_pair, small_pendulum
from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import DRPointwise
from drlyap.compute import Compute
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.verification import verify_condition
system = small_pendulum()
lyap, ctrl = linear_pair(system)
xi = torch.tensor({xi}, dtype=torch.float64)
compute = Compute(checkpoint_dir={folder!r}, checkpoint_every=0.0)
res = verify_condition(ClosedLoop(system, lyap, ctrl), DRPointwise(0.01, 0.3, xi, decay_rate=0.05),
                       Region.of(system, 0.1), Budget(seconds=600, batch=32, compute=compute))
print(json.dumps([res.status, res.boxes_processed, res.resumed_boxes]))
'''


def _checkpoint_meta(folder):
    import numpy as np

    files = list(folder.glob("proof-*.npz"))
    if not files:
        return None
    try:
        with np.load(files[0], allow_pickle=False) as data:
            return json.loads(bytes(data["__header__"]).decode())
    except Exception:  # being replaced right now
        return None


def test_a_proof_killed_half_way_resumes_from_its_checkpoint(pendulum_loop, tmp_path):
    loop, condition, region = pendulum_loop
    fresh = verify_condition(loop, condition, region, Budget(seconds=600, batch=32))
    folder = tmp_path / "checkpoints"
    script = _SCRIPT.format(tests=os.path.dirname(__file__), xi=XI.tolist(), folder=str(folder))
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        meta = _checkpoint_meta(folder)
        if meta is not None and meta["processed"] >= fresh.boxes_processed // 3:
            break
        time.sleep(0.005)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    meta = _checkpoint_meta(folder)
    assert meta is not None and not meta["finished"], "the proof should have been killed part way"
    compute = Compute(checkpoint_dir=str(folder), checkpoint_every=0.0)
    resumed = verify_condition(loop, condition, region, Budget(seconds=600, batch=32, compute=compute))
    assert resumed.resumed_boxes is not None and 0 < resumed.resumed_boxes < fresh.boxes_processed
    _same(fresh, resumed)
    # a finished proof's checkpoint gives its result again without bounding a box
    again = verify_condition(loop, condition, region, Budget(seconds=600, batch=32, compute=compute))
    assert again.resumed_boxes == fresh.boxes_processed
    _same(fresh, again)


def test_a_damaged_checkpoint_is_ignored_with_a_warning(pendulum_loop, tmp_path):
    loop, condition, region = pendulum_loop
    compute = Compute(checkpoint_dir=str(tmp_path), checkpoint_every=0.0)
    first = verify_condition(loop, condition, region, Budget(seconds=600, batch=64, compute=compute))
    (path,) = tmp_path.glob("proof-*.npz")
    path.write_bytes(b"not a checkpoint")
    with pytest.warns(UserWarning, match="cannot be read"):
        again = verify_condition(loop, condition, region, Budget(seconds=600, batch=64, compute=compute))
    assert again.resumed_boxes is None
    _same(first, again)


def test_another_proof_does_not_read_the_checkpoint(pendulum_loop, tmp_path):
    loop, condition, region = pendulum_loop
    compute = Compute(checkpoint_dir=str(tmp_path), checkpoint_every=0.0)
    verify_condition(loop, condition, region, Budget(seconds=600, batch=64, compute=compute))
    other = DRPointwise(0.02, 0.3, XI, decay_rate=0.05)  # another radius: another proof
    res = verify_condition(loop, other, region, Budget(seconds=600, batch=64, compute=compute))
    assert res.resumed_boxes is None
    assert len(list(tmp_path.glob("proof-*.npz"))) == 2


# --------------------------------------------------------------------------- Ray
def test_ray_backend_on_two_local_workers_proves_the_same_and_the_checker_accepts_it(pendulum_loop, wide_loop, tmp_path,
                                                                                    monkeypatch):
    pytest.importorskip("ray")
    import cloudpickle

    import drlyap.verification.bounding as bounding
    import handmade

    cloudpickle.register_pickle_by_value(handmade)  # Ray's workers do not see this folder: the test's system travels
    loop, condition, region = pendulum_loop
    one = verify_condition(loop, condition, region, Budget(seconds=600, batch=64))
    monkeypatch.setattr(bounding, "CHUNK", 96)  # batches of several chunks, dealt to the actors in turn
    wide_one = verify_condition(*wide_loop, Budget(seconds=600, batch=1000))
    try:
        two = verify_condition(loop, condition, region,
                               Budget(seconds=600, batch=64, compute=Compute(workers=2, backend="ray")))
        wide_two = verify_condition(*wide_loop, Budget(seconds=600, batch=1000, compute=Compute(workers=2,
                                                                                              backend="ray")))
    finally:
        close_pools()
    _same(one, two)
    _same(wide_one, wide_two)  # every bound bit for bit
    torch.save({"lyapunov": loop.lyapunov.state_dict(), "controller": loop.controller.state_dict()},
               tmp_path / "weights.pt")
    write_certificate(tmp_path, "trained", two, Stated(condition, region), loop.system,
                      PairFiles(tmp_path / "weights.pt", loop.lyapunov.alpha_hat))
    header, arrays = read_certificate(tmp_path, "trained")
    res = check_certificate("trained", header, arrays, loop.system,
                            torch.load(tmp_path / "weights.pt", weights_only=True), sha256_file(tmp_path / "weights.pt"),
                            system_digest(loop.system))
    assert res.ok, res.failures


def test_ctrl_c_while_workers_bound_keeps_the_batches_in_flight_and_the_proof_resumes(pendulum_loop, tmp_path,
                                                                                       monkeypatch):
    import drlyap.parallel as parallel

    loop, condition, region = pendulum_loop
    fresh = verify_condition(loop, condition, region, Budget(seconds=600, batch=32))
    calls = {"n": 0}
    result = parallel.Pending.result

    def interrupted(self):
        calls["n"] += 1
        if calls["n"] == 6:  # a batch prefetched behind this one is in flight too
            raise KeyboardInterrupt
        return result(self)

    monkeypatch.setattr(parallel.Pending, "result", interrupted)
    compute = _up(2, checkpoint_dir=str(tmp_path), checkpoint_every=3600.0)  # saved at the interruption
    with pytest.raises(KeyboardInterrupt):
        verify_condition(loop, condition, region, Budget(seconds=600, batch=32, compute=compute))
    monkeypatch.setattr(parallel.Pending, "result", result)
    meta = _checkpoint_meta(tmp_path)
    assert meta is not None and meta["processed"] == 5 * 32 and not meta["finished"]
    resumed = verify_condition(loop, condition, region, Budget(seconds=600, batch=32, compute=compute))
    assert resumed.resumed_boxes == 5 * 32
    _same(fresh, resumed)


# --------------------------------------------------------------------------- verify: certificates that are not proved again
@pytest.fixture
def linear_run(tmp_path):
    from handmade import linear_run_dir

    return linear_run_dir(tmp_path / "run"), f"{os.path.dirname(__file__)}/handmade.py:small_pendulum"


def test_verify_rechecks_a_certificate_instead_of_proving_it_again(linear_run):
    from click.testing import CliRunner

    from drlyap.cli import main

    run, spec = linear_run
    runner = CliRunner()

    def verify(*args):
        out = runner.invoke(main, ["verify", str(run), "--system", spec, "--xi", "0.1,0.05", "--json", *args])
        assert out.exit_code == 0, out.output
        return json.loads(out.stdout)

    first = verify()  # proves both and writes their certificates
    assert first["trained"].get("source") is None and first["true_model"].get("source") is None
    assert (run / "certificates" / "true-model.json").is_file() and not (run / "checkpoints").exists()
    second = verify("--workers", "2")  # the checker confirms them (on two workers) and records it
    for key in ("trained", "true_model"):
        assert second[key]["source"] == "certificate" and second[key]["status"] == "verified"
        assert second[key]["boxes_processed"] == first[key]["boxes_processed"] and "checked_at" not in second[key]
    assert (run / "certificates" / "trained.check.json").is_file()
    third = verify()  # the record of these very files
    assert third["trained"]["source"] == "certificate" and third["trained"]["checked_at"]
    text = runner.invoke(main, ["verify", str(run), "--system", spec])
    assert "confirmed by the checker on" in text.output and "not proved again" in text.output
    again = verify("--reprove")
    assert again["trained"].get("source") is None and again["trained"]["status"] == "verified"
    assert not (run / "certificates" / "trained.check.json").exists()  # a new certificate: its record is gone
    header = json.loads((run / "certificates" / "trained.json").read_text())
    header["claim"]["condition"]["wasserstein_radius"] = 0.0  # a claim that is not the condition to prove
    (run / "certificates" / "trained.json").write_text(json.dumps(header))
    assert verify()["trained"].get("source") is None  # proved anew, and its certificate written again
    assert json.loads((run / "certificates" / "trained.json").read_text())["claim"]["condition"][
        "wasserstein_radius"] == 0.01
    checked = runner.invoke(main, ["check", str(run), "--system", spec, "--workers", "2"])
    assert checked.exit_code == 0 and checked.output.count("CHECKED") == 2
    close_pools()


def test_train_rechecks_the_certificate_it_saved_so_that_verify_takes_it_as_it_stands(linear_run):
    from click.testing import CliRunner

    from drlyap.cli import main
    from drlyap.cli.train import _check_saved
    from drlyap.systems import resolve_system

    run, spec = linear_run
    runner = CliRunner()
    assert _check_saved(run, resolve_system(spec), Compute(), None) is None  # no certificate yet: nothing to check
    first = runner.invoke(main, ["verify", str(run), "--system", spec, "--json"])  # proves it, writes its certificate
    assert json.loads(first.stdout)["trained"].get("source") is None
    assert not (run / "certificates" / "trained.check.json").exists()
    results = _check_saved(run, resolve_system(spec), Compute(), None)  # what train does once the run is saved
    assert [r.name for r in results] == ["trained"] and results[0].ok and results[0].proved > 0
    assert (run / "certificates" / "trained.check.json").is_file()
    again = json.loads(runner.invoke(main, ["verify", str(run), "--system", spec, "--json"]).stdout)
    assert again["trained"]["source"] == "certificate" and again["trained"]["checked_at"]
    usage = runner.invoke(main, ["train", "--help"])
    assert "--check / --no-check" in usage.output


def test_the_certified_radius_and_shift_box_are_written_as_certificates_the_checker_confirms(linear_run):
    from click.testing import CliRunner

    from drlyap.cli import main

    run, spec = linear_run
    runner = CliRunner()
    out = runner.invoke(main, ["verify", str(run), "--system", spec, "--max-radius", "--time-limit", "10", "--json"])
    assert out.exit_code == 0, out.output
    found = json.loads(out.stdout)["robustness"]["radius"]
    assert found["radius"] > 0.01 and found["unproved"] <= found["radius"] * 1.01  # above the trained radius
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["certificate"]["radius"]["radius"] == found["radius"]
    header = json.loads((run / "certificates" / "radius.json").read_text())
    assert header["claim"]["condition"]["wasserstein_radius"] == found["radius"]
    assert header["claim"]["condition"]["name"] == "pointwise" and len(header["claim"]["condition"]["xi"]) == 3
    checked = runner.invoke(main, ["check", str(run), "--system", spec, "--name", "radius"])
    assert checked.exit_code == 0 and "radius: CHECKED" in checked.output, checked.output
    box = json.loads(out.stdout)["robustness"]["shift_box"]
    assert box["s"] > 0 and metrics["certificate"]["shift_box"]["s"] == box["s"]
    header = json.loads((run / "certificates" / "shift-box.json").read_text())
    condition = header["claim"]["condition"]
    assert condition["name"] == "true" and condition["xi"] is None
    assert condition["xi_box"]["high"][0] == [hi for _, hi in box["box"].values()]
    assert "for every shift xi in" in header["claim"]["statement"]
    checked = runner.invoke(main, ["check", str(run), "--system", spec, "--name", "shift-box"])
    assert checked.exit_code == 0 and "shift-box: CHECKED" in checked.output, checked.output
    metrics["certificate"]["radius"]["radius"] = found["radius"] * 1.01  # a larger radius than the file proves
    metrics["certificate"]["shift_box"]["s"] = box["s"] * 1.01  # a larger box than the file proves
    (run / "metrics.json").write_text(json.dumps(metrics))
    wrong = runner.invoke(main, ["check", str(run), "--system", spec])
    assert wrong.exit_code == 1 and "not the run's radius condition (wasserstein_radius" in wrong.output
    assert "not the run's shift box condition (xi_box" in wrong.output
    condition["xi_box"] = {k: [[30 * v for v in row] for row in rows] for k, rows in condition["xi_box"].items()}
    metrics["certificate"]["shift_box"]["s"] = box["s"] * 30  # a claim the partition does not prove: the checker's
    (run / "metrics.json").write_text(json.dumps(metrics))  # own bounds at the shifts refuse it
    (run / "certificates" / "shift-box.json").write_text(json.dumps(header))
    false = runner.invoke(main, ["check", str(run), "--system", spec, "--name", "shift-box"])
    assert false.exit_code == 1 and "boxes are not proved by the checker's bounds" in false.output, false.output


def test_an_interrupted_verify_resumes_its_proof_and_clears_its_checkpoints(linear_run, monkeypatch):
    from click.testing import CliRunner

    import drlyap.verification.bounding as bounding
    from drlyap.cli import main

    run, spec = linear_run
    runner = CliRunner()
    fresh = json.loads(runner.invoke(main, ["verify", str(run), "--system", spec, "--reprove", "--json"]).stdout)
    calls = {"n": 0}
    bound = bounding.ConditionJob.__call__

    def interrupted(self, lo, hi):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return bound(self, lo, hi)

    monkeypatch.setattr(bounding.ConditionJob, "__call__", interrupted)
    small = ["--time-limit", "600"]
    out = runner.invoke(main, ["verify", str(run), "--system", spec, "--reprove", *small])
    assert out.exit_code == 130 and list((run / "checkpoints").glob("proof-*.npz"))  # as train: Ctrl-C is 130
    assert out.output.strip().splitlines()[-1] == (f"drlyap: interrupted; the proof's progress is kept in "
                                                   f"{run / 'checkpoints'}: the same command, run again, resumes it")
    monkeypatch.setattr(bounding.ConditionJob, "__call__", bound)
    out = runner.invoke(main, ["verify", str(run), "--system", spec, "--reprove", "--json", *small])
    assert out.exit_code == 0, out.output
    resumed = json.loads(out.stdout)["trained"]
    assert resumed["resumed_boxes"] > 0 and resumed["boxes_processed"] == fresh["trained"]["boxes_processed"]
    assert resumed["status"] == "verified" and not (run / "checkpoints").exists()


def test_train_with_two_workers_gives_the_same_run_and_leaves_no_checkpoints(tmp_path):
    from click.testing import CliRunner

    from drlyap.cli import main

    runner = CliRunner()
    outs = {}
    for workers in ("1", "2"):
        out = tmp_path / f"w{workers}"
        res = runner.invoke(main, ["train", "pendulum", "--iters", "30", "--quiet", "--verify-rounds", "1",
                                   "--verify-boxes", "20000", "--workers", workers, "--out", str(out)])
        assert res.exit_code == 0, res.output
        assert not (tmp_path / f".w{workers}.proofs").exists()
        outs[workers] = json.loads((out / "metrics.json").read_text())["cegis"]
    strip = ("time_s", "total_time_s", "falsify_time_s", "train_time_s")

    def rounds(c):
        return [{k: v for k, v in r["verification"].items() if k not in strip} for r in c["rounds"]]

    assert rounds(outs["1"]) == rounds(outs["2"])
    assert (tmp_path / "w1" / "weights.pt").read_bytes() == (tmp_path / "w2" / "weights.pt").read_bytes()
    close_pools()
