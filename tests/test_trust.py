"""A run directory may come from anyone: nothing read from one (checker records, proof checkpoints, certificates it
rests on) turns a false claim into a printed VERIFIED or CHECKED, and the commands' exit statuses say what was
proved."""

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from drlyap.cli import main
from handmade import linear_pair, linear_run_dir, small_pendulum

F64 = torch.float64
XI = torch.tensor([[0.02, 0.01], [-0.01, 0.0], [0.05, -0.02]], dtype=F64)
SPEC = f"{Path(__file__).parent / 'handmade.py'}:small_pendulum"


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _verify(run, *args):
    return CliRunner().invoke(main, ["verify", str(run), "--system", SPEC, *args])


# --------------------------------------------------------------------------- seals
def test_a_seal_opens_only_with_the_key_that_made_it(tmp_path, monkeypatch):
    from drlyap import seal

    monkeypatch.setenv("DRLYAP_STATE_DIR", str(tmp_path / "here"))
    mark = seal.seal(b"payload")
    assert mark is not None and seal.opens(b"payload", mark)
    assert not seal.opens(b"payload!", mark) and not seal.opens(b"payload", None)
    key = tmp_path / "here" / seal.KEY_FILE
    assert key.stat().st_mode & 0o777 == 0o600 and len(key.read_bytes()) == seal.KEY_BYTES
    monkeypatch.setenv("DRLYAP_STATE_DIR", str(tmp_path / "elsewhere"))  # another machine's key
    assert not seal.opens(b"payload", mark)
    key.chmod(0o644)  # a key others can read authenticates nothing
    monkeypatch.setenv("DRLYAP_STATE_DIR", str(tmp_path / "here"))
    assert seal.seal(b"payload") is None and not seal.opens(b"payload", mark)


def test_a_record_made_elsewhere_or_edited_is_not_taken(tmp_path, monkeypatch):
    from drlyap.checker.record import recorded, write_record

    (tmp_path / "certificates").mkdir()
    prints = {"header_sha256": "a" * 64, "weights_sha256": "b" * 64}
    monkeypatch.setenv("DRLYAP_STATE_DIR", str(tmp_path / "here"))
    path = write_record(tmp_path, "trained", prints, 10, 1.0)
    assert recorded(tmp_path, "trained", prints) is not None
    data = json.loads(path.read_text())
    data["weights_sha256"] = "c" * 64  # the hashes of other files, as anyone can recompute them
    path.write_text(json.dumps(data))
    assert recorded(tmp_path, "trained", {**prints, "weights_sha256": "c" * 64}) is None
    monkeypatch.setenv("DRLYAP_STATE_DIR", str(tmp_path / "elsewhere"))
    write_record(tmp_path, "trained", prints, 10, 1.0)
    monkeypatch.setenv("DRLYAP_STATE_DIR", str(tmp_path / "here"))
    assert recorded(tmp_path, "trained", prints) is None


