"""How a run stops on SIGINT or SIGTERM, from the entry module's first statement to its exit.

:func:`install` (the first statement of :mod:`ncore_convert.entry`, before any worker, fork server,
thread or Ray connection exists) routes both signals here for the life of the process and makes
the process a child subreaper (Linux), so that every process the run starts stays its descendant
even when its parent (the fork server) dies first.

- While a run loop takes stops itself (:func:`deferred`, the whole of ``runner.run_logs``), the
  first signal only sets the run's stop event: the loop abandons its logs in flight, records what it
  published, and ends the process with :func:`end`.
- At any other moment (importing, planning, the pool's start, printing the last lines), and on a
  second signal, the process ends at once with :func:`end`.

:func:`end` kills every descendant of the process (fork server, workers: SIGKILL, so nothing of the
run writes after it), waits for multiprocessing's resource tracker to exit on its own (it unlinks
what the killed workers left), prints the run's last lines, and exits 130.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time

TYPE_CHECKING = False  # typing is not imported at run time: the window before install() stays short
if TYPE_CHECKING:
    from collections.abc import Callable
    from typing import NoReturn

#: The signals that stop a run (Ctrl-C; what Slurm and Kubernetes send before they kill).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: The exit status of a stopped run (128 + SIGINT, as shells report Ctrl-C).
STOPPED_EXIT = 130
#: How long :func:`end` waits for the resource tracker to exit once every other process is gone.
TRACKER_WAIT_S = 2.0
_PR_SET_CHILD_SUBREAPER = 36


def _default_farewell(signal_name: str) -> list[str]:
    return [f"{signal_name}: run stopped before any log started (exit {STOPPED_EXIT})"]


class _State:
    """The process's stop state: the run loop that takes signals, if any, and its last lines."""

    def __init__(self) -> None:
        self.deferring: tuple[threading.Event, list[str]] | None = None
        self.farewell: Callable[[str], list[str]] = _default_farewell
        self.cleanups: list[Callable[[], object]] = []  #: what :func:`end` removes (the run's spool)


_state = _State()


