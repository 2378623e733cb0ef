"""The words of a certificate's claim: the condition, the region it holds on and its level, as a certificate file
states them (:func:`claim_sentence`). Kept apart from :mod:`drlyap.render` so that the checker, which prints the
claims it re-checks, loads nothing of the verifier."""

from __future__ import annotations

import math
from decimal import ROUND_CEILING, ROUND_FLOOR, Decimal

CERTIFICATES = ("trained", "true-model", "radius", "shift-box", "uniform", "roa", "roa-ball", "ellipsoid", "practical",
                "band")
"""The names of a run's certificate files (:mod:`drlyap.runs.certificates` says what each claims)."""


def level_text(level: float, digits: int = 6, up: bool = False) -> str:
    """A level of V (or of z'Pz) in at most ``digits`` significant digits that never claims more than was proved:
    rounded down for a set ``{V <= c}`` proved (a smaller set is proved too, and ``V > c`` on the faces then holds
    as well), so 0.9999999999999991 prints as 0.999999, not 1; rounded up with ``up`` for a set that others are
    proved to end up in. A number that reads back as the stored one prints as it is (1.0 as 1)."""
    text = f"{level:.{digits}g}"
    if not math.isfinite(level) or (float(text) >= level if up else float(text) <= level):
        return text
    exact = Decimal(level)
    step = Decimal(1).scaleb(exact.adjusted() - digits + 1)
    return f"{float(exact.quantize(step, rounding=ROUND_CEILING if up else ROUND_FLOOR)):.{digits}g}"


def faces_rule(entry: dict) -> str:
    """The rule for the box's faces a region claim, or ``metrics.json``'s report of a region, states: ``"above"`` (V
    above the level there; the default, written as nothing) or ``"inward"`` (the set cut by the box, the flow entering
    it wherever the set meets a face)."""
    return entry.get("faces", "above")


def condition_region(level: float | None, delta: float, faces: str = "above") -> str:
    """The region a trained condition is proved on: X_delta, or with a level its sublevel set, which V keeps off the
    box's faces (``faces`` ``"above"``) or which the box cuts, the flow entering the box wherever the set meets a face
    (``"inward"``)."""
    region = f"state box minus the open ball ||x - x*|| < {delta:g}"
    if level is not None:
        c = level_text(level)
        region = f"{{V <= {c}}} minus the open ball ||x - x*|| < {delta:g}, with V > {c} on the box's faces"
        if faces == "inward":
            region = (f"{{V <= {c}}} in the state box minus the open ball ||x - x*|| < {delta:g}, the flow entering the "
                      f"box at every point of its faces with V <= {c}")
    return region


def of_region(region: str) -> str:
    """``region`` (:func:`condition_region`'s words) after "every state of": with "the" before the state box, not
    before a set ``{V <= c}`` or X_delta."""
    return region if region.startswith("{") or region == "X_delta" else f"the {region}"