def test_a_record_that_cannot_be_written_loses_nothing(tmp_path, monkeypatch):
    import errno

    from drlyap.checker.record import write_record

    (tmp_path / "certificates").mkdir()

    def refuse(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(Path, "write_text", refuse)
    monkeypatch.setattr(Path, "unlink", refuse)  # the handler's own clean-up fails too on a read-only folder
    assert write_record(tmp_path, "trained", {}, 1, 0.0) is None


# --------------------------------------------------------------------------- forged check records
def _destabilise(run: Path) -> None:
    """Flip the sign of the controller's output layer in ``run/weights.pt``: pi(x) = +K z instead of -K z."""
    weights = torch.load(run / "weights.pt", weights_only=True)
    weights["controller"]["varphi.layers.1.weight"].neg_()
    torch.save(weights, run / "weights.pt")


def test_forged_check_records_do_not_make_verify_print_verified(tmp_path):
    """Weights changed so that the conditions are false, every hash in the certificates and the records recomputed:
    verify does not take the records, checks again, proves again and exits 3 on the violation."""
    run = linear_run_dir(tmp_path / "run")
    assert _verify(run, "--xi", "0.1,0.05").exit_code == 0
    second = _verify(run, "--xi", "0.1,0.05", "--json")  # the checker confirms both and records it
    assert second.exit_code == 0, second.output
    folder = run / "certificates"
    assert (folder / "trained.check.json").is_file() and (folder / "true-model.check.json").is_file()
    _destabilise(run)
    for name in ("trained", "true-model"):
        header = json.loads((folder / f"{name}.json").read_text())
        header["networks"]["weights_sha256"] = _sha(run / "weights.pt")
        (folder / f"{name}.json").write_text(json.dumps(header))
        record = json.loads((folder / f"{name}.check.json").read_text())
        record.update(header_sha256=_sha(folder / f"{name}.json"), weights_sha256=_sha(run / "weights.pt"))
        (folder / f"{name}.check.json").write_text(json.dumps(record))
    out = _verify(run, "--xi", "0.1,0.05")
    assert out.exit_code == 3, out.output
    assert "VERIFIED (recorded" not in out.output and "certificate: VERIFIED" not in out.output
    assert "violated" in out.output.lower()
    data = json.loads(_verify(run, "--xi", "0.1,0.05", "--json").stdout)
    assert data["trained"]["status"] == "violated" and data["outcome"] == "violated"
    assert data["trained"].get("source") != "certificate"


# --------------------------------------------------------------------------- edited checkpoints
@pytest.fixture(scope="module")
def pendulum_loop():
    from drlyap.closed_loop import ClosedLoop
    from drlyap.conditions import DRPointwise
    from drlyap.regions import Region

    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    return ClosedLoop(system, lyap, ctrl), DRPointwise(0.01, 0.3, XI, decay_rate=0.05), Region.of(system, 0.1)


def _emptied(path: Path) -> tuple[dict, dict]:
    """The arrays and header of a checkpoint, its queue of boxes emptied and the search marked finished."""
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k].copy() for k in data.files}
    header = json.loads(bytes(arrays["__header__"]).decode())
    header.update(finished=True, stopped="finished")
    arrays["__header__"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    n = arrays["queue_lo"].shape[1]
    arrays.update(queue_lo=np.zeros((0, n)), queue_hi=np.zeros((0, n)), queue_ids=np.zeros(0, dtype=np.int64))
    return arrays, header


def test_an_edited_checkpoint_is_refused_and_no_proof_verifies_with_an_open_leaf(pendulum_loop, tmp_path):
    from drlyap.compute import Compute
    from drlyap.proof_settings import Budget
    from drlyap.verification import verify_condition
    from drlyap.verification.checkpoints import save_checkpoint

    loop, condition, region = pendulum_loop
    fresh = verify_condition(loop, condition, region, Budget(seconds=600, batch=32))
    assert fresh.status == "verified"
    compute = Compute(checkpoint_dir=str(tmp_path), checkpoint_every=0.0)
    part = verify_condition(loop, condition, region, Budget(seconds=600, batch=32, boxes=96, compute=compute))
    assert part.status == "unknown"
    (path,) = tmp_path.glob("proof-*.npz")
    arrays, header = _emptied(path)
    np.savez(path, **arrays)  # the pending boxes dropped, the seal left as it was
    with pytest.warns(UserWarning, match="seal does not open"):
        again = verify_condition(loop, condition, region, Budget(seconds=600, batch=32, compute=compute))
    assert again.resumed_boxes is None and again.status == "verified"
    assert again.boxes_processed == fresh.boxes_processed
    # the same state sealed by this machine (as a bug of its own would leave it): the tree's undecided leaves keep the
    # proof from being verified
    path.unlink()
    verify_condition(loop, condition, region, Budget(seconds=600, batch=32, boxes=96, compute=compute))
    arrays, header = _emptied(path)
    meta = {k: v for k, v in header.items() if k not in ("format", "version", "key")}
    save_checkpoint(tmp_path, header["key"], {k: torch.from_numpy(v) for k, v in arrays.items()
                                              if not k.startswith("__")}, meta)
    left = verify_condition(loop, condition, region, Budget(seconds=600, batch=32, compute=compute))
    assert left.status == "unknown" and left.partition is None and left.n_unverified > 0
    assert left.stopped == "leaves of its tree were left undecided" and left.verified_fraction < 1


# --------------------------------------------------------------------------- certificates a claim rests on
def test_a_region_is_not_checked_when_the_certificate_it_rests_on_fails(tmp_path):
    run = linear_run_dir(tmp_path / "run", delta=0.5)
    out = _verify(run, "--xi", "0.1,0.05", "--roa")
    assert out.exit_code == 0, out.output
    header = json.loads((run / "certificates" / "roa-ball.json").read_text())
    outer = header["claim"]["outer"]
    path = run / "certificates" / f"{outer}.npz"
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k].copy() for k in data.files}
    proved = np.flatnonzero(arrays["verdict"] == 1)
    arrays["verdict"][proved[: max(1, proved.size // 3)]] = 4  # leaves left open
    np.savez(path, **arrays)
    outer_header = json.loads((run / "certificates" / f"{outer}.json").read_text())
    outer_header["partition"]["sha256"] = _sha(path)
    (run / "certificates" / f"{outer}.json").write_text(json.dumps(outer_header))
    checked = CliRunner().invoke(main, ["check", str(run), "--system", SPEC, "--name", "roa-ball", "--json"])
    assert checked.exit_code == 1, checked.output
    results = {r["name"]: r for r in json.loads(checked.stdout)["certificates"]}
    assert set(results) == {"roa-ball", outer} and not results[outer]["ok"] and not results["roa-ball"]["ok"]
    assert any(f"rests on {outer}" in f for f in results["roa-ball"]["failures"])
    assert not (run / "certificates" / "roa-ball.check.json").exists()


# --------------------------------------------------------------------------- exit statuses
def test_verify_exits_non_zero_on_a_violated_or_unknown_claim(tmp_path):
    run = linear_run_dir(tmp_path / "run")
    _destabilise(run)
    violated = _verify(run, "--json")
    assert violated.exit_code == 3 and json.loads(violated.stdout)["outcome"] == "violated"
    good = linear_run_dir(tmp_path / "good")
    unknown = _verify(good, "--reprove", "--time-limit", "1e-9")
    assert unknown.exit_code == 4, unknown.output


def test_train_is_not_verified_when_its_checker_does_not_confirm(tmp_path, monkeypatch):
    import drlyap.cli.train as cli_train
    from drlyap.checker.check import CheckResult
    from drlyap.render import certificate_line
    from drlyap.verification import Certificate

    cert = Certificate(status="verified", condition="dr pointwise", region="X_delta", time_s=1.0, boxes=10)
    assert certificate_line(cert).startswith("certificate: VERIFIED")
    assert certificate_line(cert, confirmed=False).startswith("certificate: NOT VERIFIED (the independent checker")
    failed = CheckResult(name="trained", claim="the condition", ok=False, failures=["1 of 9 boxes are not proved"])
    monkeypatch.setattr(cli_train, "_check_saved", lambda *args: [failed])
    out = CliRunner().invoke(main, ["train", "pendulum", "--iters", "2", "--quiet", "--no-verify",
                                    "--out", str(tmp_path / "run")])
    assert out.exit_code == 1, out.output
    assert "trained: FAILED" in out.output and "certificate: VERIFIED" not in out.output


# --------------------------------------------------------------------------- read-only run directories
def _read_only(folder: Path, *command: str) -> subprocess.CompletedProcess:
    """``command`` with ``folder`` mounted read-only in a namespace of its own (skips where that is not allowed)."""
    if shutil.which("unshare") is None:
        pytest.skip("no unshare")
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", f"mount --bind {folder} {folder} && mount -o "
                            f"remount,bind,ro {folder}"], capture_output=True)
    if probe.returncode:
        pytest.skip("mount namespaces are not allowed here")
    script = 'mount --bind "$1" "$1" && mount -o remount,bind,ro "$1" && shift && exec "$@"'
    env = {**os.environ, "DRLYAP_THREADS": "1"}
    return subprocess.run(["unshare", "-rm", "sh", "-c", script, "sh", str(folder), *command], capture_output=True,
                          text=True, env=env, timeout=300)


def test_verify_and_check_on_a_read_only_run_directory(tmp_path):
    run = linear_run_dir(tmp_path / "run")
    assert _verify(run, "--xi", "0.1,0.05").exit_code == 0
    drlyap = [sys.executable, "-c", "from drlyap.cli import main; main()"]
    done = _read_only(run, *drlyap, "verify", str(run), "--system", SPEC, "--xi", "0.1,0.05", "--reprove")
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr and done.stdout.count(": VERIFIED;") == 2
    assert "cannot be written" in done.stdout
    done = _read_only(run, *drlyap, "check", str(run), "--system", SPEC)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    assert done.stdout.count("CHECKED") == 2


# --------------------------------------------------------------------------- metrics.json
def test_a_region_in_metrics_json_is_drawn_as_recorded_not_as_certified(tmp_path):
    """A region of attraction written into metrics.json by hand (no proof, no certificate): plot draws it as what
    metrics.json records, not as a certified region, and export says its status is the run's record."""
    run = linear_run_dir(tmp_path / "run")
    metrics = json.loads((run / "metrics.json").read_text())
    metrics["certificate"] = {"status": "verified", "condition": "DR pointwise",
                              "roa": {"level": 0.5, "kind": "region of attraction", "certified": True,
                                      "xi": [0.1, 0.05], "share_of_box": 0.9}}
    (run / "metrics.json").write_text(json.dumps(metrics))
    out = CliRunner().invoke(main, ["plot", str(run), "--system", SPEC, "--xi", "0.1,0.05", "--n-init", "2",
                                    "--horizon", "1", "--out", str(tmp_path / "fig")])
    assert out.exit_code == 0, out.output
    assert "as metrics.json records it, not re-proved here: certified region of attraction" in out.output
    out = CliRunner().invoke(main, ["export", str(run), "--system", SPEC, "--out", str(tmp_path / "export")])
    assert out.exit_code == 0, out.output
    assert "certificate: VERIFIED" not in out.output and "as its metrics.json records it: verified" in out.output
