"""Worker processes that run one function on the chunks of a batch: local processes or Ray actors.

A proof bounds its boxes a batch at a time; with :class:`~drlyap.compute.Compute` ``workers > 1`` (or the Ray
backend) each batch is cut into chunks, and the workers run the same *job* on the chunks: a picklable callable
``job(*arrays) -> dict[str, Tensor]`` whose arrays and results are batched on axis 0. The job (the networks, the
system, the condition) is sent to a worker once, serialised with cloudpickle (so a system from a user's file travels
by value: that file ran because the user named it); only the chunks travel after that. Results come back in the order
the batches were submitted, so the caller's bookkeeping, and therefore what it proves, is the same for any number of
workers.

A caller that names a chunk size (``submit(..., chunk=size)``) gets chunks of that many rows, the same ones
:func:`run_in_chunks` bounds in this process, dealt to the workers in turn: each chunk's results are then the same
bits wherever it is bounded. The bits of a row can depend on the rows bounded with it (float64 matrix products
take another kernel for the rows beyond a multiple of the kernel's block, so a box's bound may change in its last
bits with the number of boxes beside it); a chunk per worker, as without a size, would make them depend on the number
of workers.

* :func:`pool_for` -- the pool of a :class:`~drlyap.compute.Compute` (kept for the rest of the process, so that the
  proofs of one command share their workers); None where boxes are bounded in this process;
* :meth:`Pool.submit` -- send a batch, get a :class:`Pending` whose :meth:`~Pending.result` waits for it;
* :func:`run_in_chunks` -- the same chunks, bounded in this process;
* :func:`map_chunks` -- a list of whole chunks, each one call of a job, here or on the workers, results in order;
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
import traceback
import types
import weakref
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from drlyap.compute import Compute
from drlyap.lifeline import bound_main, ray_processes, reap_with_me, start_fork_server
from drlyap.memory import keep_freed_memory

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
    """The jobs a worker holds, by token (the latest :attr:`KEEP`: a proof's job is used for all of its batches)."""

    KEEP = 4

    def __init__(self, keep: int = KEEP) -> None:
        self.keep, self.jobs = keep, {}

    def load(self, token: int, payload: bytes) -> None:
        import cloudpickle

        self.jobs[token] = cloudpickle.loads(payload)
        while len(self.jobs) > self.keep:
            self.jobs.pop(next(iter(self.jobs)))

    def run(self, token: int, arrays: tuple) -> dict:
        return run_chunk(self.jobs[token], arrays)


# --------------------------------------------------------------------------- the worker process
def _worker_main(requests, results, threads: int) -> None:
    """A local worker: load jobs, run chunks, until told to stop (it was bound to its parent before it imported this
    module: :func:`drlyap.lifeline.bound_main`). Ctrl-C is the parent's to handle (it stops the workers)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.environ["OMP_NUM_THREADS"] = str(threads)
    torch.set_num_threads(threads)
    keep_freed_memory()  # as the parent does: without it a worker faults in its batches' pages again, every batch
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
def _join(parts: list[dict]) -> dict:
    """The results of a batch's chunks, in order, as one: tensors joined on axis 0; anything else the first chunk's."""
    if len(parts) == 1:
        return parts[0]
    return {k: torch.cat([p[k] for p in parts]) if isinstance(parts[0][k], Tensor) else parts[0][k] for k in parts[0]}


class Pending:
    """A batch submitted to a pool; :meth:`result` waits for its chunks and joins them (axis 0, in order)."""

    def __init__(self, fetch: Callable[[], list[dict]]) -> None:
        self._fetch, self._value = fetch, None

    def result(self) -> dict:
        if self._value is None:
            self._value = _join([_to_torch(p) for p in self._fetch()])
        return self._value


class Pool:
    """Workers that run a job on the chunks of a batch (see the module docstring)."""

    workers = 1
    name = "pool"

    def __init__(self) -> None:
        self._tokens: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
        self._turn = 0  # the worker that gets the next chunk

    def _token(self, job: Job) -> tuple[int, bool]:
        """The job's token, and whether it is new to this pool (its workers must load it)."""
        token = self._tokens.get(job)
        if token is not None:
            return token, False
        token = next(_TOKENS)
        self._tokens[job] = token
        return token, True

    def _deal(self, count: int, among: int | None = None) -> list[int]:
        """The workers of ``count`` chunks (among the first ``among``, default all), in turn from where the last batch
        left off (so that a small batch sent while another is in flight goes to other workers)."""
        among = among or self.workers
        start = self._turn % among
        self._turn = (start + count) % among
        return [(start + i) % among for i in range(count)]

    def submit(self, job: Job, *arrays: Tensor, chunk: int | list[int] | None = None) -> Pending:
        """Run ``job`` on ``arrays`` (each batched on axis 0, the same length), cut into chunks of ``chunk`` rows (the
        last one shorter; a list: chunks of those sizes; each chunk one call of ``job``, the calls
        :func:`run_in_chunks` makes) dealt to the workers in turn, else (None) into one chunk per worker."""
        raise NotImplementedError

    def close(self) -> None:
        """Stop the workers."""


def _chunks(arrays: tuple, parts: int, size: int | list[int] | None = None) -> list[tuple]:
    """``arrays`` (each ``(B, ...)``) cut on axis 0 into chunks of ``size`` rows (the last one shorter; one chunk where
    ``B <= size``; a list: chunks of those sizes, in order, summing to ``B``), or (``size`` None) into ``parts`` chunks of
    about the same length: a list of tuples of views."""
    if size is not None:
        if min([size] if isinstance(size, int) else size) < 1:
            raise ValueError(f"a chunk holds at least one row, got {size}")
        pieces = [torch.split(a, size) for a in arrays]
    else:
        pieces = [torch.tensor_split(a, max(1, min(parts, int(arrays[0].shape[0])))) for a in arrays]
    return list(zip(*pieces))


def run_in_chunks(job: Job, arrays: tuple, size: int | list[int]) -> dict:
    """``job`` on ``arrays`` (each ``(B, ...)``) in this process, one call per chunk of ``size`` rows (or of the sizes
    listed; the chunks a pool's ``submit(job, *arrays, chunk=size)`` deals to its workers), the results joined on axis
    0 in order: the same bits as the pool's."""
    return _join([job(*chunk) for chunk in _chunks(arrays, 1, size)])


def map_chunks(job: Job, chunks: list[tuple], compute: Compute, done: Callable[[int], None] | None = None) -> list[dict]:
    """``job(*chunk)`` for each of ``chunks`` (tuples of arrays, each ``(B_i, ...)``), in this process on
    ``compute.device`` (the job's ``on(device)`` where it has one) or whole on ``compute``'s workers, two per worker
    in flight; the results in the chunks' order, ``done(B_i)`` called as each comes back (a progress line)."""
    pool = pool_for(compute)
    results, flight = [], []
    tell = done or (lambda rows: None)
    if pool is None:
        local = job.on(compute.device) if hasattr(job, "on") else job
        for chunk in chunks:
            results.append(local(*chunk))
            tell(int(chunk[0].shape[0]))
        return results
    for chunk in chunks:
        flight.append((pool.submit(job, *chunk, chunk=int(chunk[0].shape[0])), int(chunk[0].shape[0])))
        if len(flight) > 2 * pool.workers:
            pending, rows = flight.pop(0)
            results.append(pending.result())
            tell(rows)
    for pending, rows in flight:
        results.append(pending.result())
        tell(rows)
    return results


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


def _context():
    """How local workers start: on Linux forked from a fork server that imported torch and the modules a job needs
    once (:func:`drlyap.lifeline.start_fork_server`; a worker is then ready in milliseconds, where a spawned one imports
    torch itself, about 2.5 s and as much CPU each); elsewhere spawned. The fork server ends when this process ends, and
    the workers with it."""
    import multiprocessing

    if start_fork_server():  # from the calling thread: the server ends when that thread ends
        return multiprocessing.get_context("forkserver"), None
    return multiprocessing.get_context("spawn"), os.getpid()


class LocalPool(Pool):
    """``workers`` processes on this machine (:func:`_context`), one torch thread each.

    They start in the background: until the first of them is up (the fork server's first start imports torch, about
    2.5 s) this process bounds the chunks itself, so that a proof starts at once; a chunk's bounds are the same bits
    wherever it is bounded. Afterwards the chunks go to the workers that are up, in turn."""

    name = "local"

    def __init__(self, workers: int, threads: int = 1) -> None:
        super().__init__()
        self.workers, self._threads = workers, threads
        self._procs, self._requests, self._results = [], [], []  # of the workers up, in the order they came up
        self._payloads: dict[int, bytes] = {}  # token: the job as bytes (the latest _JobCache.KEEP)
        self._loaded: list[set[int]] = []  # per worker up: the tokens it holds
        self._lock = threading.Lock()
        self._failed: BaseException | None = None
        self._stopping = False
        ctx, parent = _context()
        self._starter = threading.Thread(target=self._start, args=(ctx, parent), daemon=True, name="drlyap-pool-start")
        self._starter.start()

    def _start(self, ctx, parent: int | None) -> None:
        try:
            for _ in range(self.workers):
                req, res = ctx.Queue(), ctx.Queue()
                proc = ctx.Process(target=bound_main, args=(parent, __name__, "_worker_main", req, res,
                                                            self._threads), daemon=True, name="drlyap-proof-worker")
                _start_without_main(proc)
                with self._lock:
                    if self._stopping:
                        proc.kill()
                        return
                    self._procs.append(proc)
                    self._requests.append(req)
                    self._results.append(res)
                    self._loaded.append(set())
        except BaseException as err:  # noqa: BLE001 - reported by the next submit
            self._failed = err

    def _up(self) -> int:
        """How many workers are up now."""
        if self._failed is not None:
            raise WorkerError(f"the proof workers could not start: {self._failed}")
        with self._lock:
            return len(self._procs)

    def wait_up(self, timeout: float = 120.0) -> list[int]:
        """Wait until every worker is up (at most ``timeout`` seconds); their process ids."""
        self._starter.join(timeout)
        self._up()
        if self._starter.is_alive():
            raise WorkerError(f"the proof workers were not up after {timeout:g} s")
        return [proc.pid for proc in self._procs]

    def submit(self, job: Job, *arrays: Tensor, chunk: int | list[int] | None = None) -> Pending:
        if self._stopping:
            raise WorkerError("the proof workers were stopped")
        up = self._up()
        chunks = _chunks(arrays, self.workers, chunk)
        if not up:  # none up yet: this process bounds them, when asked for the result
            return Pending(lambda: [job(*part) for part in chunks])
        token, _ = self._token(job)
        if token not in self._payloads:
            self._payloads[token] = _dumps(job)
            while len(self._payloads) > _JobCache.KEEP:
                self._payloads.pop(next(iter(self._payloads)))
        used = self._deal(len(chunks), up)
        for i, part in zip(used, chunks):
            if token not in self._loaded[i]:
                self._requests[i].put(("load", token, self._payloads[token]))
                self._loaded[i] = (self._loaded[i] | {token}) if len(self._loaded[i]) < _JobCache.KEEP else {token}
            self._requests[i].put(("run", token, _to_numpy(part)))

        def fetch() -> list[dict]:
            # every chunk's reply, so that none is left for the next batch; a worker answers its chunks in the order
            # they were sent, and batches are fetched in the order they were submitted
            replies = [self._receive(i) for i in used]
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
        with self._lock:  # a worker that comes up after this is stopped by the thread that started it
            self._stopping = True
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
            reap_with_me(ray_processes())  # its agents are no children of this process: they would outlive a kill
        actor = ray.remote(num_cpus=1, max_restarts=0)(_RayWorker)
        self._actors = [actor.remote(threads) for _ in range(workers)]
        self._loads: dict[int, tuple[object, set[int]]] = {}  # token: (the job in Ray's store, the actors that have it)

    def submit(self, job: Job, *arrays: Tensor, chunk: int | list[int] | None = None) -> Pending:
        token, _ = self._token(job)
        if token not in self._loads:  # each actor loads the job with its first chunk of it: errors surface there
            self._loads[token] = (self.ray.put(_dumps(job)), set())
            while len(self._loads) > _JobCache.KEEP:  # what the actors forgot too
                self._loads.pop(next(iter(self._loads)))
        payload, loaded = self._loads[token]
        chunks = _chunks(arrays, self.workers, chunk)
        refs = []
        for i, part in zip(self._deal(len(chunks)), chunks):
            refs.append(self._actors[i].run.remote(token, _to_numpy(part), None if i in loaded else payload))
            loaded.add(i)

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
        keep_freed_memory()
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