def claim_sentence(claim: dict) -> str:
    """A certificate file's claim (``claim`` of its header: ``condition`` and ``region`` as written by
    :mod:`drlyap.runs.certificates`) in words, from its fields: what the file states and what ``drlyap check``
    re-proves."""
    try:
        c, r = claim["condition"], claim["region"]
        xi = c.get("xi") or []
        decay = decay_words(float(c.get("decay_rate") or 0), float(c.get("exp_rate") or 0))
        if c.get("name") == "true" and c.get("xi_box"):
            low, high = c["xi_box"]["low"], c["xi_box"]["high"]
            shifts = "; ".join(f"[{a:.4g}, {b:.4g}]" for a, b in zip(low[0], high[0]))
            what = f"decrease on the true model for every shift xi in {shifts} ({decay})"
        elif c.get("name") == "true":
            what = f"decrease on the true model at xi = {xi[0] if len(xi) == 1 else xi} ({decay})"
        elif c.get("name") == "pointwise":
            what = (f"the DR pointwise condition (r = {float(c['wasserstein_radius']):g}, eps = "
                    f"{float(c['risk_level']):g}, {len(xi)} samples of xi, {decay})")
        elif c.get("name") == "uniform":
            return (f"the DR uniform condition (r = {float(c['wasserstein_radius']):g}, eps = "
                    f"{float(c['risk_level']):g}, {len(xi)} samples of xi, {decay}) holds over "
                    f"{of_region(condition_region(r.get('level'), float(r['delta'])))} as one inequality: (r/eps) sup "
                    "||W^T grad V|| + CVaR_eps over the samples of sup (Vdot + decay) <= 0")
        elif c.get("name") == "plain":
            model = "the true model at xi = " + str(xi[0] if len(xi) == 1 else xi) if c.get("model") == "true" else \
                f"the design model at each of {len(xi)} sample(s) of xi"
            what = f"decrease on {model} ({decay})"
        else:
            what = f"the {c.get('label', c.get('name'))} condition ({len(xi)} sample(s) of xi, {decay})"
        level = r.get("level")
        if claim.get("ellipsoid") is not None:  # the closed loop's own quadratic region
            half = ", ".join(f"{float(h):.3g}" for h in claim["ellipsoid"]["box"])
            ring = "" if not claim["ellipsoid"].get("ring") else (
                f"; outside ||x - x*|| < {float(r['delta']):g}, {what.replace('decrease', 'decrease of W', 1)} on it")
            return (f"{{z'Pz <= {level_text(level)}}} (W = z'Pz, P in the file) is a region of attraction: W decreases on "
                    f"it except at x*, on the box |x_i - x*_i| <= [{half}] by the Jacobian's enclosure{ring}")
        if claim.get("practical") is not None:  # practical stability: V's bound on the ball, the decrease outside
            model = what.split(" (")[0].replace("decrease on ", "")
            cut = " in the state box" if faces_rule(claim) == "inward" else ""
            return (f"trajectories of {model} from {{V <= {level_text(level)}}}{cut} stay in it and end up in "
                    f"{{V <= {level_text(float(claim['practical']['level']), up=True)}}}: V is at most that on the ball "
                    f"||x - x*|| < {float(r['ball_of']):g}, and decreases outside it by the certificate "
                    f"{claim.get('outer')!r}")
        if claim.get("band") is not None:  # practical stability on a band c1 <= V <= c2 (the field's form)
            return band_sentence(what, float(claim["band"]["low"]), float(level))
        core = claim.get("core")
        if core is not None:  # V's region resting on the closed loop's ellipsoid (linearisation route, band proof)
            ellipsoid = (f"{{z'Pz <= {level_text(float(core['level']))}}} (P in the file; a region of attraction by "
                         f"the certificate {core.get('certificate')!r})")
            if r.get("ball_of") is not None:
                return (f"V decreases on {{V <= {level_text(level)}}} inside the ball ||x - x*|| < "
                        f"{float(r['ball_of']):g}: {what} on the ball's box outside the ellipsoid {ellipsoid}; outside "
                        f"the ball by the certificate {claim.get('outer')!r}")
            return (f"{what} holds at every state of {{V <= {level_text(level)}}} outside the ellipsoid {ellipsoid}, "
                    f"with V > {level_text(level)} on the box's faces")
        if claim.get("cube") is not None:  # roa-ball: V's decrease inside the delta-ball
            half = ", ".join(f"{float(h):.3g}" for h in claim["cube"]["half"])
            rest = "" if float(r["delta"]) >= float(r["ball_of"]) else (  # no ring: the cube covers the ball
                f"; {what} on the rest of the ball's box outside ||x - x*|| < {float(r['delta']):g}")
            return (f"V decreases on {{V <= {level_text(level)}}} inside the ball ||x - x*|| < {float(r['ball_of']):g}: "
                    f"Vdot < 0 on the cube |x_i - x*_i| <= [{half}] except at x* (second order){rest}; outside "
                    f"the ball by the certificate {claim.get('outer')!r}")
        return (f"{what} holds at every state of "
                f"{of_region(condition_region(level, float(r['delta']), faces_rule(claim)))}")
    except (KeyError, TypeError, ValueError, IndexError):
        return "(an unreadable claim)"


def decay_words(gamma: float, alpha: float) -> str:
    """A decrease's decay terms as a claim states them: ``gamma = G`` and, where it is not 0, ``alpha = A``."""
    return f"gamma = {gamma:g}" + (f", alpha = {alpha:g}" if alpha else "")


def band_sentence(what: str, low: float, high: float) -> str:
    """A band claim (:mod:`drlyap.verification.band_claim`) in words: ``what`` (the decrease, as
    :func:`claim_sentence` names it) on ``low <= V <= high``, and what follows."""
    model = what.split(" (")[0].replace("decrease on ", "")
    c1, c2 = level_text(low, up=True), level_text(high)
    return (f"trajectories of {model} from {{V <= {c2}}} in the state box stay in it and reach {{V <= {c1}}}: {what} "
            f"on the band {c1} <= V <= {c2}, and the flow enters the box wherever V <= {c2} on its faces (V as the run's "
            "files give it)")
