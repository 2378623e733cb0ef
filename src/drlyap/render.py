"""Every sentence the tool prints about a proof: typed results (:mod:`drlyap.verification.results`) in words.

A claim is worded exactly as it was proved: "verified" names the condition and the region, a region of attraction
is called one only when every trajectory from it converges to x*, a proved share is never rounded up to a proof,
and what was only sampled says so. The command line, the reports, the comparison table and the figures all take
their wording from here; none of them decides again from the numbers what was proved.
"""

from __future__ import annotations

import math
from pathlib import Path

from drlyap.claims.band import band_sentence
from drlyap.io import proved_percent
from drlyap.kinds import Status
from drlyap.records import ProofRound, TrainingRecord
from drlyap.verification.results import (
    Certificate,
    ConditionProof,
    CoveringCheck,
    ProofAttempt,
    RegionOfAttraction,
    RunRobustness,
    RunVerification,
    UniformMargin,
)
from drlyap.wording import decay_words, level_text, of_region


def proved_share(result: ConditionProof, decimals: int = 4) -> str:
    """The share of X_delta a proof covered, never rounded up to 100% unless it is verified."""
    return proved_percent(result.verified_fraction, result.status == Status.VERIFIED, decimals)


def _num(value, digits: int = 4) -> str:
    """Bounds left unbounded by a time limit come back as None (or infinite)."""
    return "unbounded" if value is None or not math.isfinite(value) else f"{value:.{digits}g}"


# --------------------------------------------------------------------------- a run's trained condition
def certificate_line(cert: Certificate, verify_command: str = "drlyap verify RUN", confirmed: bool = True) -> str:
    """The one line that says what was proved about a run's trained condition; ``verify_command``: the command that
    proves it, named when nothing was checked; ``confirmed``: False where the independent checker did not confirm the
    proof's certificate (the verdict is then not stronger than the checker's)."""
    status = cert.status
    if status == "not checked":
        return f"certificate: NOT CHECKED ({cert.condition} condition; run `{verify_command}`)"
    where = cert.region or "X_delta"
    if status == Status.VERIFIED and not confirmed:
        return (f"certificate: NOT VERIFIED (the independent checker did not confirm the proof's certificate, below) - "
                f"the {cert.condition} condition on {of_region(where)}")
    if status == Status.VERIFIED:
        holds = (f"holds over {of_region(where)} (one inequality: its suprema over the region)"
                 if cert.margin_upper is not None else f"holds at every state of {of_region(where)}")
        return f"certificate: VERIFIED - the {cert.condition} condition {holds} (proof {cert.time_s:.2f} s, {cert.boxes} boxes)"
    share = cert.verified_fraction
    proved = "" if share is None else f"; {100 * share:.4f}% of it proved"
    cex = cert.counterexample
    found = " (found by the falsifier after the proof ran out of time)" if cert.counterexample_source else ""
    extra = f"; counterexample x = {[round(v, 5) for v in cex]}{found}" if cex else ""
    return f"certificate: NOT VERIFIED ({status}) - the {cert.condition} condition on {of_region(where)}{proved}{extra}"


def unverified_warning(cert: Certificate, system: str, method: str) -> str:
    """The warning of a training run whose trained condition is not verified (every condition has proof rounds:
    more of them may prove it)."""
    share = cert.verified_fraction
    detail = "" if share is None else f"; {100 * share:.4f}% of X_delta proved"
    return (f"drlyap: the trained {cert.condition} condition of this {system} {method} run is NOT verified "
            f"({cert.status}{detail}); raise verify_rounds")


