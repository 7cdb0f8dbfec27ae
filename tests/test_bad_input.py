"""The damaged-input corpus: every case has one specified outcome (docs/damaged-input.md).

Each case damages a copy of a small synthetic dataset (AV2, TbV or OPV2V), converts it with the
runner's per-log wrapper and validation, exactly as the CLI does, and checks the outcome:

- ``fail``: the log fails with one line that names ``file`` and contains ``cause``; nothing is
  left in the output folder (no sequence, no partial folder);
- ``warn``: the log converts and validates against its source, and a warning names ``file`` and
  contains ``cause`` (the data it affects are skipped, counted and, for frames, declared in the
  sensor's ``skipped_frames``).
"""

from __future__ import annotations

import errno
import os
import re
import resource
import shutil
import signal
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.feather as feather
import pytest
from conftest import AV2_SAMPLE_LOG, REPO, find_opv2v_agent
from upath import UPath

from ncore_convert.converters.argoverse2 import Argoverse2Options, convert_log
from ncore_convert.converters.opencood import OpenCoodOptions, convert_scenario
from ncore_convert.run.runner import convert_one
from ncore_convert.sources import store
from ncore_convert.synth import opencood as synth_opencood
from ncore_convert.synth.argoverse2 import SynthConfig, write_log
from ncore_convert.validate.tree import convert_and_validate

CAMERAS = ("ring_front_center", "ring_side_left")


@dataclass(frozen=True)
class Case:
    dataset: str  #: "av2", "real" (the real AV2 sample), "tbv", "opv2v" or "one-tick" (a V2XSet tick)
    damage: Callable[[Path], Path]  #: damages the log (or scenario) folder, returns the file at fault
    outcome: str  #: "fail", "usage" (fails as a usage error: the options cannot apply) or "warn"
    cause: str
    options: dict = field(default_factory=dict)  #: conversion options of the case (a clip window)


# ------------------------------------------------------------------------------------------------
# Damage, applied to a copy of the log (AV2, TbV) or scenario (OPV2V) folder
# ------------------------------------------------------------------------------------------------


def _sweeps(log: Path) -> list[Path]:
    return sorted((log / "sensors" / "lidar").glob("*.feather"))


def _image(log: Path) -> Path:
    return sorted((log / "sensors" / "cameras" / CAMERAS[0]).glob("*.jpg"))[1]


def _poses(log: Path) -> Path:
    return log / "city_SE3_egovehicle.feather"


def _edit_table(path: Path, edit: Callable[[pa.Table], pa.Table]) -> Path:
    feather.write_feather(edit(feather.read_table(path)), path)
    return path


def _truncate(path: Path) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def _garble(path: Path) -> Path:
    path.write_bytes(np.random.default_rng(0).bytes(path.stat().st_size))
    return path


def _rows(table: pa.Table, rows) -> pa.Table:
    return table.take(pa.array(rows, pa.int64()))


def _without_sensor(path: Path, sensor: str) -> Path:
    return _edit_table(path, lambda t: t.filter(pc.not_equal(t["sensor_name"], sensor)))


def _cast(path: Path, column: str, to: pa.DataType) -> Path:
    return _edit_table(path, lambda t: t.set_column(t.schema.get_field_index(column), column, t[column].cast(to)))


def _sensor_end_ns(log: Path) -> int:
    """The latest sensor time of the log: its last image, or its last sweep's last point."""
    last = _sweeps(log)[-1]
    images = [int(p.stem) for p in (log / "sensors" / "cameras").glob("*/*.jpg")]
    return max([int(last.stem) + int(feather.read_table(last)["offset_ns"].to_numpy().max()), *images])


def _poses_until(log: Path, end_ns: int) -> Path:
    return _edit_table(_poses(log), lambda t: t.filter(pc.less_equal(t["timestamp_ns"], end_ns)))


