"""The docs stay true: every `drlyap` command line shown in README.md and docs/ parses (its command exists, its
options exist and take the values shown), and every relative link points at a file that exists."""

import re
import shlex
from pathlib import Path

import click
import pytest

from drlyap.cli import main

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").rglob("*.md"))]


def command_lines():
    """(page, line) of every shell line in a fenced block that runs drlyap (continuations joined)."""
    for page in PAGES:
        block = False
        pending = ""
        for raw in page.read_text().splitlines():
            if raw.startswith("```"):
                block, pending = not block, ""
                continue
            if not block:
                continue
            line = pending + raw.strip()
            if line.endswith("\\"):
                pending = line[:-1] + " "
                continue
            pending = ""
            line = re.sub(r"^(\.venv/bin/)?", "", line).split(" #")[0].strip()
            if line.startswith("drlyap ") and "Usage:" not in line:
                yield page.relative_to(ROOT), line


LINES = list(command_lines())


def test_the_docs_show_commands():
    assert len(LINES) > 30


@pytest.mark.parametrize("page, line", LINES, ids=[f"{p}:{i}" for i, (p, _) in enumerate(LINES)])
def test_every_documented_command_parses(page, line):
    args = shlex.split(line)[1:]
    command, ctx_args = main, args
    while isinstance(command, click.Group):
        name = ctx_args[0]
        assert name in command.commands, f"{page}: unknown command {name!r} in {line!r}"
        command, ctx_args = command.commands[name], ctx_args[1:]
    try:
        command.make_context(name, list(ctx_args))
    except click.exceptions.Exit:
        pass
    except click.UsageError as err:
        pytest.fail(f"{page}: {line!r}: {err}")


def test_relative_links_point_at_files():
    broken = []
    for page in PAGES:
        for target in re.findall(r"\]\(([^)#:\s]+)(?:#[^)]*)?\)", page.read_text()):
            if not (page.parent / target).exists():
                broken.append(f"{page.relative_to(ROOT)} -> {target}")
    assert not broken, broken
