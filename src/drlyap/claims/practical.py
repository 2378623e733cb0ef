"""``practical`` stability: trajectories from ``{V <= c}`` stay in it and end up in ``{V <= c0}``, because V is at
most ``c0`` on the open delta-ball (the checker's bisection, :func:`~drlyap.checker.levels.ball_below`) and decreases
outside it by the certificate the claim names (``outer``). Its region is the delta-ball's box; it has no partition."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from drlyap.claims.kind import ClaimKind
from drlyap.wording import exact_text, faces_part, faces_rule, level_text, model_words

if TYPE_CHECKING:
    from drlyap.checker.reading import CheckResult, Reading


def practical_parts(ball_of: float, outer: str, level: float, faces: str) -> dict:
    """A practical claim's parts as its certificate writes them: the delta-ball (``ball_of``) its region is the box of,
    the certificate of the decrease outside it (``outer``), the level trajectories end up in and the rule for the
    box's faces of the set they start in."""
    return {"ball_of": float(ball_of), "outer": outer, "practical": {"level": float(level)}} | faces_part(faces)


class Practical(ClaimKind):
    name = "practical"
    files = ("practical",)
    rank = 5
    parts = ("practical",)
    without_partition = True
    rests_on = ("outer",)

    def states(self, marks: frozenset[str], ball: bool, claim: dict) -> bool:
        return marks == {"practical"} and ball

    def sentence(self, claim: dict, what: str) -> str:
        r = claim["region"]
        model = model_words(what)
        cut = " in the state box" if faces_rule(claim) == "inward" else ""
        return (f"trajectories of {model} from {{V <= {level_text(r.get('level'))}}}{cut} stay in it and end up in "
                f"{{V <= {level_text(float(claim['practical']['level']), up=True)}}}: V is at most that on the ball "
                f"||x - x*|| < {exact_text(float(r['ball_of']))}, and decreases outside it by the certificate "
                f"{claim.get('outer')!r}")

    def before_partition(self, out: CheckResult, cert: Reading, header: dict, system) -> bool:
        """Its level ``c0`` below the set's ``c``, and ``V <= c0`` on the open delta-ball (``[lo, hi]`` its box) by
        the checker's bisection (recorded in ``out``); no partition."""
        from drlyap.checker.levels import ball_below

        claim = cert.claim
        c0, c = float(claim["practical"]["level"]), float(claim["region"]["level"])
        if not (math.isfinite(c0) and c0 < c):
            out.failures.append(f"the level trajectories end up in ({c0:g}) is not below the set's ({c:g})")
            return False
        holds, out.ball_max, out.ball_boxes = ball_below(cert.pair, cert.lo, cert.hi,
                                                         float(claim["region"]["ball_of"]), c0)
        if not holds:
            out.failures.append(f"V <= {c0:g} is not established on the ball (V's upper bound there "
                                f"{out.ball_max:.6g}, {out.ball_boxes} boxes)")
        return False


KIND = Practical()
