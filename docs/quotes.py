"""The outputs the README and docs quote, produced by the commands that print them.

    python docs/quotes.py                 # rewrite every quote (the pendulum reproduction: about 2 minutes)
    python docs/quotes.py --only help     # only docs/cli.md's --help blocks (seconds)
    python docs/quotes.py --check         # rewrite nothing; name every stale quote and exit 1

A quote is a fenced block found by its first line: `Usage: drlyap ...` in docs/cli.md is that command's --help;
`| seed | method | 10 test states ...` in README.md is the table of `drlyap reproduce pendulum`; `$ drlyap check
runs/pendulum-dr` is what that command prints after the README's API block (`drlyap train pendulum --method dr`).
Seconds are the machine's: --check does not compare them. The reproduction's numbers depend on the float kernels
(drlyap.kernels; its quote names their fingerprint): --check compares them where this machine's fingerprint is the
quote's, and only the words elsewhere. The tests run --check's comparison (the help blocks always, the reproduction
behind -m slow).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from drlyap.workflows.reproduce import KERNELS_LINE  # the line drlyap reproduce prints under its table

ROOT = Path(__file__).resolve().parents[1]
HELP_WIDTH = 112
REPRODUCTION_HEADER = "| seed | method | 10 test states"
CHECK_COMMAND = "$ drlyap check runs/pendulum-dr"
FINGERPRINT = re.compile(r"fingerprint ([0-9a-f]{16})")
NUMBER = re.compile(r"-?\d[\d,]*(\.\d+)?(e[-+]?\d+)?%?")


@dataclass(frozen=True)
class Quote:
    """One quoted block: where it is, how to find it, which group produces it."""

    page: Path
    first_line: str        # the block's first line starts with this
    group: str             # "help" or "reproduction"
    name: str


def fenced_blocks(text: str) -> Iterator[tuple[int, int]]:
    """(first, end) line indices of every fenced block's body in `text` (end exclusive)."""
    start = None
    for i, line in enumerate(text.splitlines()):
        if line.startswith("```"):
            if start is None:
                start = i + 1
            else:
                yield start, i
                start = None


def quoted(page: Path, first_line: str) -> str:
    """The body of the one fenced block of `page` whose first line starts with `first_line`."""
    lines = page.read_text().splitlines()
    found = [(a, b) for a, b in fenced_blocks(page.read_text()) if b > a and lines[a].startswith(first_line)]
    if len(found) != 1:
        raise LookupError(f"{page.name}: {len(found)} blocks start with {first_line!r} (expected one)")
    a, b = found[0]
    return "\n".join(lines[a:b])


def replace(page: Path, first_line: str, body: str) -> None:
    """Write `body` as the block of `page` that starts with `first_line`."""
    text = page.read_text()
    old = quoted(page, first_line)
    page.write_text(text.replace("\n" + old + "\n", "\n" + body + "\n", 1))


def help_quotes() -> list[Quote]:
    """docs/cli.md's --help blocks, one per command (the group's own help included)."""
    page = ROOT / "docs" / "cli.md"
    lines = page.read_text().splitlines()
    firsts = [lines[a] for a, b in fenced_blocks(page.read_text()) if b > a and lines[a].startswith("Usage: drlyap")]
    heads = [first.split("[OPTIONS]")[0] + "[OPTIONS]" for first in firsts]
    return [Quote(page, head, "help", head.removeprefix("Usage: ").removesuffix(" [OPTIONS]")) for head in heads]


_HELP_SCRIPT = """
import json, sys
from click.testing import CliRunner
from drlyap.cli import main
out = {}
for command in json.loads(sys.argv[1]):
    done = CliRunner().invoke(main, [*command, "--help"], prog_name="drlyap", terminal_width=int(sys.argv[2]))
    if done.exit_code != 0:
        sys.exit(f"drlyap {' '.join(command)} --help failed: {done.output}")
    out[" ".join(command)] = done.output.rstrip("\\n")
print(json.dumps(out))
"""


