"""Worker processes that run one function on the chunks of a batch: local processes or Ray actors.

A proof bounds its boxes a batch at a time; with :class:`~drlyap.compute.Compute` ``workers > 1`` (or the Ray
backend) each batch is cut into one chunk per worker, and every worker runs the same *job* on its chunk: a picklable
callable ``job(*arrays) -> dict[str, Tensor]`` whose arrays and results are batched on axis 0. The job (the networks,
the system, the condition) is sent to a worker once, serialised with cloudpickle (so a system from a user's file
travels by value: that file ran because the user named it); only the chunks travel after that. Results come back in
the order the batches were submitted, so the caller's bookkeeping, and therefore what it proves, is the same for any
number of workers.

* :func:`pool_for` -- the pool of a :class:`~drlyap.compute.Compute` (kept for the rest of the process, so that the
  proofs of one command share their workers); None where boxes are bounded in this process;
* :meth:`Pool.submit` -- send a batch, get a :class:`Pending` whose :meth:`~Pending.result` waits for it;
* :func:`close_pools` -- stop every worker (also at exit).

Local workers are ``spawn``-ed processes with one torch thread each that end when this process ends, however it ends.
Ray workers are actors that ask for one CPU each, on the cluster at ``address`` (or ``RAY_ADDRESS``), else on a local
Ray started with ``workers`` CPUs; each must be able to ``import drlyap`` (and the module of a system named as
``package.module:factory``; a system from a file travels by value).
"""

from __future__ import annotations

import atexit
import itertools
import os
import queue
import signal
import sys
import threading
import time
import traceback
import types
import weakref
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from drlyap.compute import Compute

Job = Callable[..., dict]
_TOKENS = itertools.count(1)


class WorkerError(RuntimeError):
    """A worker process failed: its job raised (the worker's traceback follows) or the process died."""


def _to_numpy(arrays: tuple) -> tuple:
    return tuple(a.detach().cpu().numpy() if isinstance(a, Tensor) else a for a in arrays)


def _tensor(a):
    """A numpy array as a tensor (copied when read-only, as Ray hands them over); anything else as it is."""
    if not isinstance(a, np.ndarray):
        return a
    return torch.from_numpy(a if a.flags.writeable else a.copy())


def _to_torch(out: dict) -> dict:
    return {k: _tensor(v) for k, v in out.items()}


def _dumps(job: Job) -> bytes:
    """The job as bytes; the modules of user system files (``drlyap_user_*``) travel by value."""
    import cloudpickle

    for name, module in list(sys.modules.items()):
        if name.startswith("drlyap_user_") and module is not None:
            try:
                cloudpickle.register_pickle_by_value(module)
            except ValueError:  # already registered, or not a module cloudpickle can take
                pass
    return cloudpickle.dumps(job)


def run_chunk(job: Job, arrays: tuple) -> dict:
    """What a worker does with a chunk: the job on torch tensors, its results as numpy arrays."""
    out = job(*(_tensor(a) for a in arrays))
    return {k: v.detach().cpu().numpy() if isinstance(v, Tensor) else v for k, v in out.items()}


class _JobCache:
    """The jobs a worker holds, by token (the latest few: a proof's job is used for all of its batches)."""

    def __init__(self, keep: int = 4) -> None:
        self.keep, self.jobs = keep, {}

    def load(self, token: int, payload: bytes) -> None:
        import cloudpickle

        self.jobs[token] = cloudpickle.loads(payload)
        while len(self.jobs) > self.keep:
            self.jobs.pop(next(iter(self.jobs)))

    def run(self, token: int, arrays: tuple) -> dict:
        return run_chunk(self.jobs[token], arrays)


# --------------------------------------------------------------------------- the worker process
def _watch_parent(parent: int, every: float = 0.5) -> None:
    while True:
        time.sleep(every)
        if os.getppid() != parent:
            os._exit(1)


