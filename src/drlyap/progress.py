"""One progress convention for every long loop (a leaf module: imports nothing from drlyap).

On a terminal (stderr is a tty): a tqdm bar. Otherwise (piped, logged, CI): one plain line on
stderr at most every ``every`` seconds, plus one at the end. Disabled: nothing.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


class _NoBar:
    def update(self, n: int = 1) -> None: ...
    def set_postfix(self, **kw: object) -> None: ...
    def close(self) -> None: ...


class _LineBar:
    """``desc: i/total (p%) key=value, 12 s`` (``desc: i key=value, 12 s`` without a total) on ``stream`` at most
    every ``every`` seconds."""

    def __init__(self, total: int | None, desc: str, stream: TextIO, every: float) -> None:
        self.total, self.desc, self.stream, self.every = total, desc, stream, every
        self.count, self.shown, self.postfix = 0, 0, ""
        self.start = self.last = time.monotonic()

    def _line(self) -> None:
        self.shown = self.count
        count = f"{self.count}/{self.total} ({100 * self.count / self.total:.0f}%)" if self.total else f"{self.count}"
        extra = f" {self.postfix}" if self.postfix else ""
        print(f"{self.desc}: {count}{extra}, {time.monotonic() - self.start:.0f} s", file=self.stream, flush=True)

    def update(self, n: int = 1) -> None:
        self.count += n
        now = time.monotonic()
        if now - self.last >= self.every:
            self.last = now
            self._line()

    def set_postfix(self, **kw: object) -> None:
        self.postfix = " ".join(f"{k}={v}" for k, v in kw.items())

    def close(self) -> None:
        if self.shown != self.count and time.monotonic() - self.start >= self.every:  # short loops stay silent
            self._line()


def progress(total: int | None, desc: str, enabled: bool = True, stream: TextIO | None = None, every: float = 5.0):
    """A progress reporter for ``total`` steps (None: a count with no known end) with ``update(n)``,
    ``set_postfix(**kw)`` and ``close()``.

    A tqdm bar when ``stream`` (default ``sys.stderr``) is a terminal, else a line every ``every`` seconds;
    nothing when ``enabled`` is false.
    """
    if not enabled:
        return _NoBar()
    stream = stream if stream is not None else sys.stderr
    if getattr(stream, "isatty", lambda: False)():
        from tqdm.auto import tqdm

        return tqdm(total=total, desc=desc, leave=False, dynamic_ncols=True, file=stream)
    return _LineBar(total, desc, stream, every)
