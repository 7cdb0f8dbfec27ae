"""Local process pool for the independent jobs of a conversion, with progress across processes.

Without a pool, callers run jobs inline (see :func:`run_inline`), e.g. in tests.

Jobs are module-level functions called as ``fn(*args, progress=progress)`` with a :class:`Progress`:
``progress(n)`` sends ``n`` finished frames to the parent and ``progress.total(n)`` the number of
frames to expect; the parent forwards them to the callbacks of the job's run.
Workers start from a fork server that has imported the converter modules once, so a job starts in
milliseconds, and no worker inherits the parent's threads.
"""

from __future__ import annotations

import contextlib
import itertools
import multiprocessing as mp
import multiprocessing.forkserver
import multiprocessing.resource_tracker
import os
import signal
import sys
import threading
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_EXCEPTION, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
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


def _ignore(n: int) -> None:
    pass


@dataclass(frozen=True)
class Progress:
    """Given to every job: ``progress(n)`` reports ``n`` more frames written, ``progress.total(n)``
    the number of frames the job will write (when it learns it)."""

    frames: Callable[[int], None] = _ignore
    total: Callable[[int], None] = _ignore

    def __call__(self, n: int) -> None:
        self.frames(n)


def _init_worker(queue) -> None:
    global _progress_queue
    _progress_queue = queue
    # Ctrl-C reaches the whole process group: the parent alone decides (it abandons the jobs in
    # flight and kills the workers). SIGTERM keeps its default: the pool ends its workers with it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent()


def _die_with_parent() -> None:
    """Linux: this process is killed (SIGKILL) when its parent ends. A worker's parent is the fork
    server, and the fork server's the run (see ``_FORK_SERVER``): so a run killed with SIGKILL leaves
    no worker writing into a log's ``.partial`` folder, which the next run may be writing again.
    (The kernel watches the thread that started the process: pools start in the main thread.)"""
    with contextlib.suppress(OSError, AttributeError):
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


#: A run stopped by a signal ends with ``os._exit`` (``run/runner.py``): multiprocessing's resource
#: tracker then unlinks the killed pool's semaphores itself, as it is there to do, and warns about
#: each one. To a user who pressed Ctrl-C that is noise: the tracker starts with this filter.
_QUIET_TRACKER = "ignore:resource_tracker:UserWarning"

#: Set (to the run's pid) in the environment the fork server starts with: the fork server imports
#: this module first (its preload), finds the mark and ties its life to the run's.
_FORK_SERVER = "NCORE_CONVERT_FORK_SERVER_OF"
if os.environ.get(_FORK_SERVER) == str(os.getppid()):
    _die_with_parent()


@contextlib.contextmanager
def _sigint_blocked():
    """Block SIGINT in this thread while the fork server and the resource tracker start: they keep
    the mask, and so does every worker forked from the fork server, so a Ctrl-C sent to the process
    group reaches the run alone (which stops them), never a process importing its preload (a
    KeyboardInterrupt traceback). A SIGINT sent meanwhile is delivered to the run when unblocked."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def _call(fn: Callable[..., Any], args: tuple, run_id: int) -> tuple[Any, int, list[int]]:
    """Run a job; return its result, the frames and the totals it reported (the parent delivers
    what is still in the pipe when the run ends)."""
    sent, totals = 0, []

    def frames(n: int) -> None:
        nonlocal sent
        sent += n
        _progress_queue.put((run_id, False, n))

    def total(n: int) -> None:
        totals.append(n)
        _progress_queue.put((run_id, True, n))

    return fn(*args, progress=Progress(frames, total)), sent, totals


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


def run_inline(jobs: Sequence[Job], progress: Progress | None = None) -> list[Any]:
    """Run jobs one after another in this process (same contract as :meth:`JobPool.run`)."""
    progress = progress or Progress()
    return [fn(*args, progress=progress) for fn, args in jobs]


def default_workers() -> int:
    """Processes available to this run (CPU affinity aware)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


