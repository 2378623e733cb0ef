"""The DR ``uniform`` condition: one inequality over X_delta, ``(r/eps) sup ||W^T grad V|| + CVaR_eps`` over the
samples of ``sup (Vdot + decay) <= 0``. The checker bounds each supremum over every leaf of the partition
(:mod:`drlyap.checker.uniform`) and the margin made of them must be ``<= 0``."""

from __future__ import annotations

from typing import TYPE_CHECKING

from drlyap.claims.kind import ClaimKind
from drlyap.wording import condition_region, of_region

if TYPE_CHECKING:
    from drlyap.checker.reading import CheckResult, Leaves, Reading


class Uniform(ClaimKind):
    name = "uniform"
    files = ("trained", "uniform")
    rank = 1

    def states(self, marks: frozenset[str], ball: bool, claim: dict) -> bool:
        return not marks and not ball and (claim.get("condition") or {}).get("name") == "uniform"

    def refusal(self, claim: dict) -> str | None:
        if claim["region"].get("level") is not None:
            return "the DR uniform condition is one inequality over X_delta: its claim states no level"
        return None

    def sentence(self, claim: dict, what: str) -> str:
        r = claim["region"]
        return (f"{what} holds over {of_region(condition_region(r.get('level'), float(r['delta'])))} as one "
                "inequality: (r/eps) sup ||W^T grad V|| + CVaR_eps over the samples of sup (Vdot + decay) <= 0")

    def leaves(self, out: CheckResult, cert: Reading, leaves: Leaves, prove) -> None:
        """One margin over all the proved leaves (each leaf's recorded bound is its own margin, which may not lie
        below the margin at its centre)."""
        from drlyap.checker.arith import EPS
        from drlyap.checker.leaves import MIN_PIECES
        from drlyap.checker.model import centre_lower
        from drlyap.checker.reading import vector_text
        from drlyap.checker.uniform import uniform_margin_bound

        lo, hi, bound = leaves.proved_boxes()
        margin, suprema, out.refined, out.pieces = uniform_margin_bound(cert.residual, lo, hi, cert.hi - cert.lo,
                                                                        leaves.refine,
                                                                        max(MIN_PIECES, int(lo.shape[0])))
        out.proved = int(lo.shape[0]) if margin <= 0 else 0
        if margin > 0:
            out.failures.append(f"the checker's bound of the uniform margin over the {lo.shape[0]} leaves is "
                                f"{margin:.6g} > 0 (suprema of ||W^T grad V||, Vdot_j + decay: {vector_text(suprema)})")
        centre_low = centre_lower(cert.residual, lo, hi)
        false = bound < centre_low - 4 * EPS * centre_low.abs()
        if bool(false.any()):
            out.failures.append(f"{int(false.sum())} recorded bounds lie below the margin at their box's centre")


KIND = Uniform()
