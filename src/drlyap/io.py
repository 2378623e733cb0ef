"""I/O helpers with no drlyap dependencies: strict JSON for results and run directories."""

from __future__ import annotations

import json
import math
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
