"""What a verification leaves in a run directory: ``metrics.json``'s account of the true model and the region (one
account, whatever sequence of ``verify`` calls made it) and the certificate files of every proof that ended verified,
for ``drlyap check`` (:func:`record_region`, :func:`record_certificates`, :func:`record_roa`,
:func:`record_robustness`, :func:`record_band`; an imported pair's: :func:`record_imported_certificates`). The proofs are
:mod:`drlyap.workflows.verify`'s."""

from __future__ import annotations

from pathlib import Path

import torch

from drlyap.claims.band import band_parts
from drlyap.claims.core import core_parts
from drlyap.claims.ellipsoid import ellipsoid_parts
from drlyap.claims.practical import practical_parts
from drlyap.claims.roa_ball import cored_parts, cube_parts
from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition, decay_at_shift
from drlyap.io import jsonable
from drlyap.kinds import Loss
from drlyap.regions import Region
from drlyap.runs import Run
from drlyap.runs.certificates import PairFiles, Stated, remove_certificate, write_certificate
from drlyap.verification import (
    ConditionProof,
    ProofConfig,
    ProofRules,
    RegionOfAttraction,
    RunRobustness,
    RunVerification,
    shift_box_condition,
    verify_condition,
)
from drlyap.verification.band_claim import BandProof, band_region
from drlyap.verification.roa import band_proof, ellipsoid_proof, linearisation_proofs
from drlyap.wording import faces_part

REGION_CERTIFICATES = ("roa-ball", "roa", "ellipsoid", "practical")
"""The certificates of a region of attraction: they state the region ``metrics.json`` reports
(``certificate.roa``), and are removed whenever that entry is replaced or dropped."""


def record_region(run: Run, ver: RunVerification) -> None:
    """Keep what ``ver`` proved at a shift in the run's ``metrics["certificate"]``: the region of attraction
    (``roa``), which ``drlyap plot`` draws, and on the run's own delta the decrease on the true model it rests on
    (``true_model``; at another delta the run's account of its true model and its certificate stay as they are); then
    rewrite ``metrics.json`` (atomically). The certificates of the region reported before are removed first (those of
    this one are written by :func:`record_roa`), and so is a ``true-model`` certificate that ``ver`` did not take as it
    stands (:func:`record_certificates` writes ``ver``'s). Nothing is kept of a verification without a region."""
    if ver.roa is None:
        return
    entries = region_record(ver)
    if ver.true_model is not None and float(ver.delta) == float(run.config.delta):
        _drop_true_model_certificate(run.path, ver)
    else:
        entries.pop("true_model", None)
    _remove_region_certificates(run.path)
    run.keep(entries, certificate=True)


def region_record(ver: RunVerification) -> dict:
    """What a run's ``metrics["certificate"]`` keeps of a verification with a region (``ver.roa``): the region
    (``roa``) and the decrease on the true model it rests on (``true_model``), each with the decay asked at the shift
    where it is not the run's (:func:`shift_decay`), for the checker to compare."""
    rate = shift_decay(ver)
    kept = {"roa": jsonable({**ver.roa.to_dict(), "xi": ver.roa.xi} | rate)}  # xi None: about the trained condition
    if ver.true_model is not None:
        kept["true_model"] = true_model_record(ver)
    return kept


def shift_decay(ver: RunVerification) -> dict:
    """The decay asked of the true model at the shift where it is not the run's (``roa_rate`` of
    :func:`~drlyap.workflows.verify.verify`: :func:`~drlyap.conditions.decay_at_shift`), as ``{"exp_rate",
    "decay_rate"}``; else nothing."""
    if ver.roa_rate is None:
        return {}
    gamma, alpha = decay_at_shift(0.0, 0.0, ver.roa_rate)
    return {"exp_rate": alpha, "decay_rate": gamma}


def true_model_record(ver: RunVerification) -> dict:
    """What ``metrics["certificate"]["true_model"]`` keeps of ``ver``'s decrease on the true model: its verdict and
    shift, with the decay asked there where it is not the run's (``exp_rate``); the ``true-model`` certificate, where
    there is one, states that shift and decay (:func:`record_certificates`)."""
    rate = shift_decay(ver)
    keys = ("status", "xi", "verified_fraction", "time_s", "counterexample", "counterexample_source")
    return jsonable({k: getattr(ver.true_model, k) for k in keys} | rate)


