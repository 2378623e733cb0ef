"""Writing a directory so that nothing is lost: checked before the work starts, filled in a temporary sibling,
published by a rename that never replaces what is there, and locked while a process owns it.

* :func:`check_writable` -- an output directory's place is writable and has room, before long work starts;
* :func:`atomic_dir` -- fill a temporary sibling, then rename it into place (:func:`rename_noreplace`); an
  interrupted fill leaves nothing, and temporaries of processes that died are cleaned on the next write there;
* :class:`DirectoryLock` -- a directory owned by one process (a running sweep); :func:`held_by_another` says
  whether one is, so that a second sweep, or a run written into it, is refused;
* :func:`complete_run_dir` -- whether a directory was published complete (its ``run.json`` is written last).

Imports no numerical code, so that a command checks its paths at once.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import os
import re
import shutil
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

from filelock import FileLock, Timeout


class RunDirError(ValueError):
    """A run directory is missing, incomplete, damaged, or does not fit the request."""


class DestinationError(RunDirError):
    """A path to write to that cannot be used. Its message asks a Python caller to pass another path; the command
    line words the same for its option (:meth:`for_option`)."""

    def __init__(self, before: str, after: str = "") -> None:
        self.before, self.after = before, after
        super().__init__(f"{before}pass another path{after}")

    def for_option(self, option: str) -> str:
        """The message for a command whose ``option`` (``--out``) named the path."""
        return f"{self.before}choose another {option}{self.after}"


MIN_FREE_BYTES = 64 * 2**20
"""Room an output directory's file system must have before a run starts (a run directory is a few MB)."""

LOCK_FILE = ".drlyap.lock"
_HELD: set[str] = set()  # lock files this process holds


def complete_run_dir(path: str | os.PathLike) -> Path:
    """The ``run.json`` of the run directory ``path``, the file that marks it complete (written last); a
    :class:`RunDirError` naming ``path`` where it does not exist or is incomplete."""
    path = Path(path)
    if not path.is_dir():
        raise RunDirError(f"run directory {path} does not exist")
    marker = path / "run.json"
    if not marker.is_file():
        raise RunDirError(f"{path} is not a complete drlyap run directory (no run.json)")
    return marker


def ensure_new(out: str | os.PathLike) -> None:
    """Refuse an output directory that already exists, or is a symbolic link in any form (one that points nowhere
    included: the final rename would fail on it), checked before long work starts: a :class:`DestinationError`."""
    out = Path(out)
    if out.is_symlink():
        raise DestinationError(f"{out} is a symlink to {_link_target(out)}; drlyap writes a new directory, never "
                               "through a link: ", " or remove the link")
    if out.exists():
        raise DestinationError(f"{out} already exists; ", " or remove it")


def _link_target(link: Path) -> str:
    """Where the symbolic link ``link`` points, and whether that exists."""
    try:
        target = os.readlink(link)
    except OSError:
        return "an unreadable target"
    return target if link.exists() else f"{target}, which does not exist"


def proof_checkpoints(out: str | os.PathLike) -> Path:
    """Where the proofs of a run that will be published at ``out`` keep their checkpoints while it is made: a hidden
    sibling ``.NAME.proofs`` (the run directory itself appears only at the end), found again by the same command."""
    out = Path(out)
    return out.parent / f".{out.name}.proofs"


def check_writable(out: str | os.PathLike, need: int | None = None) -> None:
    """Refuse ``out`` before any work when it exists or is a symbolic link, when a process owns its parent (a
    running sweep), or when the nearest existing folder above it cannot be written to (a read-only file system), is
    a link that points nowhere, has less than ``need`` bytes free, or when the process may not write files that
    large (``ulimit -f``)."""
    out = Path(out)
    ensure_new(out)
    if held_by_another(out.parent):
        raise DestinationError(f"{out.parent} is in use by another drlyap process (a sweep is running there); ")
    base = out.parent
    while not base.exists() and base != base.parent:
        if base.is_symlink():  # mkdir would fail on it at the end
            raise DestinationError(f"cannot create {out}: {base} is a symlink to {_link_target(base)}; ")
        base = base.parent
    if not base.is_dir():
        raise RunDirError(f"cannot create {out}: {base} is not a directory")
    try:
        fd, probe = tempfile.mkstemp(prefix=".drlyap-probe-", dir=base)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise DestinationError(f"cannot write to {base} ({err.strerror or err}); ") from None
    need = MIN_FREE_BYTES if need is None else need
    free = shutil.disk_usage(base).free
    if free < need:
        raise DestinationError(f"{base} has {free / 2**20:.1f} MB free, less than the {need / 2**20:.0f} MB a run "
                               "needs; free some space or ")
    limit = _file_size_limit()
    if limit is not None and limit < need:
        raise RunDirError(f"cannot write {out}: this process may write files of {_size(limit)} at most (ulimit -f), "
                          f"less than the {_size(need)} a run needs; raise the limit (ulimit -f unlimited)")


