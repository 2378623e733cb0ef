"""What the checker confirmed, written beside the certificate: ``RUN/certificates/NAME.check.json``.

When the checker confirms a certificate it records the sha256 of exactly what it read (the header, the partition, the
weights, the system's description) and the drlyap version it ran as. ``drlyap verify`` takes a certificate whose record
matches those files for confirmed without re-checking it (the same bytes, the same checker), which makes a second
``verify`` of a large proof take seconds; ``drlyap check`` always checks again from the files, and rewrites the record
(or removes it, when the certificate is no longer confirmed). A record carries this machine's seal
(:mod:`drlyap.seal`): one made elsewhere or edited is not taken, whatever hashes it states.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from drlyap.seal import canonical, opens, seal

FORMAT = "drlyap-check"
VERSION = 1


def checker_version() -> str:
    try:
        return version("drlyap")
    except PackageNotFoundError:
        return "unknown"


def _path(run_dir: str | os.PathLike, name: str) -> Path:
    return Path(run_dir) / "certificates" / f"{name}.check.json"


def fingerprint(run_dir: str | os.PathLike, name: str, header: dict, weights_sha256: str, system_sha256: str) -> dict:
    """The hashes a record is about: the header file, the partition (its sha256 as the header states it, which
    :func:`~drlyap.runs.certificates.read_certificate` compared with the file), the weights and the system."""
    head = Path(run_dir) / "certificates" / f"{name}.json"
    return {"header_sha256": hashlib.sha256(head.read_bytes()).hexdigest(),
            "partition_sha256": str((header.get("partition") or {}).get("sha256")),
            "weights_sha256": weights_sha256, "system_sha256": system_sha256, "checker": checker_version()}


def write_record(run_dir: str | os.PathLike, name: str, prints: dict, leaves: int, seconds: float,
                 faces_min: float | None = None) -> Path | None:
    """Record that the checker confirmed certificate ``name`` (atomically, sealed), with ``faces_min``, its own lower
    bound of V on the box's faces where it established one; None where the folder cannot be written or there is no key
    to seal it with (nothing is lost: the next ``verify`` checks again)."""
    path = _path(run_dir, name)
    data = {"format": FORMAT, "version": VERSION, "confirmed": True, **prints, "leaves": int(leaves),
            "time_s": float(seconds), "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "faces_min": None if faces_min is None or not math.isfinite(faces_min) else float(faces_min)}
    mark = seal(canonical(data))
    if mark is None:
        return None
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_text(json.dumps({**data, "seal": mark}, indent=1) + "\n")
        os.replace(tmp, path)
    except OSError:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:  # a read-only folder: nothing was written
            pass
        return None
    return path


def drop_record(run_dir: str | os.PathLike, name: str) -> None:
    """Remove the record of certificate ``name`` (it is not, or no longer, confirmed)."""
    try:
        _path(run_dir, name).unlink(missing_ok=True)
    except OSError:
        pass


def recorded(run_dir: str | os.PathLike, name: str, prints: dict) -> dict | None:
    """The record of certificate ``name`` when this machine sealed it and it confirms exactly the files ``prints``
    describes with this drlyap's checker, else None."""
    try:
        data = json.loads(_path(run_dir, name).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("format") != FORMAT or data.get("version") != VERSION:
        return None
    mark = data.pop("seal", None)
    try:
        if not opens(canonical(data), mark):
            return None
    except ValueError:  # not canonical JSON (a NaN)
        return None
    if data.get("confirmed") is not True or any(data.get(k) != v for k, v in prints.items()):
        return None
    return data