def _leaves_true_model_certificate(found) -> bool:
    """Whether a proof of the decrease on the true model leaves a ``true-model`` certificate stating it: verified,
    and with its partition (written by :func:`record_certificates`) or taken from that certificate as it stands."""
    return isinstance(found, ConditionProof) and found.verified and (
        found.partition is not None or found.source == "certificate")


def _drop_true_model_certificate(folder: Path, ver: RunVerification) -> None:
    """Remove ``folder``'s ``true-model`` certificate unless ``ver`` took it as it stands (the same claim, confirmed by
    the checker): it states another shift or decay, or a decrease ``ver`` did not prove again (a verified proof
    writes its own anew)."""
    found = ver.true_model
    if not (isinstance(found, ConditionProof) and found.verified and found.source == "certificate"):
        remove_certificate(folder, "true-model")


def _remove_region_certificates(folder: Path) -> None:
    for name in REGION_CERTIFICATES:
        remove_certificate(folder, name)


def _region_stands(reported: dict, ver: RunVerification) -> bool:
    """Whether the region a run's ``metrics["certificate"]`` reports (``reported``: its ``roa`` and ``true_model``)
    stands beside ``ver``'s decrease on the true model, where ``ver`` certified no region: a region about the trained
    condition does (its certificates rest on ``trained``); one at a shift only where ``ver`` leaves a ``true-model``
    certificate at that very shift, decay and delta, which the region's certificates may name for the decrease
    outside the ball (all that is about a shift is about one shift)."""
    region = reported.get("roa")
    if not isinstance(region, dict):
        return True
    xi = region["xi"] if "xi" in region else (reported.get("true_model") or {}).get("xi")  # older runs: see Certificate
    if xi is None:
        return True
    found = ver.true_model
    rate = None if ver.roa_rate is None else float(ver.roa_rate)
    return (_leaves_true_model_certificate(found) and [float(v) for v in xi] == [float(v) for v in found.xi]
            and region.get("exp_rate") == rate and region.get("delta") == float(ver.delta))


def _settle_true_model(folder: Path, reported: dict, ver: RunVerification) -> bool:
    """Make ``reported`` (a run's ``metrics["certificate"]``, changed in place) the account of ``ver``'s decrease on
    the true model, after removing from ``folder`` what no longer agrees with it: the ``true-model`` certificate
    (:func:`_drop_true_model_certificate`) and, where ``ver`` certified no region, a region reported at another shift
    (:func:`_region_stands`): its entry and its certificates. Returns whether ``reported`` changed."""
    _drop_true_model_certificate(folder, ver)
    changed = False
    if ver.roa is None and "roa" in reported and not _region_stands(reported, ver):
        _remove_region_certificates(folder)
        del reported["roa"]
        changed = True
    entry = true_model_record(ver)
    if reported.get("true_model") != entry:
        reported["true_model"] = entry
        changed = True
    return changed


