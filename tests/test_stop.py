"""A stopped run leaves nothing running (issue 65, docs/scale-out.md): SIGTERM to the process or
SIGINT to its process group, at any moment from the command's first second on, ends the run with
exit 130 and the stop's lines only; no process of the run (fork server, workers, resource tracker)
is alive 3 s later and nothing under the output folder changes after the exit.

Two trials per suite run at seeded random moments over the span the issue names (0.3-2.0 s: imports,
planning, the pool's start, the first logs); bench/bench_stop.py runs the acceptance's full grid.
"""

from __future__ import annotations

import random
import re
import signal

import pytest
from conftest import av2_command
from stop_trials import trial
from upath import UPath

from ncore_convert.synth.argoverse2 import SynthConfig, write_log

#: What a stopped run may print: per-log lines, the stop notice, the counts and the last line.
STOP_LINES = re.compile(r"^(ok    |skip  |stop  |left  |      |SIG(INT|TERM): |\d+ converted, \d+ skipped, \d+ failed)")


@pytest.fixture(scope="module")
def six_logs(tmp_path_factory):
    root = tmp_path_factory.mktemp("six")
    for seed in range(401, 407):
        write_log(UPath(root / "val"), SynthConfig(seconds=0.5, seed=seed, camera_fps=0))
    return root


@pytest.mark.parametrize(
    ("signum", "group", "workers"),
    [(signal.SIGTERM, False, ("--workers", "2")), (signal.SIGINT, True, ())],
    ids=["SIGTERM-process-2-workers", "SIGINT-group-default-workers"],
)
def test_a_signal_at_any_moment_ends_the_run_and_everything_it_started(six_logs, tmp_path, signum, group, workers):
    moment_s = random.Random(f"{signum}-{group}-65").uniform(0.3, 2.0)
    out = tmp_path / "out"
    result = trial(av2_command(six_logs, out, *workers), out, moment_s, signum, group)
    where = f"{signal.Signals(signum).name} at {moment_s:.2f} s:\n{result.output}"
    assert result.returncode == 130, where
    assert not result.survivors, where + f"\nalive 3 s after the exit: {result.survivors}"
    assert not result.changed, where + f"\nchanged after the exit: {result.changed}"
    lines = result.output.strip().splitlines()
    assert lines and all(STOP_LINES.match(line) for line in lines), where  # no traceback, nothing else
    assert f"{signal.Signals(signum).name}: " in lines[-1] and "run stopped" in lines[-1], where