def training_lines(system: str, method: str, record: TrainingRecord) -> list[str]:
    """What ``drlyap train`` prints about a training (``record``: what it recorded): iterations and seconds, the
    acceptance check, V's local rate near x* where it was asked, and the retraining rounds."""
    iterations, seconds = record.total_iterations, record.total_time_s
    if record.retraining_rounds:
        kept = "the first training" if record.returned_round == 0 else f"retraining round {record.returned_round}"
        lines = [f"{system} {method}: {iterations} iterations in all ({seconds:.1f} s, {record.retraining_rounds} "
                 f"retraining round(s)); the pair kept is from {kept} (in that run: {record.status})"]
    else:
        lines = [f"{system} {method}: {record.status} ({iterations} iterations, {seconds:.1f} s in all)"]
    acc = record.acceptance
    lines.append(f"  acceptance check: {'PASSED' if acc.passed else 'NOT PASSED'}; the trained condition's max "
                 f"violation {acc.max_violation:.3g} on {100 * acc.violating_fraction:.2f}% of "
                 f"{acc.validation_states} validation states; closed-loop Jacobian at x* Hurwitz at every xi "
                 f"sample: {acc.hurwitz}; other closed-loop equilibria found: {len(acc.other_equilibria)}"
                 + (f" ({len(acc.blocking_equilibria)} in the trained set)"
                    if len(acc.blocking_equilibria) != len(acc.other_equilibria) else ""))
    if acc.local_rate_max is not None:
        rate = acc.local_rate_max
        lines.append(f"  V near x*: Vdot <= {rate:+.3g} V to second order at the worst training sample "
                     f"({'V decreases' if rate < 0 else 'V does NOT decrease along every direction'})")
    grown = record.reshape
    if grown and grown.get("steps"):
        mix = grown.get("mix")
        if not grown["kept"]:
            kept = "NOT kept (the grown V and its mixtures with the trained one failed the acceptance check)"
        elif mix in (None, 1.0):
            kept = "kept"
        else:
            kept = f"kept {mix:g} of the way from the trained V ({grown['share_kept']:.3g})"
        lines.append(f"  V's set grown by {grown['steps']} convex program(s) with the controller fixed: "
                     f"{grown['share_before']:.3g} -> {grown['share_after']:.3g} of the box, {kept}")
    elif grown:
        lines.append(f"  V's set not grown by convex programs: {grown['stopped']}")
    if record.proved_in_rounds:
        lines.append(f"  proof: {record.retraining_rounds} retraining round(s) (kept round {record.returned_round})")
    return lines


def cut_set_line(level: float, test_xi, verify_hint: str) -> str:
    """What ``drlyap train`` adds for a run trained with ``exit_faces``: the set it trained beyond the claim (up to
    the trained ``level``, :attr:`~drlyap.sections.RegionGoal.level`), cut by the box where the flow enters it, and
    the command that searches it for a certified region of attraction at the system's test shift ``test_xi``."""
    xi = ",".join(f"{float(v):g}" for v in test_xi)
    return (f"  trained up to {{V <= {level:g}}} in the box, V held above that level only where the flow may leave "
            f"the box: `{verify_hint} --xi {xi} --roa` searches that set cut by the box for a certified region of "
            f"attraction at the test shift (with the strict decrease a region of attraction needs there)")


def proof_round_line(entry: ProofRound) -> str:
    """One line per proof round of counterexample-guided training (or of the DR uniform margin's rounds)."""
    added = entry.added or {}
    if entry.verified_fraction is None:  # the DR uniform condition's margin
        proof = UniformMargin.from_dict(entry.verification)
        what, capped = f"margin in [{_num(proof.margin_lower)}, {_num(proof.margin_upper)}]", ""
        retrain = (f"the {added.get('peaks_added')} states where its suprema lie "
                   f"(+{added.get('neighbours_added')} neighbours)")
    else:
        proof = ConditionProof.from_dict(entry.verification)
        what = f"{proved_share(proof)} of X_delta proved"
        capped = ", stopped by its time cap: the pair may differ on a faster machine" if proof.stopped == "time limit" \
            else ""
        retrain = (f"{added.get('counterexamples_added')} counterexamples (+{added.get('neighbours_added')} "
                   f"neighbours, {added.get('box_centres_added')} box centres)")
        if added.get("open_boxes"):
            retrain += f" and the verifier's bound over {added['open_boxes']} open boxes"
    same = " (the retraining before it left the pair unchanged)" if entry.unchanged else ""
    ended = "" if proof.status != Status.UNKNOWN else f"; ended by {_stopped(proof.stopped)}"
    if getattr(proof, "resumed_boxes", None):
        ended += f"; resumed from its checkpoint after {proof.resumed_boxes:,} boxes"
    line = (f"  proof round {entry.round}: {proof.status.upper()}{same}, {what} ({proof.boxes_processed:,} boxes, "
            f"{proof.time_s:.2f} s{capped}{ended})")
    if entry.added:
        nxt = added.get("next_iterations")
        plan = (f"retraining round {entry.round + 1} of at most {added.get('max_rounds')} ({nxt} iterations from "
                f"this pair)" if nxt is not None else "retraining")
        return line + f"; {plan} on {retrain}"
    return line + (f"; no more retraining: {entry.stopped}" if entry.stopped and not entry.verified else "")


