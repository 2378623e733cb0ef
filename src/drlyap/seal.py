"""Seals: what this machine wrote and may take back without proving again, authenticated by a key that never leaves it.

A run directory may come from anyone, and every file in it can be rewritten with hashes recomputed. Two kinds of file
are still worth reusing: the checker's record that it confirmed a certificate (``certificates/NAME.check.json``) and a
long proof's checkpoint. Each carries a seal, an HMAC-SHA256 of its content under a key of 32 random bytes kept in
this user's state folder (``$DRLYAP_STATE_DIR``, else ``$XDG_STATE_HOME/drlyap``, else ``~/.local/state/drlyap``;
file ``seal.key``, mode 0600, made on first use). A file whose seal does not open under this key (made elsewhere,
edited, or forged) is not reused: the certificate is checked again, the proof starts afresh. Where no key can be
read or made, nothing is sealed and nothing is reused.

Imports nothing of drlyap, nor torch.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
from pathlib import Path

KEY_BYTES = 32
KEY_FILE = "seal.key"


def state_dir() -> Path:
    """The folder of this user's drlyap state (where the key lives)."""
    explicit = os.environ.get("DRLYAP_STATE_DIR")
    if explicit:
        return Path(explicit)
    xdg = os.environ.get("XDG_STATE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".local" / "state") / "drlyap"


def _read_key(path: Path) -> bytes | None:
    try:
        st = path.lstat()
        if not path.is_file() or path.is_symlink() or st.st_mode & 0o077 or st.st_uid != os.getuid():
            return None  # a key others can read or write, or that is not this user's, authenticates nothing
        data = path.read_bytes()
    except OSError:
        return None
    return data if len(data) == KEY_BYTES else None


def machine_key() -> bytes | None:
    """This user's key (made on first use, atomically: the first process to link its file wins), or None where it
    cannot be read or made."""
    path = state_dir() / KEY_FILE
    key = _read_key(path)
    if key is not None or path.exists():
        return key
    try:
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        tmp = path.with_name(f".{KEY_FILE}.tmp-{os.getpid()}")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.write(fd, os.urandom(KEY_BYTES))
            os.fsync(fd)
        finally:
            os.close(fd)
        try:
            os.link(tmp, path)  # never replaces a key another process made meanwhile
        except FileExistsError:
            pass
        finally:
            tmp.unlink(missing_ok=True)
    except OSError:
        return None
    return _read_key(path)


def seal(payload: bytes) -> str | None:
    """The seal of ``payload`` (hex), or None where there is no key."""
    key = machine_key()
    return None if key is None else hmac.new(key, payload, hashlib.sha256).hexdigest()


def opens(payload: bytes, mark: object) -> bool:
    """Whether ``mark`` is this machine's seal of ``payload`` (False without a key)."""
    key = machine_key()
    if key is None or not isinstance(mark, str):
        return False
    return hmac.compare_digest(hmac.new(key, payload, hashlib.sha256).hexdigest(), mark)


def canonical(data: dict) -> bytes:
    """The bytes a JSON record is sealed as: sorted keys, no spaces."""
    return json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()
