"""The README's and docs' quoted outputs are what the commands print: docs/quotes.py produces them and these tests
compare (seconds aside). The --help blocks of docs/cli.md always; the README's reproduction table and check lines
from a fresh `drlyap reproduce pendulum` and `drlyap train pendulum --method dr` (about 2 min: behind -m slow).
docs/results/pendulum.md's seed-0 rows must say what the README's quoted table says."""

import re
from pathlib import Path

import pytest

from handmade import doc_quotes

ROOT = Path(__file__).resolve().parents[1]
quotes = doc_quotes()


def test_every_help_block_is_what_help_prints():
    assert len(quotes.help_quotes()) >= 15
    assert quotes.stale(["help"]) == [], "run: python docs/quotes.py --only help"


def test_a_changed_quote_is_found_stale(tmp_path):
    page = tmp_path / "cli.md"
    page.write_text((ROOT / "docs" / "cli.md").read_text().replace("  --seed INTEGER", "  --seed INT", 1))
    moved = [quotes.Quote(page, q.first_line, q.group, q.name) for q in quotes.help_quotes()]
    texts = quotes.help_texts(moved)
    assert [q.name for q in moved if quotes.differs(q, texts[q.first_line])] == ["drlyap train"]


def test_the_numbers_are_compared_only_where_the_float_kernels_are_the_quotes(tmp_path):
    """The reproduction's digits depend on the float kernels (drlyap.kernels): where this machine's are not the
    quote's, a quote with other numbers is not stale, one with other words is."""
    header = quotes.REPRODUCTION_HEADER + " | region |"
    quote = "\n".join([header, "|---|", "| 0 | dr | 10/10 | verified | 41.8% |", "",
                       "float kernels: torch 2.13.0+cpu, cpu AVX2 kernels, 1 thread, fingerprint 0123456789abcdef"])
    page = tmp_path / "README.md"
    page.write_text(f"text\n\n```\n{quote}\n```\n")
    q = quotes.Quote(page, quotes.REPRODUCTION_HEADER, "reproduction", "table")
    other_kernels = quote.replace("41.8%", "28.2%").replace("0123456789abcdef", "fedcba9876543210")
    assert quotes.kernels_of_groups([(q, other_kernels)]) == {"reproduction": ("0123456789abcdef", "fedcba9876543210")}
    assert not quotes.differs(q, other_kernels, digits=False)
    assert quotes.differs(q, other_kernels.replace("verified", "violated"), digits=False)
    assert quotes.differs(q, quote.replace("41.8%", "28.2%"))  # the same kernels: every number counts
    assert not quotes.differs(q, quote)


def test_seconds_are_not_compared():
    table = "| seed | train s | x |\n|---|---|---|\n| 0 | 9 | a (0.07 s) |"
    assert quotes.without_seconds(table) == quotes.without_seconds(table.replace("9", "15").replace("0.07", "1.3"))
    assert quotes.without_seconds(table) != quotes.without_seconds(table.replace("| a", "| b"))


def _rows(text: str, header: str) -> list[dict[str, str]]:
    lines = [line for line in text.splitlines() if line.startswith("|")]
    start = next(i for i, line in enumerate(lines) if line.startswith(header))
    names = [c.strip() for c in lines[start].strip().strip("|").split("|")]
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("| "):
            break
        cells = [re.sub(r"\*\*", "", c).strip() for c in line.strip().strip("|").split("|")]
        rows.append(dict(zip(names, cells)))
    return rows


def test_the_pendulum_page_agrees_with_the_readme_on_seed_0():
    readme = _rows(quotes.quoted(ROOT / "README.md", quotes.REPRODUCTION_HEADER), quotes.REPRODUCTION_HEADER)
    page = [r for r in _rows((ROOT / "docs" / "results" / "pendulum.md").read_text(), "| seed | method | paper 10")
            if r["seed"] == "0"]
    assert [r["method"] for r in readme] == [r["method"] for r in page] == ["baseline", "dr"]
    for ours, theirs in zip(readme, page):
        assert ours["10 test states"] == theirs["paper 10"]
        assert ours["200 more"] == theirs["200 more"]
        assert ours["acceptance"] == theirs["acceptance"]
        assert theirs["trained condition"].startswith(ours["trained condition (verifier)"])
        assert ours["decrease on the true model at the test shift"] == \
            theirs["decrease on the true model at the test shift"]
        assert ours["certified region of attraction"] == theirs["certified region of attraction (share of the box)"]


@pytest.mark.slow
def test_the_readme_quotes_are_what_the_commands_print():
    assert quotes.stale(["reproduction"]) == [], "run: python docs/quotes.py --only reproduction"
