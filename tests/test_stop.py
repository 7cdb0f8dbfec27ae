"""A stopped run leaves nothing running (issue 65, docs/scale-out.md): SIGTERM to the process or
SIGINT to its process group, at any moment from the command's first second on, ends the run with
exit 130 and the stop's lines only; no process of the run (fork server, workers, resource tracker)
is alive 3 s later and nothing under the output folder changes after the exit.

Two trials per suite run at seeded random moments over the span the issue names (0.3-2.0 s: imports,
planning, the pool's start, the first logs); bench/bench_stop.py runs the acceptance's full grid.

A signal that arrives while a module is half imported (issue 72) is delivered deterministically: an
import hook (tests/signal_at_import/sitecustomize.py) makes the command signal itself as the named
module starts importing, for each module the command imports on its way to a run, both signals.
"""

from __future__ import annotations

import os
import random
import re
import signal
import subprocess
from pathlib import Path

import pytest
from conftest import BIN, av2_command
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


HOOK = Path(__file__).parent / "signal_at_import"
#: The modules a run imports on its way (a local run with two workers unless a command is named):
#: the window before the handlers (importlib.metadata: the package's version), the CLI and its
#: libraries, multiprocessing and the submodules the pool starts, the runner, the NCore library,
#: and the S3 stack (an s3:// input) and Ray (--executor ray) where those are used.
IMPORT_MOMENTS = {
    "importlib.metadata": "local",
    "ncore_convert.cli": "local",
    "click": "local",
    "numpy": "local",
    "pyarrow": "local",
    "fsspec": "local",
    "multiprocessing": "local",
    "multiprocessing.connection": "local",
    "multiprocessing.spawn": "local",
    "multiprocessing.forkserver": "local",
    "multiprocessing.resource_tracker": "local",
    "ncore_convert.run.runner": "local",
    "ncore": "local",
    "s3fs": "s3",
    "botocore": "s3",
    "aiobotocore": "s3",
    "ray": "ray",
}


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("module", list(IMPORT_MOMENTS))
def test_a_signal_as_a_module_starts_importing_ends_the_run_with_its_one_line(six_logs, tmp_path, module, signum):
    roots = {"local": str(six_logs), "s3": "s3://ncore-convert-absent-bucket/source", "ray": str(six_logs)}
    group = ["--workers", "2"] + (["--executor", "ray"] if IMPORT_MOMENTS[module] == "ray" else [])
    command = [str(BIN / "ncore-convert"), "--root-dir", roots[IMPORT_MOMENTS[module]]]
    command += ["--output-dir", str(tmp_path / "out"), *group, "argoverse2-v4", "--split", "val"]
    env = {**os.environ, "PYTHONPATH": str(HOOK), "NCORE_CONVERT_SIGNAL_AT": f"{module}:{int(signum)}"}
    env.update(AWS_ACCESS_KEY_ID="test", AWS_SECRET_ACCESS_KEY="test", AWS_EC2_METADATA_DISABLED="true")
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)
    name = signal.Signals(signum).name
    where = f"{name} as {module} starts importing: exit {done.returncode}\n{done.stdout}{done.stderr}"
    marker = f"[signal-at-import: {module}]"
    assert marker in done.stderr, where + "\n(the command never imported the module: the hook did not fire)"
    assert done.returncode == 130, where
    assert done.stderr.strip() == marker, where  # no traceback, no message but the stop's
    lines = done.stdout.strip().splitlines()
    assert lines and all(STOP_LINES.match(line) for line in lines), where
    assert lines[-1].startswith(f"{name}: ") and "run stopped" in lines[-1], where
