"""Proving what a run directory holds: its trained condition, the uniform DR margin, the decrease on the true model
at a shift, its certified region of attraction (:func:`verify`), its robustness (:func:`run_robustness`) and
the Lipschitz covering check (:func:`run_covering`). The proofs themselves are :mod:`drlyap.verification`'s; this
module picks the run's conditions, region and proof settings."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition
from drlyap.kinds import Enclosure, Loss, Method, Status
from drlyap.regions import Region
from drlyap.runs import Run
from drlyap.runs.certificates import certificate_partition
from drlyap.verification import (
    Budget,
    ConditionProof,
    CoveringCheck,
    ProofConfig,
    RegionOfAttraction,
    RunRobustness,
    RunVerification,
    SearchLimits,
    certified_radius,
    certified_roa,
    certified_shift_box,
    lipschitz_covering,
    prove_trained,
    shift_scale,
    uniform_margin,
)
from drlyap.verification.band_claim import BandProof, band_request, prove_band
from drlyap.verification.roa import REGION_RATE, region_rate
from drlyap.verification.robustness import SEARCH_BUDGET

CHECKPOINTS = "checkpoints"
"""The folder of a run directory where its long proofs keep their progress while they run."""


def run_checkpoints(run: Run) -> str | None:
    """Where ``run``'s proofs keep their checkpoints (``RUN/checkpoints``), or None when the run directory cannot be
    written (its proofs then do not resume)."""
    import os

    return str(run.path / CHECKPOINTS) if os.access(run.path, os.W_OK) else None


def clear_checkpoints(run: Run) -> None:
    """Remove ``run``'s checkpoints once the command that proved them has ended (its results are recorded)."""
    import shutil

    shutil.rmtree(run.path / CHECKPOINTS, ignore_errors=True)


def run_proof(run: Run, proof: ProofConfig | None = None) -> ProofConfig:
    """The proof settings for ``run``, resolved for its system: ``proof``, else those the run was trained with,
    else the defaults."""
    return (proof or run.proof or ProofConfig()).resolved(run.system)


def _region(run: Run, delta: float | None) -> Region:
    delta = float(run.config.delta if delta is None else delta)
    if not (math.isfinite(delta) and delta >= 0):
        raise ValueError(f"delta must be finite and >= 0, got {delta}")
    return Region.of(run.system, delta)


def confirmed_certificate(run: Run, name: str, condition, region: Region, level: float | None,
                          proof: ProofConfig) -> ConditionProof | None:
    """The verdict of the run's certificate file ``name`` (``trained`` or ``true-model``) when it states exactly this
    claim (the condition with its samples or shift, the region, the level), is about the run's own weights and
    system, and the checker (:mod:`drlyap.checker`, its own arithmetic, where ``proof`` says) confirms it, now or in a
    record of these very files (:mod:`drlyap.checker.record`): a verified :class:`ConditionProof` with ``source``
    ``certificate``; None otherwise (the caller then proves it anew)."""
    import hashlib

    from drlyap.checker.check import LeafSettings, check_certificate
    from drlyap.checker.record import fingerprint, recorded, write_record
    from drlyap.runs.certificates import FOLDER, certificate_claim, read_certificate, system_digest
    from drlyap.runs.validate import load_weights

    if not (run.path / FOLDER / f"{name}.json").is_file() or not (run.path / "weights.pt").is_file():
        return None
    try:
        header, arrays = read_certificate(run.path, name)
    except ValueError:
        return None
    claim = dict(header.get("claim") or {})
    claim.pop("statement", None)
    if claim != certificate_claim(condition, region, level):
        return None
    data = (run.path / "weights.pt").read_bytes()
    weights_sha, system_sha = hashlib.sha256(data).hexdigest(), system_digest(run.system)
    prints = fingerprint(run.path, name, header, weights_sha, system_sha)
    record = recorded(run.path, name, prints)
    faces = None  # V's least value on the faces, as the checker bounded it (never the header's own number)
    if record is not None and (level is None or isinstance(record.get("faces_min"), (int, float))):
        leaves, seconds, when, faces = int(record["leaves"]), 0.0, str(record.get("date")), record.get("faces_min")
    else:
        result = check_certificate(name, header, arrays, run.system, load_weights(run.path / "weights.pt", data),
                                   weights_sha, system_sha, LeafSettings(compute=proof.compute))
        if not result.ok:
            return None
        write_record(run.path, name, prints, result.proved, result.time_s, result.faces_min)
        leaves, seconds, when, faces = result.proved, result.time_s, None, result.faces_min
    counts = (header.get("proof") or {})
    return ConditionProof(condition=condition.label, status=Status.VERIFIED, verified_fraction=1.0, delta=region.delta,
                          boxes_processed=int(counts.get("boxes_processed") or 0), boxes_verified=leaves,
                          time_s=seconds, stopped="finished", level=level,
                          boundary_min_lower=faces if level is not None else None,
                          source="certificate", checked_at=when)


