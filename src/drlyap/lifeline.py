"""Worker processes that end with the process that started them, however it ends (``kill -9`` included).

:func:`bind_to_parent` is the first thing a worker runs: on Linux it asks the kernel to kill it the moment its parent
ends (``PR_SET_PDEATHSIG``), and on every system a thread checks every half second that the parent is still there.
It imports nothing but the standard library, so that a worker is bound before it spends seconds importing torch (a
worker bound only after that outlived a killed sweep by 20-30 s).

Imports nothing of drlyap, nor torch.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

_PR_SET_PDEATHSIG = 1


def _watch(parent: int, every: float) -> None:
    while True:
        time.sleep(every)
        if os.getppid() != parent:
            os._exit(1)


def die_with_parent(parent: int) -> None:
    """Ask the kernel to kill this process the moment its parent ends (Linux; elsewhere nothing), and end now where
    ``parent`` already has."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent:  # the parent ended before the request took effect
        os._exit(1)


def bind_to_parent(parent: int, every: float = 0.5) -> None:
    """End this process when ``parent`` (the pid that started it) ends: at once where the kernel offers it, else
    within ``every`` seconds."""
    die_with_parent(parent)
    threading.Thread(target=_watch, args=(parent, every), daemon=True, name="drlyap-parent-watch").start()


def bound_main(parent: int | None, module: str, name: str, *args) -> None:
    """A process's target that binds it to ``parent`` (None: the process that started it, such as a fork server
    that ends with the process that started it: :func:`fork_server_pid`) before it imports ``module`` (torch, say)
    and runs its function ``name(*args)``."""
    if parent is None:
        _let_the_fork_server_end()
        parent = fork_server_pid()
    bind_to_parent(parent)
    import importlib

    getattr(importlib.import_module(module), name)(*args)


FORK_SERVER_PRELOAD = ("drlyap.fork_server", "drlyap.parallel", "drlyap.verification.bounding", "drlyap.checker.check")
"""What the fork server of the local proof workers imports once, before it forks them: first what binds it to this
process, then the modules a proof's and a check's jobs need."""


def start_fork_server() -> bool:
    """Start multiprocessing's fork server for the local proof workers (Linux; elsewhere nothing: False), if it does
    not run yet. It returns at once: the server imports torch meanwhile, so that a command that starts it early finds
    it ready when its first proof needs workers. The server ends when the thread that started it ends (the kernel's
    parent-death signal follows the parent thread), and with it the process."""
    if not sys.platform.startswith("linux"):
        return False
    import multiprocessing
    import multiprocessing.forkserver

    multiprocessing.get_context("forkserver").set_forkserver_preload(list(FORK_SERVER_PRELOAD))
    multiprocessing.forkserver.ensure_running()
    return True


def fork_server_pid() -> int:
    """In a process forked by the fork server of :func:`start_fork_server`: that server's pid, even where it has ended
    meanwhile (``os.getppid()`` then names the process that adopted this one). Elsewhere: this process's parent."""
    server = sys.modules.get("drlyap.fork_server")
    return server.SERVER if server is not None and server.SERVER != os.getpid() else os.getppid()


def _let_the_fork_server_end() -> None:
    """In a process forked by multiprocessing's fork server: close the end of the pipe by which the fork server learns
    that the process that started it has ended (each forked process gets a copy). Held here, it would keep the server,
    and so this process, alive after that process was killed."""
    import multiprocessing.forkserver as forkserver

    server = getattr(forkserver, "_forkserver", None)
    fd = getattr(server, "_forkserver_alive_fd", None)
    if fd is not None:
        try:
            os.close(fd)
        except OSError:
            pass
        server._forkserver_alive_fd = None


def init_worker(threads: int, parent: int) -> None:
    """A pool worker's initializer: bound to ``parent`` first, then ``threads`` torch threads (set in the environment
    for torch to read when it is first imported, and in torch itself if it already is)."""
    bind_to_parent(parent)
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = str(threads)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(threads)


def process_table() -> dict[int, list[str]]:
    """Every process's fields of ``/proc/PID/stat`` after its name (``[1]``: its parent, ``[19]``: its start time)."""
    stats = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            stats[int(stat.parent.name)] = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
    return stats


def descendants(pid: int | None = None, stats: dict[int, list[str]] | None = None) -> list[int]:
    """The processes below ``pid`` (default: this one), children first, read from /proc (empty elsewhere);
    ``stats``: a :func:`process_table` already read."""
    parents: dict[int, list[int]] = {}
    for child, fields in (process_table() if stats is None else stats).items():
        parents.setdefault(int(fields[1]), []).append(child)
    found, todo = [], [os.getpid() if pid is None else pid]
    while todo:
        kids = parents.get(todo.pop(0), [])
        found += kids
        todo += kids
    return found


def _is_ray(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().startswith(b"ray::")
    except OSError:
        return False


def ray_processes() -> list[int]:
    """The processes below this one that a local Ray started under names of its own (``ray::...``: its dashboard and
    runtime-environment agents, idle workers). Its servers (gcs_server, raylet) end with this process by themselves
    and stop their workers as they do; those agents did not (seen: 50 s and more after a ``kill -9``)."""
    return [pid for pid in descendants() if _is_ray(pid)]


def reap(parent: int, marks: list[str]) -> None:
    """The reaper's loop (:func:`reap_with_me`): while ``parent`` lives, take in the ``ray::`` processes below it every
    half second; then kill those of them still running (``marks``: ``PID:START``, the start time telling the very
    process from one that took its pid) and what they started."""
    known = {int(pid): start for pid, start in (m.split(":") for m in marks)}
    while os.getppid() == parent:
        stats = process_table()
        for pid in descendants(parent, stats):
            if pid != os.getpid() and pid not in known and _is_ray(pid):
                known[pid] = stats[pid][19]
        time.sleep(0.5)
    stats = process_table()
    doomed = [pid for pid, start in known.items() if pid in stats and stats[pid][19] == start]
    for root in list(doomed):
        doomed += [p for p in descendants(root, stats) if p not in doomed]
    for pid in doomed:
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass


def reap_with_me(pids: list[int]) -> None:
    """Start a small process (:func:`reap`) that kills ``pids`` (processes a library started below this one that are
    not bound to it, such as a local Ray's agents), the ``ray::`` processes that appear below this one later and what
    they started, within half a second of this process ending, however it ends. It runs in a session of its own, so
    that a Ctrl-C to this process does not end it first; a pid taken by another process meanwhile is left alone."""
    stats = process_table()
    marks = [f"{pid}:{stats[pid][19]}" for pid in pids if pid in stats]
    if marks:
        code = "import sys\nfrom drlyap.lifeline import reap\nreap(int(sys.argv[1]), sys.argv[2:])"
        subprocess.Popen([sys.executable, "-c", code, str(os.getpid()), *marks], start_new_session=True,
                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
