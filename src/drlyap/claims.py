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


CLAIM_KINDS = ("condition", "uniform", "ellipsoid", "practical", "band", "roa-ball", "core")
"""The kinds of claim a certificate states, each read from its parts by :func:`claim_kind`: a decrease ``condition``
on X_delta or a sublevel set; the DR ``uniform`` condition (one inequality); the closed loop's own quadratic region
(``ellipsoid``); ``practical`` stability (V's bound on the delta-ball, the decrease outside it resting on an ``outer``
certificate); the decrease on a ``band`` c1 <= V <= c2; V's decrease inside the delta-ball (``roa-ball``: by second
order on a ``cube``, or outside a ``core`` ellipsoid, resting on an ``outer`` certificate); and V's set resting on a
``core`` ellipsoid over the box."""

KINDS_OF = {"trained": ("condition", "uniform"), "true-model": ("condition",), "radius": ("condition",),
            "shift-box": ("condition",), "uniform": ("uniform",), "roa": ("condition", "core"), "roa-ball": ("roa-ball",),
            "ellipsoid": ("ellipsoid",), "practical": ("practical",), "band": ("band",)}
"""The kinds of claim each certificate file (:data:`CERTIFICATES`) may state: what its name means, and what the checks
that go by the name (the run's agreement, a claim's premises) are written for."""

PREMISES = {"outer": ("roa", "trained", "true-model"), "core": ("ellipsoid",)}
"""The certificates a claim may rest on: for the decrease outside the delta-ball (``outer``), and for its ``core``
ellipsoid."""

_MARKS = ("ellipsoid", "practical", "band", "cube", "core")
"""The parts of a claim that mark its kind."""

_KIND_OF_PARTS = {((), False): "condition", (("ellipsoid",), False): "ellipsoid", (("practical",), True): "practical",
                  (("band",), False): "band", (("cube",), True): "roa-ball", (("core",), True): "roa-ball",
                  (("core",), False): "core"}
"""A claim's kind by the parts that mark it and whether its region is the delta-ball's box (``ball_of``)."""


def claim_kind(claim: dict) -> str:
    """The kind (:data:`CLAIM_KINDS`) of a certificate's claim, from the parts that mark it and whether its region is
    the delta-ball's box (``ball_of``); a ValueError where they make no kind drlyap states (two kinds at once, or a
    region in the ball's box for a claim whose words are about the whole box), so that a claim is never checked on less
    than its sentence says."""
    marks = [k for k in _MARKS if claim.get(k) is not None]
    ball = claim["region"].get("ball_of") is not None
    kind = _KIND_OF_PARTS.get((tuple(marks), ball))
    if kind is None:
        raise ValueError(f"the claim's parts ({', '.join(marks) or 'none'}) and its region "
                         f"({'the delta-ball' if ball else 'the state'}'s box) make no kind of claim drlyap states")
    if kind == "condition" and claim["condition"].get("name") == "uniform":
        if claim["region"].get("level") is not None:
            raise ValueError("the DR uniform condition is one inequality over X_delta: its claim states no level")
        return "uniform"
    return kind


def claim_sentence(claim: dict) -> str:
    """A certificate file's claim (``claim`` of its header: ``condition`` and ``region`` as written by
    :mod:`drlyap.runs.certificates`) in words, from its fields and its kind (:func:`claim_kind`): what the file states
    and what ``drlyap check`` re-proves."""
    try:
        return _SENTENCES[claim_kind(claim)](claim, condition_words(claim["condition"]))
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, ArithmeticError):
        return UNREADABLE


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


def _condition_sentence(claim: dict, what: str) -> str:
    r = claim["region"]
    return (f"{what} holds at every state of "
            f"{of_region(condition_region(r.get('level'), float(r['delta']), faces_rule(claim)))}")


def _uniform_sentence(claim: dict, what: str) -> str:
    r = claim["region"]
    return (f"{what} holds over {of_region(condition_region(r.get('level'), float(r['delta'])))} as one inequality: "
            "(r/eps) sup ||W^T grad V|| + CVaR_eps over the samples of sup (Vdot + decay) <= 0")


