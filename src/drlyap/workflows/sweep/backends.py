"""Where a sweep's combinations run: local worker processes (:class:`LocalBackend`) or Ray tasks
(:class:`RayBackend`), each yielding the rows of :func:`~drlyap.workflows.sweep.task.run_combination` as they finish."""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence

from drlyap.lifeline import init_worker, ray_processes, reap_with_me
from drlyap.workflows.sweep.grid import Combination, SweepError
from drlyap.workflows.sweep.task import run_combination

Task = tuple[dict, dict, str]  # (spec dict, combination dict, sweep directory): the arguments of run_combination


class Backend:
    """Runs tasks (:func:`run_combination` arguments) and yields their rows as they finish, in any order."""

    name = "backend"

    def run(self, tasks: Sequence[Task]) -> Iterator[dict]:
        raise NotImplementedError

    def __enter__(self) -> Backend:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Release what the backend started."""


def _crashed(task: Task, err: BaseException) -> dict:
    combo = Combination(**task[1])
    return {"name": combo.name, **task[1], "status": "failed", "error": f"worker crashed: {type(err).__name__}: {err}",
            "traceback": [], "task_time_s": None}


class LocalBackend(Backend):
    """``workers`` local processes (``spawn``, standard library), ``threads`` torch threads each."""

    name = "local"

    def __init__(self, workers: int = 1, threads: int = 1) -> None:
        if workers < 1 or threads < 1:
            raise SweepError(f"workers and threads must be >= 1, got {workers} and {threads}")
        self.workers, self.threads = workers, threads
        self._pool = None

    def run(self, tasks: Sequence[Task]) -> Iterator[dict]:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        if not tasks:
            return
        self._pool = ProcessPoolExecutor(max_workers=min(self.workers, len(tasks)),
                                         mp_context=multiprocessing.get_context("spawn"),
                                         initializer=init_worker, initargs=(self.threads, os.getpid()))
        futures = {self._pool.submit(run_combination, *task, self.threads): task for task in tasks}
        try:
            for future in as_completed(futures):
                try:
                    yield future.result()
                except Exception as err:  # the worker process died (e.g. killed, out of memory)
                    yield _crashed(futures[future], err)
        finally:
            self.close()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


class RayBackend(Backend):
    """One Ray task per combination. Without ``address`` Ray starts locally with ``workers`` CPUs;
    with one (``"auto"``, ``"ray://host:10001"``, ``"host:6379"``) it joins that cluster. Each task asks
    for one CPU and uses ``threads`` torch threads; workers must be able to ``import drlyap``."""

    name = "ray"

    def __init__(self, workers: int = 1, threads: int = 1, address: str | None = None) -> None:
        try:
            import ray
        except ImportError:
            raise SweepError("the Ray backend needs Ray: pip install 'drlyap[ray]' (or pip install 'ray>=2.9')") from None
        if workers < 1 or threads < 1:
            raise SweepError(f"workers and threads must be >= 1, got {workers} and {threads}")
        self.ray, self.threads, self._started = ray, threads, False
        if not ray.is_initialized():
            env = {"env_vars": {"OMP_NUM_THREADS": str(threads)}}
            if address:
                ray.init(address=address, runtime_env=env, log_to_driver=False)
            else:
                ray.init(num_cpus=workers, include_dashboard=False, runtime_env=env, log_to_driver=False,
                         configure_logging=False)
            self._started = True
            reap_with_me(ray_processes())  # its agents are no children of this process: they would outlive a kill

    def run(self, tasks: Sequence[Task]) -> Iterator[dict]:
        ray = self.ray
        remote = ray.remote(num_cpus=1, max_retries=0)(run_combination)
        pending = {remote.remote(*task, self.threads): task for task in tasks}
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    task = pending.pop(ref)
                    try:
                        yield ray.get(ref)
                    except Exception as err:  # the worker died
                        yield _crashed(task, err)
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)

    def close(self) -> None:
        if self._started:
            self.ray.shutdown()
            self._started = False


def make_backend(kind: str, workers: int = 1, address: str | None = None, threads: int = 1) -> Backend:
    """``"local"`` or ``"ray"``; ``address`` only for Ray."""
    if kind == "local":
        if address:
            raise SweepError("--address is for --backend ray; the local backend runs on this machine")
        return LocalBackend(workers, threads)
    if kind == "ray":
        return RayBackend(workers, threads, address)
    raise SweepError(f"backend {kind!r}; valid: local, ray")
