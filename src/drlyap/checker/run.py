"""Re-check the certificates of a run directory (``drlyap check RUN``): read the run as data, check each certificate
(:func:`~drlyap.checker.check.check_certificate`) with the certificates it rests on, ask whether each claim is the
run's (:mod:`~drlyap.checker.agreement`), and record what the checker confirmed (:mod:`~drlyap.checker.record`). A
claim that rests on another certificate (a ``roa-ball`` on the decrease outside the ball, a region on its core's
ellipsoid) is confirmed only where that one is too: asking for it checks that one as well.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import torch

from drlyap.checker.agreement import claim_mismatch, core_missing, outer_missing
from drlyap.checker.check import REFINE, LeafSettings, check_certificate
from drlyap.checker.levels import outside_positive
from drlyap.checker.quadratic import surely_semidefinite
from drlyap.checker.reading import CertificateError, CheckResult, claim_box, pair_of
from drlyap.checker.record import drop_record, fingerprint, write_record
from drlyap.claims.registry import kinds_stating
from drlyap.compute import Compute


def check_run(run_dir: str | Path, system=None, trust: bool = False, names: list[str] | None = None,
              refine: int = REFINE, compute: Compute = Compute(), pieces_per_leaf: float = 1.0) -> list[CheckResult]:
    """Re-check the certificates of a run directory (``names``: which; default every one it holds). ``system`` and
    ``trust``: as for :func:`drlyap.runs.load_run` (a system from a file runs only when named or trusted); the rest:
    as for :func:`check_certificate`. A run without certificates is a ValueError that says so."""
    from drlyap.runs.certificates import FOLDER, NAMES, networks_digest, read_certificate, system_digest
    from drlyap.runs.reading import read_run_json, read_run_kind, run_system
    from drlyap.runs.validate import RunDirError, load_weights

    run_dir = Path(run_dir)
    imported = read_run_kind(run_dir).get("kind") == "imported"
    info, config, metrics = read_run_json(run_dir, "imported" if imported else "lyapunov", "run.json", "config.json",
                                          "metrics.json")
    system = run_system(run_dir, str(config.get("system")), system, info, trust)
    present = [k for k in NAMES if (run_dir / FOLDER / f"{k}.json").is_file()]
    names = present if names is None else names
    if not names:
        raise ValueError(f"{run_dir} holds no certificate ({run_dir / FOLDER} is empty or missing): a verified "
                         "`drlyap train` or `drlyap verify` writes one")
    files = [run_dir / "graphs.json", run_dir / "tensors.pt"] if imported else [run_dir / "weights.pt"]
    try:
        contents = [f.read_bytes() for f in files]  # read once: the bytes hashed are the bytes checked
    except FileNotFoundError as err:
        raise RunDirError(f"{err.filename} is missing") from None
    if imported:  # the graphs as data (JSON) and their constants (tensors only)
        try:
            graphs = json.loads(contents[0])
        except (UnicodeDecodeError, json.JSONDecodeError) as err:
            raise RunDirError(f"{files[0]} is damaged: {err}") from None
        weights = {"graphs": graphs, "tensors": load_weights(files[1], contents[1])}
    else:
        weights = load_weights(files[0], contents[0])
    digest, system_sha = networks_digest(contents), system_digest(system)
    names = _with_premises(run_dir, list(names), NAMES)
    results: dict[str, CheckResult] = {}
    headers: dict[str, dict] = {}
    for name in names:
        header, arrays = read_certificate(run_dir, name)
        result = check_certificate(name, header, arrays, system, weights, digest, system_sha,
                                   LeafSettings(refine, compute, pieces_per_leaf))
        result.failures += claim_mismatch(name, header, config, metrics)
        if _rests_on_outer(name) or (header.get("claim") or {}).get("outer") is not None:
            result.failures += outer_missing(run_dir, header, _positive_outside(result, weights, header, system))
        if (header.get("claim") or {}).get("core") is not None:
            result.failures += core_missing(run_dir, header)
        results[name], headers[name] = result, header
    for name in names:  # a claim holds only where the certificates it rests on are confirmed too
        result = results[name]
        result.failures += [f"it rests on {theirs}, which the checker did not confirm"
                            for theirs in _premises(headers[name]) if theirs not in results or not results[theirs].ok]
        result.ok = not result.failures
        if result.ok:
            write_record(run_dir, name, fingerprint(run_dir, name, headers[name], digest, system_sha), result.proved,
                         result.time_s, result.faces_min)
        else:
            drop_record(run_dir, name)
    return [results[name] for name in names]


def _rests_on_outer(name: str) -> bool:
    """Whether every kind the file ``name`` may state rests on a decrease outside the ball (``outer``): its claim must
    name one, checked even where it names none."""
    kinds = kinds_stating(name)
    return bool(kinds) and all("outer" in k.rests_on for k in kinds)


def _premises(header: dict) -> list[str]:
    """The certificates a claim rests on: the decrease outside the ball (``outer``) and its core's ellipsoid."""
    claim = header.get("claim") or {}
    names = [claim.get("outer"), (claim.get("core") or {}).get("certificate")]
    return [n for n in names if isinstance(n, str)]


def _with_premises(run_dir: Path, names: list[str], known: tuple[str, ...]) -> list[str]:
    """``names`` and, before each, the certificates it rests on (:func:`_premises`, read from the headers; those not
    there are left to the claim's own check, which fails on them), each once."""
    from drlyap.runs.certificates import FOLDER

    out: list[str] = []

    def add(name: str, seen: tuple[str, ...]) -> None:
        if name in out or name in seen:
            return
        try:
            header = json.loads((run_dir / FOLDER / f"{name}.json").read_text())
        except (OSError, ValueError):
            header = {}
        for theirs in _premises(header if isinstance(header, dict) else {}):
            if theirs in known and (run_dir / FOLDER / f"{theirs}.json").is_file():
                add(theirs, (*seen, name))
        out.append(name)

    for name in names:
        add(name, ())
    return out


def _positive_outside(out: CheckResult, weights: dict, header: dict, system) -> Callable[[dict], str]:
    """For :func:`~drlyap.checker.agreement.outer_missing`: ``V > 0`` on an outer claim's region (its state box minus
    its open delta-ball) by the checker's bisection (:func:`~drlyap.checker.levels.outside_positive`, recorded in
    ``out``); "" where it holds, else why not."""

    def positive(region: dict) -> str:
        start = time.perf_counter()
        try:
            lo, hi = claim_box(region, system)
            pair, delta = pair_of(weights, header, system.n), float(region["delta"])
        except (CertificateError, KeyError, TypeError, ValueError) as err:
            return f"V > 0 outside the ball cannot be checked ({err})"
        p = getattr(pair, "p", None)  # the quadratic V of a controller imported alone: positive definite by its P
        if p is not None and bool(torch.equal(p, p.T)) and bool(surely_semidefinite(p)):
            return ""
        holds, out.positive_min, out.positive_boxes = outside_positive(pair, lo, hi, delta)
        out.time_s += time.perf_counter() - start
        return "" if holds else (f"V > 0 outside the ball is not established (V's smallest lower bound there "
                                 f"{out.positive_min:.6g}, {out.positive_boxes} boxes)")

    return positive
