"""OPV2V / V2XSet camera labels (``--camera-labels``), ``GT_SYNTHETIC``: one per camera frame and kind.

CARLA takes every point and picture of a tick at the tick, so a camera frame's labels come from
its own tick:

- ``depth.z@<camera>``: the agent's own lidar points of the tick
  (:func:`ncore_convert.transforms.camera.labels.depth_z`), the tick's other labelled vehicles as
  solid occluders; written as each lidar frame streams past. A tick whose lidar frame is unreadable
  gets an empty label that says why.
- ``mask.dynamic@<camera>``, ``segmentation.instance@<camera>``: the tick's merged labelled vehicles
  (the agent's own excepted), which one each pixel shows
  (:func:`ncore_convert.transforms.camera.labels.box_index`); written with each image.
"""

from __future__ import annotations

import time

import numpy as np

from ncore_convert import contract
from ncore_convert.converters.opencood.records import VEHICLE_CLASS, AgentPlan, ScenarioPlan
from ncore_convert.errors import SourceError
from ncore_convert.sources import opencood as src
from ncore_convert.sources.opencood import LIDAR
from ncore_convert.transforms.camera import labels as camera_labels
from ncore_convert.transforms.camera.visibility import CameraView
from ncore_convert.transforms.carla import points_right_handed
from ncore_convert.transforms.geometry import invert_se3
from ncore_convert.transforms.lidar.range_image import RangeImage
from ncore_convert.transforms.objects.cores import CELL_M
from ncore_convert.transforms.objects.track_shapes import TrackShapes
from ncore_convert.writer import CameraLabelStream, SequenceWriter

#: The component metadata of each kind: how the labels were made.
GENERATOR = {
    "depth": {
        "generator": "ncore-convert transforms.camera_labels.depth_z",
        "from": "the agent's own lidar points of the camera frame's CARLA tick (points and pictures share the tick)",
        "value": "z in metres (camera frame, OpenCV) of the nearest lidar point the camera sees in the pixel; 0: none",
        "occlusion": "visibility.visible_pixels: depth buffer of the tick's points and the tick's labelled vehicles",
    },
    "boxes": {
        "generator": "ncore-convert transforms.camera_labels.box_index",
        "from": "the tick's merged labelled vehicles (every agent's YAML), the agent's own vehicle excepted, and"
        " the agent's own lidar points of the tick",
        "pixel": "the vehicle the ray through the pixel's centre meets first (nearest box first where boxes overlap)",
        "masks": camera_labels.MASKS_MADE,
        "not_known": "surfaces other than the labelled vehicles (buildings, poles, unlabelled actors) do not hide"
        " a vehicle; a mask may over-cover its vehicle where the points do not show the box empty",
    },
}
DYNAMIC_RULE = (
    "1 where the box shown is a dynamic track's (transforms.objects.dynamic: CARLA's speed above 1 km/h); 0 elsewhere"
)


def instance_table(plan: ScenarioPlan) -> tuple[dict[int, int], dict[str, dict]]:
    """The scenario's instance index of every labelled actor (actor id -> 1 upwards, by actor id: the
    same in every sequence and camera of the scenario), and the table index -> track id, class and
    whether it is dynamic, as ``segmentation.instance``'s metadata holds it."""
    actors = sorted({int(a) for boxes in plan.boxes.values() for a in boxes.actor_ids})
    if len(actors) > np.iinfo(np.uint16).max:
        raise ValueError(f"{len(actors)} actors: more than a uint16 instance label holds")
    index = {actor: k + 1 for k, actor in enumerate(actors)}
    class_id = plan.cuboid_labels.class_map[VEHICLE_CLASS]
    table = {
        str(k): {"track_id": str(actor), "class_id": class_id, "dynamic": str(actor) in plan.cuboid_labels.dynamic}
        for actor, k in index.items()
    }
    return index, table


def tick_boxes(plan: ScenarioPlan, agent: AgentPlan, key: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The labelled vehicles of tick ``key`` but the agent's own, where they are at the tick (CARLA
    takes every point and picture of a tick at the tick): actor ids [K], box -> world_global [K,4,4],
    half sizes [K,3] (m). The one list of a tick's occluders: labels and lidar colours both use it."""
    boxes = plan.boxes.get(key)
    if boxes is None:
        return np.zeros(0, np.int64), np.zeros((0, 4, 4)), np.zeros((0, 3))
    others = boxes.actor_ids != (int(agent.agent_id) if agent.kind == "cav" else -1)
    return boxes.actor_ids[others], boxes.T_box_world_global[others], boxes.dims_m[others] / 2.0