def _stopped(why: str | None) -> str:
    """Why a proof that is neither verified nor refuted stopped, in words."""
    return {"box budget": "its box budget", "time limit": "its time cap", None: "its budget"}.get(why, why)


# --------------------------------------------------------------------------- verify
def condition_lines(proof: ConditionProof, title: str) -> list[str]:
    """What ``drlyap verify`` prints for one condition's proof."""
    where = "X_delta" if proof.level is None else f"X_delta (condition or V > {level_text(proof.level)})"
    if proof.source == "certificate":
        checked = (f"confirmed by the checker on {proof.checked_at} (recorded for these very files)"
                   if proof.checked_at else f"confirmed by the checker in {proof.time_s:.2f} s")
        how = f"its certificate file ({proof.boxes_processed} boxes), {checked}; not proved again (--reprove proves it anew)"
    else:
        how = f"{proof.boxes_processed} boxes, {proof.time_s:.2f} s, {proof.stopped}"
        if proof.resumed_boxes:
            how += f"; resumed from a checkpoint after {proof.resumed_boxes} boxes"
    lines = [f"{title}: {proof.status.upper()}; verified {proved_share(proof)} of {where} ({how})"]
    if proof.level is not None:
        low = proof.boundary_min_lower
        inside = low is not None and low > proof.level
        digits = 6 if low is None or inside or f"{low:.6g}" != f"{proof.level:.6g}" else 12  # 0.9999999 is not 1
        bound = "unbounded (time limit)" if low is None else f">= {low:.{digits}g}"
        lines.append(f"  on {{V <= {level_text(proof.level)}}} only; min of V on the box's faces {bound} (so the set lies "
                     f"inside the box: {'proved' if inside else 'NOT proved'})")
    if proof.counterexample is not None:
        by = " (the falsifier's, after the proof ran out of time)" if proof.counterexample_source else ""
        lines.append(f"  counterexample x = {[round(v, 6) for v in proof.counterexample]}{by} with residual "
                     f"{proof.counterexample_value:.4g} > 0 (float32 networks: {proof.counterexample_value_float32:.4g})")
    elif proof.status != Status.VERIFIED:
        lines.append(f"  {proof.n_unverified} boxes left unverified")
    return lines


def band_lines(band) -> list[str]:
    """What ``drlyap verify --band`` prints of a band claim (:class:`~drlyap.verification.band_claim.BandProof`)."""
    c1, c2 = level_text(band.low, up=True), level_text(band.high)
    title = f"  band {c1} <= V <= {c2} on the true model at xi = {band.xi}, decay {band.exp_rate:g} V"
    proof = band.decrease
    counts = (proof.partition.counts() if proof.partition is not None else {})
    how = (f"{proof.boxes_processed} boxes, {band.time_s:.2f} s" + (
        f": {counts.get('proved', 0)} proved, {counts.get('below level', 0)} below the band, "
        f"{counts.get('above level', 0)} above it" if counts else ""))
    if band.status == Status.VERIFIED:
        what = f"decrease on the true model at xi = {band.xi} ({decay_words(0.0, band.exp_rate)})"
        return [f"{title}: VERIFIED ({how})",
                f"    {band_sentence(what, band.low, band.high)}",
                f"    practical stability: convergence to {{V <= {c1}}}, not to x* (no region of attraction of x* is "
                "claimed)"]
    lines = [f"{title}: {band.status.upper()}; {band.reason} (verified {proved_share(proof)} of the box; {how})"]
    if proof.counterexample is not None:
        lines.append(f"    counterexample x = {[round(v, 6) for v in proof.counterexample]} with residual "
                     f"{proof.counterexample_value:.4g} > 0 on the band")
    return lines


