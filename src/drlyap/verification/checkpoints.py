"""Checkpoints of a long branch and bound, so that the same proof started again after it was killed resumes.

A checkpoint is one file ``DIR/proof-KEY.npz`` (numpy arrays, read with ``allow_pickle=False``): the boxes still
queued, the tree of boxes proved so far, the counters, and a header (format, version, the key). ``KEY`` is the sha256 of
everything the proof's course depends on (:func:`proof_key`: the networks' float64 weights, the system's description
and dynamics code, the condition and its samples, the region, the level, the starting grid, the enclosure, the batch
and the splitting limits), so a checkpoint is only ever read by the very same proof; budgets in boxes and seconds are
not part of it (a resumed proof may be given more). It is written to a temporary file and renamed into place, so a
kill leaves the previous checkpoint or the new one, never half of one. Its content is sealed with this machine's key
(:mod:`drlyap.seal`): the key names the proof, not what it found, so a checkpoint edited (an emptied queue, leaves
marked proved) or made elsewhere is refused like a damaged one. A checkpoint that cannot be read or whose seal does
not open is ignored (the proof starts afresh, with a warning); without a key none is written. The caller removes a
finished proof's checkpoint.
"""

from __future__ import annotations

import hashlib
import io
import json
import marshal
import os
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from drlyap.seal import opens, seal

FORMAT = "drlyap-proof-checkpoint"
VERSION = 1
SAVE_SPACING = 20
"""A proof's checkpoints are at least this many times as long apart as the last one took to save (the cart-pole's
proof: about 7 ms a save, so every 2 s, ``Compute.checkpoint_every``; a proof of millions of boxes saves less often)."""


def update_hash(h, t: Tensor) -> None:
    """Feed a tensor's shape, dtype and bytes to the hash ``h``."""
    t = t.detach().cpu().contiguous()
    h.update(str((tuple(t.shape), str(t.dtype))).encode())
    h.update(t.numpy().tobytes() if t.dtype != torch.bfloat16 else t.float().numpy().tobytes())


def _code_bytes(fn) -> bytes:
    code = getattr(fn, "__code__", None)
    if code is None:
        return repr(fn).encode()
    try:
        return marshal.dumps(code)
    except ValueError:
        return repr(fn).encode()


def proof_key(loop, condition, region, **settings) -> str:
    """The sha256 (hex) of what a proof's course depends on (see the module docstring); ``settings``: the rest of it
    (level, grid, enclosure, batch, limits), JSON-friendly values."""
    h = hashlib.sha256(f"{FORMAT}/{VERSION}".encode())
    for net in (loop.lyapunov, loop.controller):
        h.update(type(net).__name__.encode())
        for name, value in sorted(net.state_dict().items()):
            h.update(name.encode())
            update_hash(h, value.to(torch.float64) if value.is_floating_point() else value)
    system = loop.system
    h.update(json.dumps(system.describe(), sort_keys=True, default=str).encode())
    for fn in (system.dynamics, getattr(system, "perturbation", None)):
        h.update(_code_bytes(fn))
    h.update(type(condition).__name__.encode())
    h.update(json.dumps(condition.describe(), sort_keys=True, default=str).encode())
    xi = condition.xi
    if isinstance(xi, Tensor):
        update_hash(h, xi)
    elif xi is not None:  # an interval of shifts
        update_hash(h, xi.lo)
        update_hash(h, xi.hi)
    for t in (region.lo, region.hi):
        update_hash(h, t)
    h.update(json.dumps({"delta": float(region.delta), **settings}, sort_keys=True, default=str).encode())
    return h.hexdigest()


def _path(directory: str | os.PathLike, key: str) -> Path:
    return Path(directory) / f"proof-{key[:32]}.npz"


def _content(header: bytes, arrays: dict[str, np.ndarray]) -> bytes:
    """What a checkpoint's seal is of: its header and every array's name, type, shape and bytes, in name order."""
    h = hashlib.sha256(header)
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(json.dumps([name, a.dtype.str, list(a.shape)]).encode())
        h.update(a.tobytes())
    return h.digest()


def save_checkpoint(directory: str | os.PathLike, key: str, arrays: dict[str, Tensor], meta: dict) -> Path | None:
    """Write the checkpoint atomically (a temporary file renamed into place), sealed; ``meta``: JSON-friendly values.
    None (nothing written) where there is no key to seal it with."""
    path = _path(directory, key)
    header = json.dumps({"format": FORMAT, "version": VERSION, "key": key, **meta}).encode()
    data = {k: v.detach().cpu().numpy() for k, v in arrays.items()}
    mark = seal(_content(header, data))
    if mark is None:
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    np.savez(buf, __header__=np.frombuffer(header, dtype=np.uint8), __seal__=np.frombuffer(mark.encode(), np.uint8),
             **data)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            f.write(buf.getvalue())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        raise
    return path


def load_checkpoint(directory: str | os.PathLike | None, key: str) -> tuple[dict[str, Tensor], dict] | None:
    """The arrays and header of the checkpoint of the proof ``key``, or None (none there, or not readable: then a
    warning says so and the proof starts afresh)."""
    if directory is None:
        return None
    path = _path(directory, key)
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            raw = bytes(data["__header__"])
            mark = bytes(data["__seal__"]).decode() if "__seal__" in data.files else None
            loaded = {k: data[k].copy() for k in data.files if k not in ("__header__", "__seal__")}
        if not opens(_content(raw, loaded), mark):
            raise ValueError("its seal does not open with this machine's key: it was edited or made elsewhere")
        header = json.loads(raw.decode())
        arrays = {k: torch.from_numpy(v) for k, v in loaded.items()}
        if header.get("format") != FORMAT or header.get("version") != VERSION or header.get("key") != key:
            raise ValueError("it belongs to another proof or format")
    except Exception as err:  # noqa: BLE001 - any damage: start afresh, lose nothing else
        warnings.warn(f"the proof checkpoint {path} cannot be read ({type(err).__name__}: {err}); the proof starts "
                      "afresh", stacklevel=3)
        return None
    return arrays, header


def drop_checkpoint(directory: str | os.PathLike | None, key: str) -> None:
    """Remove the checkpoint of the proof ``key`` (a finished proof), if there is one."""
    if directory is not None:
        _path(directory, key).unlink(missing_ok=True)
