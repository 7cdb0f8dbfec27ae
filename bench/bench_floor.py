"""Benchmark: the library floor, and ours above it (issue 42). Not a test.

The floor is what any converter built on nvidia-ncore pays to write what ours writes. For the 15 s
synthetic AV2 log (``synth argoverse2 --seconds 15 --seed 2 --pictures 16``, as ``bench_speed.py``), ours is run
once with ``--no-validate``; everything it wrote (lidar rays with their times, distances,
intensities, model elements and ``dynamic_flag``; the JPEGs as stored; poses, models, masks,
cuboids; all metadata) is read back into this process's memory through the library's component
readers, untimed. The floor then writes it again with the bare nvidia-ncore V4 component writers:
the same store layout (``separate-sensors``, ``itar``), the same parts (the base components, the
lidars, one part per camera) on 2 worker processes (forked after the load, so each holds the data),
every store fsync'd, the sequence meta with the library's md5 of each store, then ``sync``. No
transforms, no checks, no estimates. Its wall time starts at the fork; the start-up of a bare
interpreter importing ``ncore.data.v4`` is measured apart and added (ours are whole commands).

Interleaved in every round, medians of --repeat:
- ``cp -r`` of the log + ``sync``;
- the floor;
- ``ncore-convert --no-validate argoverse2-v4``;
- the default command (validated against the source).

    python bench/bench_floor.py [--work /tmp/ncore-bench] [--repeat 3]
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing as mp
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from bench_argoverse2 import bench_parser, copy, process_tree, work_dir
from bench_speed import ours, speed_log, timed
from ncore.data.v4 import (
    CameraSensorComponent,
    CuboidsComponent,
    IntrinsicsComponent,
    LidarSensorComponent,
    MasksComponent,
    PosesComponent,
    SequenceComponentGroupsReader,
    SequenceComponentGroupsWriter,
)
from ncore.impl.common.transformations import HalfClosedInterval
from ncore.impl.data.v4.types import ComponentGroupAssignments
from upath import UPath

from ncore_convert.storage import flush_to_disk

WORKERS = 2
_DATA: dict = {}  #: the loaded sequence, inherited by the forked workers


def _component(reader: SequenceComponentGroupsReader, kind, name: str):
    return reader.open_component_readers(kind.Reader)[name]


def load(sequence_json: Path) -> dict:
    """Everything the sequence holds, in memory, by part: ``base`` and one per sensor."""
    meta = json.loads(sequence_json.read_text())
    reader = SequenceComponentGroupsReader([UPath(sequence_json)])
    poses = _component(reader, PosesComponent, "default")
    intrinsics = _component(reader, IntrinsicsComponent, "default")
    masks = _component(reader, MasksComponent, "default")
    cuboids = _component(reader, CuboidsComponent, "default")
    lidar_readers = reader.open_component_readers(LidarSensorComponent.Reader)
    camera_readers = reader.open_component_readers(CameraSensorComponent.Reader)
    base = {
        "poses_meta": poses.generic_meta_data,
        "poses_data": {n: poses.get_generic_data(n) for n in poses.get_generic_data_names()},
        "static": list(poses.get_static_poses()),
        "dynamic": list(poses.get_dynamic_poses()),
        "cameras": {c: intrinsics.get_camera_model_parameters(c) for c in camera_readers},
        "lidars": {lidar: intrinsics.get_lidar_model_parameters(lidar) for lidar in lidar_readers},
        "masks": {c: dict(masks.get_camera_mask_images(c)) for c in camera_readers},
        "cuboids": list(cuboids.get_observations()),
        "cuboids_meta": cuboids.generic_meta_data,
    }
    for image in (m for per_camera in base["masks"].values() for m in per_camera.values()):
        image.load()
    lidars = {}
    for lidar_id, lidar in lidar_readers.items():
        frames = []
        for ts in lidar.frames_timestamps_us[:, 1]:
            ts = int(ts)
            names = lidar.get_frame_generic_data_names(ts)
            frames.append(
                {
                    "direction": lidar.get_frame_ray_bundle_data(ts, "direction"),
                    "timestamp_us": lidar.get_frame_ray_bundle_data(ts, "timestamp_us"),
                    "model_element": lidar.get_frame_ray_bundle_data(ts, "model_element")
                    if lidar.has_frame_ray_bundle_data(ts, "model_element")
                    else None,
                    "distance_m": lidar.get_frame_ray_bundle_return_data(ts, "distance_m", None),
                    "intensity": lidar.get_frame_ray_bundle_return_data(ts, "intensity", None),
                    "frame_timestamps_us": lidar.get_frame_timestamps_us(ts),
                    "generic_data": {n: lidar.get_frame_generic_data(ts, n) for n in names},
                    "generic_meta_data": lidar.get_frame_generic_meta_data(ts),
                }
            )
        lidars[lidar_id] = {"meta": lidar.generic_meta_data, "frames": frames}
    cameras = {}
    for camera_id, camera in camera_readers.items():
        frames = []
        for ts in camera.frames_timestamps_us[:, 1]:
            data = camera.get_frame_data(int(ts))
            frames.append(
                (
                    data.get_encoded_image_data(),
                    data.get_encoded_image_format(),
                    camera.get_frame_timestamps_us(int(ts)),
                )
            )
        cameras[camera_id] = {"meta": camera.generic_meta_data, "frames": frames}
    interval = meta["sequence_timestamp_interval_us"]
    return {
        "sequence_id": meta["sequence_id"],
        "interval": (int(interval["start"]), int(interval["stop"])),
        "generic_meta_data": meta["generic_meta_data"],
        "base": base,
        "lidars": lidars,
        "cameras": cameras,
    }


def _write_part(job: tuple[str, str, tuple[str, ...]]):
    """Write one part (``base``, ``lidars`` or ``camera``) of ``_DATA`` into ``out``; the part's
    sequence meta."""
    kind, out, sensors = job
    data = _DATA
    groups = ComponentGroupAssignments.create(
        camera_ids=list(data["cameras"]),
        lidar_ids=list(data["lidars"]),
        radar_ids=[],
        point_clouds_ids=[],
        camera_labels_ids=[],
        profile="separate-sensors",
    )
    start, stop = data["interval"]
    writer = SequenceComponentGroupsWriter(
        output_dir_path=UPath(out),
        store_base_name=data["sequence_id"],
        sequence_id=data["sequence_id"],
        sequence_timestamp_interval_us=HalfClosedInterval(start, stop),
        generic_meta_data=data["generic_meta_data"],
        store_type="itar",
    )
    if kind == "base":
        base = data["base"]
        poses = writer.register_component_writer(
            PosesComponent.Writer, "default", groups.poses_component_group, base["poses_meta"]
        )
        for (source, target), pose in base["static"]:
            poses.store_static_pose(source, target, pose)
        for (source, target), (T, t_us) in base["dynamic"]:
            poses.store_dynamic_pose(source, target, T, t_us)
        if base["poses_data"]:
            poses.set_generic_data(base["poses_data"], base["poses_meta"])
        intrinsics = writer.register_component_writer(
            IntrinsicsComponent.Writer, "default", groups.intrinsics_component_group
        )
        for camera_id, params in base["cameras"].items():
            intrinsics.store_camera_intrinsics(camera_id, params)
        for lidar_id, params in base["lidars"].items():
            if params is not None:
                intrinsics.store_lidar_intrinsics(lidar_id, params)
        masks = writer.register_component_writer(MasksComponent.Writer, "default", groups.masks_component_group)
        for camera_id, images in base["masks"].items():
            masks.store_camera_masks(camera_id, images)
        cuboids = writer.register_component_writer(
            CuboidsComponent.Writer, "default", groups.cuboid_track_observations_component_group
        )
        cuboids.store_observations(base["cuboids"])
        cuboids.set_generic_data({}, base["cuboids_meta"])
    elif kind == "lidars":
        for lidar_id in sensors:
            lidar = data["lidars"][lidar_id]
            stream = writer.register_component_writer(
                LidarSensorComponent.Writer, lidar_id, groups.lidar_component_groups.get(lidar_id), lidar["meta"]
            )
            for frame in lidar["frames"]:
                stream.store_frame(**frame)
    else:
        (camera_id,) = sensors
        camera = data["cameras"][camera_id]
        stream = writer.register_component_writer(
            CameraSensorComponent.Writer, camera_id, groups.camera_component_groups.get(camera_id), camera["meta"]
        )
        for image, image_format, frame_us in camera["frames"]:
            stream.store_frame(image, image_format, frame_us, {}, {})
    paths = writer.finalize()
    for path in paths:
        flush_to_disk(path)
    return SequenceComponentGroupsReader(paths).get_sequence_meta()


def floor(data: dict, out: Path) -> float:
    """Wall seconds to write ``data`` with the bare library (parts on WORKERS forked processes,
    longest first), the sequence meta included, then ``sync``."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    _DATA.clear()
    _DATA.update(data)
    jobs = [("lidars", str(out), tuple(data["lidars"]))] if data["lidars"] else []
    by_size = sorted(data["cameras"], key=lambda c: -sum(len(f[0]) for f in data["cameras"][c]["frames"]))
    jobs += [("camera", str(out), (camera_id,)) for camera_id in by_size] + [("base", str(out), ())]
    subprocess.run(["sync"], check=True)
    started = time.perf_counter()
    with mp.get_context("fork").Pool(WORKERS) as pool:
        parts = pool.map(_write_part, jobs, chunksize=1)
    stores = [store for part in parts for store in part.component_stores]
    meta = dataclasses.replace(parts[0], component_stores=stores)
    path = out / f"{data['sequence_id']}.json"
    path.write_text(json.dumps(meta.to_dict(), indent=2))
    flush_to_disk(UPath(path))
    subprocess.run(["sync"], check=True)
    return time.perf_counter() - started