def margin_line(uni: UniformMargin) -> str:
    """The uniform DR condition's bracket."""
    return (f"uniform DR condition: {uni.status.upper()}; margin in [{_num(uni.margin_lower)}, "
            f"{_num(uni.margin_upper)}] (<= 0 required), (r/eps) L_h <= {_num(uni.lipschitz_term[1])}")


def _sublevel(r: RegionOfAttraction) -> str:
    """The certified set: ``{V <= c}``, or its part in the box where the flow keeps it off the faces."""
    return f"{{V <= {level_text(r.level)}}}" + (" in the box" if r.faces == "inward" else "")


def _faces(r: RegionOfAttraction) -> str:
    return "" if r.faces != "inward" else (
        f"; the set meets the box's faces, and the flow there is proved to enter the box (V >= "
        f"{r.exit_min_lower:.4g} where it may leave)")


def roa_line(r: RegionOfAttraction, true_model: bool) -> str:
    """What a certified-region search proved, named for what it is."""
    if r.error is not None:
        return f"region of attraction: {r.error}"
    model = "the true model at --xi" if true_model else "the design model at each training sample"
    share = r.share_of_box
    size = (f"{100 * share:.2f}% of the box" if share >= 1e-4 or share == 0 else f"{share:.2g} of the box (estimated)"
            ) + f", limited by {r.limited_by}"
    if r.kind == "region of attraction":
        local = r.local
        how = ""
        if r.method == "linearisation":
            how = (f"; near x* by the closed-loop linearisation's z'Pz, proved decreasing on {{z'Pz <= "
                   f"{level_text(local.q_level)}}} which contains {{V <= {level_text(local.inner_level)}}}")
        elif r.method == "band":
            low = local.v_on_ellipsoid[0]
            how = (f"; V proved decreasing on it outside the closed loop's certified ellipsoid {{z'Pz <= "
                   f"{level_text(local.q_level)}}} (--json: roa.band.P), on whose boundary V is as low as {low:.3g} "
                   f"(sampled): " + ("the set reaches beyond the ellipsoid" if r.beyond_ellipsoid else
                                     "the set may lie inside the ellipsoid"))
        elif r.strict is not None and r.strict.by == "proof":
            how = (f"; V > 0 outside the ball proved (V >= {r.strict.lower:.3g} there), which makes its decrease "
                   "alpha V strict")
        return (f"region of attraction: CERTIFIED {_sublevel(r)} ({size}): every trajectory of {model} "
                f"that starts there converges to x*{how}{_faces(r)}")
    if r.kind == "practical stability":
        line = (f"region of attraction: NOT CERTIFIED ({r.local.reason}); practical stability instead: "
                f"trajectories of {model} from {_sublevel(r)} ({size}) end up in "
                f"{{V <= {level_text(r.practical_level, up=True)}}}{_faces(r)}")
    else:
        proved = "none" if r.level is None or not math.isfinite(r.level) else level_text(r.level)
        line = (f"region of attraction: NOT CERTIFIED (largest proved level {proved}, limited by "
                f"{r.limited_by}; inside the ball: {r.local.reason or 'proved'})")
    quad = r.quadratic
    if r.ellipsoid_certified:
        line += (f"\n  the closed loop's own quadratic Lyapunov function: CERTIFIED region of attraction {{z'Pz <= "
                 f"{level_text(quad.q_level)}}} ({quad.share_of_box:.3g} of the box, |x_i - x*_i| up to "
                 f"{[float(f'{e:.3g}') for e in quad.extent]}; P chosen from the closed-loop linearisation, --json: "
                 f"roa.quadratic.P): every trajectory of {model} that starts there converges to x*")
    elif quad:
        line += f"\n  the closed loop's own quadratic Lyapunov function: none ({quad.reason})"
    return line


