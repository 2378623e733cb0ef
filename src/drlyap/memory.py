"""How the process keeps freed memory: the verifier allocates tensors of the same few sizes (megabytes each) batch
after batch, and glibc's malloc by default returns such blocks to the system when they are freed (``mmap`` /
``munmap``, heap trimming), so every batch faults its pages in again. Measured on the cart-pole's proof (one thread,
119,779 boxes): 45.7 s with 7.1 s of system time, and 33.0 s with 0.5 s once freed memory is kept.

:func:`keep_freed_memory` asks glibc to keep it (``mallopt``); elsewhere (another OS or C library) it does nothing.
``DRLYAP_MALLOC=system`` leaves malloc's defaults as they are.
"""

from __future__ import annotations

import ctypes
import os
import sys

_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3  # glibc's mallopt parameters
_MMAP_THRESHOLD = 32 * 2**20  # glibc's largest: blocks above it are still mapped and unmapped one by one
_TRIM_THRESHOLD = 2**30  # free memory at the heap's top is returned to the system only above 1 GiB
_TOP_PAD = 64 * 2**20

_kept: bool | None = None


def keep_freed_memory() -> bool:
    """Ask glibc's malloc to keep freed blocks of up to 32 MiB for reuse and not to trim its heap below 1 GiB of free
    memory (once per process). Returns whether it took effect: False off Linux, without glibc, or with
    ``DRLYAP_MALLOC=system``. The process's resident memory then stays near its peak until it ends."""
    global _kept
    if _kept is None:
        _kept = False
        if sys.platform.startswith("linux") and os.environ.get("DRLYAP_MALLOC", "") != "system":
            try:
                libc = ctypes.CDLL("libc.so.6")
                _kept = all(libc.mallopt(param, value) == 1 for param, value in (
                    (_M_MMAP_THRESHOLD, _MMAP_THRESHOLD), (_M_TRIM_THRESHOLD, _TRIM_THRESHOLD), (_M_TOP_PAD, _TOP_PAD)))
            except (OSError, AttributeError):
                _kept = False
    return _kept