def help_texts(quotes: list[Quote]) -> dict[str, str]:
    """What `drlyap ... --help` prints for each quote, at the width the docs use, by a fresh Python (what the help
    says must not depend on what else ran in this process): first line -> text."""
    commands = [q.first_line.split()[2:-1] for q in quotes]
    done = subprocess.run([sys.executable, "-c", _HELP_SCRIPT, json.dumps(commands), str(HELP_WIDTH)],
                          capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(done.stderr.strip().splitlines()[-1] if done.stderr.strip() else "--help failed")
    texts = json.loads(done.stdout)
    return {q.first_line: texts[" ".join(c)] for q, c in zip(quotes, commands)}


@contextmanager
def _in_scratch() -> Iterator[Path]:
    here = Path.cwd()
    with tempfile.TemporaryDirectory(prefix="drlyap-quotes-") as scratch:
        os.chdir(scratch)
        try:
            yield Path(scratch)
        finally:
            os.chdir(here)


def reproduction_texts() -> dict[str, str]:
    """The README's reproduction table and check lines, from the commands (run in a scratch folder)."""
    from click.testing import CliRunner

    from drlyap.cli import main

    def run(*args: str) -> str:
        done = CliRunner().invoke(main, list(args), prog_name="drlyap")
        if done.exit_code != 0:
            raise RuntimeError(f"drlyap {' '.join(args)} exited {done.exit_code}: {done.output[-2000:]}")
        return done.output

    with _in_scratch():
        printed = run("reproduce", "pendulum")
        table = [line for line in printed.splitlines() if line.startswith("|")]
        run("train", "pendulum", "--method", "dr", "--out", "runs/pendulum-dr")
        check = run(*CHECK_COMMAND.split()[2:]).rstrip("\n")
    header = next(i for i, line in enumerate(table) if line.startswith(REPRODUCTION_HEADER))
    rows = [line for line in table[header + 2:] if line.startswith("| 0 | ")][:2]
    kernels = next(line for line in printed.splitlines() if line.startswith(KERNELS_LINE))
    return {REPRODUCTION_HEADER: "\n".join(table[header:header + 2] + rows + ["", kernels]),
            CHECK_COMMAND: CHECK_COMMAND + "\n" + check}


def reproduction_quotes() -> list[Quote]:
    readme = ROOT / "README.md"
    return [Quote(readme, REPRODUCTION_HEADER, "reproduction", "README reproduction table"),
            Quote(readme, CHECK_COMMAND, "reproduction", "README check lines")]


def without_seconds(text: str) -> str:
    """`text` with what depends on the machine's speed blanked: seconds in parentheses, a table's `train s` column."""
    text = re.sub(r"\(\d+(\.\d+)? s\)", "(_ s)", text)
    lines = text.splitlines()
    if lines and lines[0].startswith("|"):
        cells = [c.strip() for c in lines[0].strip().strip("|").split("|")]
        if "train s" in cells:
            k = cells.index("train s")
            lines = [line if line.startswith("|---") else
                     "|".join(c if i != k + 1 else " _ " for i, c in enumerate(line.split("|"))) for line in lines]
    return "\n".join(lines)


GROUPS: dict[str, tuple[Callable[[], list[Quote]], Callable[[list[Quote]], dict[str, str]]]] = {
    "help": (help_quotes, help_texts),
    "reproduction": (reproduction_quotes, lambda quotes: reproduction_texts()),
}


def produce(groups: list[str]) -> list[tuple[Quote, str]]:
    """Every quote of `groups` with the text its command prints now."""
    out = []
    for group in groups:
        find, make = GROUPS[group]
        quotes = find()
        texts = make(quotes)
        out += [(q, texts[q.first_line]) for q in quotes]
    return out


def words_only(text: str) -> str:
    """`text` without its float kernels' line and with every number blanked: what other float kernels print alike."""
    return NUMBER.sub("#", "\n".join(line for line in text.splitlines() if not line.startswith(KERNELS_LINE)))


def fingerprint(text: str) -> str | None:
    """The float kernels' fingerprint a quote or an output names (None: it names none)."""
    found = FINGERPRINT.search(text)
    return found.group(1) if found else None


def differs(quote: Quote, text: str, digits: bool = True) -> bool:
    """Whether `quote` as its page has it says other than `text` (seconds aside; with `digits` False, numbers aside
    too: they depend on the float kernels, drlyap.kernels)."""
    old, new = without_seconds(quoted(quote.page, quote.first_line)), without_seconds(text)
    return old != new if digits else words_only(old) != words_only(new)


def kernels_of_groups(produced: list[tuple[Quote, str]]) -> dict[str, tuple[str | None, str | None]]:
    """Per group: the fingerprint its quotes were made with and the one here (None, None: the group's output does
    not depend on the float kernels)."""
    out: dict[str, tuple[str | None, str | None]] = {}
    for q, text in produced:
        here = fingerprint(text)
        if here is not None:
            out[q.group] = (fingerprint(quoted(q.page, q.first_line)), here)
    return out


def stale(groups: list[str], log: Callable[[str], None] | None = None) -> list[str]:
    """Names of the quotes of `groups` that differ from what their commands print now: every word and number where
    this machine's float kernels are the quotes' (and for output that does not depend on them), the words only
    where they are not (`log` says so)."""
    produced = produce(groups)
    kernels = kernels_of_groups(produced)
    for group, (then, now) in kernels.items():
        if then != now and log is not None:
            log(f"{group}: numbers not compared, the float kernels differ (quoted: {then}, here: {now})")
    return [q.name for q, text in produced
            if differs(q, text, digits=q.group not in kernels or kernels[q.group][0] == kernels[q.group][1])]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=sorted(GROUPS), action="append", help="only these quotes")
    parser.add_argument("--check", action="store_true", help="rewrite nothing; exit 1 naming the stale quotes")
    args = parser.parse_args(argv)
    os.environ.setdefault("DRLYAP_THREADS", "1")
    groups = args.only or sorted(GROUPS)
    if args.check:
        names = stale(groups, log=lambda line: print(line, file=sys.stderr))
        for name in names:
            print(f"stale: {name}", file=sys.stderr)
        return 1 if names else 0
    for quote, text in produce(groups):
        replace(quote.page, quote.first_line, text)
        print(f"wrote {quote.name} ({quote.page.relative_to(ROOT)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