def unwritten_region_line(roa: RegionOfAttraction | None, written: list) -> str | None:
    """Where a certified region of attraction has no certificate among the files ``written`` (its proofs, made again
    with their partitions kept, did not all hold again): the line that says so, else None."""
    if roa is None or not roa.certified:
        return None
    names = {Path(p).name for p in written}
    if ("roa.json" if roa.method == "band" else "roa-ball.json") in names:
        return None
    ellipsoid = "ellipsoid.json" in names
    return (f"  no certificate file for the region of attraction: its proofs ({roa.method} route) did not all hold "
            "again with their partitions kept (drlyap check cannot re-check this region" +
            ("; the closed loop's ellipsoid is written as ellipsoid)" if ellipsoid else ")"))


def verification_lines(ver: RunVerification, system: str, method: str) -> list[str]:
    """Everything ``drlyap verify`` prints about a run."""
    alone = ver.band is not None and ver.trained is None  # the band claim has no delta-ball
    lines = [f"{system} ({method})" + ("" if alone else f", delta = {ver.delta:g}")]
    if isinstance(ver.trained, ConditionProof):
        lines += condition_lines(ver.trained, f"  trained condition ({ver.trained.condition})")
    elif isinstance(ver.trained, UniformMargin):  # the run's own condition is the uniform one
        lines.append("  trained condition (DR uniform): " + margin_line(ver.trained).removeprefix("uniform DR condition: "))
    if ver.uniform is not None and ver.uniform is not ver.trained:
        lines.append("  " + margin_line(ver.uniform))
    if ver.true_model is not None:
        rate = "" if ver.roa_rate is None else f", decay {ver.roa_rate:g} V"
        lines += condition_lines(ver.true_model, f"  true model at xi = {ver.true_model.xi}{rate}")
    if ver.band is not None:
        lines += band_lines(ver.band)
    if ver.roa is not None:
        lines.append("  " + roa_line(ver.roa, ver.true_model is not None))
    if ver.robustness is not None:
        lines += [f"  {line}" for line in robustness_lines(ver.robustness)]
    return lines


# --------------------------------------------------------------------------- robustness
def claim_lines(outcome) -> list[str]:
    """What ``drlyap verify --claim NAME`` prints of a kind's proof (a :class:`~drlyap.claims.kind.ClaimOutcome`):
    its verdict, the claim where it is verified, and the numbers behind it."""
    head = f"  {outcome.name}: {str(outcome.status).upper()}"
    head += f" - {outcome.sentence}" if outcome.status == "verified" else ""
    numbers = ", ".join(f"{k.replace('_', ' ')} {_num(v) if isinstance(v, float) else v}"
                        for k, v in outcome.numbers.items())
    return [head, f"    {numbers} ({outcome.time_s:.1f} s)"]


def _over(level: float | None) -> str:
    """What a radius or shift-box search proved over: X_delta, or its sublevel set ``{V <= level}``."""
    return "X_delta" if level is None else f"{{V <= {level_text(level)}}} of X_delta"


