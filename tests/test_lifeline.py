"""No worker outlives a driver killed with ``kill -9`` by more than two seconds: sweep workers and proof workers are
bound to their parent before they import anything heavy."""

import subprocess
import sys
import textwrap
import time
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


_LATE_CHILD = textwrap.dedent("""
    import os, sys, time
    import drlyap.fork_server  # as the fork server does first: this process plays the server
    from drlyap.lifeline import bound_main

    child = os.fork()
    if child == 0:
        while os.getppid() == drlyap.fork_server.SERVER:  # the server ends before this worker binds itself
            time.sleep(0.01)
        bound_main(None, "os", "mkdir", sys.argv[1])
        os._exit(0)
    print(child, flush=True)
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_worker_that_binds_itself_after_its_fork_server_ended_ends_at_once(tmp_path):
    """Its parent is the server's pid, not whichever process adopted it (seen on a busy machine: workers that came up
    after their server was killed outlived it)."""
    script, ran = tmp_path / "server.py", tmp_path / "ran"
    script.write_text(_LATE_CHILD)
    out = subprocess.run([sys.executable, str(script), str(ran)], capture_output=True, text=True, check=True).stdout
    child = int(out)
    deadline = time.monotonic() + 30
    while alive(child) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not alive(child) and not ran.exists()


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