def _pose_gap(log: Path) -> Path:
    """No pose from the first sweep until 100 ms after the third (about 300 ms)."""
    first, _, third = (int(p.stem) for p in _sweeps(log)[:3])
    third += 100_000_000
    keep = lambda t: pc.invert(  # noqa: E731
        pc.and_(pc.greater(t["timestamp_ns"], first), pc.less(t["timestamp_ns"], third))
    )
    return _edit_table(_poses(log), lambda t: t.filter(keep(t)))


def _empty(log: Path) -> Path:
    shutil.rmtree(log)
    log.mkdir()
    return log


def _offsets_late(log: Path) -> Path:
    """A middle sweep whose points claim to fire 2 s later."""
    late = lambda t: pa.array(t["offset_ns"].to_numpy() + 2_000_000_000, pa.int32())  # noqa: E731
    return _edit_table(
        _sweeps(log)[1], lambda t: t.set_column(t.schema.get_field_index("offset_ns"), "offset_ns", late(t))
    )


def _nan_pose(log: Path) -> Path:
    def edit(t: pa.Table) -> pa.Table:
        tx = t["tx_m"].to_numpy().copy()
        tx[3] = np.nan
        return t.set_column(t.schema.get_field_index("tx_m"), "tx_m", pa.array(tx))

    return _edit_table(_poses(log), edit)


def _bad_sweep_name(log: Path) -> Path:
    bad = log / "sensors" / "lidar" / "latest.feather"
    shutil.copy(_sweeps(log)[0], bad)
    return bad