def robustness_lines(result: RunRobustness) -> list[str]:
    """The certified radius and shift box (what ``drlyap verify --max-radius`` prints)."""
    lines = []
    rad, box = result.radius, result.shift_box
    decay = f"gamma={rad.decay_rate:g}" + (f", alpha={rad.exp_rate:g}" if rad.exp_rate else "")
    at = f"eps={rad.risk_level:g}, N={rad.n_samples}, {decay}"
    trained = (f"run trained at r={result.trained_radius:g}" if result.trained_radius is not None
               else f"{result.method} run: radius of the DR condition at its N samples")
    where = _over(rad.level)
    if rad.radius is None:
        lines.append(f"certified Wasserstein radius (DR pointwise over {where}): NONE at {at} ({trained}): {rad.reason}"
                     + _witness_text(rad))
    else:
        lines.append(f"certified Wasserstein radius (DR pointwise over {where}): r* in [{rad.radius:.4g}, "
                     f"{_upper(rad)}) at {at} ({trained}); {_why(rad)}; {rad.proofs} proofs, {rad.time_s:.1f} s")
    own = result.radius_training_sample
    if own is not None:
        at = f"eps={own.risk_level:g}, N=1"
        if own.radius is None:
            lines.append(f"  around its training sample (the mean, {at}): NONE: {own.reason}" + _witness_text(own))
        else:
            lines.append(f"  around its training sample (the mean, {at}): r* in [{own.radius:.4g}, {_upper(own)}); "
                         f"{_why(own)}; {own.proofs} proofs, {own.time_s:.1f} s")
    decay = f"gamma={box.decay_rate:g}" + (f", alpha={box.exp_rate:.3g}" if box.exp_rate else "")
    where = _over(box.level)
    if box.s is None:
        lines.append(f"certified shift box: NONE (decrease on the true model over {where} with {decay}): {box.reason}"
                     + _witness_text(box))
    else:
        parts = ", ".join(f"{name} in [{lo:.4g}, {hi:.4g}]" for name, (lo, hi) in box.box.items())
        unit = ", ".join(f"{w:.3g}" for w in box.scale)
        lines.append(f"certified shift box: {parts} (decrease on the true model over {where} for every xi in the "
                     f"box, with {decay}; s* = {box.s:.4g} x ({unit}), s in [{box.s:.4g}, {_upper(box)}); "
                     f"{_why(box)}; {box.proofs} proofs, {box.time_s:.1f} s)")
    return lines


def _upper(res) -> str:
    return "unbounded" if res.unproved is None else f"{res.unproved:.4g}"


def _why(res) -> str:
    if res.unproved is None:
        return f"nothing unproved found ({res.stopped})"
    text = f"upper end {res.unproved_status} ({res.unproved_by})"
    if res.stopped != "tolerance":
        text += f", stopped: {res.stopped}"
    return text


def _witness_text(res) -> str:
    w = res.witness
    if not w:
        return ""
    return f" at x = {[round(v, 5) for v in w['state']]} (residual {w['residual']:.3g} > 0)"


# --------------------------------------------------------------------------- report cells and figure labels
ACCEPTANCE_LEGEND = (
    "acceptance: the check that ends training, passed when the trained condition holds at every validation state "
    "(a dense set of X_delta not used in training, within {V <= c} for a sublevel-set run; max violation and "
    "violating % are over them), Hurwitz is True and no other eq. is found (a sublevel-set run also needs V > c at "
    "20,000 states on the box's faces; a run with --local-rate, V decaying near x*). Hurwitz: the closed-loop "
    "Jacobian at x* on the true model is Hurwitz (every eigenvalue's real part < 0) at every xi sample and at their "
    "mean. other eq.: closed-loop equilibria other than x* that a Newton root search from a grid of starts found in "
    "X_delta, at any of those xi.")
"""The definitions of a report's acceptance, Hurwitz and other eq. columns (:mod:`drlyap.training.acceptance`)."""


def roa_cell(roa: RegionOfAttraction | None) -> str | None:
    """A short name of a region-of-attraction result for a report table."""
    if roa is None or roa.error is not None or roa.level is None:
        return None
    if roa.kind == "region of attraction":
        share = roa.share_of_box
        text = f"{100 * share:.1f}%" if share >= 1e-3 or share == 0 else f"{share:.2g} of box"
        if roa.method != "band":
            return text
        return text + (" (V, band)" if roa.beyond_ellipsoid else " (V, within z'Pz)")
    if roa.ellipsoid_certified:  # V's sublevel sets are not certified; the closed loop's quadratic one is
        return f"z'Pz only, {roa.quadratic.share_of_box:.2g} of box"
    return roa.kind or "none"


