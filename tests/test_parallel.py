"""Parallel store writing: same bytes as one process, library-equal sequence meta, errors and progress."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner
from ncore.data.v4 import SequenceComponentGroupsReader
from upath import UPath

from ncore_convert.cli import cli
from ncore_convert.converters.argoverse2 import Argoverse2Options, convert_log
from ncore_convert.run.pool import JobPool, Progress
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.synth.argoverse2 import SynthConfig, write_log
from ncore_convert.writer.parts import BASE_JOB, WriteJob, independent_parts

PRELOAD = ["ncore_convert.converters.argoverse2"]


@pytest.fixture(scope="module")
def camera_root(tmp_path_factory):
    """A 0.3 s synthetic log with images at 10 fps."""
    root = tmp_path_factory.mktemp("parallel")
    truth = write_log(UPath(root / "val"), SynthConfig(seconds=0.3, seed=11, camera_fps=10, camera_scale=4))
    return root, truth


@pytest.fixture(scope="module")
def pool():
    with JobPool(2, preload=PRELOAD) as p:
        yield p


def _convert(root, out, log_id, pool, **options):
    frames, totals = [], []
    progress = Progress(frames.append, totals.append)
    summary = convert_log(
        UPath(root), UPath(out), log_id, Argoverse2Options(split="val", **options), pool=pool, progress=progress
    )
    assert totals == [sum(frames)]  # the total is announced once and the frames add up to it
    return summary, sum(frames)


def test_two_processes_write_the_same_bytes_as_one(camera_root, pool, tmp_path):
    root, truth = camera_root
    inline, inline_frames = _convert(root, tmp_path / "one", truth.log_id, None)
    parallel, parallel_frames = _convert(root, tmp_path / "two", truth.log_id, pool)
    one = {p.name: p.read_bytes() for p in (tmp_path / "one").iterdir()}
    two = {p.name: p.read_bytes() for p in (tmp_path / "two").iterdir()}
    assert len(one) == 1 + 1 + 2 + 9  # meta json, base store, two lidars, nine cameras
    assert one.keys() == two.keys()
    for name in one:
        assert one[name] == two[name], name
    expected_frames = len(truth.sweeps) + truth.n_images
    assert inline_frames == parallel_frames == expected_frames
    assert (inline.frames, inline.images, inline.cuboids, inline.points) == (
        parallel.frames,
        parallel.images,
        parallel.cuboids,
        parallel.points,
    )
    assert parallel.images == truth.n_images and parallel.cuboids == truth.n_cuboids


def test_joined_sequence_meta_equals_the_library_meta_of_all_stores(camera_root, pool, tmp_path):
    root, truth = camera_root
    _convert(root, tmp_path, truth.log_id, pool)
    ours = json.loads((tmp_path / f"{truth.log_id}.json").read_text())
    stores = [UPath(tmp_path / s["path"]) for s in ours["component_stores"]]
    library = SequenceComponentGroupsReader(stores).get_sequence_meta().to_dict()
    by_path = lambda meta: {s["path"]: s for s in meta["component_stores"]}  # noqa: E731
    assert by_path(ours) == by_path(library)
    assert {k: v for k, v in ours.items() if k != "component_stores"} == {
        k: v for k, v in library.items() if k != "component_stores"
    }
    # stores are listed base first, then lidars, then cameras, whichever process finished first
    assert [s["path"].split(".ncore4")[1] for s in ours["component_stores"][:3]] == [
        ".zarr.itar",
        "-up_lidar.zarr.itar",
        "-down_lidar.zarr.itar",
    ]


def test_independent_parts_never_share_a_store():
    cams, lidars = ["cam_a", "cam_b"], ["up", "down"]
    jobs = [BASE_JOB, WriteJob(("up", "down")), WriteJob(("cam_a",)), WriteJob(("cam_b",))]
    assert independent_parts(jobs, cams, lidars, "default") == [[0, 1, 2, 3]]
    assert independent_parts(jobs, cams, lidars, "separate-sensors") == [[0], [1], [2], [3]]
    assert independent_parts(jobs, cams, lidars, "separate-all") == [[0], [1], [2], [3]]
    # a job touching the stores of two others joins them
    four = [BASE_JOB, WriteJob(("cam_a",)), WriteJob(("up",)), WriteJob(("cam_a", "up"))]
    assert independent_parts(four, cams, lidars, "separate-sensors") == [
        [0],
        [1, 2, 3],
    ]


@pytest.mark.parametrize("workers", ["1", "2"])
def test_a_failure_inside_a_worker_names_the_file_and_leaves_nothing(camera_root, tmp_path, workers):
    import shutil

    root, truth = camera_root
    log_dir = tmp_path / "root" / "val" / truth.log_id
    shutil.copytree(truth.log_dir.path, log_dir)
    stamps = av2.list_image_timestamps_ns(UPath(log_dir), "ring_side_left")
    bad = av2.image_path(UPath(log_dir), "ring_side_left", int(stamps[-1]))
    bad.write_bytes(b"GIF89a" + bad.read_bytes()[6:])
    out = tmp_path / "out"
    result = CliRunner().invoke(
        cli,
        [
            "--no-progress",
            "--root-dir",
            str(tmp_path / "root"),
            "--output-dir",
            str(out),
            "--workers",
            workers,
            "argoverse2-v4",
            "--split",
            "val",
        ],
    )
    assert result.exit_code == 1, result.output
    fail = [line for line in result.output.splitlines() if line.startswith("FAIL")]
    assert len(fail) == 1 and str(bad) in fail[0] and "not a JPEG" in fail[0], result.output
    assert [p.name for p in out.iterdir()] == ["conversion-report.json"]


def test_pool_runs_jobs_in_order_and_reports_progress(pool):
    seen, totals = [], []
    assert pool.run([(_count_to, (n,)) for n in (3, 1, 2)], Progress(seen.append, totals.append)) == [3, 1, 2]
    assert sum(seen) == 6 and sorted(totals) == [1, 2, 3]
    with pytest.raises(ValueError, match="boom"):
        pool.run([(_count_to, (1,)), (_fail, ())])


def _count_to(n: int, progress) -> int:
    progress.total(n)
    for _ in range(n):
        progress(1)
    return n


def _fail(progress) -> None:
    raise ValueError("boom")


def test_an_unexpected_worker_error_is_reported_where_the_worker_raised_it(pool, tmp_path):
    from ncore_convert.run.runner import convert_one

    def convert(seq_dir, log_id, progress):
        return pool.run([(_fail, ())])

    result = convert_one(UPath(tmp_path), "log", convert, show_progress=False)
    assert not result.ok and result.error.startswith("ValueError: boom (at ")
    assert f"{__file__}:" in result.error and not list(tmp_path.iterdir())


def test_a_killed_worker_fails_that_run_and_fresh_workers_serve_the_next(pool):
    from ncore_convert.run.pool import WorkerDied

    with pytest.raises(WorkerDied, match="worker process died"):
        pool.run([(_kill_self, ()), (_count_to, (2,))])
    assert pool.run([(_count_to, (n,)) for n in (1, 2)]) == [1, 2]


def _kill_self(progress) -> None:
    import os
    import signal

    os.kill(os.getpid(), signal.SIGKILL)