@dataclass(frozen=True)
class VerifyRequest:
    """What :func:`verify` (or :func:`verify_imported`) is asked to prove about a run, apart from how (its
    :class:`~drlyap.proof_settings.ProofConfig`).

    ``delta``: the radius of the ball around x* left out of the region X_delta (None: the run's); ``xi``: a shift
    ``(k,)`` of the true model at which plain decrease is proved too (None: none; an imported pair needs one);
    ``roa``: also certify a region of attraction; ``uniform``: also bound the uniform DR margin (a trained run only);
    ``above_level``: whether the region-of-attraction search goes above the level the run was trained for;
    ``roa_rate``: with ``xi`` or ``band``, the decay ``alpha`` asked at the shift (None: what a region of attraction
    needs, :func:`~drlyap.verification.roa.region_rate`); ``band``: ``(c1, c2)``, prove the band claim instead.
    """

    delta: float | None = None
    xi: Sequence[float] | Tensor | None = None
    roa: bool = False
    uniform: bool = False
    above_level: bool = True
    roa_rate: float | None = None
    band: tuple[float, float] | None = None


def verify(run: Run, proof: ProofConfig | None = None, request: VerifyRequest = VerifyRequest(), *,
           reprove: bool = False) -> RunVerification:
    """Verify a loaded run (:func:`drlyap.runs.load_run`) on X_delta (``request.delta``: the run's by default).

    ``trained``: the run's own condition (pointwise / nominal by :func:`~drlyap.verification.prove_trained`, uniform by
    :func:`~drlyap.verification.uniform_margin`); with ``request.uniform``, the uniform DR margin at the run's radius,
    risk level and samples (the trained condition itself for a run trained on it); with ``request.xi``,
    ``true_model``: plain decrease on the true model at that shift; with ``request.roa``, the certified region of
    attraction of the main condition (the true model's when ``xi`` is given) within ``proof.roa_budget()`` (boxes, not
    seconds). A run trained for a region of attraction (``config.roa_level``) has its trained and true-model
    conditions proved on ``{V <= roa_level}`` with V above the level on the box's faces; the region-of-attraction
    search goes on above that level (``request.above_level`` False: at most that level, the claim the run was trained
    for). ``proof``: the settings (:func:`run_proof`). A condition whose certificate file states the same claim and is
    confirmed by the checker is not proved again (:func:`confirmed_certificate`), unless ``reprove``.
    ``request.roa_rate``: with ``xi``, the decay ``alpha`` of the true model's decrease ``Vdot + alpha V <= 0`` proved
    there and asked of its region (None: what a region of attraction needs, a strict decrease,
    :func:`~drlyap.verification.roa.region_rate`).

    ``request.band``: ``(c1, c2)``, prove the band claim there instead (:func:`band_verification`) at ``xi`` (the
    system's test shift where None) beside the trained condition; no true-model decrease on X_delta, no region.
    """
    _check_request(request)
    cfg, loop, xi = run.config, run.loop, request.xi
    band = band_request(request.band, request.roa)
    roa_rate = _shift_rate(request.roa_rate, xi is not None or band is not None, cfg)
    proof = run_proof(run, proof)
    region = _region(run, request.delta)
    level = cfg.roa_level
    own_region = not reprove and float(region.delta) == float(cfg.delta)  # a certificate file may state this claim
    trained, margin = _trained(run, proof, region, own_region, request.uniform)
    true_model, main_condition = None, run.condition
    if band is not None:
        found = band_verification(loop, run.true_condition, region, band, proof, xi, roa_rate)
        return _run_verification(run, region, proof, trained=trained, uniform=margin, band=found,
                                 roa_rate=found.exp_rate)
    if xi is not None:
        main_condition = run.true_condition(xi, roa_rate)
        true_model = confirmed_certificate(run, "true-model", main_condition, region, level, proof) \
            if own_region else None
        if true_model is None:
            true_model = prove_trained(loop, main_condition, region, proof.budget(), level,
                                       falsify_starts=proof.settle_starts)
        true_model.xi = main_condition.xi[0].tolist()
    region_of_attraction = None
    if request.roa:
        roa_condition = main_condition if main_condition.per_state else run.region_condition()
        outer = trained if true_model is None else true_model
        if roa_condition is None:
            region_of_attraction = RegionOfAttraction.unavailable(
                "the uniform DR condition with eps N > 1 implies no decrease at each sample (its CVaR is not their "
                "maximum); no sublevel-set certificate")
        else:
            proved = outer if isinstance(outer, ConditionProof) else None
            region_of_attraction = _region_of_attraction(loop, roa_condition, region, proof, level, proved,
                                                         request.above_level)
            if true_model is not None:
                region_of_attraction.xi = true_model.xi
    return _run_verification(run, region, proof, trained=trained, uniform=margin, true_model=true_model,
                             roa=region_of_attraction, roa_rate=roa_rate)