def record_robustness(run: Run, robustness: RunRobustness) -> list[Path]:
    """Keep the certified Wasserstein radius and shift box of ``robustness`` in the run's ``metrics["certificate"]``
    (``radius``, ``shift_box``) and write their certificates where the searches' own proofs are at hand: ``radius``
    (the DR pointwise condition at r*, on the run's X_delta and level) and ``shift-box`` (decrease on the true model,
    with the run's decay, for every shift in the box at s*); a certificate of an earlier search is removed. Only on the
    run's own delta. Returns the headers' paths."""
    if float(robustness.delta) != float(run.config.delta):
        return []
    radius, box = robustness.radius, robustness.shift_box
    kept = {}
    if radius is not None and radius.radius is not None:
        kept["radius"] = jsonable({"radius": radius.radius, "risk_level": radius.risk_level,
                                   "n_samples": radius.n_samples, "delta": radius.delta, "level": radius.level,
                                   "unproved": radius.unproved, "unproved_status": radius.unproved_status})
    if box is not None and box.s is not None:
        kept["shift_box"] = jsonable({"s": box.s, "box": box.box, "scale": box.scale, "parameters": box.parameters,
                                      "delta": box.delta, "level": box.level, "unproved": box.unproved,
                                      "unproved_status": box.unproved_status})
    run.keep(kept, certificate=True)
    region = Region.of(run.system, float(robustness.delta))
    written = []
    if radius is not None and radius.radius is not None:
        if radius.proof is None:  # r* is the trained radius: the trained certificate states it
            remove_certificate(run.path, "radius")
        else:
            condition = run.sections.condition.build(run.xi_samples, Loss.POINTWISE).with_radius(radius.radius)
            written.append(write_certificate(run.path, "radius", radius.proof, Stated(condition, region), run.system,
                                             PairFiles.networks(run.path, run.config.alpha_hat)))
    if box is not None and box.s is not None:
        if box.proof is None:
            remove_certificate(run.path, "shift-box")
        else:
            condition = shift_box_condition(torch.as_tensor(box.scale, dtype=torch.float64), box.s,
                                            run.config.decay_rate, run.config.exp_rate)
            written.append(write_certificate(run.path, "shift-box", box.proof, Stated(condition, region), run.system,
                                             PairFiles.networks(run.path, run.config.alpha_hat)))
    return written


def record_certificates(run: Run, ver: RunVerification) -> list[Path]:
    """Write a certificate file (:mod:`drlyap.runs.certificates`) into the run directory for each proof of ``ver``
    that is verified on X_delta and kept its partition: ``trained``, with a shift ``true-model``, and the DR uniform
    margin at the run's radius as ``uniform`` (a run trained on the uniform condition has it as ``trained``). Only on
    the run's own delta (the claim ``drlyap check`` compares with the run). With a shift, ``metrics.json``'s
    ``certificate.true_model`` becomes the account of ``ver``'s decrease there before the certificate is written: an
    earlier ``true-model`` certificate is removed (unless ``ver`` took it as it stands), and where ``ver`` certified
    no region, so is a region reported at another shift, decay or delta, with its certificates
    (:func:`_settle_true_model`). Returns the headers' paths (an OSError where the directory cannot be written)."""
    if float(ver.delta) != float(run.config.delta):  # a certificate states the run's own X_delta (check compares)
        return []
    if ver.true_model is not None:  # metrics.json's account first, the files it no longer describes removed
        reported = run.metrics.get("certificate") or {}
        if _settle_true_model(run.path, reported, ver):
            run.keep({"true_model": reported["true_model"]}, certificate=True)
    region = Region.of(run.system, float(ver.delta))
    written = []
    uniform = None if ver.uniform is None or ver.uniform is ver.trained else ver.uniform
    for name, proof, condition in (("trained", ver.trained, run.condition),
                                   ("true-model", ver.true_model,
                                    None if ver.true_model is None else run.true_condition(ver.true_model.xi,
                                                                                           ver.roa_rate)),
                                   ("uniform", uniform, run.sections.condition.build(run.xi_samples, Loss.UNIFORM))):
        if proof is not None and proof.verified and proof.partition is not None:
            written.append(write_certificate(run.path, name, proof, Stated(condition, region), run.system,
                                             PairFiles.networks(run.path, run.config.alpha_hat)))
    return written


def record_roa(run: Run, ver: RunVerification, proof: ProofConfig) -> list[Path]:
    """Write the certificates of the region of attraction ``ver`` certified (on the run's own delta), what ``drlyap
    check`` needs to confirm it (:func:`region_certificates`), naming the run's ``trained`` or ``true-model`` for the
    decrease outside the ball where that proof is on ``{V <= c'}`` with ``c' >= c``. Returns the headers' paths."""
    roa = ver.roa
    if roa is None or float(ver.delta) != float(run.config.delta):
        return []
    if roa.error is not None:  # no region: none of an earlier one stays (record_region replaced its entry)
        _remove_region_certificates(run.path)
        return []
    condition = run.region_condition(roa.xi, ver.roa_rate)
    outer = ("trained", ver.trained) if roa.xi is None else ("true-model", ver.true_model)
    return region_certificates(run.path, run.loop, condition, Region.of(run.system, float(ver.delta)), roa, outer,
                               proof, PairFiles.networks(run.path, run.config.alpha_hat))


