"""No worker outlives a driver killed with ``kill -9`` by more than two seconds: sweep workers and proof workers are
bound to their parent before they import anything heavy."""

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

_DRIVER = textwrap.dedent("""
    import multiprocessing, os, sys, time
    from concurrent.futures import ProcessPoolExecutor
    from drlyap.lifeline import init_worker

    def work(seconds):
        time.sleep(seconds)
        return os.getpid()

    if __name__ == "__main__":
        pool = ProcessPoolExecutor(max_workers=2, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=init_worker, initargs=(1, os.getpid()))
        futures = [pool.submit(work, 120) for _ in range(2)]
        while len(pool._processes) < 2:
            time.sleep(0.05)
        print(" ".join(str(p) for p in pool._processes), flush=True)
        time.sleep(120)
""")


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie waiting to be reaped counts as ended)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


_PROOF_DRIVER = textwrap.dedent("""
    import time
    from drlyap.parallel import LocalPool

    if __name__ == "__main__":
        pool = LocalPool(2)
        print(" ".join(str(p.pid) for p in pool._procs), flush=True)
        time.sleep(120)
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("driver_code", [_DRIVER, _PROOF_DRIVER], ids=["sweep-pool", "proof-workers"])
def test_workers_end_within_two_seconds_of_a_killed_driver(tmp_path, driver_code):
    script = tmp_path / "driver.py"
    script.write_text(driver_code)
    driver = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        workers = [int(p) for p in driver.stdout.readline().split()]
        assert len(workers) == 2 and all(_alive(p) for p in workers)
        time.sleep(0.5)  # bound: they sleep in their task now
        os.kill(driver.pid, signal.SIGKILL)
        driver.wait()
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline and any(_alive(p) for p in workers):
            time.sleep(0.05)
        assert not [p for p in workers if _alive(p)], "workers outlived their killed driver by more than 2 s"
    finally:
        driver.kill()


def test_sweep_and_proof_workers_are_bound_first():
    """The pools' initializers bind the worker to its parent before anything else runs there."""
    import drlyap.workflows.sweep.backends as backends
    from drlyap.lifeline import init_worker

    assert backends.init_worker is init_worker
    source = Path(backends.__file__).read_text()
    assert "initializer=init_worker" in source
