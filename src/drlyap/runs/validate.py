"""Reading a run directory's files as data, never as code, and refusing damaged ones with one line that names the
file and what is wrong: the JSON files against their schemas (``drlyap/schemas``), the configuration against its
types and ranges, the samples against the system, the weights as tensors only (no pickled objects), all finite."""

from __future__ import annotations

import dataclasses
import io
import json
import math
import pickle
from functools import cache
from importlib import resources
from pathlib import Path

import torch
from jsonschema import Draft202012Validator

from drlyap.config import TrainConfig
from drlyap.runs.publish import RunDirError


@cache
def _validator(name: str) -> Draft202012Validator:
    schema = json.loads(resources.files("drlyap").joinpath("schemas", f"{name}.schema.json").read_text())
    return Draft202012Validator(schema)


def check_schema(path: Path, data, name: str) -> None:
    """``data`` (the parsed ``path``) against the schema ``name`` (``run`` or ``metrics``): the first problem, named
    by its place in the file."""
    errors = sorted(_validator(name).iter_errors(data), key=lambda e: list(e.path))
    if errors:
        err = errors[0]
        where = "/".join(str(p) for p in err.path) or "the top level"
        raise RunDirError(f"{path}: {where}: {err.message}")


CORE_KEYS = ("system", "method", "loss", "wasserstein_radius", "risk_level", "decay_rate", "delta", "seed", "iters",
             "n_states", "lyapunov_hidden", "controller_hidden")
"""Keys every run's ``config.json`` has held since format 1 (a format-2 run holds every field of TrainConfig)."""

LATER_FIELDS = {"outside_weight": 0.0, "exclude_weight": 0.0, "grow_weight": 0.0, "adversarial_share": 0.0,
                "level_margin": 0.0, "controller_skip": False,
                "lyapunov_skip": False, "reshape_steps": 0, "exit_faces": False,
                "exit_margin": 0.0}
"""TrainConfig fields added after format 2, with the value every run saved before them was trained with (their
absence means exactly that value)."""


def check_config(path: Path, data: dict, format_version: int = 2) -> TrainConfig:
    """``config.json`` as a complete training configuration: every field present (format 2; format 1: the
    :data:`CORE_KEYS`), of the right type, every resolved field filled. A missing key is refused, never defaulted:
    a default would silently prove another condition (a baseline run without ``method`` read as DR)."""
    if not isinstance(data, dict):
        raise RunDirError(f"{path}: a JSON object of training settings expected, got {type(data).__name__}")
    expected = [f.name for f in dataclasses.fields(TrainConfig)] if format_version >= 2 else list(CORE_KEYS)
    data = {**LATER_FIELDS, **data}
    absent = [k for k in expected if k not in data]
    if absent:
        raise RunDirError(f"{path}: invalid training config: missing {', '.join(absent)} (the file is incomplete)")
    try:
        config = TrainConfig.from_dict(data)
    except (TypeError, ValueError) as err:
        raise RunDirError(f"{path}: {err}") from None
    problems = config.type_problems() + [f"{name} is missing (null)" for name in config.missing()]
    if problems:
        raise RunDirError(f"{path}: invalid training config: {'; '.join(problems)}")
    return config


def check_samples(path: Path, metrics: dict, k: int) -> None:
    """The samples of xi in ``metrics.json`` have one column per uncertain parameter (``k``) and are finite."""
    for key in ("xi_samples", "xi_train"):
        rows = metrics[key]
        if any(len(row) != k for row in rows):
            raise RunDirError(f"{path}: {key} must have {k} value(s) per sample (one per uncertain parameter), got "
                              f"rows of {sorted({len(r) for r in rows})}")
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for row in rows for v in row):
            raise RunDirError(f"{path}: {key} contains NaN, inf or non-numbers")


def load_weights(path: Path, data: bytes | None = None) -> dict:
    """The state dicts in a weights file, read as tensors only (``weights_only``: no object is unpickled), every
    one finite; a damaged file or non-finite weights are named as such. ``data``: the file's bytes, already read
    (what was hashed is then what is loaded)."""
    try:
        weights = torch.load(path if data is None else io.BytesIO(data), map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise RunDirError(f"{path} is missing") from None
    except Exception as err:  # any failure to parse the bytes (torch's reader raises many kinds) is damage
        if isinstance(err, EOFError):
            reason = "empty or cut short"
        elif isinstance(err, pickle.UnpicklingError) and "Weights only load failed" in str(err):
            reason = "its contents are not tensors saved by torch; nothing in it was unpickled"
        elif isinstance(err, RuntimeError) and str(err).strip():
            reason = str(err).strip().splitlines()[0]
        else:
            reason = "unreadable contents"
        raise RunDirError(f"{path} is damaged: not a torch weights file drlyap wrote ({reason[:120]})") from None
    if not isinstance(weights, dict):
        raise RunDirError(f"{path} is damaged: it holds a {type(weights).__name__}, not the networks' weights")
    for group, state in weights.items():
        if not isinstance(state, dict):
            raise RunDirError(f"{path} is damaged: {group!r} is not a state dict")
        for key, value in state.items():
            if not isinstance(value, torch.Tensor):
                raise RunDirError(f"{path} is damaged: {group}.{key} is not a tensor")
            if value.is_complex() or value.dtype == torch.bool:
                raise RunDirError(f"{path} is damaged: {group}.{key} is not a real tensor ({value.dtype})")
            if value.is_floating_point() and not bool(torch.isfinite(value).all()):
                raise RunDirError(f"{path} holds NaN or inf in {group}.{key}: the run's networks are not usable")
    return weights


def restore_infinite(tensors: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The constants of an imported pair's ``tensors.pt`` with the infinite bounds of one-sided clamps restored: a
    weights file holds finite numbers only, so each ``NAME#inf`` int8 sign (+1, -1, 0) marks where ``NAME`` is
    +-inf."""
    out = {k: v for k, v in tensors.items() if not k.endswith("#inf")}
    for name, sign in tensors.items():
        if name.endswith("#inf") and name[:-4] in out:
            base = out[name[:-4]]
            out[name[:-4]] = torch.where(sign != 0, sign.to(base.dtype) * math.inf, base)
    return out
