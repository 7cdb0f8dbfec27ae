"""Local process pool for the independent jobs of a conversion, with progress across processes.

Without a pool, callers run jobs inline (see :func:`run_inline`), e.g. in tests.

Jobs are module-level functions called as ``fn(*args, progress=report)``; ``report(n)`` adds ``n``
finished frames to a counter shared with the parent, which forwards it to the progress bar.
Workers start from a fork server that has imported the converter modules once, so a job starts in
milliseconds, and no worker inherits the parent's threads.
"""

from __future__ import annotations

import contextlib
import itertools
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

_progress_queue = None  # (run id, frames) messages to the parent, set in each worker


class WorkerDied(RuntimeError):
    """A worker process ended abruptly (SIGKILL, out of memory) while running a job."""


def _init_worker(queue) -> None:
    global _progress_queue
    _progress_queue = queue


def _call(fn: Callable[..., Any], args: tuple, run_id: int) -> Any:
    return fn(*args, progress=lambda n: _progress_queue.put((run_id, n)))


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
        # a SimpleQueue writes straight to its pipe, so a job's messages are there before its result
        self._queue = ctx.SimpleQueue()
        self._callbacks: dict[int, Callable[[int], None]] = {}
        self._lock = threading.Lock()
        self._next_run = itertools.count()
        threading.Thread(target=self._dispatch_progress, daemon=True).start()
        self._start_executor()

    def _start_executor(self) -> None:
        self._executor = ProcessPoolExecutor(
            self.workers, mp_context=self._ctx, initializer=_init_worker, initargs=(self._queue,)
        )
        # start the workers in the background: the fork server imports the preload modules (about a
        # second) while the caller reads its inputs
        threading.Thread(target=self._start_workers, args=(self._executor,), daemon=True).start()

    def _dispatch_progress(self) -> None:
        """Forward the workers' progress messages to the callback of the run they belong to."""
        while (message := self._queue.get()) is not None:
            run_id, n = message
            with self._lock:
                callback = self._callbacks.get(run_id)
            if callback:
                callback(n)

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
        self._queue.put(None)  # stops the progress dispatcher

    def run(self, jobs: Sequence[Job], on_progress: Callable[[int], None] | None = None) -> list[Any]:
        """Run all jobs; return their results in job order.

        Jobs are submitted in the given order (put the longest first). If a job fails, jobs not yet
        started are cancelled, running ones are awaited (so nothing writes after this returns),
        and the first failure is raised. If a worker process dies (killed, out of memory), the
        run fails with :class:`WorkerDied` and fresh workers serve the next run.
        """
        with self._lock:
            run_id, executor = next(self._next_run), self._executor
            self._callbacks[run_id] = on_progress or (lambda n: None)
        try:
            return self._run(executor, jobs, run_id)
        except BrokenProcessPool as err:
            with self._lock:  # several runs may see the same broken pool: replace it once
                if self._executor is executor:
                    executor.shutdown(wait=True, cancel_futures=True)
                    self._start_executor()
            raise WorkerDied("a worker process died (killed or out of memory) before its job finished") from err
        finally:
            self._flush_progress(run_id)

    def _flush_progress(self, run_id: int) -> None:
        """Deliver this run's last progress messages, then forget the run."""
        done = threading.Event()
        with self._lock:
            self._callbacks[-1 - run_id] = lambda n: done.set()
        self._queue.put((-1 - run_id, 0))  # queued after every message the run's jobs sent
        done.wait(timeout=10)
        with self._lock:
            self._callbacks.pop(run_id, None)
            self._callbacks.pop(-1 - run_id, None)

    def _run(self, executor: ProcessPoolExecutor, jobs: Sequence[Job], run_id: int) -> list[Any]:
        futures: list[Future] = [executor.submit(_call, fn, args, run_id) for fn, args in jobs]
        pending = set(futures)
        while pending:
            done, pending = wait(pending, return_when=FIRST_EXCEPTION)
            failed = [f for f in done if f.exception() is not None]
            if failed:
                for f in pending:
                    f.cancel()
                wait(pending)
                raise failed[0].exception()
        return [f.result() for f in futures]