def region_certificates(folder: Path, loop: ClosedLoop, condition: Condition, region: Region,
                        roa: RegionOfAttraction, outer: tuple[str, ConditionProof | None], proof: ProofConfig,
                        pair: PairFiles) -> list[Path]:
    """Write into ``folder`` the certificates of a region of attraction ``roa`` of ``condition``, by its route:

    * V's own proofs: ``roa-ball``, V's decrease on ``{V <= c}`` inside the delta-ball (the second-order cube and the
      ring's partition), naming the certificate of the decrease outside the ball (:func:`_outer_certificate`);
    * the closed loop's linearisation: ``ellipsoid`` (the ellipsoid ``L`` it rests on) and ``roa-ball``, V's strict
      decrease inside the ball's box except in ``L`` (its ``core``), naming the one outside the ball as above;
    * the band proof: ``roa``, V's strict decrease on ``{V <= c}`` over the box except in ``L`` (``core``), beside
      ``ellipsoid``;
    * practical stability: ``practical``, V at most ``c0`` on the delta-ball, naming the decrease outside it as above.

    Where the closed loop's own quadratic region is certified (``roa.quadratic``), ``ellipsoid`` states it. The proofs
    are made again with their partitions kept (``proof``'s budget); where one does not hold again, its certificates
    are not written. Certificates of an earlier region are removed first. ``pair``: the files of the pair they are
    about. Returns the headers' paths."""
    for name in ("roa-ball", "roa", "ellipsoid", "practical"):
        remove_certificate(folder, name)
    written: list[Path] = []

    def write(name, found, cond, where, level=None, parts=None):
        written.append(write_certificate(folder, name, found, Stated(cond, where, level=level, parts=parts),
                                         loop.system, pair))

    def write_ellipsoid(found):
        write("ellipsoid", found.ring, found.condition, found.region, found.level,
              ellipsoid_parts(found.p.tolist(), found.level, found.box.tolist(), found.tau.tolist(),
                              found.ring is not None))

    if roa.ellipsoid_certified:
        found = ellipsoid_proof(loop, condition, region, roa.quadratic.ellipsoid(), proof.budget())
        if found is not None:
            write_ellipsoid(found)
    if (roa.kind == "practical stability" and roa.level is not None and roa.practical_level is not None
            and condition.per_sample() is not None):  # a statement about each sample's trajectories
        outer_name = _outer_certificate(write, loop, condition, region, float(roa.level), outer, proof, roa.faces)
        if outer_name is not None:  # V at most c0 on the ball: the checker bisects the ball itself
            write("practical", None, condition.per_sample(), region.ball_box(region.delta), float(roa.level),
                  practical_parts(region.delta, outer_name, float(roa.practical_level), roa.faces))
        return written
    if not roa.certified or roa.level is None:
        return written
    c = float(roa.level)
    if roa.method == "band":
        cored = band_proof(loop, condition, region, roa.local, proof.budget())
        if cored is not None and "ellipsoid.json" in {p.name for p in written}:
            write("roa", cored.proof, cored.condition, cored.region, parts=core_parts(cored.p.tolist(), cored.q_level))
        return written
    if roa.method == "linearisation":
        found = linearisation_proofs(loop, condition, region, roa.local, proof.budget())
        if found is None:
            return written
        ellipsoid, cored = found
        outer_name = _outer_certificate(write, loop, condition, region, c, outer, proof, roa.faces)
        if outer_name is not None:
            write_ellipsoid(ellipsoid)
            write("roa-ball", cored.proof, cored.condition, cored.region,
                  parts=cored_parts(region.delta, outer_name, core_parts(cored.p.tolist(), cored.q_level)))
        return written
    if roa.ball is None:
        return written
    outer_name = _outer_certificate(write, loop, condition, region, c, outer, proof, roa.faces)
    if outer_name is None:
        return written
    ball = roa.ball
    parts = cube_parts(region.delta, ball.cube, outer_name)
    if ball.ring is None:  # the cube covers the ball: the claim is the cube's alone
        write("roa-ball", None, condition.per_sample(), region.ball_box(region.delta), c, parts)
    else:
        write("roa-ball", ball.ring, ball.condition, ball.region, parts=parts)
    return written


