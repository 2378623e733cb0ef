"""The field's practical stability on a ``band``: V decreases on ``c1 <= V <= c2`` of the whole state box (on the
true model at one shift, ``Vdot + alpha V <= 0`` with ``alpha > 0``) and the flow enters the box wherever
``V <= c2`` on its faces, so trajectories from ``{V <= c2}`` stay in it and reach ``{V <= c1}``; about V as the run's
files give it (an imported V need not be pinned at x*). Proved by :mod:`drlyap.verification.band_claim`; the checker
re-proves it as a claim on ``{V <= c2}`` whose leaves may lie below the band instead (V < c1 by its bisection,
:mod:`drlyap.checker.band`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from drlyap.claims.kind import ClaimKind
from drlyap.wording import level_text, model_words

if TYPE_CHECKING:
    from drlyap.checker.reading import CheckResult, Leaves, Reading


def band_sentence(what: str, low: float, high: float) -> str:
    """A band claim in words: ``what`` (the decrease, as :func:`~drlyap.wording.condition_words` names it) on
    ``low <= V <= high``, and what follows."""
    model = model_words(what)
    c1, c2 = level_text(low, up=True), level_text(high)
    return (f"trajectories of {model} from {{V <= {c2}}} in the state box stay in it and reach {{V <= {c1}}}: {what} "
            f"on the band {c1} <= V <= {c2}, and the flow enters the box wherever V <= {c2} on its faces (V as the run's "
            "files give it)")


def band_parts(low: float) -> dict:
    """A band claim's parts as its certificate writes them: ``c1`` (the level is its region's ``c2``) and the flow
    entering the box on its faces."""
    return {"band": {"low": float(low)}, "faces": "inward"}


class Band(ClaimKind):
    name = "band"
    files = ("band",)
    rank = 6
    parts = ("band",)
    own_claim = True

    def states(self, marks: frozenset[str], ball: bool, claim: dict) -> bool:
        return marks == {"band"} and not ball

    def sentence(self, claim: dict, what: str) -> str:
        return band_sentence(what, float(claim["band"]["low"]), float(claim["region"]["level"]))

    def about(self, out: CheckResult, claim: dict, pair):
        """V as the files give it (an imported V is not pinned at x* for it); what the claim must state for its
        conclusion to follow into ``out``."""
        from drlyap.checker.band import statement_failures
        from drlyap.checker.graphs import GraphPair

        out.failures += statement_failures(claim)
        return pair.as_given() if isinstance(pair, GraphPair) else pair

    def floor(self, claim: dict) -> float | None:
        return float(claim["band"]["low"])

    def after_leaves(self, out: CheckResult, cert: Reading, leaves: Leaves) -> None:
        """Its leaves below the band: ``V < c1`` there, by the checker's bisection (counted as proved)."""
        from drlyap.checker.band import below_failures
        from drlyap.checker.reading import BELOW_LEVEL

        lo, hi, bound = leaves.with_verdict(BELOW_LEVEL)
        failures, spent = below_failures(cert.pair, lo, hi, bound, cert.floor, cert.hi - cert.lo)
        out.failures, out.pieces = out.failures + failures, out.pieces + spent
        out.below_band = int(lo.shape[0]) if not failures else 0
        out.proved += out.below_band


KIND = Band()