def decrease_cell(status: str | None, fraction: float | None) -> str:
    """A condition's verdict for a report table: ``verified``, or the status with the share proved."""
    if status is None:
        return "-"
    if status == "verified":
        return "verified"
    return f"{status} ({proved_percent(fraction or 0, False)} proved)"


def region_label(roa: RegionOfAttraction | None, where: str) -> str:
    """What a sublevel set ``{V <= c}`` drawn on a figure is, in words, at ``where`` (a shift text).

    "practical stability: ... converges to {V <= c0}" when ``kind`` says so; "certified region of attraction"
    only when it is certified (and ``kind``, if set, says so); otherwise what was proved and that it certifies
    nothing. An empty string when there is no level to draw.
    """
    if roa is None or roa.level is None or not roa.level > 0:
        return ""
    c = level_text(float(roa.level))
    c0 = roa.ball_max_upper
    inner = f"{{V <= {level_text(float(c0), up=True)}}}" if c0 is not None else "the delta-ball"
    if roa.kind == "practical stability":
        return f"practical stability at {where}: from {{V <= {c}}} converges to {inner}"
    if roa.certified and roa.kind in (None, "region of attraction"):
        return f"certified region of attraction {{V <= {c}}} at {where}"
    bound = f", but V may reach {level_text(float(c0), up=True)} on the delta-ball" if c0 is not None else ""
    return f"not certified at {where}: decrease proved on {{V <= {c}}} outside the delta-ball{bound}"


def attempt_cells(attempt: ProofAttempt | None) -> tuple[str, str, str]:
    """The comparison table's cells for what a run proves at the shift: the decrease (on the set proved: X_delta,
    or ``{V <= c}`` of it), the certified region of attraction, and the certified radius and shift box."""
    if attempt is None:
        return "not checked", "not checked", "-"
    if attempt.verified_fraction is None:
        return attempt.status, "none", _robust_cell(attempt)
    where = "X_delta" if attempt.level is None else f"{{V <= {level_text(attempt.level)}}}"
    if attempt.status == Status.VERIFIED:
        proof = f"verified on {where}"
    else:
        share = proved_percent(attempt.verified_fraction, False)
        proof = (f"{attempt.status} ({share} of X_delta proved)" if attempt.level is None else
                 f"{attempt.status} on {where} ({share} of X_delta proved: the condition, or V above the level)")
    if attempt.exp_rate is not None:
        proof += f", decay {attempt.exp_rate:.3g} V"
    if attempt.roa_certified:
        roa = f"{100 * attempt.roa_share:.1f}% of the box"
    elif attempt.roa_kind == "practical stability":
        roa = f"none (practical stability on {100 * attempt.roa_share:.1f}% of the box)"
    else:
        roa = "none"
    return proof, roa, _robust_cell(attempt)


def _robust_cell(attempt: ProofAttempt) -> str:
    rob = attempt.robustness
    if not rob:
        return "-"
    if rob["radius"] is not None:
        r = f"r* {rob['radius']:.3g} (eps {rob['risk_level']:g}, N {rob['n_samples']})"
    else:
        r = "r* none" if "n_samples" in rob else "r* n/a"
    scale = ", ".join(f"{w:.3g}" for w in rob["shift_scale"])
    s = "none" if rob["shift_box_s"] is None else f"|xi| <= {rob['shift_box_s']:.3g} x ({scale})"
    return f"{r}; shift box {s}"


COMPARE_LEGEND = (
    "verified decrease at xi: Vdot + gamma |x - x*| (+ alpha V) <= 0 on the true model at xi, proved at every state of "
    "X_delta (the box minus the delta-ball) or of the sublevel set named; 'violated' means a state of that region "
    "where it fails, which does not keep a smaller set from being certified. certified region of attraction at xi: the "
    "largest sublevel set of V (an LQR or RL run: of its own quadratic z'Pz) proved to converge to x*, as a share of "
    "the box. certified radius: the largest Wasserstein radius r* at which the run's DR condition is proved; shift "
    "box |xi| <= s x (w): decrease on the true model proved for every shift with |xi_i| <= s w_i, w the size of the "
    "test shift per uncertain parameter (where it is 0: the samples' spread, else 10% of the nominal value).")