def _outer_certificate(write, loop: ClosedLoop, condition: Condition, region: Region, level: float,
                       outer: tuple[str, ConditionProof | None], proof: ProofConfig, faces: str = "above") -> str | None:
    """The name of the certificate of ``condition`` on ``{V <= level}`` outside the delta-ball that a ``roa-ball``
    names: ``outer``'s (its name and proof) where that proof is on ``{V <= c'}`` with ``c' >= level`` (V above ``c'``
    on the faces), else ``roa``, proved here (``proof``'s budget) and written with ``write``, its claim stating how
    the set keeps off the faces (``faces``: the region's); None where that proof fails."""
    outer_name, found = outer
    if (isinstance(found, ConditionProof) and found.verified and found.level is not None and found.level >= level
            and (found.partition is not None or found.source == "certificate")):
        return outer_name
    found = verify_condition(loop, condition, region, proof.budget(), level=level, rules=ProofRules(keep_partition=True))
    if not found.verified:
        return None
    write("roa", found, condition, region, parts=faces_part(faces) or None)
    return "roa"


def record_imported_certificates(run_dir: str | Path, pair, ver: RunVerification, proof: ProofConfig) -> list[Path]:
    """Write the certificates of what :func:`~drlyap.workflows.verify.verify_imported` proved about an imported pair,
    naming the pair by its ``graphs.json`` and ``tensors.pt`` (the checker reads those as data): ``true-model`` for
    its verified decrease at the shift, and with a region of attraction certified by V's own proofs its ``roa-ball``
    (and ``roa``: :func:`region_certificates`), whose level, shift and decay are kept in the run's ``metrics.json``
    (:func:`region_record`) for the checker to compare, beside the decrease at the shift (``true_model``), as for a
    run (:func:`record_region`, :func:`record_certificates`): the files the new account no longer describes are
    removed first. On a delta other than the pair's (where its export states one) no certificate is written, and only
    a region is kept. Returns the headers' paths."""
    import json

    from drlyap.io import write_json_atomic

    run_dir = Path(run_dir)
    system = pair.loop.system
    found = ver.true_model
    condition = pair.true_condition(system.check_xi(found.xi)[None], ver.roa_rate)
    region = Region.of(system, float(ver.delta))
    own = pair.delta is None or float(ver.delta) == float(pair.delta)  # the checker compares a stated delta
    metrics = json.loads((run_dir / "metrics.json").read_text())
    reported = dict(metrics.get("certificate") or {})
    if own:
        _settle_true_model(run_dir, reported, ver)
    if ver.roa is not None:
        _remove_region_certificates(run_dir)
        reported["roa"] = region_record(ver)["roa"]
    metrics["certificate"] = reported
    write_json_atomic(run_dir / "metrics.json", metrics)
    if not own:
        return []
    written = []
    if isinstance(found, ConditionProof) and found.verified and found.partition is not None:
        written.append(write_certificate(run_dir, "true-model", found, Stated(condition, region), system,
                                         PairFiles.imported(run_dir)))
    else:
        found = None
    if ver.roa is not None and ver.roa.error is None:
        written += region_certificates(run_dir, pair.loop, condition, region, ver.roa, ("true-model", found), proof,
                                       PairFiles.imported(run_dir))
    return written


def record_band(folder: Path, system, found: BandProof | None, pair: PairFiles) -> list[Path]:
    """Write the ``band`` certificate of ``found`` (a proof made now: its ``asked`` condition is the claim's) where it
    is verified, about the pair in ``pair``'s files. The
    claim is its own (its shift, levels and decay are in the file), so nothing of ``metrics.json`` is touched, and a
    band certificate of other levels stays until a verified one replaces it. Returns the header's path, if any."""
    if found is None or not found.verified or found.decrease.partition is None:
        return []
    region = band_region(Region.of(system, 0.0))
    return [write_certificate(folder, "band", found.decrease,
                              Stated(found.asked, region, parts=band_parts(found.low)), system,
                              pair)]