def _file_size_limit() -> int | None:
    """The largest file this process may write, in bytes (``ulimit -f``); None where unlimited or unknown."""
    try:
        import resource
    except ImportError:  # not on Windows
        return None
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return None if soft == resource.RLIM_INFINITY or soft < 0 else int(soft)


def _size(nbytes: int) -> str:
    return f"{nbytes / 2**20:.0f} MB" if nbytes >= 2**20 else f"{nbytes / 2**10:.0f} KB"


_RENAME_NOREPLACE = 1
_libc = None


def rename_noreplace(src: Path, dst: Path) -> None:
    """Rename ``src`` to ``dst``, failing with :class:`FileExistsError` if ``dst`` exists (even as an empty
    directory, which a plain rename would replace). Atomic on Linux (``renameat2``); elsewhere the existence check
    and the rename are two steps."""
    global _libc
    if sys.platform.startswith("linux"):
        if _libc is None:
            _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        renameat2 = getattr(_libc, "renameat2", None)
        if renameat2 is not None:
            at_fdcwd = -100
            if renameat2(at_fdcwd, os.fsencode(src), at_fdcwd, os.fsencode(dst), _RENAME_NOREPLACE) == 0:
                return
            code = ctypes.get_errno()
            if code == errno.EEXIST:
                raise FileExistsError(code, f"{dst} already exists", str(dst))
            if code not in (errno.ENOSYS, errno.EINVAL):
                raise OSError(code, os.strerror(code), str(dst))
    if dst.exists():
        raise FileExistsError(errno.EEXIST, f"{dst} already exists", str(dst))
    os.rename(src, dst)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def clean_stale(parent: Path) -> list[Path]:
    """Remove the temporary directories in ``parent`` that :func:`atomic_dir` left when its process died (killed
    before it could clean up); returns them. Those of live processes stay."""
    removed = []
    for tmp in parent.glob(".*.tmp-*-*"):
        pid = tmp.name.rsplit(".tmp-", 1)[-1].split("-", 1)[0]
        if tmp.is_dir() and pid.isdigit() and int(pid) != os.getpid() and not _alive(int(pid)):
            shutil.rmtree(tmp, ignore_errors=True)
            removed.append(tmp)
    return removed


def atomic_dir(out: Path, fill: Callable[[Path], None], overwrite: bool = False) -> Path:
    """Create ``out`` by filling a temporary sibling and renaming it into place.

    ``fill(tmp)`` writes the contents. If it raises (or the process is interrupted) the temporary directory is
    removed and ``out`` is untouched. The rename never replaces an ``out`` that appeared meanwhile (that is
    refused); with ``overwrite`` an existing ``out`` is replaced. The directory gets the permissions the umask
    allows (readable by the group, as any directory the user makes). A failed write (a full disk, a file-size
    limit, a read-only file system...) is a :class:`DestinationError` of one line naming ``out``, the OS error and
    what was kept.
    """
    out = Path(out)
    if not overwrite or out.is_symlink():  # replaced or not, a link is never written through
        ensure_new(out)
    if held_by_another(out.parent):
        raise RunDirError(f"{out.parent} is in use by another drlyap process (a sweep is running there)")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        clean_stale(out.parent)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-{os.getpid()}-", dir=out.parent))
    except OSError as err:
        raise _write_error(out, err) from None
    try:
        try:
            fill(tmp)
            os.chmod(tmp, 0o777 & ~_umask())
            if overwrite and out.exists():
                shutil.rmtree(out)
        except OSError as err:
            raise _write_error(out, err, tmp) from None
        except RuntimeError as err:  # torch.save reports a failed write as a RuntimeError, without its errno
            if not _torch_write_failure(err):
                raise
            raise _write_error(out, err, tmp) from None
        try:
            rename_noreplace(tmp, out)
        except FileExistsError:
            if out.is_symlink():
                raise DestinationError(f"{out} became a symlink while this process ran (to {_link_target(out)}); "
                                       "nothing was written through it (this run is lost: ", ")") from None
            raise DestinationError(f"{out} was created by another process while this one ran; nothing was replaced "
                                   "(this run is lost: ", ")") from None
        except OSError as err:
            raise _write_error(out, err, tmp) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


