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


def bind_to_parent(parent: int, every: float = 0.5) -> None:
    """End this process when ``parent`` (the pid that started it) ends: at once where the kernel offers it, else
    within ``every`` seconds."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent:  # the parent ended before the request took effect
        os._exit(1)
    threading.Thread(target=_watch, args=(parent, every), daemon=True, name="drlyap-parent-watch").start()


def bound_main(parent: int, module: str, name: str, *args) -> None:
    """A process's target that binds it to ``parent`` before it imports ``module`` (torch, say) and runs its
    function ``name(*args)``."""
    bind_to_parent(parent)
    import importlib

    getattr(importlib.import_module(module), name)(*args)


def init_worker(threads: int, parent: int) -> None:
    """A pool worker's initializer: bound to ``parent`` first, then ``threads`` torch threads (set in the environment
    for torch to read when it is first imported, and in torch itself if it already is)."""
    bind_to_parent(parent)
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = str(threads)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(threads)


def descendants(pid: int | None = None) -> list[int]:
    """The processes below ``pid`` (default: this one), children first, read from /proc (empty elsewhere)."""
    parents: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        parents.setdefault(ppid, []).append(int(stat.parent.name))
    found, todo = [], [os.getpid() if pid is None else pid]
    while todo:
        kids = parents.get(todo.pop(0), [])
        found += kids
        todo += kids
    return found


_REAPER = """
import os, signal, sys, time
parent = int(sys.argv[1])
known = {int(pid): start for pid, start in (a.split(":") for a in sys.argv[2:])}


def table():
    stats = {}
    for name in os.listdir("/proc"):
        if name.isdigit():
            try:
                with open(f"/proc/{name}/stat") as f:
                    stats[int(name)] = f.read().rsplit(")", 1)[1].split()
            except OSError:
                pass
    return stats


def below(stats, roots):
    found, todo = [], list(roots)
    while todo:
        parent_pid = todo.pop()
        kids = [p for p, fields in stats.items() if int(fields[1]) == parent_pid]
        found += kids
        todo += kids
    return found


while os.getppid() == parent:  # what Ray starts later (its workers) is taken in as it comes
    stats = table()
    for pid in below(stats, [parent]):
        if pid != os.getpid() and pid not in known:
            try:
                with open(f"/proc/{pid}/cmdline", "rb") as f:
                    if f.read().startswith(b"ray::"):
                        known[pid] = stats[pid][19]
            except OSError:
                pass
    time.sleep(0.5)
stats = table()
doomed = [pid for pid, start in known.items() if pid in stats and stats[pid][19] == start]
doomed += [p for p in below(stats, doomed) if p not in doomed]
for pid in doomed:
    try:
        os.kill(pid, signal.SIGKILL)
    except OSError:
        pass
"""


def _start_time(pid: int) -> str | None:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def reap_with_me(pids: list[int]) -> None:
    """Start a small process that kills ``pids`` (processes a library started below this one that are not bound to
    it, such as a local Ray's agents), the ``ray::`` processes that appear below this one later (it looks every half
    second) and what they started, within half a second of this process ending, however it ends. It runs in a session
    of its own, so that a Ctrl-C to this process does not end it first; a pid taken by another process meanwhile is
    left alone."""
    marks = [f"{pid}:{start}" for pid in pids if (start := _start_time(pid)) is not None]
    if marks:
        subprocess.Popen([sys.executable, "-c", _REAPER, str(os.getpid()), *marks], start_new_session=True,
                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def ray_processes() -> list[int]:
    """The processes below this one that a local Ray started under names of its own (``ray::...``: its dashboard and
    runtime-environment agents, idle workers). Its servers (gcs_server, raylet) end with this process by themselves
    and stop their workers as they do; those agents did not (seen: 50 s and more after a ``kill -9``)."""
    found = []
    for pid in descendants():
        try:
            command = Path(f"/proc/{pid}/cmdline").read_bytes()
        except OSError:
            continue
        if command.startswith(b"ray::"):
            found.append(pid)
    return found