def unreadable(path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Make ``path`` unreadable: mode 000; a root user reads any file, so there the open of that
    file is made to fail with EACCES, as it would for anyone else (the error path is the same)."""
    path.chmod(0)
    if os.geteuid() == 0:
        real_open = open

        def refusing_open(file, *args, **kwargs):
            if os.fspath(file) == str(path):
                raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
            return real_open(file, *args, **kwargs)

        monkeypatch.setattr(store, "open", refusing_open, raising=False)
    return path


# OPV2V: scenario folder -> first agent folder and its frame keys


def _agents(scenario: Path) -> list[Path]:
    return sorted((p for p in scenario.iterdir() if p.is_dir()), key=lambda p: int(p.name))


def _frame(scenario: Path, suffix: str, agent: int = 0, key: int = 1) -> Path:
    folder = _agents(scenario)[agent]
    keys = sorted(p.stem for p in folder.glob("*.yaml"))
    return folder / f"{keys[key]}{suffix}"


def _edit_text(path: Path, edit: Callable[[str], str]) -> Path:
    path.write_text(edit(path.read_text()))
    return path


def _pcd_short(path: Path) -> Path:
    lines = path.read_text().splitlines(keepends=True)
    body = next(i for i, line in enumerate(lines) if line.startswith("DATA")) + 1
    path.write_text("".join(lines[: body + (len(lines) - body) // 2]))
    return path


def _pcd_nan(path: Path) -> Path:
    lines = path.read_text().splitlines(keepends=True)
    row = next(i for i, line in enumerate(lines) if line.startswith("DATA")) + 1
    lines[row] = "nan " + lines[row].split(" ", 1)[1]
    path.write_text("".join(lines))
    return path


def _pcd_intensity_255(scenario: Path) -> Path:
    """A PCD with a float ``intensity`` field on a 0-255 scale (CARLA's is 0-1)."""
    path = _frame(scenario, ".pcd")
    lines = path.read_text().splitlines(keepends=True)
    row = next(i for i, line in enumerate(lines) if line.startswith("DATA")) + 1
    for i, line in enumerate(lines):
        lines[i] = line.replace("FIELDS x y z rgb", "FIELDS x y z intensity")
        if i >= row:
            lines[i] = " ".join(line.split()[:3] + ["255"]) + "\n"
    path.write_text("".join(lines))
    return path


def _agent_missing(scenario: Path) -> Path:
    folder = _agents(scenario)[1]
    key = sorted(p.stem for p in folder.glob("*.yaml"))[2]
    for f in folder.glob(f"{key}*"):
        f.unlink()
    return folder


def _drop_offsets(log: Path) -> Path:
    return _edit_table(_sweeps(log)[1], lambda t: t.drop_columns(["offset_ns"]))


def _pose_rows(order: Callable[[int], list[int]]) -> Callable[[Path], Path]:
    return lambda log: _edit_table(_poses(log), lambda t: _rows(t, order(t.num_rows)))


def _remove(path: Path) -> Path:
    shutil.rmtree(path) if path.is_dir() else path.unlink()
    return path


def _missing_camera_folder(log: Path) -> Path:
    _remove(log / "sensors" / "cameras" / CAMERAS[1])
    return log / "sensors" / "cameras"


def _pcd_nan_agent(scenario: Path) -> Path:
    _pcd_nan(_frame(scenario, ".pcd"))
    return _agents(scenario)[0]


def _cut(path: Path, fraction: float) -> Path:
    """Keep the first ``fraction`` of a file (the real V2XSet case: a PCD cut to its first 30,000 bytes)."""
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    return path


def _real_pcd_cut(scenario: Path) -> Path:
    """A real OPV2V frame in a one-tick vehicle's place, cut to its first 30,000 bytes: the real
    V2XSet scenario's case (a download that stopped mid-file; here in the 563rd point's intensity,
    which still reads as a number: the point count gives it away)."""
    path = _frame(scenario, ".pcd", agent=1, key=0)
    path.write_bytes((find_opv2v_agent() / "000070.pcd").read_bytes()[:30_000])
    return path


def _every(scenario: Path, pattern: str, agent: int = 0) -> Path:
    """Garble every file of one agent matching ``pattern``; the first of them."""
    paths = sorted(_agents(scenario)[agent].glob(pattern))
    for path in paths:
        _garble(path)
    return paths[0]


def _every_agent_frame(scenario: Path) -> Path:
    """Every agent's only PCD and PNGs damaged: no agent has a sensor left; the first file named."""
    for folder in _agents(scenario):
        for path in [*folder.glob("*.pcd"), *folder.glob("*.png")]:
            _cut(path, 0.3)
    return _frame(scenario, ".pcd", agent=0, key=0)


def _yaml_without_lidar_pose(scenario: Path) -> Path:
    return _edit_text(_frame(scenario, ".yaml"), lambda t: re.sub(r"(?m)^lidar_pose:", "lidar_pos:", t))


EXTRINSICS = ("calibration", "egovehicle_SE3_sensor.feather")
INTRINSICS = ("calibration", "intrinsics.feather")

#: The corpus: case id -> what it damages, and the specified outcome. docs/damaged-input.md's table has a row
#: per case (checked by test_readme_table_lists_every_case).
CASES: dict[str, Case] = {
    "truncated-feather": Case("av2", lambda log: _truncate(_sweeps(log)[1]), "fail", "not a readable feather table"),
    "corrupt-feather": Case(
        "av2", lambda log: _garble(log / "annotations.feather"), "fail", "not a readable feather table"
    ),
    "wrong-column-dtype": Case(
        "av2", lambda log: _cast(_poses(log), "tx_m", pa.float32()), "fail", "column 'tx_m' has type float"
    ),
    "missing-column": Case("av2", _drop_offsets, "fail", "offset_ns"),
    "missing-calibration-row": Case(
        "av2",
        lambda log: _without_sensor(log.joinpath(*EXTRINSICS), "down_lidar"),
        "fail",
        "no extrinsic for 'down_lidar'",
    ),
    "missing-intrinsics": Case(
        "av2",
        lambda log: _without_sensor(log.joinpath(*INTRINSICS), CAMERAS[1]),
        "fail",
        f"no intrinsics for '{CAMERAS[1]}'",
    ),
    "missing-camera-folder": Case(
        "av2", _missing_camera_folder, "warn", f"no images for {CAMERAS[1]}; cameras not written"
    ),
    "poses-end-early": Case(
        "av2", lambda log: _poses_until(log, int(_sweeps(log)[0].stem) + 50_000_000), "fail", "poses do not cover"
    ),
    "poses-end-slightly-early": Case(
        "av2", lambda log: _poses_until(log, _sensor_end_ns(log) - 50_000_000), "warn", "extended at constant velocity"
    ),
    "pose-gap": Case("av2", _pose_gap, "fail", "no pose for"),
    "duplicate-timestamps": Case(
        "av2", _pose_rows(lambda n: [0, 1, 1, *range(2, n)]), "fail", "duplicate timestamp_ns at row 2"
    ),
    "non-monotonic-timestamps": Case(
        "av2", _pose_rows(lambda n: [0, 2, 1, *range(3, n)]), "fail", "non-monotonic timestamp_ns at row 2"
    ),
    "duplicate-annotation": Case(
        "av2",
        lambda log: _edit_table(log / "annotations.feather", lambda t: _rows(t, [0, *range(t.num_rows)])),
        "fail",
        "annotated twice",
    ),
    "non-finite-pose": Case("av2", _nan_pose, "fail", "row 3: not a pose"),
    "corrupt-jpeg": Case("av2", lambda log: _garble(_image(log)), "fail", "not a JPEG file (missing SOI marker)"),
    "truncated-jpeg": Case("av2", lambda log: _truncate(_image(log)), "fail", "truncated JPEG (no EOI marker"),
    "point-times-outside-log": Case("av2", _offsets_late, "fail", "point times reach outside the log's time range"),
    "bad-sweep-file-name": Case("av2", _bad_sweep_name, "fail", "file name is not <timestamp_ns>.feather"),
    "empty-log-directory": Case("av2", _empty, "fail", "empty log directory"),
    "unreadable-file": Case("av2", _image, "fail", "unreadable (Permission denied)"),
    "full-output-disk": Case("av2", lambda log: log, "fail", "output not written (File too large [EFBIG])"),
    "real-truncated-sweep": Case(
        "real", lambda log: _truncate(_sweeps(log)[1]), "fail", "not a readable feather table"
    ),
    "real-non-monotonic-timestamps": Case(
        "real", _pose_rows(lambda n: [0, 2, 1, *range(3, n)]), "fail", "non-monotonic timestamp_ns at row 2"
    ),
    "tbv-without-map": Case("tbv", lambda log: _remove(log / "map"), "warn", "no map folder; no HD map written"),
    "tbv-corrupt-map": Case(
        "tbv", lambda log: _garble(next((log / "map").glob("log_map_archive_*.json"))), "fail", "not JSON"
    ),
    "pcd-wrong-header": Case(
        "opv2v",
        lambda s: _edit_text(_frame(s, ".pcd"), lambda t: t.replace("FIELDS", "FIELD")),
        "warn",
        "PCD header lacks FIELDS; lidar frame skipped",
    ),
    "pcd-short-body": Case("opv2v", lambda s: _pcd_short(_frame(s, ".pcd")), "warn", "the header says"),
    "pcd-nan": Case(
        "opv2v", _pcd_nan_agent, "warn", "1 lidar points at zero range or with non-finite coordinates not stored"
    ),
    "yaml-missing-key": Case("opv2v", _yaml_without_lidar_pose, "warn", "missing key 'lidar_pose'; frame skipped"),
    "yaml-corrupt": Case("opv2v", lambda s: _garble(_frame(s, ".yaml")), "warn", "; frame skipped"),
    "agent-missing-at-timestamp": Case(
        "opv2v", _agent_missing, "warn", "that other agents have; skipped for this agent"
    ),
    "corrupt-png": Case(
        "opv2v",
        lambda s: _garble(_frame(s, "_camera0.png")),
        "warn",
        "not a PNG file (missing signature); image skipped",
    ),
    "truncated-png": Case(
        "opv2v", lambda s: _truncate(_frame(s, "_camera0.png")), "warn", "truncated PNG (no IEND chunk at the end)"
    ),
    "unreadable-pcd": Case(
        "opv2v", lambda s: _frame(s, ".pcd"), "warn", "unreadable (Permission denied); lidar frame skipped"
    ),
    "missing-protocol": Case(
        "opv2v", lambda s: _remove(s / "data_protocol.yaml"), "warn", "not found; CARLA tick 0.05 s assumed"
    ),
    "pcd-intensity-out-of-range": Case(
        "opv2v", _pcd_intensity_255, "warn", "PCD intensity 255.0 outside [0, 1] (CARLA's ray-cast intensity)"
    ),
    "empty-scenario-folder": Case("opv2v", _empty, "fail", "empty scenario folder"),
    "one-tick-truncated-pcd": Case(
        "one-tick", lambda s: _cut(_frame(s, ".pcd", agent=1, key=0), 0.3), "warn", "no readable lidar frame of 1"
    ),
    "one-tick-real-pcd-cut": Case(
        "one-tick",
        _real_pcd_cut,
        "warn",
        "no readable lidar frame of 1 ({at_fault}: PCD body holds 562 points, the header says 57374",
    ),
    "one-tick-truncated-png": Case(
        "one-tick", lambda s: _cut(_frame(s, "_camera0.png", agent=2, key=0), 0.3), "warn", "no readable image of 1"
    ),
    "camera-every-png-corrupt": Case(
        "opv2v", lambda s: _every(s, "*_camera1.png"), "warn", "no readable image of 4 (" + "{at_fault}: not a PNG"
    ),
    "agent-every-pcd-unreadable": Case(
        "opv2v", lambda s: _every(s, "*.pcd", agent=1), "warn", "lidar_top: no readable lidar frame of 4"
    ),
    "every-agent-frame-damaged": Case(
        "one-tick", _every_agent_frame, "fail", "no agent has a sensor with a readable frame"
    ),
    "clip-window-0.01s": Case(
        "av2", lambda log: log, "usage", "holds no lidar sweep", {"seek_sec": 0.0, "duration_sec": 0.01}
    ),
    "clip-window-0.03s": Case(
        "av2", lambda log: log, "usage", "holds no lidar sweep", {"seek_sec": 0.0, "duration_sec": 0.03}
    ),
    "real-clip-window-between-sweeps": Case(
        "real", lambda log: log, "usage", "holds no lidar sweep", {"seek_sec": 0.03, "duration_sec": 0.01}
    ),
    "clip-window-camera-without-frame": Case(
        "av2",
        lambda log: log / "sensors" / "cameras",
        "warn",
        f"no images for {CAMERAS[0]} in the clip window; cameras not written",
        {"seek_sec": 0.06, "duration_sec": 0.15},
    ),
}
UNREADABLE = {"unreadable-file", "unreadable-pcd"}


# ------------------------------------------------------------------------------------------------
# Base datasets and the conversion, as the CLI runs it
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bases(tmp_path_factory, av2_sample_root) -> dict[str, tuple[Path, str]]:
    """One small intact dataset per converter, and the real sample: {dataset: (root, log id or scenario)}."""
    tmp = tmp_path_factory.mktemp("corpus")
    av2_log = write_log(
        UPath(tmp / "av2" / "val"), SynthConfig(seconds=0.3, seed=11, camera_fps=5, camera_scale=4)
    ).log_id
    tbv_log = write_log(UPath(tmp / "tbv"), SynthConfig(seconds=0.5, seed=12, camera_fps=0, tbv=True)).log_id
    config = synth_opencood.SynthConfig(dataset="opv2v", frames=4, cavs=2, lidar_columns=64, seed=13, render_step=8)
    scenario = synth_opencood.write_scenario(UPath(tmp / "opv2v" / config.split), config).scenario
    # the real V2XSet case of issue 50: three agents (two vehicles, an RSU), one tick
    config = synth_opencood.SynthConfig(
        dataset="v2xset", frames=1, cavs=2, infrastructure=1, lidar_columns=64, seed=14, render_step=8
    )
    tick = synth_opencood.write_scenario(UPath(tmp / "one-tick" / config.split), config).scenario
    return {
        "av2": (tmp / "av2", av2_log),
        "real": (av2_sample_root, AV2_SAMPLE_LOG),
        "tbv": (tmp / "tbv", tbv_log),
        "opv2v": (tmp / "opv2v", scenario),
        "one-tick": (tmp / "one-tick", tick),
    }


def source_folder(dataset: str, root: Path, name: str) -> Path:
    if dataset in ("opv2v", "one-tick"):
        return root / "test" / name
    return {"av2": root / "val" / name, "real": root / "val" / name, "tbv": root / name}[dataset]


#: Option sets the corpus runs with: the defaults, and every consumer option away from its default
#: (a window from the start to the end, so that it keeps every damaged frame).
OPTION_SETS = {
    "default": {},
    "consumer": {
        "camera_model": "ftheta",
        "class_names": "source",
        "cuboid_label_source": "autolabel",
        "world_global_mode": "identity",
        "seek_sec": 0.0,
    },
}


def task_for(dataset: str, root: Path, option_set: str = "default", case_options: dict | None = None):
    """The per-log task, as the CLI builds it (sensor selection kept small for speed)."""
    extra = {**OPTION_SETS[option_set], **(case_options or {})}
    if dataset in ("opv2v", "one-tick"):
        options = OpenCoodOptions(dataset="opv2v" if dataset == "opv2v" else "v2xset", split="test", **extra)
        return partial(convert_scenario, UPath(root), options=options)
    if dataset == "tbv":
        options = Argoverse2Options(None, **extra)
    else:
        options = Argoverse2Options(split="val", camera_ids=CAMERAS, **extra)
    return partial(convert_log, UPath(root), options=options)


def convert(dataset: str, root: Path, name: str, out: Path, option_set: str = "default", case_options=None):
    task = partial(convert_and_validate, task_for(dataset, root, option_set, case_options), source_root=UPath(root))
    return convert_one(UPath(out), name, lambda work, log_id, progress: task(work, log_id, progress=progress), False)


@contextmanager
def file_size_limit():
    """A full output disk, simulated: files may not grow past 64 KiB (RLIMIT_FSIZE), so writing a
    sequence's stores fails with EFBIG in the middle, as it would with ENOSPC."""
    previous = resource.getrlimit(resource.RLIMIT_FSIZE)
    handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a failed write, not a killed process
    resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, previous[1]))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, previous)
        signal.signal(signal.SIGXFSZ, handler)


