"""docs/pytorch-pairs.md runs as written: its modules and stand-in checkpoint, exported with torch's ONNX exporter,
imported as a pair that is not a drlyap export (plain decrease is its claim), verified at the test shift with the
decay 0.01 V a region needs, and checked; the output it quotes is what the commands print (the proof's numbers
aside: their last bits depend on the CPU's float kernels)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from drlyap.cli import main
from handmade import doc_quotes

words_only = doc_quotes().words_only

PAGE = Path(__file__).resolve().parents[1] / "docs" / "pytorch-pairs.md"


def _blocks(text: str, lang: str) -> list[str]:
    """The bodies of the page's fenced blocks opened with ```` ```lang ````."""
    found, body, opened = [], [], None
    for line in text.splitlines():
        if line.startswith("```"):
            if opened is None:
                opened, body = line[3:], []
            else:
                if opened == lang:
                    found.append("\n".join(body) + "\n")
                opened = None
        elif opened is not None:
            body.append(line)
    return found


def _drlyap(*args: str) -> str:
    done = CliRunner().invoke(main, list(args), prog_name="drlyap")
    assert done.exit_code in (0, 3), done.output  # 3: the decrease is violated somewhere in the box (the page says so)
    return done.output


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_the_pytorch_page_runs_as_written_and_prints_what_it_quotes(tmp_path, monkeypatch):
    pytest.importorskip("onnx")
    text = PAGE.read_text()
    files = {block.split("\n", 1)[0].removeprefix("# "): block for block in _blocks(text, "python")}
    assert set(files) == {"pair.py", "checkpoint.py", "export.py"}
    for name, body in files.items():
        (tmp_path / name).write_text(body)
    for script in ("checkpoint.py", "export.py"):
        subprocess.run([sys.executable, script], cwd=tmp_path, check=True, capture_output=True)
    monkeypatch.chdir(tmp_path)
    commands = [line.split() for line in _blocks(text, "bash")[0].splitlines() if line.startswith("drlyap ")]
    printed = "".join(_drlyap(*command[1:]) for command in commands)
    config = json.loads((tmp_path / "runs" / "mine" / "config.json").read_text())
    assert (config["decay_rate"], config["exp_rate"]) == (0.0, 0.0)  # not a drlyap export: plain decrease
    metrics = json.loads((tmp_path / "runs" / "mine" / "metrics.json").read_text())
    assert metrics["certificate"]["roa"]["exp_rate"] == 0.01 and metrics["certificate"]["roa"]["certified"]
    assert "roa: CHECKED" in printed and "roa-ball: CHECKED" in printed
    quoted = next(block for block in _blocks(text, "") if block.startswith("imported a pendulum pair"))
    _same_lines(quoted, printed)
    band = [line.split() for line in _blocks(text, "bash")[1].splitlines() if line.startswith("drlyap ")]
    printed = "".join(_drlyap(*command[1:]) for command in band)  # the field's claim, on a band of V
    assert "band: CHECKED" in printed
    _same_lines(next(block for block in _blocks(text, "") if block.startswith("pendulum (imported pair)")), printed)


def _same_lines(quoted: str, printed: str) -> None:
    """Every line of the page's ``quoted`` output is one ``printed`` (what import reads from the files, and the
    claims' sentences, exactly; the proofs' lines in their words)."""
    lines = [line.rstrip() for line in printed.splitlines()]
    for line in quoted.splitlines():
        if line == "...":
            continue
        line = line.removesuffix(" ...")
        if line.startswith("imported") or line.startswith("    ") or "operations" in line or "at x*" in line or (
                "CHECKED - " in line):
            assert line in lines, line  # what import reads from the files: the same on any machine
        else:  # the proof's: its words
            assert any(words_only(here).startswith(words_only(line)) for here in lines), line
