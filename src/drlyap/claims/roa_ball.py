"""V's decrease inside the delta-ball (``roa-ball``), on ``{V <= c}`` there: ``Vdot < 0`` on a ``cube`` around x*
except at x* by second order (Vdot's Hessian over the cube negative definite, :mod:`drlyap.checker.ball`), the rest
of the ball's box on a partition outside ``||x - x*|| < delta`` (a ring); or on the ball's box outside a ``core``
ellipsoid. Outside the ball, V decreases by the certificate the claim names (``outer``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from drlyap.claims.core import core_words
from drlyap.claims.kind import ClaimKind
from drlyap.wording import exact_text, half_widths_text, level_text

if TYPE_CHECKING:
    from drlyap.checker.reading import CheckResult, Reading


def cube_parts(ball_of: float, half: list[float], outer: str) -> dict:
    """A roa-ball claim by second order as its certificate writes it: the delta-ball (``ball_of``) its region is the
    box of, the cube's half-widths and the certificate of the decrease outside the ball (``outer``)."""
    return {"ball_of": float(ball_of), "cube": {"half": half}, "outer": outer}


def cored_parts(ball_of: float, outer: str, core: dict) -> dict:
    """A roa-ball claim resting on a core ellipsoid (``core``: :func:`~drlyap.claims.core.core_parts`) as its
    certificate writes it."""
    return {"ball_of": float(ball_of), "outer": outer} | core


class RoaBall(ClaimKind):
    name = "roa-ball"
    files = ("roa-ball",)
    rank = 3
    parts = ("cube", "core")
    without_partition = True
    rests_on = ("outer", "core")

    def states(self, marks: frozenset[str], ball: bool, claim: dict) -> bool:
        return marks in ({"cube"}, {"core"}) and ball

    def sentence(self, claim: dict, what: str) -> str:
        r = claim["region"]
        level, ball = level_text(r.get("level")), exact_text(float(r["ball_of"]))
        if claim.get("core") is not None:
            return (f"V decreases on {{V <= {level}}} inside the ball ||x - x*|| < {ball}: {what} on the ball's box "
                    f"outside the ellipsoid {core_words(claim)}; outside the ball by the certificate "
                    f"{claim.get('outer')!r}")
        half = half_widths_text(claim["cube"]["half"])
        rest = "" if float(r["delta"]) >= float(r["ball_of"]) else (  # no ring: the cube covers the ball
            f"; {what} on the rest of the ball's box outside ||x - x*|| < {exact_text(float(r['delta']))}")
        return (f"V decreases on {{V <= {level}}} inside the ball ||x - x*|| < {ball}: Vdot < 0 on the cube "
                f"|x_i - x*_i| <= [{half}] except at x* (second order){rest}; outside the ball by the certificate "
                f"{claim.get('outer')!r}")

    def before_partition(self, out: CheckResult, cert: Reading, header: dict, system) -> bool:
        """The cube by second order; a partition follows where there is a ring (or a core: the partition only)."""
        from drlyap.checker.ball import ball_failures

        if cert.claim.get("cube") is None:
            return True
        ring = header["partition"] is not None
        failures, out.cube_bound = ball_failures(cert.claim, cert.pair, system, cert.lo, cert.hi, cert.delta, ring)
        out.failures += failures
        return ring  # without one the cube covers the ball


KIND = RoaBall()