def install() -> None:
    """Route SIGINT and SIGTERM to this module for the life of the process; on Linux, adopt the
    orphans of the process's descendants (PR_SET_CHILD_SUBREAPER), so that :func:`end` finds them."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, _handler)
    with _suppress(OSError, AttributeError):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_CHILD_SUBREAPER, 1)


def at_end(step: Callable[[], object]) -> Callable[[], None]:
    """Have :func:`end` call ``step`` (removing what the run keeps on local disk) if the process
    ends while it is registered; returns the function that unregisters it."""
    _state.cleanups.append(step)
    return lambda: _state.cleanups.remove(step) if step in _state.cleanups else None


def set_farewell(lines: Callable[[str], list[str]]) -> None:
    """What an immediate stop prints (given the signal's name): the run's counts once it knows its output."""
    _state.farewell = lines


def _handler(signum: int, frame) -> None:
    try:
        name = signal.Signals(signum).name
    except ValueError:
        name = f"signal {signum}"
    if _state.deferring is None:
        end(_farewell_lines(name))
    event, received = _state.deferring
    if event.is_set():  # the run is already stopping: a second signal ends it at once
        end([f"{name}: a second signal; run stopped at once (exit {STOPPED_EXIT})"])
    received.append(name)
    event.set()


def _farewell_lines(name: str) -> list[str]:
    """The run's last lines (:func:`set_farewell`), or the default ones if they cannot be made."""
    try:
        return list(_state.farewell(name))
    except Exception:  # noqa: BLE001 - the way out never raises
        return _default_farewell(name)


class deferred:  # noqa: N801 - used as ``with deferred(event, received):``
    """While the block runs, the first SIGINT/SIGTERM appends its name to ``received`` and sets
    ``event`` (the run ends its logs in flight and records what it published); a second one ends
    the process at once (:func:`end`). Only in the main thread, where Python delivers signals."""

    def __init__(self, event: threading.Event, received: list[str]) -> None:
        self.event, self.received = event, received
        self.previous: dict | None = None

    def __enter__(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        self.previous = {sig: signal.signal(sig, _handler) for sig in STOP_SIGNALS}
        self.outer, _state.deferring = _state.deferring, (self.event, self.received)

    def __exit__(self, *exc) -> None:
        if self.previous is None:
            return
        _state.deferring = self.outer
        for sig, old in self.previous.items():
            signal.signal(sig, old)


class _suppress:  # noqa: N801
    """``contextlib.suppress``, written here so that the stop module, imported before the handlers
    are installed, does not import contextlib (4 ms of the window before them)."""

    def __init__(self, *kinds: type[BaseException]) -> None:
        self.kinds = kinds

    def __enter__(self) -> None:
        return None

    def __exit__(self, kind, value, traceback) -> bool:
        return kind is not None and issubclass(kind, self.kinds)


def end(lines: list[str]) -> NoReturn:
    """Kill every descendant process, print ``lines`` (after what stdout still buffers) and exit 130
    at once: threads of this process that are planning or writing are not awaited.

    Nothing on this path imports or raises: it may run while any module is half imported (a signal
    arrives as an import starts), so what it cleans up it finds among the modules already loaded (a
    module not loaded has nothing to clean), each step on its own, and the exit comes whatever fails."""
    try:
        for step in (_ignore_signals, _no_new_processes, _flush, _silence_stderr, kill_descendants, _clean_up):
            _attempt(step)
        with _suppress(Exception):
            os.write(sys.stdout.fileno() if sys.stdout else 1, "".join(f"{line}\n" for line in lines).encode())
        _attempt(_await_tracker)
    finally:
        os._exit(STOPPED_EXIT)


def _attempt(step: Callable[[], object]) -> None:
    with _suppress(Exception):
        step()


def _ignore_signals() -> None:
    """A further signal while the process ends changes nothing (main thread only, where handlers run)."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)


def _flush() -> None:
    for stream in (sys.stdout, sys.stderr):
        with _suppress(Exception):  # a handler may interrupt a print
            stream.flush()


def _loaded(name: str, attribute: str):
    """``attribute`` of the module ``name`` if that module is loaded and has it (a module that is
    still importing may not have it yet), else None: never an import."""
    return getattr(sys.modules.get(name), attribute, None)


def _clean_up() -> None:
    """What the run holds outside its processes: a publish's multipart uploads under way (if the
    output module is loaded), what the run registered (:func:`at_end`: its spool of fetched files),
    and multiprocessing's temporary folder (the fork server's socket; its finalizer does not run on
    this way out)."""
    if callable(step := _loaded("ncore_convert.storage", "abort_uploads_in_flight")):
        _attempt(step)  # a publish to a bucket: no multipart upload left
    for step in list(_state.cleanups):
        _attempt(step)
    process = _loaded("multiprocessing.process", "current_process")
    tempdir = process()._config.get("tempdir") if callable(process) else None
    if tempdir and callable(rmtree := _loaded("shutil", "rmtree")):
        _attempt(lambda: rmtree(tempdir, ignore_errors=True))


def _refuse(*args, **kwargs) -> NoReturn:
    raise RuntimeError("the run is stopping: no process starts")


def _no_new_processes() -> None:
    """From now on, a thread of this process (a pool's management thread replacing a killed worker)
    cannot start a fork server or a resource tracker again (if multiprocessing loaded them at all)."""
    for module, instance in (
        ("multiprocessing.forkserver", "_forkserver"),
        ("multiprocessing.resource_tracker", "_resource_tracker"),
    ):
        if (found := _loaded(module, instance)) is not None:
            with _suppress(Exception):
                found.ensure_running = _refuse


def _silence_stderr() -> None:
    threading.excepthook = lambda args: None
    with _suppress(OSError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 2)


def _live_children() -> dict[int, list[int]]:
    """Every live (not zombie) process by its parent's pid, from ``/proc`` (empty elsewhere)."""
    children: dict[int, list[int]] = {}
    with _suppress(OSError):
        for entry in os.scandir("/proc"):
            if not entry.name.isdigit():
                continue
            try:
                with open(f"/proc/{entry.name}/stat") as f:
                    state, ppid = f.read().rsplit(")", 1)[1].split()[:2]
            except (OSError, ValueError):
                continue  # gone meanwhile
            if state != "Z":
                children.setdefault(int(ppid), []).append(int(entry.name))
    return children


def descendants(pid: int) -> set[int]:
    """The live descendants of a process (Linux; empty where ``/proc`` cannot be read)."""
    children, found, todo = _live_children(), set(), [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            if child not in found:
                found.add(child)
                todo.append(child)
    return found


def _tracker_pid() -> int | None:
    return getattr(_loaded("multiprocessing.resource_tracker", "_resource_tracker"), "_pid", None)


def kill_descendants() -> None:
    """SIGKILL every descendant but the resource tracker, until none is left: a process forked
    while its parent was being killed is adopted by this one (the subreaper) and found on the next
    pass. Zombies are reaped."""
    spare = {_tracker_pid()}
    for _ in range(100):
        alive = descendants(os.getpid()) - spare
        if not alive:
            break
        for pid in alive:
            with _suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        time.sleep(0.005)
    _reap()


def _reap() -> None:
    with _suppress(ChildProcessError):
        while os.waitpid(-1, os.WNOHANG)[0]:
            pass


def _await_tracker() -> None:
    """Close this process's end of the resource tracker's pipe and wait for the tracker to exit (it
    does once no process holds the pipe: every other descendant is dead); kill it after TRACKER_WAIT_S."""
    tracker = _loaded("multiprocessing.resource_tracker", "_resource_tracker")
    pid, fd = getattr(tracker, "_pid", None), getattr(tracker, "_fd", None)
    if pid is None:
        return
    with _suppress(OSError, TypeError):
        os.close(fd)
    deadline = time.monotonic() + TRACKER_WAIT_S
    while time.monotonic() < deadline:
        try:
            if os.waitpid(pid, os.WNOHANG)[0]:
                return
        except ChildProcessError:  # not this process's child (or reaped already)
            return
        time.sleep(0.005)
    with _suppress(OSError):
        os.kill(pid, signal.SIGKILL)
