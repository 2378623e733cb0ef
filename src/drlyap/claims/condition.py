"""A decrease ``condition`` on X_delta or on a sublevel set ``{V <= c}`` of it: the trained condition, decrease on
the true model at a shift or for a box of shifts, the DR pointwise condition at a radius, a region's outer decrease.
Proved on a partition of its region; on a sublevel set, V above the level on the box's faces (or, ``faces``
``"inward"``, the flow entering the box where the set meets a face)."""

from __future__ import annotations

from drlyap.claims.kind import ClaimKind
from drlyap.wording import condition_region, faces_rule, of_region


class Condition(ClaimKind):
    name = "condition"
    files = ("trained", "true-model", "radius", "shift-box", "roa")
    rank = 0

    def states(self, marks: frozenset[str], ball: bool, claim: dict) -> bool:
        return not marks and not ball and (claim.get("condition") or {}).get("name") != "uniform"

    def sentence(self, claim: dict, what: str) -> str:
        r = claim["region"]
        return (f"{what} holds at every state of "
                f"{of_region(condition_region(r.get('level'), float(r['delta']), faces_rule(claim)))}")


KIND = Condition()