def _ellipsoid_sentence(claim: dict, what: str) -> str:  # the closed loop's own quadratic region
    r = claim["region"]
    half = ", ".join(level_text(float(h), 3) for h in claim["ellipsoid"]["box"])
    ring = "" if not claim["ellipsoid"].get("ring") else (
        f"; outside ||x - x*|| < {exact_text(float(r['delta']))}, {what.replace('decrease', 'decrease of W', 1)} on it")
    return (f"{{z'Pz <= {level_text(r.get('level'))}}} (W = z'Pz, P in the file) is a region of attraction: W decreases "
            f"on it except at x*, on the box |x_i - x*_i| <= [{half}] by the Jacobian's enclosure{ring}")


def _practical_sentence(claim: dict, what: str) -> str:  # V's bound on the ball, the decrease outside it
    r = claim["region"]
    model = what.split(" (")[0].replace("decrease on ", "")
    cut = " in the state box" if faces_rule(claim) == "inward" else ""
    return (f"trajectories of {model} from {{V <= {level_text(r.get('level'))}}}{cut} stay in it and end up in "
            f"{{V <= {level_text(float(claim['practical']['level']), up=True)}}}: V is at most that on the ball "
            f"||x - x*|| < {exact_text(float(r['ball_of']))}, and decreases outside it by the certificate "
            f"{claim.get('outer')!r}")


def _band_claim_sentence(claim: dict, what: str) -> str:  # practical stability on a band c1 <= V <= c2 (the field's)
    return band_sentence(what, float(claim["band"]["low"]), float(claim["region"]["level"]))


def _core_words(claim: dict) -> str:
    core = claim["core"]
    return (f"{{z'Pz <= {level_text(float(core['level']))}}} (P in the file; a region of attraction by the certificate "
            f"{core.get('certificate')!r})")


def _roa_ball_sentence(claim: dict, what: str) -> str:  # V's decrease inside the delta-ball
    r = claim["region"]
    level = level_text(r.get("level"))
    if claim.get("core") is not None:
        return (f"V decreases on {{V <= {level}}} inside the ball ||x - x*|| < {exact_text(float(r['ball_of']))}: {what} "
                f"on the "
                f"ball's box outside the ellipsoid {_core_words(claim)}; outside the ball by the certificate "
                f"{claim.get('outer')!r}")
    half = ", ".join(level_text(float(h), 3) for h in claim["cube"]["half"])
    rest = "" if float(r["delta"]) >= float(r["ball_of"]) else (  # no ring: the cube covers the ball
        f"; {what} on the rest of the ball's box outside ||x - x*|| < {exact_text(float(r['delta']))}")
    return (f"V decreases on {{V <= {level}}} inside the ball ||x - x*|| < {exact_text(float(r['ball_of']))}: Vdot < 0 "
            f"on the "
            f"cube |x_i - x*_i| <= [{half}] except at x* (second order){rest}; outside the ball by the certificate "
            f"{claim.get('outer')!r}")


def _core_sentence(claim: dict, what: str) -> str:  # V's set resting on the closed loop's ellipsoid (the band route)
    level = level_text(claim["region"].get("level"))
    faces = (f"the flow entering the box at every point of its faces with V <= {level}"
             if faces_rule(claim) == "inward" else f"with V > {level} on the box's faces")
    return f"{what} holds at every state of {{V <= {level}}} outside the ellipsoid {_core_words(claim)}, {faces}"


_SENTENCES = {"condition": _condition_sentence, "uniform": _uniform_sentence, "ellipsoid": _ellipsoid_sentence,
              "practical": _practical_sentence, "band": _band_claim_sentence, "roa-ball": _roa_ball_sentence,
              "core": _core_sentence}
"""Each kind of claim's sentence, from the claim and its condition's words."""


def decay_words(gamma: float, alpha: float) -> str:
    """A decrease's decay terms as a claim states them: ``gamma = G`` and, where it is not 0, ``alpha = A``."""
    return f"gamma = {level_text(gamma)}" + (f", alpha = {level_text(alpha)}" if alpha else "")


def band_sentence(what: str, low: float, high: float) -> str:
    """A band claim (:mod:`drlyap.verification.band_claim`) in words: ``what`` (the decrease, as
    :func:`claim_sentence` names it) on ``low <= V <= high``, and what follows."""
    model = what.split(" (")[0].replace("decrease on ", "")
    c1, c2 = level_text(low, up=True), level_text(high)
    return (f"trajectories of {model} from {{V <= {c2}}} in the state box stay in it and reach {{V <= {c1}}}: {what} "
            f"on the band {c1} <= V <= {c2}, and the flow enters the box wherever V <= {c2} on its faces (V as the run's "
            "files give it)")