# --------------------------------------------------------------------------- the covering check
def covering_lines(check: CoveringCheck, system: str, method: str) -> list[str]:
    """What ``drlyap lipschitz`` prints."""
    lines = [f"{system} ({method}), {check.condition}, delta = {check.delta:g}",
             f"  grid: {check.cells} cells ({' x '.join(map(str, check.per_axis))}), spacing <= {check.spacing:.4g}, "
             f"covering radius rho = {check.covering_radius:.4g}",
             f"  max residual at the cell centres: {check.max_residual:.4g} (in X_delta: "
             f"{check.max_residual_in_x_delta:.4g})",
             f"  Lipschitz constant: {check.lipschitz_sound:.4g} (sound, interval gradient bounds); "
             f"{check.lipschitz_sampled:.4g} (largest sampled gradient)",
             f"  covering certificate: {'CERTIFIED' if check.certified else 'NOT CERTIFIED'} "
             f"(needs max residual <= -L rho = {check.required_max_residual:.4g}); with {check.safety:g} x the "
             f"sampled L: {'holds' if check.certified_estimate else 'fails'}"]
    if check.spacing_needed is not None:
        lines.append(f"  spacing needed with this L and maximum: {check.spacing_needed:.3g} "
                     f"(about {check.samples_needed:.3g} samples)")
    ver = check.verifier
    if ver is not None:
        lines.append(f"  branch and bound: {ver.status.upper()}, verified {proved_share(ver)} "
                     f"({ver.boxes_processed} boxes, {ver.time_s:.2f} s)")
    return lines


def check_lines(results) -> list[str]:
    """What ``drlyap check`` prints about each re-checked certificate (:class:`drlyap.checker.CheckResult`)."""
    lines = []
    for r in results:
        if r.ok:
            refined = f", {r.refined} of them bisected into {r.pieces} pieces" if r.refined else ""
            lines.append(f"{r.name}: CHECKED - {r.claim}")
            if r.cube_bound is not None and r.name == "ellipsoid":
                lines.append(f"  Wdot's bound P C + C'P + P D1 P + D2 over the Jacobian's enclosure on the box is negative "
                             f"definite by the checker's arithmetic (its largest eigenvalue about {r.cube_bound:.3g})")
            elif r.cube_bound is not None:
                lines.append(f"  the Hessian of Vdot on the cube is negative definite by the checker's enclosure "
                             f"(its largest eigenvalue about {r.cube_bound:.3g})")
            if r.positive_min is not None:
                lines.append(f"  V > 0 outside the ball by the checker's bisection (V's smallest lower bound there "
                             f"{r.positive_min:.3g}, {r.positive_boxes} boxes)")
            if r.ball_max is not None:
                lines.append(f"  V <= its level on the ball by the checker's bisection (V's largest upper bound there "
                             f"{r.ball_max:.6g}, {r.ball_boxes} boxes; {r.time_s:.2f} s)")
            elif r.boxes or r.cube_bound is None:
                core = f", {r.inside_core} inside the core (every vertex)" if r.inside_core else ""
                below = f" ({r.below_band} of them below the band: V < c1)" if r.below_band else ""
                ball = f", {r.inside_ball} inside the ball" if r.inside_ball or not r.below_band else ""
                lines.append(f"  {r.proved} boxes re-proved by the checker{below}{refined}{ball}{core}; "
                             f"the boxes cover the region ({r.time_s:.2f} s)")
        else:
            lines.append(f"{r.name}: FAILED - the certificate does not establish: {r.claim or 'its claim'}")
            lines.extend(f"  {reason}" for reason in r.failures)
    return lines