def camera_view(agent: AgentPlan, frame: int, t_us: int, cam: str, T_box: np.ndarray, half: np.ndarray) -> CameraView:
    """Camera ``cam`` of ``agent`` at tick frame index ``frame`` (``t_us``), with the tick's boxes
    (:func:`tick_boxes`: box -> world_global [K,4,4], half sizes [K,3]; every one a vehicle) as
    occluders; fixed frame ``world_global``."""
    T_camera_world_global = agent.T_rig_world_global[frame] @ agent.T_sensor_rig[cam]
    return CameraView(cam, t_us, invert_se3(T_camera_world_global), agent.cameras[cam].pinhole, solids=(T_box, half))


class TickLabeller:
    """Writes the labels of one agent's cameras in a sequence (see the module docstring).

    Args:
        kinds: the ``contract.CAMERA_LABEL_KINDS`` to write (depth only for an agent with a lidar).
        sensor_name: the agent's camera id -> its name in the sequence (prefixed in the scenario layout).
    """

    def __init__(
        self, plan: ScenarioPlan, agent: AgentPlan, kinds: tuple[str, ...], writer: SequenceWriter, sensor_name
    ) -> None:
        self._plan, self._agent = plan, agent
        self._index, table = instance_table(plan)
        self._streams: dict[tuple[str, str], CameraLabelStream] = {
            (kind, cam): writer.add_camera_label(kind, sensor_name(cam), "GT_SYNTHETIC", {})
            for cam in agent.camera_ids
            for kind in kinds
        }
        self._meta = {
            "depth": GENERATOR["depth"],
            "dynamic": {**GENERATOR["boxes"], "value": DYNAMIC_RULE},
            "instance": {**GENERATOR["boxes"], "value": "instance index (0: no box)", "instances": table},
        }
        self._covers: dict = {}
        self._covers_of = ""  # the tick whose cover maps ``_covers`` holds
        # the vehicles' shapes from every tick (CARLA's boxes are exact: every track pools; gather)
        self.shapes = TrackShapes() if set(kinds) & set(contract.BOX_LABEL_KINDS) else None
        self.labels = 0
        self.seconds = 0.0

    @property
    def kinds(self) -> set[str]:
        return {kind for kind, _ in self._streams}

    def gather_ticks(self, reader) -> None:
        """The first pass, before any label: :meth:`gather` every tick's PCD of every agent of the
        scenario with a lidar, this one's first (fetched through ``reader`` and kept: the lidar frames
        that follow, and the other agents' jobs, read them again; an unreadable one is skipped here
        and told by its agent's lidar frames). The agents share ``world_global`` and CARLA's ticks: a
        vehicle between two of them is seen from both sides."""
        if self.shapes is None:
            return
        others = [a for a in self._plan.agents.values() if a.lidar_ids and a.agent_id != self._agent.agent_id]
        for agent in [self._agent, *others] if self._agent.lidar_ids else others:
            pcds = [src.pcd_path(agent.agent_dir, key) for key in agent.keys]
            fetched = reader.read_ahead(pcds, agent.files, keep=True)
            for frame, (key, (_, pcd)) in enumerate(zip(agent.keys, fetched, strict=True)):
                try:
                    if isinstance(pcd, SourceError):
                        raise pcd
                    xyz_lidar_m = points_right_handed(src.read_points(agent.agent_dir, key, pcd).xyz_m)
                except SourceError:
                    continue
                self.gather(agent, frame, key, xyz_lidar_m)

    def gather(self, agent: AgentPlan, frame: int, key: str, xyz_lidar_m: np.ndarray) -> None:
        """Tick ``key``'s (``agent``'s frame index ``frame``) evidence of the vehicles' shapes from
        ``agent``'s lidar points ``xyz_lidar_m`` (its lidar frame, right-handed, [N,3], m;
        :mod:`objects.track_shapes`). CARLA's boxes are where the actors are at the tick, so every
        vehicle's boxes pool, moving or not (``agent``'s own left out: its lidar sees it from
        inside)."""
        if self.shapes is None or not len(xyz_lidar_m):
            return
        actors, T_box, half = tick_boxes(self._plan, agent, key)
        T_lidar_world_global = agent.T_rig_world_global[frame] @ agent.T_sensor_rig[LIDAR]
        xyz_m = np.asarray(xyz_lidar_m, np.float64) @ T_lidar_world_global[:3, :3].T + T_lidar_world_global[:3, 3]
        origin_m = T_lidar_world_global[:3, 3]
        model = agent.lidar_model  # its rows' median steps (without one: a cover map's cell, as box_index)
        if model is None:
            spacing_m = np.full((len(xyz_m), 2), CELL_M)
        else:
            spacing_m = np.linalg.norm(xyz_m - origin_m, axis=1)[:, None] * np.median(model.row_steps_rad(), axis=0)
        self.shapes.gather(actors.tolist(), T_box, half, xyz_m, spacing_m, origin_m, RangeImage(xyz_m, origin_m))

    def store_depth(self, frame: int, key: str, t_us: int, cameras: list[str], points, why_none: str = "") -> None:
        """The depth labels of ``cameras`` (those with a picture) at tick ``key`` (frame index
        ``frame``, ``t_us``) from ``points`` (``lidar_frames.PointData`` of the tick; None: the lidar
        frame is unreadable, ``why_none`` says why)."""
        started = time.perf_counter()
        _, T_box, half = tick_boxes(self._plan, self._agent, key)
        for cam in cameras:
            if ("depth", cam) not in self._streams:
                continue
            if points is None:
                width, height = self._agent.cameras[cam].pinhole.resolution_px
                depth, meta = np.zeros((height, width), np.float32), {"no_measurement": why_none}
            else:
                view = camera_view(self._agent, frame, t_us, cam, T_box, half)
                depth = camera_labels.depth_z(
                    view, points.xyz_fixed_m, points.timestamps_us, points.dynamic, points.spacing_m
                )
                meta = {contract.CARLA_FRAME: int(key)}
            self._streams["depth", cam].store_label(depth, t_us, meta)
            self.labels += 1
        self.seconds += time.perf_counter() - started

    def store_boxes(self, frame: int, key: str, t_us: int, cam: str, points, why_boxes: str = "") -> None:
        """The box labels of camera ``cam`` at tick ``key`` (frame index ``frame``, ``t_us``): each
        vehicle where the agent's lidar points of the tick (``points``, ``lidar_frames.PointData``)
        show it (:func:`camera_labels.box_index`); None: its whole box, ``why_boxes`` says why."""
        started = time.perf_counter()
        actors, T_box, half = tick_boxes(self._plan, self._agent, key)
        view = camera_view(self._agent, frame, t_us, cam, T_box, half)
        if points is None:
            picture = camera_labels.box_index(view, T_box, half)
            meta = {contract.CARLA_FRAME: int(key), "masks_from": f"boxes only: {why_boxes}"}
        else:
            T_lidar_world_global = self._agent.T_rig_world_global[frame] @ self._agent.T_sensor_rig[LIDAR]
            if self._covers_of != key:  # the tick's cover maps and range image, shared by its cameras
                self._covers, self._covers_of = {}, key
                self._sight = RangeImage(points.xyz_fixed_m, T_lidar_world_global[:3, 3])
            picture = camera_labels.box_index(
                view,
                T_box,
                half,
                None,
                points.xyz_fixed_m,
                points.spacing_m,
                T_lidar_world_global[:3, 3],
                self._covers,
                actors.tolist(),
                self._sight,
                self.shapes,
            )
            meta = {contract.CARLA_FRAME: int(key)}
        instance_of_box = np.array([self._index[int(a)] for a in actors], dtype=np.int64)
        dynamic_of_box = np.array([str(a) in self._plan.cuboid_labels.dynamic for a in actors], dtype=bool)
        instance, dynamic, shown = camera_labels.box_labels(picture, instance_of_box, dynamic_of_box)
        if ("dynamic", cam) in self._streams:
            self._streams["dynamic", cam].store_label(dynamic, t_us, meta)
            self.labels += 1
        if ("instance", cam) in self._streams:
            self._streams["instance", cam].store_label(instance, t_us, {**meta, "instances_shown": shown})
            self.labels += 1
        self.seconds += time.perf_counter() - started

    def finish(self) -> None:
        """Set each component's metadata."""
        for (kind, _), stream in self._streams.items():
            stream.set_meta(self._meta[kind])
