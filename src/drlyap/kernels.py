"""Which float kernels this process computes with.

Training in float32 amplifies the last bits of its sums and products, and those depend on the kernels torch and its
BLAS pick for the CPU (vector width, summation order) and on the number of threads: the same command gives the same
pair, bit for bit, on one machine, and other digits on another (docs/results/pendulum.md measures how far apart).
:func:`float_kernels` names the kernels by a fingerprint: the bits of a probe (a small tanh network's forward and
backward passes and Adam steps in float32, and the elementwise functions dynamics and losses use, in float32 and
float64, on data drawn from a fixed seed). Two processes with the same fingerprint compute the probe bit for bit
alike, which makes it likely, not certain, that they train alike (the probe covers the kernels training uses most,
not every one); another fingerprint means other digits. A run or a report that records it says which digits it can
be compared with. The proofs do not depend on it: a certificate holds on whatever machine made it, and the checker
confirms it on any other.
"""

from __future__ import annotations

import functools
import hashlib

import torch

FINGERPRINT_STEPS = 20
"""Adam steps of the fingerprint's training."""


def float_kernels(device: str | torch.device = "cpu") -> dict:
    """``{"torch", "device", "capability", "threads", "fingerprint"}`` of this process on ``device``: torch's version,
    the CPU's vector kernels torch dispatches to (``"AVX512"``, ``"AVX2"``, ...), torch's intra-op threads and the
    fingerprint (16 hex digits, module docstring). Leaves torch's global random state as it was."""
    dev = torch.device(device)
    return {"torch": torch.__version__, "device": str(dev), "capability": torch.backends.cpu.get_cpu_capability(),
            "threads": torch.get_num_threads(), "fingerprint": _fingerprint(str(dev), torch.get_num_threads())}


@functools.lru_cache(maxsize=8)
def _fingerprint(device: str, threads: int) -> str:
    gen = torch.Generator().manual_seed(20_261_207)

    def draw(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=gen, dtype=torch.float32).to(device)

    x = draw(4096, 2) * 3
    digest = hashlib.sha256()
    for z in (x, x.double()):  # the elementwise functions dynamics and losses use, in both precisions
        a, b = z[:, 0].contiguous(), z[:, 1].contiguous()  # contiguous: the vector kernels
        for value in (torch.sin(a), torch.cos(a), torch.atan2(a, b), torch.exp(-a * b), torch.log1p(a * a),
                      torch.sqrt(a.abs()), torch.tanh(a), torch.sigmoid(a), torch.nn.functional.softplus(a),
                      a.abs() ** 1.5, a / (b.abs() + 1), torch.linalg.vector_norm(z, dim=-1), z.sum(0),
                      torch.atan2(z.view(-1, 16), z[:16, 0].contiguous())):  # broadcast: a kernel of its own
            digest.update(value.cpu().contiguous().numpy().tobytes())
    params = [draw(6, 16), draw(16), draw(16, 16) / 4, draw(16), draw(16, 1) / 4, draw(1)]
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=1e-2)
    a, b = x[:, 0].contiguous(), x[:, 1].contiguous()
    features = torch.stack([torch.sin(a), torch.cos(a), torch.atan2(a, b), b, torch.exp(-b * b), torch.log1p(a * a)], -1)
    with torch.enable_grad():
        for _ in range(FINGERPRINT_STEPS):
            h = torch.tanh(features @ params[0] + params[1])
            h = torch.tanh(h @ params[2] + params[3])
            out = (h @ params[4] + params[5]).squeeze(-1)
            loss = torch.relu(out + 0.1 * x.square().sum(-1)).mean() + out.square().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
    for p in params:
        digest.update(p.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()[:16]


def describe(kernels: dict) -> str:
    """One line: ``torch 2.13.0+cpu, cpu AVX512 kernels, 1 thread, fingerprint 0123456789abcdef``."""
    threads = kernels["threads"]
    return (f"torch {kernels['torch']}, {kernels['device']} {kernels['capability']} kernels, {threads} "
            f"thread{'s' if threads != 1 else ''}, fingerprint {kernels['fingerprint']}")