def _check_request(request) -> None:
    """A TypeError where ``request`` is not a :class:`VerifyRequest` (say, proof settings given in its place)."""
    if not isinstance(request, VerifyRequest):
        raise TypeError(f"request must be a VerifyRequest (what is proved), got {type(request).__name__}")


def _trained(run: Run, proof: ProofConfig, region: Region, own_region: bool, uniform: bool) -> tuple:
    """The proofs of the run's trained condition and of the uniform DR margin (None where not asked): by the
    confirmed certificate of the same claim where ``own_region`` allows one, else proved anew."""
    condition, loop = run.condition, run.loop
    if condition.name == Loss.UNIFORM:
        trained = uniform_margin(loop, condition, region, proof.budget(), keep_partition=True)
        return trained, trained
    level = run.config.roa_level
    trained = confirmed_certificate(run, "trained", condition, region, level, proof) if own_region else None
    if trained is None:
        trained = prove_trained(loop, condition, region, proof.budget(), level, falsify_starts=proof.settle_starts)
    margin = None
    if uniform:
        margin = uniform_margin(loop, run.sections.condition.build(run.xi_samples, Loss.UNIFORM), region,
                                proof.budget(proof.uniform_time), keep_partition=True)
    return trained, margin


def _run_verification(run: Run, region: Region, proof: ProofConfig, **found) -> RunVerification:
    """A trained run's :class:`RunVerification` of what was ``found`` on ``region``."""
    cfg = run.config
    return RunVerification(run_dir=str(run.path), system=run.system.name, method=cfg.method,
                           loss=cfg.loss if cfg.method == Method.DR else None, delta=region.delta,
                           enclosure=proof.enclosure, **found)


def band_verification(loop: ClosedLoop, true_condition, region: Region, band: tuple[float, float],
                      proof: ProofConfig, xi: Sequence[float] | Tensor | None, rate: float | None) -> BandProof:
    """The band claim ``band = (c1, c2)`` (:func:`~drlyap.verification.band_claim.prove_band`) on the true model at
    ``xi`` (the system's test shift where None) with the decay ``rate V`` (:data:`REGION_RATE` where None),
    ``true_condition(xi, rate)`` building the condition, within ``proof.budget()``."""
    system = loop.system
    if xi is None and system.test_xi is None:
        raise ValueError(f"a band claim is about the true model at a shift: give --xi ({system.k} values)")
    shift = system.check_xi(xi if xi is not None else list(system.test_xi))
    condition = true_condition(shift, REGION_RATE if rate is None else float(rate))
    return prove_band(loop, condition, region, *band, proof.budget(), falsify_starts=proof.settle_starts)


