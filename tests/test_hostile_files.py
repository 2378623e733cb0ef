"""A hostile or unlucky user: an ``--out`` that is a symlink, a disk that fills or a file-size limit while a run
directory is written, and tiny ONNX files that declare huge tensors. Each is refused with one line naming the path,
before any work or allocation, and nothing is left behind."""

import errno
import os
import re
import resource
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from drlyap.cli import main
from drlyap.runs import atomic_dir, check_writable
from drlyap.runs.publish import DestinationError, proof_checkpoints
from drlyap.systems import get_system

DRLYAP = Path(sys.executable).with_name("drlyap")


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def one_line_error(result) -> str:
    """The error of a failed command: exit status 1, one line starting with 'Error:', no traceback."""
    assert result.exit_code == 1, result.output
    lines = [line for line in result.output.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.output
    return lines[0]


def leftovers(folder: Path) -> list[str]:
    """Temporary directories of :func:`atomic_dir` left in ``folder``."""
    return [p.name for p in folder.iterdir() if ".tmp-" in p.name]


# ------------------------------------------------------------------ 1. --out as a symlink
@pytest.fixture(params=["dangling", "to a directory", "to a file"])
def linked_out(request, tmp_path) -> Path:
    """An ``--out`` that is a symlink: to nothing, to an existing directory, to an existing file."""
    target = {"dangling": tmp_path / "nowhere" / "x", "to a directory": tmp_path / "folder",
              "to a file": tmp_path / "file.txt"}[request.param]
    if request.param == "to a directory":
        target.mkdir()
    elif request.param == "to a file":
        target.write_text("mine")
    out = tmp_path / "out"
    out.symlink_to(target)
    return out


def test_a_symlink_out_is_refused_before_any_work(linked_out, tmp_path):
    with pytest.raises(DestinationError, match=r"out is a symlink to .*never through a link"):
        check_writable(linked_out)
    filled = []
    with pytest.raises(DestinationError, match="is a symlink"):
        atomic_dir(linked_out, filled.append)
    assert not filled and not leftovers(tmp_path)
    run = tmp_path / "run"  # what `drlyap export` checks of RUN_DIR before --out: a complete run directory
    run.mkdir()
    (run / "run.json").write_text("{}")
    for command in (["train", "pendulum", "--iters", "1"], ["export", run],
                    ["import", "pendulum", "--controller", tmp_path / "c.onnx"]):
        line = one_line_error(invoke(*command, "--out", linked_out))
        assert f"{linked_out} is a symlink to" in line and "choose another --out or remove the link" in line, command
    assert linked_out.is_symlink() and not (tmp_path / "nowhere").exists() and not (run / "export").exists()


def test_a_dangling_symlink_above_out_is_refused_and_a_linked_folder_is_not(tmp_path):
    (tmp_path / "gone").symlink_to(tmp_path / "nowhere")
    with pytest.raises(DestinationError, match=r"cannot create .*gone is a symlink to .*nowhere, which does not exist"):
        check_writable(tmp_path / "gone" / "a" / "run")
    (tmp_path / "real").mkdir()
    (tmp_path / "runs").symlink_to(tmp_path / "real")  # a folder of runs that lives elsewhere: fine
    check_writable(tmp_path / "runs" / "run")
    atomic_dir(tmp_path / "runs" / "run", lambda tmp: (tmp / "a").write_text("x"))
    assert (tmp_path / "real" / "run" / "a").read_text() == "x"


def test_a_symlink_made_while_publishing_is_not_written_through(tmp_path):
    out, target = tmp_path / "run", tmp_path / "elsewhere"

    def fill(tmp):
        (tmp / "a").write_text("x")
        out.symlink_to(target)  # another process, while this one was filling

    with pytest.raises(DestinationError, match=r"run became a symlink while this process ran \(to .*elsewhere, which "
                                               r"does not exist\); nothing was written through it \(this run is lost"):
        atomic_dir(out, fill)
    assert out.is_symlink() and not target.exists() and not leftovers(tmp_path)


# ------------------------------------------------------------------ 2. a full disk, a file-size limit
def test_a_full_disk_while_publishing_is_one_line_and_keeps_the_proofs(tmp_path):
    out = tmp_path / "run"
    kept = proof_checkpoints(out)
    kept.mkdir()
    (kept / "proof-trained.npz").write_bytes(b"progress")

    def fill(tmp):
        (tmp / "config.json").write_text("{}")
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp / "weights.pt"))

    with pytest.raises(DestinationError) as err:
        atomic_dir(out, fill)
    message = err.value.for_option("--out")
    assert "\n" not in message and message.startswith(f"cannot write {out}: No space left on device (ENOSPC) at "
                                                       f"{out / 'weights.pt'}; nothing was written there")
    assert f"proofs' progress is kept in {kept}" in message and message.endswith("free some space or choose another --out")
    assert not out.exists() and not leftovers(tmp_path) and (kept / "proof-trained.npz").exists()


