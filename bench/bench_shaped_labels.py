"""Camera labels on shaped objects (issue 52), scored against the scene ray-cast from each camera
(``synth.raycast.cast_rays``):

- OPV2V / V2XSet scenarios whose vehicles have bodies, cabins, wheels and mirrors inside their boxes
  (``synth.shapes``), with a car queued 0.3-1.0 m ahead of the first CAV's front camera and one 1-2 m
  alongside it, converted with ``--camera-labels depth,dynamic,instance``;
- the AV2 world (shaped cars, pedestrians and cyclists, a car just ahead of the ego and one
  alongside): both VLP-32C units fire every sweep of the log, and five ring cameras (at half size)
  label ``--scored`` sweeps spread over it at their middles with the label kernel itself
  (``transforms.camera.labels``), the annotated vehicles' true boxes as the occluders' boxes (AV2's
  0.5 m slack) and as the masks' boxes.

Each is run twice, side by side (issue 74): with each frame's own sweep (tick) only, as before,
and with the vehicles' shapes pooled over their whole tracks (``objects.track_shapes``: the OPV2V
labeller's first pass; for AV2 the parked vehicles, as the AV2 labeller pools its static tracks).

The figures:

- depth: the share of the pixels that a raw point hits and the camera sees in truth that are
  labelled, on vehicles (the pixel's centre ray hits a vehicle) and overall; occlusion errors (a label
  more than 0.5 m behind everything its pixel shows, sampled near its four corners);
- masks: per object view (an instance in one camera frame, >= 50 sampled pixels in truth or in the
  label), the IoU and recall of ``segmentation.instance`` against the object's true silhouette
  (every second pixel); the pooled recall; the ``mask.dynamic`` IoU and recall against the moving
  vehicles; and the queued car's share of the front camera's picture, labelled and true.

    python bench/bench_shaped_labels.py [--seeds 101,102] [--av2-seeds 5,6,7] [--seconds 4] [--scored 5]
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import tempfile
from pathlib import Path

import numpy as np
from ncore.data.v4 import SequenceComponentGroupsReader, SequenceLoaderV4
from ncore.impl.data.types import LabelType
from upath import UPath

from ncore_convert.converters.opencood import OpenCoodOptions, convert_scenario
from ncore_convert.converters.opencood import labels as opencood_labels
from ncore_convert.sources.opencood import load_yaml
from ncore_convert.sources.pcd import read_pcd
from ncore_convert.synth import carla as synth_carla
from ncore_convert.synth import opencood as synth
from ncore_convert.synth.argoverse2 import calibration, simulate_unit
from ncore_convert.synth.raycast import cast_rays, seen_through
from ncore_convert.synth.scene import make_scene
from ncore_convert.transforms.camera.labels import DYNAMIC_DT_US, box_index, depth_z, points_at_frame
from ncore_convert.transforms.camera.models import Pinhole
from ncore_convert.transforms.camera.visibility import CameraView
from ncore_convert.transforms.geometry import invert_se3
from ncore_convert.transforms.lidar import vlp32c
from ncore_convert.transforms.lidar.model import SpinningLidarModel
from ncore_convert.transforms.lidar.range_image import RangeImage
from ncore_convert.transforms.objects.classes import AV2_TO_NCORE
from ncore_convert.transforms.objects.cores import VEHICLE, kind_of
from ncore_convert.transforms.objects.dynamic import static_pose
from ncore_convert.transforms.objects.track_shapes import TrackShapes

CAMERAS = ("camera_front", "camera_right_rear", "camera_left_rear", "camera_back")
KINDS = ("depth", "dynamic", "instance")
MIN_VIEW_PX = 50  #: sampled pixels (every second one) that make an object view
#: Where a labelled pixel's truth is sampled: near its corners, so that the samples span the depths it
#: shows (the ground 90 m ahead of an AV2 camera changes depth by 7 m from one pixel row to the next)
PIXEL_SPAN = [0.02, 0.98]


def _seen(truth, agent_id, key, index, u, v):
    """z (m, inf: nothing) and the actor (-1 ground or nothing, -2 pillar, -3 building) that camera
    ``index`` of ``agent_id`` sees through image points at tick ``key``, [K] each."""
    scene, actor_of_box = truth.agents[agent_id].scenes[key]
    T = truth.agents[agent_id].T_cam_world[key][index] @ synth_carla.T_UE4_OPENCV
    z, box = seen_through(scene, T, synth_carla.PINHOLE, 0.0, u, v, ground_z_m=0.0)
    return z, np.r_[actor_of_box, -1][box]


def _raw_pixels(truth, agent_id: str, key: str, index: int):
    """The raw PCD points in camera ``index``'s picture as OpenCOOD projects them: column, row, z."""
    frame = load_yaml(UPath(truth.scenario_dir) / agent_id / f"{key}.yaml")
    E, K = np.array(frame[f"camera{index}"]["extrinsic"]), np.array(frame[f"camera{index}"]["intrinsic"])
    cloud = read_pcd(UPath(truth.scenario_dir) / agent_id / f"{key}.pcd")
    xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float64)
    ue4 = xyz @ E[:3, :3].T + E[:3, 3]
    x, y, z = ue4[:, 1], -ue4[:, 2], ue4[:, 0]
    ahead = z > 0.3
    u, v, z = K[0, 0] * x[ahead] / z[ahead] + K[0, 2], K[1, 1] * y[ahead] / z[ahead] + K[1, 2], z[ahead]
    inside = (u >= 0) & (u < synth_carla.WIDTH) & (v >= 0) & (v < synth_carla.HEIGHT)
    return u[inside].astype(np.int64), v[inside].astype(np.int64), z[inside]


