"""A line on stderr when a command's start-up is slow: importing torch (and the numerical code behind it) takes about
3 s on a laptop-class CPU, and far longer on the first run after an install, when Python compiles what it imports.
The command line imports torch only when a command needs it (a bad argument is refused before), so the line is tied
to that import: it is printed when the import is still running 2 s after it began, and never otherwise."""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import sys
import threading

import click

SLOW = 2.0
"""Seconds of loading after which the line is printed."""


class _Loader(importlib.abc.Loader):
    """The real loader of a module, with a timer around its execution."""

    def __init__(self, real: importlib.abc.Loader, name: str) -> None:
        self.real, self.name = real, name

    def create_module(self, spec):
        return self.real.create_module(spec)

    def exec_module(self, module) -> None:
        line = f"drlyap: loading {self.name} and the numerical code (a few seconds; longer on the first run after an install)"
        timer = threading.Timer(SLOW, click.echo, args=(line,), kwargs={"err": True})
        timer.daemon = True
        timer.start()
        module.__loader__ = module.__spec__.loader = self.real  # the module sees its own loader
        try:
            self.real.exec_module(module)
        finally:
            timer.cancel()


class _Finder(importlib.abc.MetaPathFinder):
    """Wraps the loader of ``name`` the first time it is imported, then steps aside."""

    def __init__(self, name: str) -> None:
        self.name = name

    def find_spec(self, fullname, path, target=None):
        if fullname != self.name:
            return None
        sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(fullname, path)
        if spec is not None and spec.loader is not None:
            spec.loader = _Loader(spec.loader, fullname)
        return spec


def announce_slow_loading(name: str = "torch") -> None:
    """Print one line on stderr if importing ``name`` (not yet imported) takes more than :data:`SLOW` seconds."""
    if name not in sys.modules and not any(isinstance(f, _Finder) for f in sys.meta_path):
        sys.meta_path.insert(0, _Finder(name))