class JobPool:
    """Runs lists of jobs on ``workers`` worker processes.

    Use as a context manager. The workers start at construction, in the background, so their
    start-up overlaps with whatever the caller does before the first :meth:`run`.

    ``preload``: modules the fork server imports once, so that each worker starts with them. A
    process has one fork server, started by its first pool: later pools share it and its preload.
    """

    def __init__(self, workers: int, preload: Sequence[str] = ()) -> None:
        if workers < 1:
            raise ValueError("workers must be >= 1")
        self.workers = workers
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload([__name__, *preload])
        # the fork server (and so every worker) inherits the environment
        if _QUIET_TRACKER not in sys.warnoptions:  # read when the resource tracker starts, just below
            sys.warnoptions.append(_QUIET_TRACKER)
        os.environ.pop(_FORK_SERVER, None)  # inherited from another run's worker: this run's mark wins
        with _environment({**WORKER_ENVIRONMENT, _FORK_SERVER: str(os.getpid())}):
            # the tracker first: its start unblocks SIGINT again (multiprocessing.resource_tracker)
            multiprocessing.resource_tracker.ensure_running()
            with _sigint_blocked():
                multiprocessing.forkserver.ensure_running()
        self._ctx = ctx
        self._progress: dict[int, Progress] = {}
        self._delivered: dict[int, int] = {}
        self._delivered_totals: dict[int, list[int]] = {}
        self._lock = threading.Lock()
        self._next_run = itertools.count()
        self._start_executor()

    def _start_executor(self) -> None:
        # A fresh progress queue per set of workers: a worker killed while writing to a queue can
        # leave its lock held for good, so a queue is never reused after a worker died.
        progress_queue = self._ctx.SimpleQueue()  # writes go straight to the pipe, no feeder thread
        threading.Thread(target=self._dispatch_progress, args=(progress_queue,), daemon=True).start()
        self._executor = ProcessPoolExecutor(
            self.workers, mp_context=self._ctx, initializer=_init_worker, initargs=(progress_queue,)
        )
        # start the workers in the background: the fork server imports the preload modules (about a
        # second) while the caller reads its inputs
        threading.Thread(target=self._start_workers, args=(self._executor,), daemon=True).start()

    def _dispatch_progress(self, progress_queue) -> None:
        """Forward the workers' progress messages to the callbacks of the run they belong to."""
        while True:
            try:
                run_id, is_total, n = progress_queue.get()
            except Exception:  # noqa: BLE001 - a message cut short by a killed worker ends this queue
                return
            with self._lock:
                progress = self._progress.get(run_id)
                if progress and not is_total:
                    self._delivered[run_id] += n
                elif progress:
                    self._delivered_totals[run_id].append(n)
            if progress:
                (progress.total if is_total else progress.frames)(n)

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

    def abandon(self) -> None:
        """Kill the workers now (their jobs are abandoned) and shut the pool down without waiting."""
        with self._lock:
            executor = self._executor
        # the workers as ProcessPoolExecutor keeps them; there is no public handle
        for process in list((getattr(executor, "_processes", None) or {}).values()):
            with contextlib.suppress(OSError, AttributeError):
                process.kill()
        executor.shutdown(wait=False, cancel_futures=True)

    def run(self, jobs: Sequence[Job], progress: Progress | None = None) -> list[Any]:
        """Run all jobs; return their results in job order.

        Jobs are submitted in the given order (put the longest first). If a job fails, jobs not yet
        started are cancelled, running ones are awaited (so nothing writes after this returns),
        and the first failure is raised. If a worker process dies (killed, out of memory), the
        run fails with :class:`WorkerDied` and fresh workers serve the next run.
        """
        progress = progress or Progress()
        with self._lock:
            run_id, executor = next(self._next_run), self._executor
            self._progress[run_id], self._delivered[run_id], self._delivered_totals[run_id] = progress, 0, []
        try:
            done = self._run(executor, jobs, run_id)
        except BrokenProcessPool as err:
            self._forget(run_id)
            with self._lock:  # several runs may see the same broken pool: replace it once
                if self._executor is executor:
                    # no wait: a broken pool has terminated its workers, and joining its management
                    # thread after a worker was killed mid-message can block for good
                    executor.shutdown(wait=False, cancel_futures=True)
                    self._start_executor()
            raise WorkerDied("a worker process died (killed or out of memory) before its job finished") from err
        except BaseException:
            self._forget(run_id)
            raise
        delivered, delivered_totals = self._forget(run_id)
        missing = sum(sent for _, sent, _ in done) - delivered
        if missing > 0:  # messages still in the pipe: deliver them now, they are dropped later
            progress(missing)
        for n, count in (Counter(n for _, _, totals in done for n in totals) - Counter(delivered_totals)).items():
            for _ in range(count):
                progress.total(n)
        return [result for result, _, _ in done]

    def _forget(self, run_id: int) -> tuple[int, list[int]]:
        """Stop forwarding a run's progress; returns the frames and the totals delivered so far."""
        with self._lock:
            self._progress.pop(run_id, None)
            return self._delivered.pop(run_id, 0), self._delivered_totals.pop(run_id, [])

    def _run(self, executor: ProcessPoolExecutor, jobs: Sequence[Job], run_id: int) -> list[tuple[Any, int, list[int]]]:
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