def _label(loader, cam: str, label_type: LabelType, position: int):
    (labels,) = loader.query_camera_labels(cam, label_type=label_type)
    label = labels.get_label(int(np.sort(labels.label_timestamps_us)[position]))
    return label.get_data(), labels.labels_generic_meta_data


def score_scenario(truth, out: Path, tally: dict, positions: list[int]) -> None:
    """Add one converted scenario's figures at ticks ``positions`` (indices) to ``tally``."""
    labelled_now = {
        key: {
            int(a)
            for agent in truth.agents
            for a in load_yaml(UPath(truth.scenario_dir) / agent / f"{key}.yaml").get("vehicles", {})
        }
        for key in truth.keys
    }
    front_cav = next(iter(truth.agents))
    for agent_id in truth.agents:
        loader = SequenceLoaderV4(
            SequenceComponentGroupsReader([UPath(out / agent_id / f"{truth.scenario}_agent{agent_id}.json")])
        )
        for position in positions:
            key = truth.keys[position]
            for index, cam in enumerate(CAMERAS):
                depth, _ = _label(loader, cam, LabelType.DEPTH_Z_M, position)
                # depth: coverage of the truly visible raw points' pixels, on vehicles and overall
                cols, lines, z_m = _raw_pixels(truth, agent_id, key, index)
                first_z, actor = _seen(truth, agent_id, key, index, cols + 0.5, lines + 0.5)
                seen = first_z >= z_m - 0.05 * np.maximum(1.0, z_m / 10.0)
                pixel, first = np.unique(lines[seen] * synth_carla.WIDTH + cols[seen], return_index=True)
                on_vehicle = actor[seen][first] >= 0
                covered = depth.reshape(-1)[pixel] > 0
                tally["covered"].append(covered)
                tally["covered_vehicle"].append(covered[on_vehicle])
                # depth: occlusion errors
                ll, cc = np.nonzero(depth)
                du, dv = np.meshgrid(PIXEL_SPAN, PIXEL_SPAN)
                u = (cc[:, None] + du.reshape(-1)).reshape(-1)
                v = (ll[:, None] + dv.reshape(-1)).reshape(-1)
                z_true, _ = _seen(truth, agent_id, key, index, u, v)
                tally["behind"].append(np.all(depth[ll, cc][:, None] - z_true.reshape(len(ll), -1) > 0.5, axis=1))
                # masks against the true silhouettes, every second pixel
                instances, meta = _label(loader, cam, LabelType.SEGMENTATION_INSTANCE, position)
                ours_dynamic = _label(loader, cam, LabelType.MASK_DYNAMIC, position)[0][::2, ::2] > 0
                actor_of_instance = {int(k): int(v["track_id"]) for k, v in meta["instances"].items()}
                ours = instances[::2, ::2]
                vv, uu = np.mgrid[0 : synth_carla.HEIGHT : 2, 0 : synth_carla.WIDTH : 2] + 0.5
                _, true_actor = _seen(truth, agent_id, key, index, uu.reshape(-1), vv.reshape(-1))
                true_actor = true_actor.reshape(uu.shape)
                lookup = np.full(max([int(ours.max()), *actor_of_instance]) + 1, -1, np.int64)
                for k, a in actor_of_instance.items():
                    lookup[k] = a
                ours_actor = lookup[ours]
                unknown = (true_actor >= 0) & ~np.isin(true_actor, list(labelled_now[key]))
                judged = ~unknown
                for a in np.unique(np.r_[ours_actor[ours_actor >= 0], true_actor[(true_actor >= 0) & judged]]):
                    mine, real = (ours_actor == a) & judged, (true_actor == a) & judged
                    if max(mine.sum(), real.sum()) < MIN_VIEW_PX:
                        continue
                    inter = np.sum(mine & real)
                    tally["iou"].append(inter / np.sum(mine | real))
                    tally["recall"].append((inter, real.sum()))
                    tally["missed"].append((np.sum(real & ~mine & (ours_actor >= 0)), np.sum(real & (ours_actor < 0))))
                    tally["views"].append(
                        (f"{truth.scenario}/{agent_id}/{key}/{cam}", int(a), int(mine.sum()), int(real.sum()))
                    )
                moving = np.isin(true_actor, [a for a, s in truth.actor_speed_mps.items() if s > 0]) & judged
                tally["dynamic"].append((np.sum(ours_dynamic & moving), np.sum(ours_dynamic | moving), moving.sum()))
                if agent_id == front_cav and index == 0:  # the car queued ahead
                    queued = int(np.bincount(true_actor[true_actor >= 0]).argmax()) if np.any(true_actor >= 0) else -1
                    tally["queued"].append((np.mean(ours_actor == queued), np.mean(true_actor == queued)))