_SPACE_HINTS = {errno.ENOSPC: "free some space or ", errno.EDQUOT: "free some space (the disk quota is used up) or ",
                errno.EFBIG: "raise the file-size limit (ulimit -f) or "}


def _torch_write_failure(err: RuntimeError) -> bool:
    """Whether ``err`` is torch's report of a file it could not write (its zip writer's ``enforce fail``)."""
    text = str(err)
    return "inline_container" in text or "PytorchStreamWriter" in text or "file write failed" in text


def _kept_note(out: Path) -> str:
    """What is kept beside ``out`` when it could not be written: the progress of its proofs (a hidden
    ``.NAME.proofs``, :func:`proof_checkpoints`), which the same command resumes; empty where there is none."""
    kept = proof_checkpoints(out)
    try:
        if any(kept.glob("proof-*")):
            return f"; its proofs' progress is kept in {kept}: the same command, run again, resumes them"
    except OSError:
        pass
    return ""


def _write_error(out: Path, err: Exception, tmp: Path | None = None) -> DestinationError:
    """The one-line :class:`DestinationError` for a write of ``out`` that failed with ``err`` (an OSError: a full
    disk, a file-size limit, a read-only file system...; or torch's report of a failed write), its temporary ``tmp``
    (named in the error as ``out``) being removed."""
    if isinstance(err, OSError):
        code = errno.errorcode.get(err.errno or 0)
        reason = f"{err.strerror or err}" + (f" ({code})" if code else "")
        name = err.filename
        if name is not None and tmp is not None and str(name).startswith(str(tmp)):
            name = str(out) + str(name)[len(str(tmp)):]
        elif name is not None and Path(name).name.startswith(f".{out.name}.tmp-"):
            name = None  # the temporary folder that could not be made: the error is about out's place
        where = f" at {name}" if name is not None and str(name) != str(out) else ""
        hint = _SPACE_HINTS.get(err.errno or 0, "")
    else:  # torch's writer says only that a file came out short: a file-size limit or a full disk
        first = (str(err).strip().splitlines() or [""])[0]
        detail = re.sub(r"^\[enforce fail at [^\]]*\]\s*\.?\s*", "", first).strip()
        reason, where = f"a file could not be written in full (torch: {detail})", ""
        limit = _file_size_limit()
        if limit is not None:
            reason += f"; files are limited to {_size(limit)} (ulimit -f)"
            hint = "raise the file-size limit (ulimit -f) or "
        else:
            hint = "free some space or "
    removed = "" if tmp is None else "; nothing was written there (its temporary folder is removed)"
    return DestinationError(f"cannot write {out}: {reason}{where}{removed}{_kept_note(out)}; {hint}")


class DirectoryLock:
    """Ownership of a directory by this process for the duration of a ``with`` block (a lock file in it, released
    when the process ends, however it ends). Raises :class:`RunDirError` when another process holds it."""

    def __init__(self, directory: Path, what: str = "this directory") -> None:
        self.directory, self.what = Path(directory), what
        self._lock = FileLock(str(self.directory / LOCK_FILE))

    def __enter__(self) -> DirectoryLock:
        self.directory.mkdir(parents=True, exist_ok=True)
        try:
            self._lock.acquire(timeout=0)
        except Timeout:
            raise DestinationError(f"{self.directory} is in use by another drlyap process ({self.what}); wait for it "
                                   "to end or ") from None
        _HELD.add(str(self.directory.resolve() / LOCK_FILE))
        return self

    def __exit__(self, *exc) -> None:
        _HELD.discard(str(self.directory.resolve() / LOCK_FILE))
        self._lock.release()


def held_by_another(directory: Path) -> bool:
    """Whether another process owns ``directory`` (a :class:`DirectoryLock` held elsewhere)."""
    path = Path(directory) / LOCK_FILE
    if not path.exists() or str(path.resolve()) in _HELD:
        return False
    lock = FileLock(str(path))
    try:
        lock.acquire(timeout=0)
    except Timeout:
        return True
    lock.release()
    return False
