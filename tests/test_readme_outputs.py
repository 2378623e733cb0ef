"""The README's quoted outputs are what the commands print: the quickstart's reproduction table and the checker's
lines for its DR pair, from a fresh `drlyap reproduce pendulum` (about 90 s: behind -m slow). Seconds are the
machine's and are not compared."""

import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from drlyap.cli import main

README = Path(__file__).resolve().parents[1] / "README.md"


def _blocks() -> list[str]:
    """The README's fenced blocks, each as its text."""
    blocks, current = [], None
    for line in README.read_text().splitlines():
        if line.startswith("```"):
            if current is None:
                current = []
            else:
                blocks.append("\n".join(current))
                current = None
        elif current is not None:
            current.append(line)
    return blocks


def _without_seconds(row: str) -> list[str]:
    """A table row's cells but the training seconds (the column headed 'train s')."""
    cells = [c.strip() for c in row.strip().strip("|").split("|")]
    return cells[:9] + cells[10:]


@pytest.mark.slow
def test_the_quoted_reproduction_and_check_are_what_the_commands_print(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    done = CliRunner().invoke(main, ["reproduce", "pendulum"])
    assert done.exit_code == 0, done.output
    quoted = next(b for b in _blocks() if b.startswith("| seed | method | 10 test states"))
    printed = [line for line in done.output.splitlines() if line.startswith("| 0 | ")][:2]
    assert [_without_seconds(r) for r in printed] == [_without_seconds(r) for r in quoted.splitlines()[2:4]]
    check = CliRunner().invoke(main, ["check", "runs/reproduce-pendulum/seed0/dr", "--name", "trained"])
    assert check.exit_code == 0, check.output
    block = next(b for b in _blocks() if b.startswith("$ drlyap check"))
    first, second = block.splitlines()[1:3]
    lines = check.output.splitlines()
    assert lines[0] == first
    assert re.sub(r"\(\d+\.\d+ s\)", "", lines[1]) == re.sub(r"\(\d+\.\d+ s\)", "", second)