def _worker_main(requests, results, threads: int, parent: int) -> None:
    """A local worker: load jobs, run chunks, until told to stop or the parent is gone. Ctrl-C is the parent's to
    handle (it stops the workers)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.environ["OMP_NUM_THREADS"] = str(threads)
    torch.set_num_threads(threads)
    threading.Thread(target=_watch_parent, args=(parent,), daemon=True, name="drlyap-parent-watch").start()
    cache = _JobCache()
    while True:
        msg = requests.get()
        if msg[0] == "stop":
            return
        try:
            if msg[0] == "load":
                cache.load(msg[1], msg[2])
                continue
            results.put(("ok", cache.run(msg[1], msg[2])))
        except BaseException:  # noqa: BLE001 - the parent re-raises it with this traceback
            results.put(("error", traceback.format_exc()))


# --------------------------------------------------------------------------- pools
class Pending:
    """A batch submitted to a pool; :meth:`result` waits for its chunks and joins them (axis 0, in order)."""

    def __init__(self, fetch: Callable[[], list[dict]]) -> None:
        self._fetch, self._value = fetch, None

    def result(self) -> dict:
        if self._value is None:
            parts = [_to_torch(p) for p in self._fetch()]
            self._value = {k: torch.cat([p[k] for p in parts]) if isinstance(parts[0][k], Tensor) else parts[0][k]
                           for k in parts[0]}
        return self._value


class Pool:
    """Workers that run a job on the chunks of a batch (see the module docstring)."""

    workers = 1
    name = "pool"

    def __init__(self) -> None:
        self._tokens: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

    def _token(self, job: Job) -> tuple[int, bool]:
        """The job's token, and whether it is new to this pool (its workers must load it)."""
        token = self._tokens.get(job)
        if token is not None:
            return token, False
        token = next(_TOKENS)
        self._tokens[job] = token
        return token, True

    def submit(self, job: Job, *arrays: Tensor) -> Pending:
        """Run ``job`` on ``arrays`` (each batched on axis 0, the same length), cut into one chunk per worker."""
        raise NotImplementedError

    def close(self) -> None:
        """Stop the workers."""


def _chunks(arrays: tuple, parts: int) -> list[tuple]:
    count = max(1, min(parts, int(arrays[0].shape[0])))
    pieces = [torch.tensor_split(a, count) for a in arrays]
    return [tuple(p[i] for p in pieces) for i in range(count)]


def _start_without_main(proc) -> None:
    """Start a ``spawn`` process without it running the caller's ``__main__`` again: the workers need nothing of it
    (jobs travel by value), and a user's script without an ``if __name__ == "__main__"`` guard would otherwise start
    its work anew in every worker."""
    main = sys.modules["__main__"]
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        proc.start()
    finally:
        sys.modules["__main__"] = main


class LocalPool(Pool):
    """``workers`` processes on this machine (``spawn``), one torch thread each."""

    name = "local"

    def __init__(self, workers: int, threads: int = 1) -> None:
        import multiprocessing

        super().__init__()
        ctx = multiprocessing.get_context("spawn")
        self.workers = workers
        self._procs, self._requests, self._results = [], [], []
        for _ in range(workers):
            req, res = ctx.Queue(), ctx.Queue()
            proc = ctx.Process(target=_worker_main, args=(req, res, threads, os.getpid()), daemon=True,
                               name="drlyap-proof-worker")
            _start_without_main(proc)
            self._procs.append(proc)
            self._requests.append(req)
            self._results.append(res)
        self._outstanding = 0

    def submit(self, job: Job, *arrays: Tensor) -> Pending:
        if not self._procs:
            raise WorkerError("the proof workers were stopped")
        token, new = self._token(job)
        if new:
            payload = _dumps(job)
            for req in self._requests:
                req.put(("load", token, payload))
        chunks = _chunks(arrays, self.workers)
        for req, chunk in zip(self._requests, chunks):
            req.put(("run", token, _to_numpy(chunk)))
        used = list(range(len(chunks)))

        def fetch() -> list[dict]:
            replies = [self._receive(i) for i in used]  # every chunk's reply, so that none is left for the next batch
            for kind, value in replies:
                if kind == "error":
                    raise WorkerError(f"a proof worker failed:\n{value}")
            return [value for _, value in replies]

        return Pending(fetch)

    def _receive(self, i: int) -> tuple[str, object]:
        while True:
            try:
                return self._results[i].get(timeout=1.0)
            except queue.Empty:
                if not self._procs[i].is_alive():
                    code = self._procs[i].exitcode
                    self.close()
                    raise WorkerError(f"a proof worker process died (exit code {code}); the proof stopped") from None

    def close(self) -> None:
        for req, proc in zip(self._requests, self._procs):
            if proc.is_alive():
                try:
                    req.put(("stop",))
                except (OSError, ValueError):
                    pass
        for proc in self._procs:
            proc.join(timeout=2.0)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=2.0)
        for q in [*self._requests, *self._results]:
            q.close()
            q.cancel_join_thread()
        self._procs, self._requests, self._results = [], [], []