def _shift_rate(roa_rate: float | None, at_shift: bool, decay) -> float | None:
    """The decay alpha asked of the true model at a shift: ``roa_rate``, refused where it is not a finite number > 0 or
    comes without a shift (``at_shift`` False); None: :func:`~drlyap.verification.roa.region_rate` of ``decay``'s."""
    if roa_rate is not None and not (at_shift and math.isfinite(roa_rate) and roa_rate > 0):
        raise ValueError(f"roa_rate must be > 0 and given with a shift (xi), got {roa_rate}"
                         + ("" if at_shift else " without one"))
    if roa_rate is None and at_shift:
        return region_rate(float(decay.decay_rate or 0.0), float(decay.exp_rate or 0.0))
    return roa_rate


def _region_of_attraction(loop: ClosedLoop, condition: Condition, region: Region, proof: ProofConfig,
                          level: float | None, proved: ConditionProof | None, above_level: bool) -> RegionOfAttraction:
    """``certified_roa`` in ``proof.roa_budget()``, up to ``level`` (``proved`` there) unless ``above_level``."""
    return certified_roa(loop, condition, region, proof.roa_budget(),
                         max_level=math.inf if level is None or above_level else float(level),
                         band_time=proof.band_time, proved=None if above_level else proved)


def verify_imported(pair, run_dir: str, proof: ProofConfig | None = None, *, request: VerifyRequest) -> RunVerification:
    """Verify an imported pair (:class:`drlyap.runs.imported.ImportedPair`, ``drlyap import``): plain decrease on the
    true model at the shift ``request.xi (k,)`` (required) with the pair's decay, on X_delta (``request.delta``: the
    pair's, from the export of a drlyap run, else the system's default), by the same proof as for a trained run's
    ``--xi``: on ``{V <= level}`` with V above the level on the box's faces for a pair exported from a run trained for
    a region of attraction (and with ``request.roa`` its certified region of attraction there, above that level as for
    its run; ``request.above_level`` False: at most that level). An imported pair has no trained condition
    (``trained`` is None; ``request.uniform`` is refused). ``request.roa_rate``: the decay ``alpha`` asked at the
    shift, of the decrease and of its region (None: :func:`~drlyap.verification.roa.region_rate` of the pair's).
    ``request.band``: ``(c1, c2)``, prove the band claim at ``xi`` instead (:func:`band_verification`), what the
    field's pairs claim: no decrease down to x*, no region; about V as the file gives it (not pinned at x*: the levels
    are in its own units)."""
    _check_request(request)
    if request.xi is None or request.uniform:
        raise ValueError("an imported pair has no trained condition: its request needs a shift xi and no uniform margin")
    xi = request.xi
    band = band_request(request.band, request.roa)
    if band is None and not pair.pinned:
        raise ValueError("the pair's V is not least at x* (imported as given): it claims no decrease down to x* and no "
                         "region of attraction of x*; prove the claim it can state, on a band: --band C1,C2")
    roa_rate = _shift_rate(request.roa_rate, True, pair)
    loop = pair.loop
    system = loop.system
    proof = (proof or ProofConfig()).resolved(system)
    delta = request.delta
    if delta is None:
        delta = system.defaults.delta if pair.delta is None else pair.delta
    region = Region.of(system, float(delta))
    level = pair.level
    if band is not None:
        found = band_verification(pair.given_loop, lambda shift, rate: pair.true_condition(shift[None], rate), region,
                                  band, proof, xi, roa_rate)
        return RunVerification(run_dir=str(run_dir), system=system.name, method="imported", loss=None,
                               delta=region.delta, enclosure=proof.enclosure, trained=None, band=found,
                               roa_rate=found.exp_rate)
    condition = pair.true_condition(system.check_xi(xi)[None], roa_rate)
    true_model = prove_trained(loop, condition, region, proof.budget(), level, falsify_starts=proof.settle_starts)
    true_model.xi = condition.xi[0].tolist()
    region_of_attraction = None
    if request.roa:
        region_of_attraction = _region_of_attraction(loop, condition, region, proof, level, true_model,
                                                     request.above_level)
        region_of_attraction.xi = true_model.xi
    return RunVerification(run_dir=str(run_dir), system=system.name, method="imported", loss=None, delta=region.delta,
                           enclosure=proof.enclosure, trained=None, true_model=true_model, roa=region_of_attraction,
                           roa_rate=roa_rate)


