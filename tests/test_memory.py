"""drlyap.memory: glibc's malloc is asked to keep freed memory (Linux with glibc only), unless DRLYAP_MALLOC=system."""

import os
import platform
import subprocess
import sys

import pytest

CODE = "from drlyap.memory import keep_freed_memory; print(keep_freed_memory(), keep_freed_memory())"


def _run(**env: str) -> str:
    out = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, check=True,
                         env={**os.environ, **env})
    return out.stdout.strip()


@pytest.mark.skipif(not (sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"),
                    reason="mallopt is glibc's")
def test_freed_memory_is_kept_on_glibc_once_per_process():
    assert _run(DRLYAP_MALLOC="") == "True True"


def test_drlyap_malloc_system_leaves_malloc_alone():
    assert _run(DRLYAP_MALLOC="system") == "False False"