AV2_CAMERAS = ("ring_front_center", "ring_front_left", "ring_front_right", "ring_side_left", "ring_side_right")
T0_NS = 1_000_000_000
SWEEP_S = 0.1  #: a sweep's length; sweep k spans [k, k + 1) sweeps, its cameras at its middle


def _av2_sweep(scene, T_sensor_ego: dict, k: int) -> dict:
    """Sweep ``k`` of both VLP-32C units: the hits (city frame), where each unit was as it measured
    each one, its lines of sight, which hits are on moving objects, times (µs), spacing (m [N,2])."""
    parts = []
    window = (T0_NS + round(k * SWEEP_S * 1e9), T0_NS + round((k + 1) * SWEEP_S * 1e9))
    for unit in ("up_lidar", "down_lidar"):
        T = T_sensor_ego[unit]
        parts.append(simulate_unit(unit, window, T0_NS, scene, lambda t_s, T=T: scene.ego.T_ego_city(t_s) @ T))
    hits = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    origins_m = np.concatenate(  # where each unit was as it measured each point
        [
            np.einsum("nij,j->ni", scene.ego.T_ego_city((p["time_ns"] - T0_NS) * 1e-9), T_sensor_ego[unit][:, 3])[:, :3]
            for p, unit in zip(parts, ("up_lidar", "down_lidar"), strict=True)
        ]
    )
    moving = np.r_[[bool(np.any(b.velocity_mps)) for b in scene.boxes], False]
    elevations = np.radians(vlp32c.BEAM_ELEVATION_DEG)  # each beam's step, as the converter's model gives it
    model = SpinningLidarModel(
        10.0, "ccw", elevations, np.zeros(32), np.linspace(-np.pi, np.pi, 1800, endpoint=False), np.arange(32)
    )
    return {
        "xyz": hits["xyz_city_m"],
        "origins": origins_m,
        "sight": RangeImage(hits["xyz_city_m"], origins_m),
        "dynamic": moving[hits["box_index"]],
        "times_us": (hits["time_ns"] - T0_NS) // 1000,
        "spacing": hits["distance_m"][:, None] * model.row_steps_rad()[hits["beam"]],
        "box_index": hits["box_index"],
    }