@pytest.mark.parametrize("option_set", list(OPTION_SETS))
@pytest.mark.parametrize("case_id", list(CASES))
def test_damaged_input_has_its_specified_outcome(case_id, option_set, bases, tmp_path, monkeypatch):
    case = CASES[case_id]
    base_root, name = bases[case.dataset]
    root = tmp_path / "root"
    folder = source_folder(case.dataset, root, name)
    shutil.copytree(source_folder(case.dataset, base_root, name), folder)
    at_fault = case.damage(folder)
    if case_id in UNREADABLE:
        unreadable(at_fault, monkeypatch)
    out = tmp_path / "out"
    out.mkdir()
    if case_id == "full-output-disk":
        with file_size_limit():
            result = convert(case.dataset, root, name, out, option_set)
        at_fault = out / name  # the output that could not be written
    else:
        result = convert(case.dataset, root, name, out, option_set, case.options)
    cause = case.cause.format(at_fault=at_fault)
    if case.outcome in ("fail", "usage"):
        assert not result.ok, f"{case_id}: converted, expected a failure"
        assert "\n" not in result.error and cause in result.error and str(at_fault) in result.error, result.error
        assert result.usage_error == (case.outcome == "usage"), result.error
        assert list(out.iterdir()) == [], "a failed log leaves nothing in the output folder"
        assert result.error_file in (None, str(at_fault)) or case.outcome == "usage", result.error_file
        if case_id == "every-agent-frame-damaged":  # a failed log keeps its warnings (the report's)
            assert sum("sensor not written" in w for w in result.warnings) == 3 * 5, result.warnings
            assert sum(w.endswith("no sensor with a readable frame; agent not written") for w in result.warnings) == 3
    else:
        assert result.ok, f"{case_id}: {result.error}"
        assert result.summary.validation["ok"], result.summary.validation["failed"]
        named = [w for w in result.warnings if str(at_fault) in w and cause in w]
        assert named, f"{case_id}: no warning naming {at_fault} with {cause!r} in {result.warnings}"
        assert (out / name).is_dir()


