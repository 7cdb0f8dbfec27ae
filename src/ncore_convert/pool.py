"""Local process pool for the independent jobs of a conversion, with progress across processes.

Without a pool, callers run jobs inline (see :func:`run_inline`), e.g. in tests.

Jobs are module-level functions called as ``fn(*args, progress=report)``; ``report(n)`` adds ``n``
finished frames to a counter shared with the parent, which forwards it to the progress bar.
Workers start from a fork server that has imported the converter modules once, so a job starts in
milliseconds, and no worker inherits the parent's threads.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import multiprocessing.forkserver
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_EXCEPTION, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

Job = tuple[Callable[..., Any], tuple]

#: Environment of the worker processes (values the user has set win):
#: - workers fill the cores themselves, so numerical libraries get one thread each; otherwise every
#:   worker's OpenBLAS spins a thread per core on tiny matrix products;
#: - glibc malloc keeps freed memory instead of returning each multi-MB per-sweep array to the
#:   kernel and faulting it in again on the next sweep (this was ~10% of the lidar path).
WORKER_ENVIRONMENT = {
    "OPENBLAS_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "MALLOC_MMAP_THRESHOLD_": str(256 * 2**20),
    "MALLOC_TRIM_THRESHOLD_": str(512 * 2**20),
}

_frames_done = None  # shared counter, set in each worker


class WorkerDied(RuntimeError):
    """A worker process ended abruptly (SIGKILL, out of memory) while running a job."""


def _init_worker(counter) -> None:
    global _frames_done
    _frames_done = counter


def _report(n: int) -> None:
    with _frames_done.get_lock():
        _frames_done.value += n


def _call(fn: Callable[..., Any], args: tuple) -> Any:
    return fn(*args, progress=_report)


def _warm_up() -> int:
    return os.getpid()


@contextlib.contextmanager
def _environment(values: dict[str, str]):
    """Temporarily set environment variables the user has not set."""
    added = {k: v for k, v in values.items() if k not in os.environ}
    os.environ.update(added)
    try:
        yield
    finally:
        for k in added:
            del os.environ[k]


def run_inline(jobs: Sequence[Job], on_progress: Callable[[int], None] | None = None) -> list[Any]:
    """Run jobs one after another in this process (same contract as :meth:`JobPool.run`)."""
    progress = on_progress or (lambda n: None)
    return [fn(*args, progress=progress) for fn, args in jobs]


def default_workers() -> int:
    """Processes available to this run (CPU affinity aware)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


class JobPool:
    """Runs lists of jobs on ``workers`` worker processes.

    Use as a context manager. The workers start at construction, in the background, so their
    start-up overlaps with whatever the caller does before the first :meth:`run`.
    """

    def __init__(self, workers: int, preload: Sequence[str] = ()) -> None:
        if workers < 1:
            raise ValueError("workers must be >= 1")
        self.workers = workers
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload(list(preload))
        with _environment(WORKER_ENVIRONMENT):  # the fork server (and so every worker) inherits it
            multiprocessing.forkserver.ensure_running()
        self._ctx = ctx
        self._counter = ctx.Value("q", 0)
        self._start_executor()

    def _start_executor(self) -> None:
        self._executor = ProcessPoolExecutor(
            self.workers, mp_context=self._ctx, initializer=_init_worker, initargs=(self._counter,)
        )
        # start the workers in the background: the fork server imports the preload modules (about a
        # second) while the caller reads its inputs
        threading.Thread(target=self._start_workers, args=(self._executor,), daemon=True).start()

    def _start_workers(self, executor: ProcessPoolExecutor) -> None:
        with contextlib.suppress(RuntimeError):  # the pool was closed (or broke) before it started
            for _ in range(self.workers):
                executor.submit(_warm_up)

    def __enter__(self) -> JobPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._executor.shutdown(wait=True, cancel_futures=True)

    def run(self, jobs: Sequence[Job], on_progress: Callable[[int], None] | None = None) -> list[Any]:
        """Run all jobs; return their results in job order.

        Jobs are submitted in the given order (put the longest first). If a job fails, jobs not yet
        started are cancelled, running ones are awaited (so nothing writes after this returns),
        and the first failure is raised. If a worker process dies (killed, out of memory), the
        run fails with :class:`WorkerDied` and fresh workers serve the next run.
        """
        try:
            return self._run(jobs, on_progress or (lambda n: None))
        except BrokenProcessPool as err:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._start_executor()
            raise WorkerDied("a worker process died (killed or out of memory) before its job finished") from err

    def _run(self, jobs: Sequence[Job], progress: Callable[[int], None]) -> list[Any]:
        with self._counter.get_lock():
            self._counter.value = 0
        futures: list[Future] = [self._executor.submit(_call, fn, args) for fn, args in jobs]
        reported = 0
        pending = set(futures)
        while pending:
            done, pending = wait(pending, timeout=0.2, return_when=FIRST_EXCEPTION)
            reported = self._forward(reported, progress)
            failed = [f for f in done if f.exception() is not None]
            if failed:
                for f in pending:
                    f.cancel()
                wait(pending)
                raise failed[0].exception()
        self._forward(reported, progress)
        return [f.result() for f in futures]

    def _forward(self, reported: int, progress: Callable[[int], None]) -> int:
        value = self._counter.value
        if value > reported:
            progress(value - reported)
        return value