def score_av2_log(seed: int, seconds: float, scored: int, tally: dict, whole_track: bool) -> None:
    """Add the AV2 world of ``seed`` (``seconds`` long, both units) to ``tally``: ``scored`` sweeps
    spread over the log, each labelled at its middle by five cameras at half size with the label
    kernel (``transforms.camera.labels``) as the labeller calls it, on the boxes it has: each
    object's annotated boxes (the generator's jitter), a parked one's median box over the sweeps.
    With ``whole_track``, a first pass gathers every sweep's evidence of the vehicles
    (``objects.track_shapes``, as ``FrameLabeller.gather``: the parked ones at their median box, the
    moving ones along their annotated boxes, registered)."""
    scene = make_scene(
        np.random.default_rng(seed), seconds, np.random.default_rng([seed, 1]), shapes=True, close_range=True
    )
    T_sensor_ego, cams = calibration(camera_scale=2)
    annotated = [k for k, b in enumerate(scene.boxes) if b.annotated]
    kind = np.array([kind_of(AV2_TO_NCORE[scene.boxes[k].category]) for k in annotated])
    n_sweeps = max(1, int(round(seconds / SWEEP_S)))
    boxes = _AnnotatedBoxes(scene, annotated, n_sweeps)
    picked = sorted(set(np.linspace(0, n_sweeps - 1, scored).round().astype(int).tolist()))
    shapes, kept = (TrackShapes() if whole_track else None), {}
    vehicles = np.flatnonzero(kind == VEHICLE)
    for k in range(n_sweeps) if whole_track else picked:
        sweep = _av2_sweep(scene, T_sensor_ego, k)
        if shapes is not None:
            t_s = (k + 0.5) * SWEEP_S
            T, half, velocity = boxes.at(t_s)
            shapes.gather(
                vehicles.tolist(),
                T[vehicles],
                half[vehicles],
                sweep["xyz"],
                sweep["spacing"],
                sweep["origins"],
                sweep["sight"],
                velocity[vehicles],
                sweep["times_us"] * 1e-6 - t_s,
                register=boxes.moves[vehicles],
                time_us=round(t_s * 1e6),
            )
        if k in picked:
            kept[k] = sweep
    for k in picked:
        _score_av2_frame(
            scene, T_sensor_ego, cams, annotated, kind, kept.pop(k), (k + 0.5) * SWEEP_S, shapes, tally, boxes
        )


