"""No worker outlives a driver killed with ``kill -9`` by more than two seconds: sweep workers and proof workers are
bound to their parent before they import anything heavy."""

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from handmade import alive, survivors_of_kill

_PROOF_DRIVER = textwrap.dedent("""
    import sys, time
    from drlyap.lifeline import descendants
    from drlyap.parallel import LocalPool

    if __name__ == "__main__":
        pool = LocalPool(2)
        if sys.argv[1] == "up":
            workers = pool.wait_up()
        else:
            workers = []
            time.sleep(0.5)  # the fork server is still importing torch
        print(" ".join(str(p) for p in workers), flush=True)
        print(" ".join(str(p) for p in descendants()), flush=True)
        time.sleep(120)
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("when", ["up", "starting"])
def test_proof_workers_end_within_two_seconds_of_a_killed_driver(tmp_path, when):
    """Killed with its workers up, or while they still start (the fork server importing torch); the sweep's:
    tests/test_sweep.py."""
    script = tmp_path / "driver.py"
    script.write_text(_PROOF_DRIVER)
    driver = subprocess.Popen([sys.executable, str(script), when], stdout=subprocess.PIPE, text=True)
    try:
        workers = [int(p) for p in driver.stdout.readline().split()]
        # below the driver there are also short-lived helpers (``ldconfig -p`` run by ctypes while torch loads)
        below = [int(p) for p in driver.stdout.readline().split()]
        assert len(workers) == (2 if when == "up" else 0) and all(alive(p) for p in workers)
        assert set(workers) <= set(below) and len(below) >= len(workers) + 1  # and the fork server
        assert not survivors_of_kill(driver, below, 2.0), "workers outlived their killed driver by more than 2 s"
    finally:
        driver.kill()


def test_sweep_and_proof_workers_are_bound_first():
    """The pools' initializers bind the worker to its parent before anything else runs there."""
    import drlyap.workflows.sweep.backends as backends
    from drlyap.lifeline import init_worker

    assert backends.init_worker is init_worker
    source = Path(backends.__file__).read_text()
    assert "initializer=init_worker" in source


_RAY_DRIVER = textwrap.dedent("""
    import time
    from drlyap.parallel import RayPool

    if __name__ == "__main__":
        pool = RayPool(2)
        pool.ray.get([actor.__ray_ready__.remote() for actor in pool._actors])
        print("ready", flush=True)
        time.sleep(120)
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_local_ray_ends_within_two_seconds_of_a_killed_driver(tmp_path):
    """Its servers, its actors and its agents (which outlived the driver by 50 s and more)."""
    pytest.importorskip("ray")
    from drlyap.lifeline import descendants

    script = tmp_path / "driver.py"
    script.write_text(_RAY_DRIVER)
    driver = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                              text=True)
    try:
        assert driver.stdout.readline().strip() == "ready"
        started = descendants(driver.pid)
        assert len(started) >= 4  # gcs_server, raylet, two actors (and the agents)
        assert not survivors_of_kill(driver, started, 2.0), "a process of the local Ray outlived its driver by 2 s"
    finally:
        driver.kill()
