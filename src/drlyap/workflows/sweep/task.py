"""One combination of a sweep, start to end (:func:`run_combination`, the task a backend runs):

1. trains the pair as ``drlyap train`` does (:func:`drlyap.train`: counterexample-guided rounds until the trained
   condition is proved, at most ``verify_rounds``; ``verify=False`` skips them);
2. saves it as a run directory (:func:`drlyap.runs.save_run`) in a staging folder;
3. verifies it (:func:`drlyap.workflows.verify.verify` at the system's test shift with ``roa=True``): the
   trained condition over X_delta, the plain decrease on the true model at the test shift, and the certified region
   of attraction there;
4. evaluates it on the true model at k x the test shift (:func:`drlyap.workflows.reproduce.evaluate_run`) from the
   seed's evaluation states (:func:`drlyap.workflows.reproduce.test_initial_states`);
5. writes ``result.json`` (the row, the sha256 of ``weights.pt`` and of the grid) into the run directory and renames
   the staging folder to ``OUT/<combination>/`` by a rename that never replaces a directory already there: a
   combination directory exists only when it is complete.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import time
import traceback
from pathlib import Path

import torch

from drlyap.io import jsonable, write_json
from drlyap.runs import load_run, save_run
from drlyap.runs.publish import rename_noreplace
from drlyap.systems import resolve_system, system_source
from drlyap.training import train
from drlyap.verification import ProofConfig, RunVerification
from drlyap.workflows.reproduce import evaluate_run, test_initial_states
from drlyap.workflows.sweep.grid import RESULT_FILE, STAGING, Combination, SweepSpec
from drlyap.workflows.verify import VerifyRequest, verify


def verification_row(ver: RunVerification) -> dict:
    """The columns a sweep keeps of a run's verification at the test shift."""
    roa = ver.roa
    certified = roa is not None and roa.certified
    return {
        "trained_condition": ver.trained.status,
        "trained_verified_fraction": ver.trained.verified_fraction,
        "test_decrease": None if ver.true_model is None else ver.true_model.status,
        "test_verified_fraction": None if ver.true_model is None else ver.true_model.verified_fraction,
        "roa_certified": certified,
        "roa_share": float(roa.share_of_box) if certified else 0.0,
        "verify_time_s": sum(float(v.time_s or 0.0) for v in (ver.trained, ver.true_model) if v is not None),
    }


def file_sha256(path: Path) -> str:
    """The sha256 of a file's bytes (hex)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def spec_sha256(spec_dict: dict) -> str:
    """The sha256 of a grid (its canonical JSON): recorded with every finished combination, so that a damaged
    ``sweep.json`` can be rebuilt from the combinations on disk."""
    return hashlib.sha256(json.dumps(jsonable(spec_dict), sort_keys=True).encode()).hexdigest()


def staging_dir(out: Path, name: str) -> Path:
    """Where this process writes combination ``name`` before publishing it (one folder per process, so that a
    worker left over from a killed sweep never writes into the folder of a running one)."""
    return Path(out) / STAGING / f"{name}.{os.getpid()}"


def run_combination(spec_dict: dict, combo_dict: dict, out: str, threads: int = 1) -> dict:
    """Train, save, verify and evaluate one combination into ``out/<name>/`` (the worker's task).

    Never raises: a failure comes back as a row with ``status = "failed"``, the error and the last
    lines of its traceback. Returns the row (also written to ``out/<name>/result.json`` on success).
    """
    torch.set_num_threads(threads)
    spec, combo = SweepSpec.from_dict(spec_dict), Combination(**combo_dict)
    row: dict = {"name": combo.name, **dataclasses.asdict(combo)}
    tic = time.perf_counter()
    staging = staging_dir(Path(out), combo.name)
    try:
        system = resolve_system(spec.system)
        result = train(spec.train_config(combo, system), system, spec.proof(), progress=False, warn=False)
        if staging.exists():
            shutil.rmtree(staging)
        save_run(staging, result, source=system_source(spec.system, system))
        run = load_run(staging, system)
        xi_test = torch.tensor(system.test_xi, dtype=torch.float64)
        record = result.record
        row.update({"passed_acceptance": record.passed, "iterations": record.iterations,
                    "train_time_s": record.total_time_s,
                    "violating_fraction": float(record.acceptance.violating_fraction)})
        ver = verify(run, ProofConfig(time_limit=spec.verify_time_limit), VerifyRequest(xi=xi_test, roa=True))
        row.update(verification_row(ver))
        _, x0 = test_initial_states(system, combo.seed, n_more=spec.n_init)
        success = {}
        for k in spec.shift_factors:
            ev = evaluate_run(run, k * xi_test, x0, spec.horizon)
            success[f"{k:g}"] = ev["success_rate"]
        row["success"] = success
        row["status"] = "ok"
        row["error"] = None
        row["task_time_s"] = time.perf_counter() - tic
        row["run_dir"] = combo.name
        run.keep({"sweep": {k: row[k] for k in ("trained_condition", "test_decrease", "roa_share", "success")}})
        row["weights_sha256"] = file_sha256(staging / "weights.pt")
        row["spec_sha256"] = spec_sha256(spec_dict)
        write_json(staging / RESULT_FILE, row)
        rename_noreplace(staging, Path(out) / combo.name)  # the driver removed a broken one before this task ran
        return jsonable(row)
    except Exception as err:  # a failing combination is recorded, the others go on
        shutil.rmtree(staging, ignore_errors=True)
        lines = traceback.format_exc().strip().splitlines()
        row.update({"status": "failed", "error": f"{type(err).__name__}: {err}", "traceback": lines[-6:],
                    "task_time_s": time.perf_counter() - tic})
        return jsonable(row)