def test_drlyap_train_on_a_full_disk_says_so_in_one_line_and_keeps_its_proofs(tmp_path, monkeypatch):
    out = tmp_path / "run"
    kept = proof_checkpoints(out)
    kept.mkdir()
    (kept / "proof-trained.npz").write_bytes(b"progress")  # what an earlier, interrupted run's proof left

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full)  # the run's weights.pt
    line = one_line_error(invoke("train", "pendulum", "--iters", "1", "--no-verify", "--no-check", "--quiet",
                                 "--out", out))
    assert line == (f"Error: cannot write {out}: No space left on device (ENOSPC); nothing was written there (its "
                    f"temporary folder is removed); its proofs' progress is kept in {kept}: the same command, run "
                    "again, resumes them; free some space or choose another --out")
    assert not out.exists() and not leftovers(tmp_path) and (kept / "proof-trained.npz").exists()


@pytest.mark.parametrize("code, hint", [(errno.EROFS, "(EROFS)"), (errno.EACCES, "(EACCES)"),
                                        (errno.EDQUOT, "disk quota")])
def test_other_write_errors_are_named(tmp_path, code, hint):
    def fill(tmp):
        raise OSError(code, os.strerror(code))

    with pytest.raises(DestinationError, match=rf"cannot write .*run: {os.strerror(code)}.*{hint}") as err:
        atomic_dir(tmp_path / "run", fill)
    assert "proofs" not in str(err.value) and not leftovers(tmp_path)