def test_readme_table_lists_every_case():
    """docs/damaged-input.md's table has exactly one row per corpus case, with its outcome."""
    text = (REPO / "docs" / "damaged-input.md").read_text()
    rows = re.findall(r"^\| `([a-z0-9.-]+)` \|[^|]*\| (fails|usage error|converts, warns) \|", text, flags=re.M)
    assert sorted(r[0] for r in rows) == sorted(CASES)
    names = {"fail": "fails", "usage": "usage error", "warn": "converts, warns"}
    for case_id, outcome in rows:
        assert outcome == names[CASES[case_id].outcome], case_id


def test_export_writes_back_what_was_converted_and_says_what_was_left_out(bases, tmp_path):
    """The one-tick V2XSet scenario with one vehicle's PCD and the other's front PNG cut short:
    ``export-opencood`` writes every converted file back as it was, leaves out the damaged ones
    and the agent without a lidar (OpenCOOD reads each agent-frame by its PCD), and says so."""
    from click.testing import CliRunner

    from ncore_convert.cli import cli

    base_root, name = bases["one-tick"]
    root = tmp_path / "root"
    folder = source_folder("one-tick", root, name)
    shutil.copytree(source_folder("one-tick", base_root, name), folder)
    agents = [a.name for a in _agents(folder)]
    pcd = _cut(_frame(folder, ".pcd", agent=1, key=0), 0.3)
    png = _cut(_frame(folder, "_camera0.png", agent=2, key=0), 0.3)
    out = tmp_path / "out"
    out.mkdir()
    result = convert("one-tick", root, name, out)
    assert result.ok and result.summary.validation["ok"], result.error
    export = tmp_path / "export"
    run = CliRunner().invoke(cli, ["export-opencood", str(out / name / "scenario.json"), "--out", str(export)])
    assert run.exit_code == 0, run.output
    assert (
        f"left out: agent {agents[1]}: lidar_top not written (no readable lidar frame; 1 file(s): {pcd}" in run.output
    )
    assert f"left out: agent {agents[2]}: camera_front not written (no readable image; 1 file(s): {png}" in run.output
    assert f"left out: agent {agents[1]}: not exported" in run.output
    written = export / name
    assert sorted(p.name for p in written.iterdir()) == sorted(["data_protocol.yaml", agents[0], agents[2]])
    for agent in (agents[0], agents[2]):
        source = {p.name: p for p in (folder / agent).iterdir() if p != png}
        assert sorted(p.name for p in (written / agent).iterdir()) == sorted(source), agent
        for file_name, path in source.items():
            if not file_name.endswith(".pcd"):  # PNGs and YAMLs come back byte for byte
                assert (written / agent / file_name).read_bytes() == path.read_bytes(), file_name
