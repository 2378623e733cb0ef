"""Whether a certificate's claim is the run's (``drlyap check``'s first question, beside the boxes): the condition,
region and level each certificate must state for what ``config.json`` and ``metrics.json`` say the run was trained
for and was shown to satisfy, so that a file proving a weaker or another claim is not taken for the run's, and that
a region's certificate inside the ball names one outside it about the same claim. Read as JSON: nothing is bounded
here."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

from drlyap.claims.kind import PREMISES
from drlyap.claims.registry import kinds_stating
from drlyap.wording import faces_rule


def outer_missing(run_dir: Path, header: dict, positive: Callable[[dict], str] | None = None) -> list[str]:
    """Where the certificate a ``roa-ball`` names for the decrease outside the ball (``outer``) does not cover its
    region: missing, on another delta or a lower level, about other samples, a rule for the box's faces other than
    the one the claim states (a ``practical`` claim's ``faces``), or a decrease that is not strict (that
    certificate's boxes are checked on their own). Where only ``alpha V`` can make it strict and V is not positive by
    its form (an imported V), ``positive(outer's region)`` must establish V > 0 outside the ball: it returns "" where
    it does, else why not (None: nothing establishes it)."""

    region = header["claim"]["region"]
    if header["claim"].get("outer") not in PREMISES["outer"]:
        return [f"the certificate it names for the decrease outside the ball ({header['claim'].get('outer')!r}) is not "
                f"one of {', '.join(PREMISES['outer'])}"]
    path = run_dir / "certificates" / f"{header['claim'].get('outer')}.json"
    try:
        outer_header = json.loads(path.read_text())
        claim = outer_header["claim"]
        outer, samples = claim["region"], claim["condition"]["xi"]
    except (OSError, ValueError, KeyError, TypeError):
        return [f"the certificate it names for the decrease outside the ball ({path.name}) cannot be read"]
    level, theirs = region.get("level"), outer.get("level")
    if outer.get("delta") != region.get("ball_of") or level is None or theirs is None or not theirs >= level:
        return [f"{path.name} does not prove the decrease outside the ball on {{V <= {level}}}"]
    if samples != header["claim"]["condition"].get("xi") or \
            claim["condition"].get("xi_box") != header["claim"]["condition"].get("xi_box"):
        return [f"{path.name} is about other samples or another shift than the decrease inside the ball"]
    mine = header["claim"]  # a roa-ball's sentence leaves the set's faces to its outer; a practical one states them
    if ("faces" in mine or "practical" in mine) and faces_rule(mine) != faces_rule(claim):
        return [f"the rule for the box's faces it states ({faces_rule(mine)!r}) is not {path.name}'s"]
    strict = _strict(claim["condition"], outer_header.get("networks") or {})
    if strict == "positive" and positive is not None:
        why = positive(outer)
        return [f"{path.name}'s decrease is strict only where V > 0, and {why}"] if why else []
    if strict not in ("decay", "form"):
        return [f"{path.name}'s decrease is not strict (no decay gamma ||z||, and no alpha V with V > 0 away from x* "
                "by its form or proved): V's decrease outside the ball does not rule out rest points there"]
    return []


def core_missing(run_dir: Path, header: dict) -> list[str]:
    """Where the certificate a claim with a ``core`` names for its ellipsoid (``core.certificate``) does not state that
    ellipsoid a region of attraction of the same closed loop: missing, another ``P`` or level, or about other samples
    or another model (that certificate is checked on its own)."""
    claim = header["claim"]
    core = claim.get("core") or {}
    if core.get("certificate") not in PREMISES["core"]:
        return [f"the certificate it names for its core ({core.get('certificate')!r}) is not one of "
                f"{', '.join(PREMISES['core'])}"]
    path = run_dir / "certificates" / f"{core.get('certificate')}.json"
    try:
        theirs = json.loads(path.read_text())["claim"]
        ellipsoid, condition = theirs["ellipsoid"], theirs["condition"]
    except (OSError, ValueError, KeyError, TypeError):
        return [f"the certificate it names for its core ({path.name}) cannot be read, or states no ellipsoid"]
    if ellipsoid.get("P") != core.get("P") or ellipsoid.get("level") != core.get("level"):
        return [f"{path.name} is about another ellipsoid than the core"]
    mine = claim["condition"]
    if any(condition.get(k) != mine.get(k) for k in ("xi", "xi_box", "model")):
        return [f"{path.name} is about other samples or another model than the decrease around its core"]
    return []


def _strict(condition: dict, networks: dict) -> str:
    """What makes a decrease condition ``Vdot < 0`` away from x*: ``"decay"`` (``gamma ||z||`` with ``gamma > 0``),
    ``"form"`` (``alpha V`` with ``alpha > 0`` and V positive away from x* by its form: drlyap's V with
    ``alpha_hat > 0``), ``"positive"`` (``alpha V`` with ``alpha > 0``, and V > 0 there still to establish: an
    imported V), or "" (nothing)."""
    gamma, alpha = float(condition.get("decay_rate") or 0.0), float(condition.get("exp_rate") or 0.0)
    alpha_hat = networks.get("alpha_hat")
    if not (gamma >= 0 and alpha >= 0):  # a negative term weakens the decrease below Vdot <= 0
        return ""
    if gamma > 0:
        return "decay"
    if not alpha > 0:
        return ""
    return "form" if isinstance(alpha_hat, (int, float)) and alpha_hat > 0 else "positive"


def _trained_condition(config: dict, metrics: dict) -> dict:
    """The fields of the condition a run was trained on, as its certificates state them: the DR loss with its radius
    and risk level, or the nominal condition, at the training samples."""
    if config.get("method") != "dr":
        return {"name": "nominal", "xi": metrics.get("xi_train")}
    return {"name": config.get("loss"), "xi": metrics.get("xi_train"),
            "wasserstein_radius": config.get("wasserstein_radius"), "risk_level": config.get("risk_level")}


def _region_plain(reported: dict, config: dict, metrics: dict) -> dict:
    """The plain decrease a region's certificates near x* state (``reported``: ``metrics.json``'s
    ``certificate.roa``): on the true model at the shift it reports, else on the design model at the run's training
    samples, with no ``alpha V``."""
    xi = reported.get("xi")
    samples = [list(map(float, xi))] if xi is not None else _trained_condition(config, metrics)["xi"]
    return {"name": "plain", "model": "true" if xi is not None else "design", "xi": samples, "exp_rate": 0.0}


def _roa_claim(name: str, header: dict, config: dict, metrics: dict, expected: dict,
               delta) -> tuple[dict, dict, list[str]]:
    """The condition and region a ``roa`` or ``roa-ball`` certificate must state for the region of attraction
    ``metrics.json`` reports (``certificate.roa``: its level and shift): ``roa`` the run's trained condition (for
    the DR uniform condition the decrease at each sample it implies), or decrease on the true model at the shift, on
    ``{V <= level}`` (for the band proof, with a ``core``: plain decrease on the same model at each of its samples
    over the box, no inner ball); ``practical`` (practical stability: ``metrics.json`` reports that kind, its level
    and the level trajectories end up in) as ``roa-ball`` without a partition; ``roa-ball`` plain decrease on the
    same model at each of its samples inside the
    delta-ball (a strict decay, checked with the cube or the core), naming as ``outer`` a certificate of the same
    model on ``{V <= c'}``, ``c' >=`` the level. A ``roa`` and a ``practical`` claim state the rule for the box's
    faces ``metrics.json`` reports (``faces``, ``"above"`` where absent). ``delta``: the run's. Returns (expected
    condition fields, expected region fields, other problems)."""
    reported = (metrics.get("certificate") or {}).get("roa") or {}
    xi = reported.get("xi")
    practical = name in ("practical", "roa") and reported.get("kind") == "practical stability"  # roa: its outer
    level = reported.get("level", "none reported in metrics.json") if reported.get("certified") or practical else \
        "no certified region reported in metrics.json"
    condition = {"name": "true", "model": "true", "xi": [list(map(float, xi))]} if xi is not None else \
        _trained_condition(config, metrics)
    if xi is not None and reported.get("exp_rate") is not None:  # the decay asked at the shift (verify --roa-rate)
        condition["exp_rate"] = float(reported["exp_rate"])
        condition["decay_rate"] = float(reported.get("decay_rate", config.get("decay_rate") or 0.0))
    if condition["name"] == "uniform":  # one inequality: its region rests on the decrease at each sample it implies
        condition = {"name": "plain", "xi": condition["xi"]}
    claim = header["claim"]
    ball = _region_plain(reported, config, metrics)
    faces = [] if faces_rule(claim) == faces_rule(reported) else [
        "faces (not the rule for the box's faces metrics.json reports)"]
    if name == "roa" and claim.get("core") is not None:  # the band proof: V's strict decrease outside the core
        return {k: v for k, v in expected.items() if k != "decay_rate"} | ball, {"delta": 0.0, "level": level}, faces
    if name == "roa":
        return expected | condition, {"delta": delta, "level": level}, faces
    decay = claim["condition"].get("decay_rate")
    expected = {k: v for k, v in expected.items() if k not in ("decay_rate", "exp_rate", "model")} | ball | {
        "decay_rate": decay if header.get("partition") is not None else 0.0}
    problems = []
    if claim["region"].get("ball_of") != delta:
        problems.append("the ball (not the run's delta)")
    outer = claim.get("outer")
    want = "true-model" if xi is not None else "trained"
    if outer not in ("roa", want):
        problems.append(f"outer (names {outer!r}, not roa or {want})")
    if name == "practical" and (claim.get("practical") or {}).get("level") != reported.get("practical_level"):
        problems.append("the level trajectories end up in (not the one metrics.json reports)")
    if name == "practical":
        problems += faces
    return expected, {"delta": claim["region"].get("delta"), "level": level}, problems


def _ellipsoid_mismatch(header: dict, config: dict, metrics: dict) -> list[str]:
    """What of an ``ellipsoid`` certificate's claim differs from the closed loop's quadratic region ``metrics.json``
    reports (``certificate.roa.quadratic``, or for a region of V from the linearisation the ellipsoid it rests on,
    ``certificate.roa.local``: its ``P`` and level), on the region's model and samples (plain decrease, as for
    ``roa-ball``)."""
    reported = (metrics.get("certificate") or {}).get("roa") or {}
    quadratic = reported.get("quadratic") or {}
    local = reported.get("local") or {}
    if not quadratic.get("proved") and local.get("method") == "linearisation" and local.get("proved"):
        quadratic = {"proved": True, "P": local.get("P"), "q_level": local.get("q_level")}  # the ellipsoid V rests on
    claim = header["claim"]
    expected = _region_plain(reported, config, metrics)
    differ = [k for k, v in expected.items() if claim["condition"].get(k) != v]
    ellipsoid = claim.get("ellipsoid") or {}
    if not quadratic.get("proved"):
        differ.append("ellipsoid (no certified one reported in metrics.json)")
    else:
        differ += [k for k, mine in (("P", "P"), ("level", "q_level")) if ellipsoid.get(k) != quadratic.get(mine)]
    return differ


def claim_mismatch(name: str, header: dict, config: dict, metrics: dict) -> list[str]:
    """Where a certificate's claim is not the run's: for ``trained``, the condition the run was trained on (method
    and loss, radius, risk level, decay, samples, delta, level); for ``true-model``, the run's decay and the shift
    its metrics report the decrease at (where they report one); for ``radius``, the DR pointwise condition at the
    run's risk level, decay and samples (all of them) at the certified radius its metrics report; for ``uniform``,
    the DR uniform condition at the run's radius, risk level, decay and samples (all of them), on X_delta (a uniform
    claim has no level, a run trained on it neither); for ``shift-box``,
    decrease on the true model with the run's decay for every shift in the box its metrics report; a ``band`` claim
    states its own shift, levels and decay (only V's ``alpha_hat`` is the run's). A certificate that
    proves a weaker condition than the run's is then not taken for the run's."""
    kinds = kinds_stating(name)
    if kinds and all(k.own_claim for k in kinds):
        # a claim of its own: what it is about is the file's (its kind's checks read it), only V's alpha_hat the run's
        same = (header.get("networks") or {}).get("alpha_hat") == config.get("alpha_hat")
        return [] if same else ["the certificate's alpha_hat is not the run's (config.json)"]
    try:
        claim = header["claim"]["condition"]
        region = header["claim"]["region"]
    except (KeyError, TypeError):
        return ["the header has no claim"]
    expected = {"decay_rate": float(config.get("decay_rate") or 0.0), "exp_rate": float(config.get("exp_rate") or 0.0),
                "model": "true" if name in ("true-model", "shift-box") else "design"}
    problems = []
    if header.get("networks", {}).get("alpha_hat") != config.get("alpha_hat"):
        problems.append("alpha_hat")
    delta, level = region.get("delta"), region.get("level")
    if not (isinstance(delta, (int, float)) and math.isfinite(delta) and delta >= 0):
        problems.append("delta (not a finite number >= 0)")
    if level is not None and not (isinstance(level, (int, float)) and math.isfinite(level)):
        problems.append("level (not finite)")
    if name == "trained":
        expected |= _trained_condition(config, metrics)
    elif name == "radius":  # the DR pointwise condition at all the run's samples, at the radius its metrics report
        reported = (metrics.get("certificate") or {}).get("radius") or {}
        expected |= {"name": "pointwise", "xi": metrics.get("xi_samples"), "risk_level": config.get("risk_level"),
                     "wasserstein_radius": reported.get("radius", "none reported in metrics.json")}
    elif name == "uniform":  # the DR uniform condition at all the run's samples and its radius
        expected |= {"name": "uniform", "xi": metrics.get("xi_samples"), "risk_level": config.get("risk_level"),
                     "wasserstein_radius": config.get("wasserstein_radius")}
    elif name == "shift-box":  # every shift in the box its metrics report, [-s* scale, s* scale]
        reported = (metrics.get("certificate") or {}).get("shift_box") or {}
        half = [float(reported["s"]) * float(w) for w in reported.get("scale") or []] if "s" in reported else None
        expected |= {"name": "true", "xi": None,
                     "xi_box": "none reported in metrics.json" if half is None else
                     {"low": [[-h for h in half]], "high": [half]}}
    else:
        expected |= {"name": "true"}
        reported = (metrics.get("certificate") or {}).get("true_model") or {}
        if reported.get("xi") is not None:  # the shift the run reports its decrease and region at
            expected |= {"xi": [list(map(float, reported["xi"]))]}
        if reported.get("exp_rate") is not None and claim.get("exp_rate") == reported["exp_rate"]:
            expected["exp_rate"] = float(reported["exp_rate"])  # the decay asked there (verify --roa-rate)
            expected["decay_rate"] = float(reported.get("decay_rate", expected["decay_rate"]))
    stated = {"delta": delta, "level": level}
    wanted = {"delta": config.get("delta"), "level": config.get("roa_level")}
    if expected.get("name") == "uniform":  # one inequality over X_delta: no sublevel set
        wanted["level"] = None
    if "certificate" in config:  # an imported pair: its claim's decay, level and delta (None: the system's delta)
        wanted = {"delta": delta if config.get("delta") is None else config["delta"], "level": config.get("level")}
    if name == "ellipsoid":  # the closed loop's own quadratic region its metrics report
        more = _ellipsoid_mismatch(header, config, metrics)
        return [] if not (problems or more) else [
            f"the certificate's claim is not the run's closed-loop ellipsoid ({', '.join(problems + more)} differ "
            "from config.json / metrics.json)"]
    if name in ("roa", "roa-ball", "practical"):  # the region its metrics report, on its model
        expected, wanted, more = _roa_claim(name, header, config, metrics, expected, wanted["delta"])
        problems += more
    expected_region = [k for k in stated if stated[k] != wanted[k]]
    differ = [k for k, v in expected.items() if claim.get(k) != v] + expected_region + problems
    if not differ:
        return []
    return [f"the certificate's claim is not the run's {name.replace('-', ' ')} condition ({', '.join(differ)} "
            "differ from config.json / metrics.json)"]