@pytest.fixture
def file_size_limit():
    """Lower this process's file-size limit (``ulimit -f``) to ``nbytes`` for a ``with`` block; Python ignores
    SIGXFSZ, so a larger write fails with EFBIG (as under ``ulimit -f``)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)

    class Limit:
        def __init__(self, nbytes: int) -> None:
            self.nbytes = nbytes

        def __enter__(self):
            resource.setrlimit(resource.RLIMIT_FSIZE, (self.nbytes, hard))

        def __exit__(self, *exc):
            resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))

    yield Limit
    resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))


def test_a_file_size_limit_while_publishing_is_one_line(tmp_path, file_size_limit):
    weights = {"w": torch.zeros(4096)}
    for name, fill in (("json", lambda tmp: (tmp / "metrics.json").write_text("0" * 20000)),
                       ("torch", lambda tmp: torch.save(weights, tmp / "weights.pt"))):
        with file_size_limit(8192), pytest.raises(DestinationError) as err:
            atomic_dir(tmp_path / name, fill)
        message = err.value.for_option("--out")
        assert "\n" not in message and f"cannot write {tmp_path / name}: " in message, message
        assert ("File too large (EFBIG)" in message if name == "json" else "files are limited to 8 KB" in message)
        assert message.endswith("raise the file-size limit (ulimit -f) or choose another --out")
        assert not (tmp_path / name).exists() and not leftovers(tmp_path)


def test_a_file_size_limit_is_refused_before_any_work(tmp_path):
    def limited():
        resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))

    start = time.monotonic()
    result = subprocess.run([str(DRLYAP), "train", "pendulum", "--iters", "1", "--out", str(tmp_path / "run")],
                            capture_output=True, text=True, preexec_fn=limited, timeout=60,
                            env=os.environ | {"OMP_NUM_THREADS": "1", "DRLYAP_THREADS": "1"})
    assert result.returncode == 1 and result.stdout == "", result.stderr
    assert result.stderr.strip().splitlines() == [
        f"Error: cannot write {tmp_path / 'run'}: this process may write files of 64 KB at most (ulimit -f), less "
        "than the 64 MB a run needs; raise the limit (ulimit -f unlimited)"]
    assert time.monotonic() - start < 20 and not (tmp_path / "run").exists()


def test_a_read_only_parent_is_refused_before_any_work(tmp_path, monkeypatch):
    if os.geteuid() == 0:  # root writes anywhere: the refusal is that of the file system
        import tempfile

        def refuse(*args, **kwargs):
            raise PermissionError(errno.EACCES, "Permission denied")

        monkeypatch.setattr(tempfile, "mkstemp", refuse)
    parent = tmp_path / "ro"
    parent.mkdir(mode=0o555)
    line = one_line_error(invoke("train", "pendulum", "--iters", "1", "--out", parent / "run"))
    assert line == f"Error: cannot write to {parent} (Permission denied); choose another --out"


# ------------------------------------------------------------------ 3. tiny ONNX files that declare huge tensors
onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from drlyap.graph import from_onnx, read_onnx  # noqa: E402


def _model(path: Path, nodes: list, inits: list, hidden: str = "h") -> Path:
    """x (batch, 2) -> ``nodes`` (which read ``x`` and make ``hidden``, (batch, 2)) -> Gemm -> u (batch, 1)."""
    inits = [numpy_helper.from_array(np.ones((1, 2)), "w_out"), *inits]
    graph = helper.make_graph([*nodes, helper.make_node("Gemm", [hidden, "w_out"], ["u"], transB=1)], "g",
                              [helper.make_tensor_value_info("x", TensorProto.DOUBLE, ["batch", 2])],
                              [helper.make_tensor_value_info("u", TensorProto.DOUBLE, ["batch", 1])], inits)
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), str(path))
    return path


def _declared(name: str, dims: list[int], raw: bytes | None = None, dtype: int = TensorProto.DOUBLE):
    """A tensor that declares ``dims`` and holds ``raw`` bytes (None: no data at all)."""
    t = TensorProto(name=name, data_type=dtype)
    t.dims.extend(dims)
    if raw is not None:
        t.raw_data = raw
    return t


def _ints(name: str, values: list[int]):
    return numpy_helper.from_array(np.array(values, dtype=np.int64), name)


def _identity():
    return helper.make_node("Identity", ["x"], ["h"])


def _hostile(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    """Files of a few hundred bytes -> what their refusal must say."""
    big = _declared("big", [100000, 100000])
    files = {
        "initializer": (_model(tmp_path / "initializer.onnx", [_identity()], [big]),
                        r"tensor 'big' has 10,000,000,000 elements \[100000, 100000\], more than the 10,000,000"),
        "short": (_model(tmp_path / "short.onnx", [_identity()], [_declared("w", [1000, 1000], b"\0" * 16)]),
                  r"tensor 'w' declares 1,000,000 elements \[1000, 1000\] \(8,000,000 bytes\) but holds 16 bytes"),
        "negative": (_model(tmp_path / "negative.onnx", [_identity()], [_declared("neg", [-1, 4], b"")]),
                     r"tensor 'neg' has a negative dimension \[-1, 4\]"),
        "rank": (_model(tmp_path / "rank.onnx", [_identity()], [_declared("deep", [1] * 40, b"\0" * 8)]),
                 r"tensor 'deep' has 40 axes; drlyap reads tensors of at most 8"),
        "constant": (_model(tmp_path / "constant.onnx", [
            helper.make_node("Constant", [], ["c"], value=_declared("v", [16384, 16384], dtype=TensorProto.FLOAT)),
            helper.make_node("Add", ["x", "c"], ["h"])], []),
            r"attribute 'value' of node 0 \(Constant\) has 268,435,456 elements"),
        "constant_of_shape": (_model(tmp_path / "fill.onnx", [
            helper.make_node("ConstantOfShape", ["s"], ["c"], name="fill"), _identity()], [_ints("s", [16384, 16384])]),
            r"node fill \(ConstantOfShape\) has 268,435,456 elements \[16384, 16384\], more than the 10,000,000"),
        "gather": (_model(tmp_path / "gather.onnx", [
            helper.make_node("ConstantOfShape", ["s"], ["rows"]),
            helper.make_node("ConstantOfShape", ["n"], ["idx"], value=numpy_helper.from_array(np.zeros(1, np.int64))),
            helper.make_node("Gather", ["rows", "idx"], ["g"], name="take"), _identity()],
            [_ints("s", [1, 10000]), _ints("n", [100000])]),
            r"node take \(Gather\) has 1,000,000,000 elements"),
        "broadcast": (_model(tmp_path / "broadcast.onnx", [
            helper.make_node("ConstantOfShape", ["a"], ["ca"]), helper.make_node("ConstantOfShape", ["b"], ["cb"]),
            helper.make_node("Mul", ["ca", "cb"], ["m"], name="outer"), _identity()],
            [_ints("a", [100000, 1]), _ints("b", [1, 100000])]),
            r"node outer \(Mul\) has 10,000,000,000 elements"),
        "wide": (_model(tmp_path / "wide.onnx", [  # a layer of width 20,000: its weights fit, its activations not
            helper.make_node("ConstantOfShape", ["s"], ["w"], value=numpy_helper.from_array(np.ones(1))),
            helper.make_node("Gemm", ["x", "w"], ["h"], transB=1)], [_ints("s", [20000, 2])]),
            r"Gemm \(node 1\): makes 20,000 values per state, more than the 10,000"),
    }
    return files


def test_tiny_onnx_files_that_declare_huge_tensors_are_refused_without_allocating(tmp_path):
    system = get_system("pendulum")
    for case, (path, message) in _hostile(tmp_path).items():
        assert path.stat().st_size < 400, case
        tracemalloc.start()
        start = time.monotonic()
        try:
            with pytest.raises(ValueError) as err:
                read_onnx(path, system, "controller")
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        text = str(err.value)
        assert "\n" not in text and text.startswith(f"{path}: "), (case, text)
        assert re.search(message, text), (case, text)
        assert peak < 20 * 2**20 and time.monotonic() - start < 2, (case, peak)


def test_the_constants_of_a_file_are_capped_in_all(tmp_path, monkeypatch):
    monkeypatch.setattr(from_onnx, "MAX_ELEMENTS", 100)
    monkeypatch.setattr(from_onnx, "MAX_TOTAL", 250)
    system = get_system("pendulum")
    ok = [numpy_helper.from_array(np.zeros((10, 10)), f"w{i}") for i in range(2)]
    read_onnx(_model(tmp_path / "ok.onnx", [_identity()], ok), system, "controller")  # 202 elements
    more = ok + [numpy_helper.from_array(np.zeros((7, 7)), "w2")]
    with pytest.raises(ValueError, match=r"tensor 'w2' brings the file's constants to 251 elements, more than the 250 "
                                         r"drlyap reads in all"):
        read_onnx(_model(tmp_path / "more.onnx", [_identity()], more), system, "controller")
    nodes = [helper.make_node("ConstantOfShape", ["s"], ["c"]),  # 90 elements, concatenated 3 times: 270
             helper.make_node("Concat", ["c", "c", "c"], ["cc"], axis=0, name="thrice"), _identity()]
    with pytest.raises(ValueError, match=r"node thrice \(Concat\) has 270 elements \[270\], more than the 100"):
        read_onnx(_model(tmp_path / "thrice.onnx", nodes, [_ints("s", [90])]), system, "controller")


def test_a_hostile_file_is_one_line_from_drlyap_import(tmp_path):
    path = _model(tmp_path / "fill.onnx", [helper.make_node("ConstantOfShape", ["s"], ["c"], name="fill"), _identity()],
                  [_ints("s", [16384, 16384])])
    line = one_line_error(invoke("import", "pendulum", "--controller", path, "--out", tmp_path / "run"))
    assert f"{path}: node fill (ConstantOfShape) has 268,435,456 elements" in line
    assert not (tmp_path / "run").exists() and not leftovers(tmp_path)