def ours_sampled(command: list[str], out: Path) -> tuple[float, float]:
    """Wall seconds of one of our commands plus ``sync`` (``out`` removed first), and the largest
    resident set any one of its processes reached (MB; /proc sampled every 50 ms)."""
    shutil.rmtree(out, ignore_errors=True)
    subprocess.run(["sync"], check=True)
    peak: dict[int, int] = {}
    started = time.perf_counter()
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    while proc.poll() is None:
        for pid, (rss, _) in process_tree(proc.pid).items():
            peak[pid] = max(peak.get(pid, 0), rss)
        time.sleep(0.05)
    if proc.returncode:
        raise SystemExit(f"{command[0]} failed: {proc.stderr.read().decode()[-2000:]}")
    subprocess.run(["sync"], check=True)
    return time.perf_counter() - started, max(peak.values(), default=0) / 2**20


def startup() -> float:
    """Wall seconds of a bare interpreter importing nvidia-ncore's V4 API (median of 3)."""
    runs = []
    for _ in range(3):
        started = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import ncore.data.v4"], check=True)
        runs.append(time.perf_counter() - started)
    return statistics.median(runs)


def main() -> None:
    parser = bench_parser(__doc__, repeat=3)
    args = parser.parse_args()
    work = work_dir(args)
    root, log_id = speed_log(work)
    log_dir = root / "val" / log_id
    reference = work / "floor-reference"
    timed(ours(root, reference, False), reference)
    started = time.perf_counter()
    data = load(reference / log_id / f"{log_id}.json")
    print(f"  loaded our output into memory in {time.perf_counter() - started:.1f} s (untimed)", flush=True)
    start_s = startup()
    rows: dict[str, list[float]] = {}
    memory: dict[str, list[float]] = {}
    for round_ in range(args.repeat):
        times = {
            "cp -r + sync": copy(log_dir, work / "floor-copy"),
            "library floor": floor(data, work / "floor-out" / log_id) + start_s,
        }
        for label, validate, folder in (
            ("ours --no-validate", False, "floor-plain"),
            ("ours default", True, "floor-default"),
        ):
            times[label], mb = ours_sampled(ours(root, work / folder, validate), work / folder)
            memory.setdefault(label, []).append(mb)
        for label, seconds in times.items():
            rows.setdefault(label, []).append(seconds)
        print(f"  round {round_ + 1}: " + ", ".join(f"{k} {v:.2f} s" for k, v in times.items()), flush=True)
    med = {label: statistics.median(seconds) for label, seconds in rows.items()}
    floor_s = med["library floor"]
    print(f"15 s AV2 log, whole commands, medians of {args.repeat} (floor: writing + {start_s:.2f} s start-up):")
    for label, seconds in med.items():
        print(f"  {label:<20} {seconds:7.2f} s  = {seconds / floor_s:.2f}x floor")
    for label, mbs in memory.items():
        print(f"  {label:<20} largest process: {statistics.median(mbs):.0f} MB resident at its peak")
    print(
        f"issue 42: --no-validate / floor = {med['ours --no-validate'] / floor_s:.2f} (target <= 1.3);"
        f" default / --no-validate = {med['ours default'] / med['ours --no-validate']:.2f} (target <= 1.15)"
    )


if __name__ == "__main__":
    main()
