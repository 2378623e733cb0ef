"""The words every kind of claim is made of: levels and radii rounded towards the weaker claim, a condition with its
shift or samples and its decay, the region a decrease is proved on. Each kind's sentence (:mod:`drlyap.claims`) is
built from them. Kept apart from :mod:`drlyap.render` so that the checker, which prints the claims it re-checks,
loads nothing of the verifier."""

from __future__ import annotations

import math
from decimal import ROUND_CEILING, ROUND_FLOOR, Decimal


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


def exact_text(value: float) -> str:
    """A radius as a claim prints it: in at most 6 significant digits where that reads back as the number itself, else
    in full (a ball printed smaller or larger than the one proved would claim more on one side of it)."""
    text = f"{value:g}"
    return text if float(text) == value else repr(float(value))


def faces_rule(entry: dict) -> str:
    """The rule for the box's faces a region claim, or ``metrics.json``'s report of a region, states: ``"above"`` (V
    above the level there; the default, written as nothing) or ``"inward"`` (the set cut by the box, the flow entering
    it wherever the set meets a face)."""
    return entry.get("faces", "above")


def condition_region(level: float | None, delta: float, faces: str = "above") -> str:
    """The region a trained condition is proved on: X_delta, or with a level its sublevel set, which V keeps off the
    box's faces (``faces`` ``"above"``) or which the box cuts, the flow entering the box wherever the set meets a face
    (``"inward"``)."""
    region = f"state box minus the open ball ||x - x*|| < {exact_text(delta)}"
    if level is not None:
        c = level_text(level)
        region = f"{{V <= {c}}} minus the open ball ||x - x*|| < {exact_text(delta)}, with V > {c} on the box's faces"
        if faces == "inward":
            region = (f"{{V <= {c}}} in the state box minus the open ball ||x - x*|| < {exact_text(delta)}, the flow "
                      "entering the "
                      f"box at every point of its faces with V <= {c}")
    return region


def of_region(region: str) -> str:
    """``region`` (:func:`condition_region`'s words) after "every state of": with "the" before the state box, not
    before a set ``{V <= c}`` or X_delta."""
    return region if region.startswith("{") or region == "X_delta" else f"the {region}"


UNREADABLE = "(an unreadable claim)"
"""What :func:`claim_sentence` says of a claim it cannot put in words (the checker confirms nothing of it)."""


def condition_words(c: dict) -> str:
    """A claim's condition (``claim["condition"]``) in words, with its shift or samples and its decay."""
    xi = c.get("xi") or []
    decay = decay_words(float(c.get("decay_rate") or 0), float(c.get("exp_rate") or 0))
    if c.get("name") == "true" and c.get("xi_box"):
        low, high = c["xi_box"]["low"], c["xi_box"]["high"]
        shifts = "; ".join(f"[{level_text(a, 4, up=True)}, {level_text(b, 4)}]" for a, b in zip(low[0], high[0]))
        return f"decrease on the true model for every shift xi in {shifts} ({decay})"
    if c.get("name") == "true":
        return f"decrease on the true model at xi = {xi[0] if len(xi) == 1 else xi} ({decay})"
    if c.get("name") in ("pointwise", "uniform"):
        return (f"the DR {c['name']} condition (r = {level_text(float(c['wasserstein_radius']))}, eps = "
                f"{level_text(float(c['risk_level']), up=True)}, {len(xi)} samples of xi, {decay})")
    if c.get("name") == "plain":
        model = "the true model at xi = " + str(xi[0] if len(xi) == 1 else xi) if c.get("model") == "true" else \
            f"the design model at each of {len(xi)} sample(s) of xi"
        return f"decrease on {model} ({decay})"
    if c.get("name") == "nominal":  # fixed words: a file's own text (its label) is never printed as its claim
        return f"the nominal (baseline) condition ({len(xi)} sample(s) of xi, {decay})"
    return f"the {c.get('name')!r} condition ({len(xi)} sample(s) of xi, {decay})"


def decay_words(gamma: float, alpha: float) -> str:
    """A decrease's decay terms as a claim states them: ``gamma = G`` and, where it is not 0, ``alpha = A``."""
    return f"gamma = {level_text(gamma)}" + (f", alpha = {level_text(alpha)}" if alpha else "")


def faces_part(faces: str) -> dict:
    """A region claim's rule for the box's faces as its certificate writes it: nothing for V above the level there
    (the default, :func:`faces_rule`), else ``{"faces": faces}``."""
    return {} if faces == "above" else {"faces": faces}


def model_words(what: str) -> str:
    """The model a decrease's words (:func:`condition_words`) are about: ``what`` without "decrease on " and its
    decay (``"the true model at xi = [0.1, 0.05]"``)."""
    return what.split(" (")[0].replace("decrease on ", "")


def half_widths_text(half) -> str:
    """A box's half-widths around x* as a claim prints them: 3 significant digits each, rounded down."""
    return ", ".join(level_text(float(h), 3) for h in half)
