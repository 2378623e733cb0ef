"""Where a proof's boxes are bounded (this process, worker processes, a Ray cluster, a GPU): :class:`Compute`.

It changes how fast a proof runs, never what it proves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

BACKENDS = ("local", "ray")
"""Where a proof's worker processes run: this machine, or a Ray cluster."""


@dataclass(frozen=True)
class Compute:
    """Where a proof's boxes are bounded; it changes how fast a proof runs, never what it proves.

    ``workers``: processes that bound the boxes of each batch (1: this process, the default); ``backend``: ``local``
    (processes on this machine, one torch thread each) or ``ray`` (actors of a Ray cluster: ``address``, else
    ``RAY_ADDRESS``, else a local Ray with ``workers`` CPUs); ``device``: where this process bounds them (``cpu`` or
    ``cuda``, float64 on the device; with one worker only); ``checkpoint_dir``: a directory where a long proof keeps
    its open boxes and proved leaves, so that the same proof, started again after it was killed, resumes there (None:
    no checkpoints), at least ``checkpoint_every`` seconds apart and at least
    :data:`drlyap.verification.checkpoints.SAVE_SPACING` times as long as
    the last save took (so that saving costs a proof at most about 5%); ``progress``: a long proof reports its boxes
    on stderr."""

    workers: int = 1
    backend: str = "local"
    address: str | None = None
    device: str = "cpu"
    checkpoint_dir: str | None = None
    checkpoint_every: float = 2.0
    progress: bool = False

    def __post_init__(self) -> None:
        problems = compute_problems(self.workers, self.backend, self.address, self.device)
        if not (math.isfinite(self.checkpoint_every) and self.checkpoint_every >= 0):
            problems.append(f"checkpoint_every = {self.checkpoint_every} (must be >= 0 seconds)")
        if problems:
            raise ValueError("invalid compute settings: " + "; ".join(problems))

    @property
    def parallel(self) -> bool:
        """Whether boxes are bounded by worker processes (not by this process)."""
        return self.workers > 1 or self.backend == "ray"


def compute_problems(workers, backend, address, device) -> list[str]:
    """What is wrong with these settings of :class:`Compute` (each named with what would be valid)."""
    problems = []
    if not (isinstance(workers, int) and not isinstance(workers, bool) and workers >= 1):
        problems.append(f"workers = {workers!r} (must be an integer >= 1)")
    if backend not in BACKENDS:
        problems.append(f"backend {backend!r} (valid: {', '.join(BACKENDS)})")
    if address is not None and backend != "ray":
        problems.append("address is for the ray backend")
    if not isinstance(device, str) or device.split(":")[0] not in ("cpu", "cuda"):
        problems.append(f"device {device!r} (valid: cpu, cuda, cuda:N)")
    elif device != "cpu" and (backend != "local" or workers != 1):
        problems.append(f"device {device!r} bounds boxes in this process: it needs workers = 1 and the local backend")
    return problems
