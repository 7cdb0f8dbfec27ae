"""Where per-log tasks run: this machine's worker processes, or an existing Ray cluster.

Both run the same task per log through :func:`~ncore_convert.run.runner.convert_one`, so a log's output
does not depend on the executor.
"""

from __future__ import annotations

import queue
import socket
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from functools import partial
from typing import Literal

from upath import UPath

from ncore_convert.run.pool import JobPool, Progress
from ncore_convert.run.runner import LogResult, LogTask, RunControl, Summary, convert_one

#: Where logs run (``--executor``): this machine's worker processes, or an existing Ray cluster.
ExecutorKind = Literal["local", "ray"]
#: How often the loops that wait for logs look at the run's stop signal (seconds).
POLL_S = 0.25


def _log_as_one_job(task: LogTask, sequence_dir: UPath, log_id: str, progress: Progress) -> Summary:
    """Pool job: a whole log (planning and every store) in one worker process."""
    return task(sequence_dir, log_id, progress=progress)


def _one_worker_per_log(pool: JobPool, task: LogTask, sequence_dir: UPath, log_id: str, progress: Progress) -> Summary:
    return pool.run([(_log_as_one_job, (task, sequence_dir, log_id))], progress)[0]


def _workers_share_log(pool: JobPool, task: LogTask, sequence_dir: UPath, log_id: str, progress: Progress) -> Summary:
    return task(sequence_dir, log_id, progress=progress, pool=pool)


class LocalExecutor:
    """Logs on this machine's worker processes (:class:`~ncore_convert.run.pool.JobPool`).

    With at least as many logs as workers, each log is one job: a worker plans and writes it
    alone, and ``workers`` logs run at a time. With fewer logs, every log in flight is planned in
    this process and its stores (base, lidars, each camera) are written by the workers in parallel.
    """

    def __init__(self, pool: JobPool) -> None:
        self.pool = pool
        self._abandoned = False  #: the workers were killed (a stopped run): nothing to join

    def __enter__(self) -> LocalExecutor:
        return self

    def __exit__(self, *exc) -> None:
        if self._abandoned:
            return  # the workers are killed; joining them could wait on a half-sent message
        self.pool.close()

    def abandon(self) -> None:
        self._abandoned = True
        self.pool.abandon()

    def results(
        self, task: LogTask, output_root: UPath, log_ids: list[str], show_progress: bool, control: RunControl
    ) -> Iterator[LogResult]:
        by_log = len(log_ids) >= self.pool.workers
        convert = partial(_one_worker_per_log if by_log else _workers_share_log, self.pool, task)
        in_flight = min(self.pool.workers, len(log_ids))
        rows: queue.SimpleQueue[int] = queue.SimpleQueue()  # progress-bar rows below the overall bar
        for row in range(1, in_flight + 1):
            rows.put(row)

        def one(log_id: str) -> LogResult | None:
            if control.stop.is_set():
                return None
            if (why := control.gate(log_id)) is not None:
                return LogResult(log_id, True, elsewhere=why)
            row = rows.get()
            try:
                return convert_one(output_root, log_id, convert, show_progress, bar_position=row, control=control)
            finally:
                rows.put(row)

        threads = ThreadPoolExecutor(max_workers=in_flight)
        pending = {threads.submit(one, log_id) for log_id in log_ids}
        try:
            while pending and not control.stop.is_set():
                done, pending = wait(pending, timeout=POLL_S, return_when=FIRST_COMPLETED)
                for future in done:
                    if (result := future.result()) is not None:
                        yield result
        finally:
            # stopped: the threads still in flight end when their workers are killed (abandon)
            threads.shutdown(wait=not control.stop.is_set(), cancel_futures=True)


def _convert_on_node(task: LogTask, output_root: UPath, log_id: str) -> LogResult:
    """Ray task: one whole log on a cluster node (no progress bars there)."""
    return convert_one(output_root, log_id, partial(_log_as_one_job, task), show_progress=False)


def _check_reachable(address: str, timeout_s: float = 10.0) -> None:
    """Raise ConnectionError unless a TCP connection to ``host:port`` (``ray://`` allowed) opens."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except ValueError:
        raise ConnectionError(f"{address!r} is not host:port") from None
    except OSError as err:
        raise ConnectionError(f"no Ray head node reachable ({err})") from None


class RayExecutor:
    """Logs as Ray tasks (one CPU each) on an existing cluster; Ray schedules them and retries a
    task whose worker died. ``address``: ``host:port`` of the head node; None connects to
    ``RAY_ADDRESS`` or the cluster started on this machine.

    Every node needs this package installed and access to the input and output paths (a shared
    file system or object storage).
    """

    def __init__(self, address: str | None) -> None:
        if address:  # before Ray's import (seconds): Ray itself retries an unreachable head for minutes
            _check_reachable(address)
        try:
            import ray
        except ImportError:
            raise ImportError("--executor ray needs Ray: pip install 'ncore-convert[ray]'") from None
        self._ray = ray
        ray.init(address=address or "auto", log_to_driver=False, logging_level="WARNING")

    def __enter__(self) -> RayExecutor:
        return self

    def __exit__(self, *exc) -> None:
        self._ray.shutdown()

    def abandon(self) -> None:
        pass  # results() cancels the tasks still running when it returns

    def results(
        self, task: LogTask, output_root: UPath, log_ids: list[str], show_progress: bool, control: RunControl
    ) -> Iterator[LogResult]:
        """Submit as many logs as the cluster has CPUs, each claimed (``control.gate``) when it is
        submitted, so that runs sharing the output split the logs; more as they finish."""
        ray = self._ray
        remote = ray.remote(num_cpus=1, max_retries=2)(_convert_on_node)
        capacity = max(1, int(ray.cluster_resources().get("CPU", 1)))
        waiting, pending = list(log_ids), {}
        try:
            while (waiting or pending) and not control.stop.is_set():
                while waiting and len(pending) < capacity:
                    log_id = waiting.pop(0)
                    if (why := control.gate(log_id)) is not None:
                        yield LogResult(log_id, True, elsewhere=why)
                    else:
                        pending[remote.remote(task, output_root, log_id)] = log_id
                if not pending:
                    continue
                done, _ = ray.wait(list(pending), num_returns=1, timeout=POLL_S)
                if not done:
                    continue
                log_id = pending.pop(done[0])
                try:
                    yield ray.get(done[0])
                except Exception as err:  # noqa: BLE001 - the task died (node lost, retries used up)
                    reason = f"Ray task failed: {type(err).__name__}: {err}".replace("\n", " ")
                    yield LogResult(log_id, False, error=reason)
        finally:
            for ref in pending:  # interrupted: kill the tasks' worker processes (a task may be uploading)
                ray.cancel(ref, force=True)