class RayPool(Pool):
    """``workers`` Ray actors (one CPU each) on the cluster at ``address`` (None: ``RAY_ADDRESS``, else a local Ray
    started with ``workers`` CPUs)."""

    name = "ray"

    def __init__(self, workers: int, address: str | None = None, threads: int = 1) -> None:
        try:
            import ray
        except ImportError:
            raise ValueError("the Ray backend needs Ray: pip install 'drlyap[ray]' (or pip install 'ray>=2.9')") from None
        super().__init__()
        self.ray, self.workers, self._started = ray, workers, False
        address = address or os.environ.get("RAY_ADDRESS") or None
        if not ray.is_initialized():
            env = {"env_vars": {"OMP_NUM_THREADS": str(threads)}}
            if address:
                ray.init(address=address, runtime_env=env, log_to_driver=False)
            else:
                ray.init(num_cpus=workers, include_dashboard=False, runtime_env=env, log_to_driver=False,
                         configure_logging=False)
            self._started = True
        actor = ray.remote(num_cpus=1, max_restarts=0)(_RayWorker)
        self._actors = [actor.remote(threads) for _ in range(workers)]

    def submit(self, job: Job, *arrays: Tensor) -> Pending:
        token, new = self._token(job)
        payload = self.ray.put(_dumps(job)) if new else None  # loaded with the job's first chunks: errors surface
        chunks = _chunks(arrays, self.workers)
        refs = [a.run.remote(token, _to_numpy(c), payload) for a, c in zip(self._actors, chunks)]

        def fetch() -> list[dict]:
            try:
                return self.ray.get(refs)
            except Exception as err:  # noqa: BLE001 - a task error or a dead actor, re-raised with its message
                raise WorkerError(f"a Ray proof worker failed: {err}") from None

        return Pending(fetch)

    def close(self) -> None:
        for a in getattr(self, "_actors", []):
            try:
                self.ray.kill(a)
            except Exception:  # noqa: BLE001 - already gone
                pass
        self._actors = []
        if self._started:
            self.ray.shutdown()
            self._started = False


class _RayWorker:
    """A Ray actor holding jobs (see :class:`_JobCache`)."""

    def __init__(self, threads: int) -> None:
        torch.set_num_threads(threads)
        self.cache = _JobCache()

    def run(self, token: int, arrays: tuple, payload: bytes | None = None) -> dict:
        if payload is not None:
            self.cache.load(token, payload)
        return self.cache.run(token, arrays)


def check_device(device: str) -> None:
    """A ValueError naming ``device`` where this process cannot compute on it (``cpu`` always can)."""
    if device == "cpu":
        return
    if not device.startswith("cuda") or not torch.cuda.is_available():
        raise ValueError(f"device {device!r}: no CUDA device is available here (torch.cuda.is_available() is "
                         f"{torch.cuda.is_available()}); use --device cpu")
    index = torch.device(device).index
    if index is not None and index >= torch.cuda.device_count():
        raise ValueError(f"device {device!r}: this machine has {torch.cuda.device_count()} CUDA device(s)")


_POOLS: dict[tuple, Pool] = {}


def pool_for(compute: Compute) -> Pool | None:
    """The pool of workers ``compute`` asks for (started on first use, then shared by every proof of this process
    that asks for the same); None where boxes are bounded in this process."""
    if not compute.parallel:
        return None
    key = (compute.backend, compute.workers, compute.address)
    pool = _POOLS.get(key)
    if pool is None:
        for other in list(_POOLS):  # one pool at a time: the workers of another setting would only compete for CPUs
            _POOLS.pop(other).close()
        pool = LocalPool(compute.workers) if compute.backend == "local" else RayPool(compute.workers, compute.address)
        _POOLS[key] = pool
    return pool


def discard_pool(pool: Pool) -> None:
    """Stop ``pool``'s workers and forget it (after an error or an interruption, whatever it still had in flight is
    lost; the next proof starts new workers)."""
    for key, value in list(_POOLS.items()):
        if value is pool:
            _POOLS.pop(key)
    pool.close()


def close_pools() -> None:
    """Stop every worker this process started."""
    while _POOLS:
        _POOLS.popitem()[1].close()


atexit.register(close_pools)