def run_robustness(run: Run, delta: float | None = None, tol: float = 0.01, budget: Budget = SEARCH_BUDGET,
                   total_time: float = 120.0, scale: Tensor | None = None,
                   trained: ConditionProof | None = None) -> RunRobustness:
    """:func:`~drlyap.verification.certified_radius` of the DR pointwise condition at the run's samples (all N, also
    for a baseline run, which trained on their mean), risk level and decay (its configured radius is only a start
    of the search), and :func:`~drlyap.verification.certified_shift_box` with the run's decay (``scale`` default
    :func:`~drlyap.verification.shift_scale` of the run's samples), over the run's X_delta (``delta`` default the
    run's; for a region-of-attraction run over its sublevel set ``{V <= roa_level}``); ``budget`` of each proof,
    ``total_time`` seconds of each search. ``trained``: the run's trained condition's proof, if at hand: where it is
    verified for a DR pointwise run on this region, the radius search starts at the run's radius (that proof is one of
    the search's), and both searches start from its partition. For a baseline run also the radius of the DR condition
    around the single sample it trained on
    (``run.xi_train``, N = 1)."""
    cfg, system, loop = run.config, run.system, run.loop
    region = _region(run, delta)
    level = cfg.roa_level  # a region-of-attraction run claims its conditions on {V <= level} only
    condition = run.sections.condition.build(run.xi_samples, Loss.POINTWISE)
    same = (cfg.method == Method.DR and cfg.loss == Loss.POINTWISE and isinstance(trained, ConditionProof) and trained.verified
            and float(trained.delta) == float(region.delta) and trained.level == level)
    start = None
    if same:  # the trained proof's partition: the search's proofs above the run's radius start from it
        start = trained.partition if trained.partition is not None else certificate_partition(run.path, "trained")
    limits = SearchLimits(tol=tol, total_time=total_time)
    radius = certified_radius(loop, condition, region, budget, limits=limits, level=level,
                              proved=cfg.wasserstein_radius if same else None, start=start)
    scale = shift_scale(system, run.xi_samples) if scale is None else scale
    box = certified_shift_box(loop, region, scale, budget, decay=(cfg.decay_rate, cfg.exp_rate), limits=limits,
                              level=level, start=start)
    own = None
    if cfg.method == Method.BASELINE:  # also around the one sample it trained on (the mean: a ball around a point mass)
        own = certified_radius(loop, run.sections.condition.build(run.xi_train, Loss.POINTWISE), region, budget,
                               limits=limits, level=level)
    return RunRobustness(method=cfg.method, trained_radius=cfg.wasserstein_radius if cfg.method == Method.DR else None,
                         delta=region.delta, radius=radius, shift_box=box, radius_training_sample=own)


def run_covering(run: Run, spacing: float | None = None, xi: Sequence[float] | Tensor | None = None,
                 compare_seconds: float = 0.0, n_samples: int = 20000) -> CoveringCheck:
    """The Lipschitz covering check (:func:`~drlyap.verification.lipschitz_covering`) of the run's trained condition,
    or with ``xi`` of plain decrease on the true model there, on the run's X_delta; with ``compare_seconds`` the
    branch and bound (mean-value form) on the same condition beside it."""
    condition = run.condition if xi is None else run.true_condition(xi)
    compare = Budget(seconds=compare_seconds, enclosure=Enclosure.MEAN_VALUE) if compare_seconds > 0 else None
    return lipschitz_covering(run.loop, condition, _region(run, None), spacing=spacing, n_samples=n_samples,
                              compare=compare)
