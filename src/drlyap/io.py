"""I/O helpers with no drlyap dependencies: strict JSON for results and run directories, proved shares as text."""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
from pathlib import Path


def jsonable(obj):
    """Non-finite floats become None (strict JSON); containers are copied."""
    if isinstance(obj, dict):
        return {k: jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_json(path: Path, data: dict) -> None:
    """Write ``data`` as indented strict JSON (NaN and inf become null)."""
    data = jsonable(data)
    path.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")


def write_bytes_of(path: Path, save) -> None:
    """Write the bytes that ``save(buffer)`` puts into an in-memory buffer (``torch.save``, ``torch.jit.save``) to
    ``path`` with Python's own file I/O, so that a failed write (a full disk, a file-size limit) is an OSError with
    its errno, not torch's RuntimeError without one."""
    buffer = io.BytesIO()
    save(buffer)
    Path(path).write_bytes(buffer.getbuffer())


def write_json_atomic(path: Path, data: dict) -> None:
    """:func:`write_json` to a temporary sibling, then renamed over ``path``: a reader sees the old file or the new
    one, never half of one."""
    tmp = path.with_name(f".{path.name}.tmp")
    write_json(tmp, data)
    os.replace(tmp, path)


def proved_percent(fraction: float, verified: bool, decimals: int = 2) -> str:
    """A proved share as ``"99.84%"``, rounded down, so a condition that is not verified never prints as
    ``"100.00%"`` (``"> 99.99%"`` then): the printed number is a lower bound and must read as one. A verified
    condition is proved on all of it: ``"100.00%"``."""
    scale = 10 ** decimals
    pct = 100.0 if verified else math.floor(100 * float(fraction) * scale) / scale
    if not verified and pct >= 100:
        return f"> {100 - 1 / scale:.{decimals}f}%"
    return f"{pct:.{decimals}f}%"


def from_fields(cls, data: dict, what: str, error: type[Exception] = ValueError):
    """``cls(**data)`` for a dataclass, refusing keys it does not have with ``error`` naming them (and the valid
    ones): a misspelt key in a saved config or sweep file is an error, not silently dropped."""
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise error(f"unknown {what} keys {unknown}; valid: {sorted(known)}")
    return cls(**data)
