"""The float kernels' fingerprint (drlyap.kernels): the same in one process and its next, another where the kernels
differ; it leaves torch's random state alone."""

import os
import subprocess
import sys

import pytest
import torch

from drlyap.kernels import describe, float_kernels

_PRINT = "import torch; torch.set_num_threads(1); from drlyap.kernels import float_kernels; " \
         "print(float_kernels()['fingerprint'])"


def test_the_fingerprint_is_the_same_each_time_and_draws_nothing_from_torch():
    before = torch.get_rng_state()
    first = float_kernels()
    assert torch.equal(before, torch.get_rng_state())
    assert first == float_kernels() and len(first["fingerprint"]) == 16
    assert first["threads"] == torch.get_num_threads() == 1 and first["device"] == "cpu"
    assert describe(first) == (f"torch {torch.__version__}, cpu {first['capability']} kernels, 1 thread, "
                               f"fingerprint {first['fingerprint']}")


@pytest.mark.skipif(torch.backends.cpu.get_cpu_capability() in ("DEFAULT", "NO AVX"),
                    reason="this CPU has no vector kernels to leave out")
def test_computed_again_the_fingerprint_is_the_same_and_other_kernels_give_another():
    from drlyap import kernels

    first = float_kernels()["fingerprint"]
    kernels._fingerprint.cache_clear()
    env = dict(os.environ, OMP_NUM_THREADS="1", ATEN_CPU_CAPABILITY="default")
    scalar = subprocess.run([sys.executable, "-c", _PRINT], env=env, capture_output=True, text=True, check=True)
    assert float_kernels()["fingerprint"] == first != scalar.stdout.strip()
