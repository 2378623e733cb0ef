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
import sys
import threading
import time

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
