"""One stop trial: the installed command converting a folder of logs, a signal at a chosen moment,
and what is left afterwards (issue 65's acceptance; used by tests/test_stop.py and bench/bench_stop.py).

Every process of the run is found by a mark in its environment (the fork server, the workers and the
resource tracker inherit it), also after it was orphaned; the output folder is listed (path, size,
mtime) at the exit and again later, so that a write after the exit shows.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

#: How long after the run's exit no process of it may be alive and nothing may change (issue 65).
AFTER_S = 3.0


@dataclass
class Trial:
    moment_s: float  #: when the signal was sent, from the start of the command
    returncode: int
    output: str  #: stdout (piped), then stderr
    exit_s: float  #: from the signal to the exit
    survivors: list[str]  #: processes of the run alive AFTER_S after its exit ("pid cmdline")
    changed: list[str]  #: paths under the output folder that changed after the exit

    @property
    def clean(self) -> bool:
        return self.returncode == 130 and not self.survivors and not self.changed


def _marked(mark: str) -> list[str]:
    found = []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            environ = Path(f"/proc/{entry.name}/environ").read_bytes()
            if f"NCORE_CONVERT_TRIAL={mark}".encode() not in environ.split(b"\0"):
                continue
            state = Path(f"/proc/{entry.name}/stat").read_text().rsplit(")", 1)[1].split()[0]
            command = Path(f"/proc/{entry.name}/cmdline").read_bytes().replace(b"\0", b" ").decode()[:120]
        except OSError:
            continue
        if state != "Z":
            found.append(f"{entry.name} {command}")
    return found


def _listing(out: Path) -> dict[str, tuple[int, int]]:
    listing = {}
    for folder, dirs, files in os.walk(out):
        for name in dirs + files:
            path = os.path.join(folder, name)
            try:
                st = os.lstat(path)
            except FileNotFoundError:
                continue
            listing[os.path.relpath(path, out)] = (st.st_size, st.st_mtime_ns)
    return listing


def trial(command: list[str], out: Path, moment_s: float, signum: int, group: bool, child: bool = False) -> Trial:
    """Start ``command`` (stdout piped, in a process group of its own), send ``signum`` at
    ``moment_s`` (to the process, or to its group with ``group``; with ``child``, to the command's
    first child instead: the run that ``unshare --pid --fork`` started as PID 1 of its namespace, as a
    container runtime signals a container), and look again AFTER_S later."""
    mark = uuid.uuid4().hex
    env = {**os.environ, "NCORE_CONVERT_TRIAL": mark}
    started = time.monotonic()
    proc = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, start_new_session=True, text=True
    )
    time.sleep(max(0.0, started + moment_s - time.monotonic()))
    sent = time.monotonic()
    if proc.poll() is None:
        target = proc.pid
        if child and not group:
            children = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()
            target = int(children[0]) if children else proc.pid
        (os.killpg if group else os.kill)(target, signum)
    try:
        stdout, stderr = proc.communicate(timeout=60)  # ends when every holder of the pipes is gone
    except subprocess.TimeoutExpired:
        proc.kill()
        stdout, stderr = proc.communicate()
        stderr += "\n[the pipes stayed open 60 s after the signal]"
    exit_s = time.monotonic() - sent
    at_exit = _listing(out)
    time.sleep(AFTER_S)
    survivors = _marked(mark)
    later = _listing(out)
    changed = sorted(p for p in set(at_exit) | set(later) if at_exit.get(p) != later.get(p))
    for line in survivors:  # leave nothing behind for the next trial
        try:
            os.kill(int(line.split()[0]), signal.SIGKILL)
        except OSError:
            pass
    return Trial(moment_s, proc.returncode, stdout + stderr, exit_s, survivors, changed)
