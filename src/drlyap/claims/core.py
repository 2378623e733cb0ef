"""V's set resting on a ``core``: decrease on ``{V <= c}`` outside the closed loop's own ellipsoid ``{z'Pz <= c'}``
(a region of attraction by the certificate the core names), V above the level on the box's faces or the flow
entering the box there. The checker places each leaf said to lie in the core inside it
(:func:`~drlyap.checker.ellipsoid.inside_core`)."""

from __future__ import annotations

from drlyap.claims.kind import ClaimKind
from drlyap.wording import faces_rule, level_text


def core_parts(p: list, level: float, certificate: str = "ellipsoid") -> dict:
    """A claim's ``core`` as its certificate writes it: the ellipsoid ``{z'Pz <= level}`` (``p``: P's rows) and the
    certificate that states it a region of attraction."""
    return {"core": {"P": p, "level": level, "certificate": certificate}}


def core_words(claim: dict) -> str:
    """The claim's core ellipsoid in words, with the certificate it is a region of attraction by."""
    core = claim["core"]
    return (f"{{z'Pz <= {level_text(float(core['level']))}}} (P in the file; a region of attraction by the certificate "
            f"{core.get('certificate')!r})")


class Core(ClaimKind):
    name = "core"
    files = ("roa",)
    rank = 2
    parts = ("core",)
    rests_on = ("core",)

    def states(self, marks: frozenset[str], ball: bool, claim: dict) -> bool:
        return marks == {"core"} and not ball

    def sentence(self, claim: dict, what: str) -> str:
        level = level_text(claim["region"].get("level"))
        faces = (f"the flow entering the box at every point of its faces with V <= {level}"
                 if faces_rule(claim) == "inward" else f"with V > {level} on the box's faces")
        return f"{what} holds at every state of {{V <= {level}}} outside the ellipsoid {core_words(claim)}, {faces}"


KIND = Core()
