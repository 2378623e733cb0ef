"""The shift a benchmark proves a run's decrease at, from its ``--xi`` text (shared by the benchmark scripts)."""

from __future__ import annotations


def run_shift(run, text: str | None) -> list[float] | None:
    """``text``: None (no shift), ``test`` (the run's system's test shift) or comma-separated numbers. A ValueError
    names what is wrong."""
    if text is None:
        return None
    if text == "test":
        if run.system.test_xi is None:
            raise ValueError(f"{run.system.name} declares no test shift")
        return list(run.system.test_xi)
    return [float(v) for v in text.split(",")]