class _AnnotatedBoxes:
    """The boxes the AV2 labeller has of the annotated objects: a moving one's annotated box (jitter
    included) at any time, a parked one's median annotated box over the sweeps
    (``dynamic.static_pose``)."""

    def __init__(self, scene, annotated: list[int], n_sweeps: int) -> None:
        self._scene, self._annotated = scene, annotated
        self.moves = np.array([bool(np.any(scene.boxes[k].velocity_mps)) for k in annotated])
        times = (np.arange(n_sweeps) + 0.5) * SWEEP_S
        self._parked = {}
        for i, k in enumerate(annotated):
            if not self.moves[i]:
                T = np.stack([scene.boxes[k].T_annotated_city(t) for t in times])
                centre, R, _ = static_pose(T[:, :3, 3], T[:, :3, :3], np.tile(scene.boxes[k].dims_m, (len(T), 1)))
                self._parked[i] = np.eye(4)
                self._parked[i][:3, :3], self._parked[i][:3, 3] = R, centre

    def at(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Box -> city [K,4,4], half sizes [K,3] and velocities [K,3] (m/s) at ``t_s``."""
        boxes = [self._scene.boxes[k] for k in self._annotated]
        T = np.stack([self._parked.get(i, b.T_annotated_city(t_s)) for i, b in enumerate(boxes)])
        half = np.stack([b.dims_m / 2 for b in boxes])
        velocity = np.stack([b.velocity_mps * (b.move_from_s <= t_s <= b.move_until_s) for b in boxes])
        return T, half, velocity


def _score_av2_frame(scene, T_sensor_ego, cams, annotated, kind, sweep, camera_s, shapes, tally, boxes) -> None:
    """Label the cameras at ``camera_s`` from ``sweep`` (:func:`_av2_sweep`) with ``boxes``
    (:class:`_AnnotatedBoxes`) and score them."""
    T_box, half, velocity = boxes.at(camera_s)
    solid = kind >= 0
    xyz_city, dynamic, times_us, spacing_m = sweep["xyz"], sweep["dynamic"], sweep["times_us"], sweep["spacing"]
    for cam in AV2_CAMERAS:
        focal, width, height = cams[cam]
        pinhole = Pinhole((focal, focal), (width / 2, height / 2), (width, height))
        T_camera_city = scene.ego.T_ego_city(np.array([camera_s]))[0] @ T_sensor_ego[cam]
        view = CameraView(
            cam,
            round(camera_s * 1e6),
            invert_se3(T_camera_city),
            pinhole,
            None,
            (T_box[solid], half[solid]),
            0.5,
            velocity[solid],
            kind[solid],
        )
        depth = depth_z(view, xyz_city, times_us, dynamic, spacing_m)

        def seen(u, v, T_camera_city=T_camera_city, pinhole=pinhole):
            return seen_through(scene, T_camera_city, pinhole, camera_s, u, v)

        xyz = xyz_city @ view.T_world_camera[:3, :3].T + view.T_world_camera[:3, 3]
        usable = (xyz[:, 2] > 0.3) & (~dynamic | (np.abs(times_us - view.timestamp_us) <= DYNAMIC_DT_US))
        u, v = pinhole.project(np.where(usable[:, None], xyz, 1.0))
        usable &= (u >= 0) & (u < width) & (v >= 0) & (v < height)
        idx = np.flatnonzero(usable)
        towards = xyz_city[idx] - T_camera_city[:3, 3]
        distance = np.linalg.norm(towards, axis=1)
        first_m, _, _ = cast_rays(
            np.broadcast_to(T_camera_city[:3, 3], towards.shape),
            towards / distance[:, None],
            np.full(len(idx), camera_s),
            scene,
            500.0,
        )
        visible = idx[first_m >= distance - 0.05]
        pixel, first = np.unique(v[visible].astype(np.int64) * width + u[visible].astype(np.int64), return_index=True)
        covered = depth.reshape(-1)[pixel] > 0
        on_object = np.isin(sweep["box_index"][visible][first], annotated)
        tally["covered"].append(covered)
        tally["covered_vehicle"].append(covered[on_object])
        ll, cc = np.nonzero(depth)
        du, dv = np.meshgrid(PIXEL_SPAN, PIXEL_SPAN)
        z_true, _ = seen((cc[:, None] + du.reshape(-1)).reshape(-1), (ll[:, None] + dv.reshape(-1)).reshape(-1))
        tally["behind"].append(np.all(depth[ll, cc][:, None] - z_true.reshape(len(ll), -1) > 0.5, axis=1))
        at_frame = points_at_frame(view, xyz_city, times_us, dynamic, spacing_m, sweep["origins"])
        keys = list(range(len(annotated)))
        picture = box_index(view, T_box, half, kind, *at_frame, {}, keys, sweep["sight"], shapes)
        ours = picture.index[::2, ::2]
        vv, uu = np.mgrid[0:height:2, 0:width:2] + 0.5
        _, true_box = seen(uu.reshape(-1), vv.reshape(-1))
        to_annotated = np.full(len(scene.boxes) + 1, -1)
        to_annotated[annotated] = np.arange(len(annotated))
        truth = to_annotated[true_box].reshape(uu.shape)
        for k in np.unique(np.r_[ours[ours >= 0], truth[truth >= 0]]):
            mine, real = ours == k, truth == k
            if max(mine.sum(), real.sum()) < MIN_VIEW_PX:
                continue
            inter = np.sum(mine & real)
            tally["iou"].append(inter / np.sum(mine | real))
            tally["recall"].append((inter, real.sum()))
            tally["missed"].append((np.sum(real & ~mine & (ours >= 0)), np.sum(real & (ours < 0))))
            tally["views"].append((f"av2 {camera_s:.2f} s/{cam}", int(k), int(mine.sum()), int(real.sum())))
        moves = np.r_[[bool(np.any(scene.boxes[k].velocity_mps)) for k in annotated], False]
        ours_moving, true_moving = moves[ours], moves[truth]
        tally["dynamic"].append(
            (np.sum(ours_moving & true_moving), np.sum(ours_moving | true_moving), true_moving.sum())
        )


def report(title: str, tally: dict, verbose: bool = False) -> None:
    covered, vehicle = np.concatenate(tally["covered"]), np.concatenate(tally["covered_vehicle"])
    behind = np.concatenate(tally["behind"])
    inter, real = (np.sum([r[i] for r in tally["recall"]]) for i in (0, 1))
    recalls = [i / r for i, r in tally["recall"] if r]
    dyn = np.sum(tally["dynamic"], axis=0)
    print(title)
    print(f"  depth: object pixels labelled  {vehicle.mean():.3f} of {len(vehicle)} (bound >= 0.95)")
    print(f"  depth: all pixels labelled     {covered.mean():.3f} of {len(covered)} (bound >= 0.97)")
    print(f"  depth: occlusion errors        {behind.mean():.4f} of {len(behind)} labels (bound <= 0.005)")
    print(f"  masks: {len(tally['iou'])} object views, median IoU {statistics.median(tally['iou']):.3f} (>= 0.85)")
    short = np.mean(np.array(recalls) < 0.98)
    print(f"  masks: pooled recall {inter / real:.3f} (>= 0.98), views with recall < 0.98: {short:.3f}")
    print(f"  dynamic mask: IoU {dyn[0] / dyn[1]:.3f}, recall {dyn[0] / dyn[2]:.3f}")
    stolen, empty = np.sum(tally["missed"], axis=0) if tally["missed"] else (0, 0)
    print(
        f"  masks: true pixels missed {(stolen + empty) / real:.3f}: shown as another object {stolen / real:.3f},"
        f" as none {empty / real:.3f}"
    )
    if verbose:
        order = np.argsort(tally["iou"])
        for i in order[: len(order) // 2]:
            view, obj, mine, real = tally["views"][i]
            inter, _ = tally["recall"][i]
            figures = f"IoU {tally['iou'][i]:.3f}, recall {inter / max(real, 1):.3f}, {mine} ours, {real} true"
            print(f"    {view} object {obj}: {figures}")
    if tally.get("queued"):
        queued = np.array(tally["queued"])
        mine, real_share = queued[:, 0].mean(), queued[:, 1].mean()
        print(f"  queued car in the front camera: labelled {mine:.3f}, true {real_share:.3f} of the picture")


def _tally() -> dict:
    keys = ("covered", "covered_vehicle", "behind", "iou", "recall", "missed", "dynamic", "queued", "views")
    return {k: [] for k in keys}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", default="101,102", help="scenario seeds, each run as OPV2V and V2XSet")
    parser.add_argument("--av2-seeds", default="5,6,7", help="AV2 world seeds")
    parser.add_argument("--seconds", type=float, default=4.0, help="each log's and scenario's length")
    parser.add_argument("--scored", type=int, default=5, help="frames (ticks, sweeps) scored, spread over each log")
    parser.add_argument("--work", type=Path, default=None)
    parser.add_argument("--verbose", action="store_true", help="list the worse half of the object views")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="shaped-labels-"))
    ticks = max(1, int(round(args.seconds * 10)))
    modes = {"one sweep": False, "whole track": True}
    tallies = {mode: _tally() for mode in modes}
    for seed in (int(s) for s in args.seeds.split(",")):
        for dataset in ("opv2v", "v2xset"):
            tmp = work / f"{dataset}-{seed}-{ticks}"
            config = synth.SynthConfig(
                dataset=dataset,
                frames=ticks,
                seed=seed,
                keep_truth=True,
                shapes=True,
                close_range=True,
                cavs=3,
                render_step=8,  # the pictures are not scored: cheap ones
            )
            (truth,) = synth.write_dataset(UPath(tmp / "src"), config)
            positions = sorted(set(np.linspace(0, ticks - 1, args.scored).round().astype(int).tolist()))
            for mode, whole_track in modes.items():
                out = tmp / mode.replace(" ", "-") / truth.scenario
                options = OpenCoodOptions(dataset, "test", camera_labels=KINDS)
                with _whole_track(whole_track):
                    convert_scenario(UPath(tmp / "src"), UPath(out), truth.scenario, options)
                score_scenario(truth, out, tallies[mode], positions)
            print(f"  {dataset} seed {seed}: {len(tallies['whole track']['iou'])} object views so far", flush=True)
    for mode in modes:
        report(
            f"shaped OPV2V/V2XSet scenarios ({mode}), seeds {args.seeds}, {ticks} ticks, {args.scored} scored:",
            tallies[mode],
            args.verbose,
        )
    for mode, whole_track in modes.items():
        av2 = _tally()
        for seed in (int(s) for s in args.av2_seeds.split(",")):
            score_av2_log(seed, args.seconds, args.scored, av2, whole_track)
        report(
            f"shaped AV2 world ({mode}), seeds {args.av2_seeds}, {args.seconds:g} s, {args.scored} sweeps scored,"
            f" {len(AV2_CAMERAS)} cameras at half size:",
            av2,
            args.verbose,
        )


@contextlib.contextmanager
def _whole_track(on: bool):
    """The OPV2V labeller with its first pass (whole-track shapes) or without (each tick's own
    evidence, as before issue 74)."""
    made = opencood_labels.TrackShapes
    if not on:
        opencood_labels.TrackShapes = lambda: None
    try:
        yield
    finally:
        opencood_labels.TrackShapes = made


if __name__ == "__main__":
    main()
