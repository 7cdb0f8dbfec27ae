"""The one place that opens what the converter wrote: sequences through ``SequenceLoaderV4`` (with
the default instance names unless asked otherwise), ``scenario.json``, and the geometry the checks
and pictures need from them (points and boxes in ``world``).

Transforms follow the house rule: ``T_a_b`` maps points from frame ``a`` to frame ``b``; every pose
comes from :mod:`.poses`, the one place that evaluates NCore's pose graph.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
from ncore.data.v4 import (
    CameraSensorComponent,
    LidarSensorComponent,
    SequenceComponentGroupsReader,
    SequenceLoaderV4,
)
from scipy.spatial.transform import Rotation
from upath import UPath

from ncore_convert.contract import DEFAULT_INSTANCE, ScenarioManifest
from ncore_convert.transforms.objects.boxes import PointGrid, box_corners, count_in_box_band
from ncore_convert.transforms.sampling import spread_indices
from ncore_convert.validate.cuboids import CuboidColumns
from ncore_convert.validate.poses import sensor_poses

#: Frames sampled over a sensor for the checks that need motion-compensated points.
SAMPLED_FRAMES = 5


@dataclass(frozen=True)
class OpenSequence:
    """A sequence opened for reading: the loader, and the reader under it (for component metadata).
    ``world_points`` keeps the frames it motion-compensated (the checks sample the same frames)."""

    loader: SequenceLoaderV4
    reader: SequenceComponentGroupsReader
    _points: dict = field(default_factory=dict, compare=False, repr=False)

    def world_points(self, lidar_id: str, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """:func:`world_points` in ``world``, computed once per lidar frame."""
        key = (lidar_id, frame)
        if key not in self._points:
            self._points[key] = world_points(self.loader, lidar_id, frame)
        return self._points[key]

    def computed_points(self) -> dict:
        """The frames :meth:`world_points` computed so far: (lidar id, frame) -> its result."""
        return dict(self._points)

    def keep_points(self, points: dict) -> None:
        """Take frames another process computed (:meth:`computed_points` there)."""
        self._points.update(points)

    def sensor_meta(self) -> dict[str, dict]:
        """Each lidar and camera component's generic metadata, by sensor id."""
        out = {}
        for component in (LidarSensorComponent, CameraSensorComponent):
            readers = self.reader.open_component_readers(component.Reader)
            out.update({name: r.generic_meta_data for name, r in readers.items()})
        return out


def open_sequence(sequence_json: UPath, poses_instance: str = DEFAULT_INSTANCE) -> OpenSequence:
    """Open ``<sequence_id>.json`` with the default component instances (``poses_instance``: the
    poses component instance, e.g. a noise setting's)."""
    reader = SequenceComponentGroupsReader([UPath(sequence_json)])
    return OpenSequence(SequenceLoaderV4(reader, poses_component_group_name=poses_instance), reader)


#: The components whose instances are sensors: each needs at least one frame to open.
SENSOR_COMPONENTS = ("cameras", "lidars", "radars")


def open_failure(sequence_json: UPath, err: Exception) -> str:
    """Why ``SequenceLoaderV4`` could not open a sequence, in one line: the component instance (and
    its store) that is empty or malformed when one is, else the library's exception."""
    raised = f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
    try:
        reader = SequenceComponentGroupsReader([UPath(sequence_json)])
        # the library has no public per-store access; its readers fail on the first bad instance
        stores = reader._component_stores.values()
        found = []
        for root, path in stores:
            for component in SENSOR_COMPONENTS:
                for instance, group in (root.get(component) or {}).items():
                    frames = group.get("frames")
                    count = None if frames is None else len(frames.attrs.get("frames_timestamps_us", []))
                    if not count:
                        what = "no frames group" if frames is None else "zero frames (an empty sensor)"
                        found.append(f"{component}/{instance} in {UPath(path).name}: {what}")
    except Exception as inner:  # noqa: BLE001 - the stores themselves do not open: that is the finding
        return f"{raised} (the component stores do not open either: {type(inner).__name__}: {inner})"
    if not found:
        return raised
    return f"{'; '.join(found)} (the library raised {raised})"


def read_manifest(manifest_path: UPath) -> ScenarioManifest:
    return ScenarioManifest.from_dict(json.loads(UPath(manifest_path).read_text()))


def sample_frames(n_frames: int) -> np.ndarray:
    """SAMPLED_FRAMES frame indices spread evenly over a sensor's ``n_frames`` frames."""
    return spread_indices(n_frames, SAMPLED_FRAMES)


def boxes_at(cuboids: CuboidColumns, t0_us: int, t1_us: int) -> CuboidColumns:
    """The cuboid observations of one labelled instant in a frame [t0_us, t1_us]: the earliest
    label time within it (consecutive lidar frames can overlap by a few ms, so a frame's interval
    may also hold the next sweep's label time)."""
    t_us = cuboids.timestamp_us
    inside = (t_us >= t0_us) & (t_us <= t1_us)
    if not inside.any():
        return cuboids.rows(inside)
    return cuboids.rows(inside & (t_us == t_us[inside].min()))


def world_points(
    loader: SequenceLoaderV4, lidar_id: str, frame: int, target: str = "world"
) -> tuple[np.ndarray, np.ndarray]:
    """A lidar frame's points, motion-compensated with the per-point times, in ``target`` (``world``
    or ``world_global``, the dataset's global frame whatever ``--world-global-mode`` stored).

    Returns:
        xyz_m in target, float64 [N,3], and the sensor's position there at the frame end, float64 [3].
    """
    lidar = loader.get_lidar_sensor(lidar_id)
    end_us = lidar.frames_timestamps_us[frame, 1:2]
    T_sensor_target = sensor_poses(loader, lidar_id, target, end_us)[0]
    xyz_sensor_m = lidar.get_frame_point_cloud(frame, motion_compensation=True, with_start_points=False).xyz_m_end
    xyz_target_m = xyz_sensor_m.astype(np.float64) @ T_sensor_target[:3, :3].T + T_sensor_target[:3, 3]
    return xyz_target_m, T_sensor_target[:3, 3]


def _T_reference_world(loader: SequenceLoaderV4, frame_id: str, t_us: int) -> np.ndarray:
    """A reference frame -> ``world`` at ``t_us``, float64 [4,4]."""
    return sensor_poses(loader, frame_id, "world", np.array([t_us]))[0]


def _reference_poses(loader: SequenceLoaderV4, boxes: CuboidColumns) -> list[tuple[list[int], np.ndarray | None]]:
    """The boxes grouped by reference frame and time: each group's box indices and that frame's pose
    in ``world`` then, float64 [4,4] (None: it cannot be posed; the cuboid checks name it)."""
    groups: dict[tuple[str, int], list[int]] = {}
    for k, key in enumerate(zip(boxes.reference_frame_id, boxes.reference_frame_timestamp_us.tolist(), strict=True)):
        groups.setdefault(key, []).append(k)
    out = []
    for (frame_id, t_us), members in groups.items():
        try:
            out.append((members, _T_reference_world(loader, frame_id, t_us)))
        except (KeyError, ValueError, AssertionError):
            out.append((members, None))
    return out


def box_centres_world(loader: SequenceLoaderV4, boxes: CuboidColumns) -> np.ndarray:
    """The box centres in ``world``, float64 [B,3] (NaN where the reference frame cannot be posed)."""
    centres = np.full((len(boxes), 3), np.nan)
    for members, T_ref_world in _reference_poses(loader, boxes):
        if T_ref_world is not None:
            centres[members] = boxes.centroid_m[members] @ T_ref_world[:3, :3].T + T_ref_world[:3, 3]
    return centres


def box_point_counts(
    loader: SequenceLoaderV4, boxes: CuboidColumns, xyz_world_m: np.ndarray, margin_m: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """How many of the points (world, float64 [N,3]) lie inside each box shrunk and grown by its
    ``margin_m`` (metres [B], 0 without: both are then the exact count;
    :func:`~ncore_convert.transforms.objects.boxes.count_in_box_band`), int [B] each. Each box is
    tested in float64 in its own reference frame at its reference time (one pose per reference frame
    and time). A box whose reference frame cannot be posed at its time counts -1."""
    inner, outer = np.zeros(len(boxes), np.int64), np.zeros(len(boxes), np.int64)
    margin_m = np.zeros(len(boxes)) if margin_m is None else margin_m
    R_box_ref = Rotation.from_euler("xyz", boxes.rot_rad).as_matrix() if len(boxes) else np.zeros((0, 3, 3))
    for members, T_ref_world in _reference_poses(loader, boxes):
        if T_ref_world is None:
            inner[members], outer[members] = -1, -1
            continue
        points = PointGrid((xyz_world_m - T_ref_world[:3, 3]) @ T_ref_world[:3, :3])
        for k in members:
            half_m = np.asarray(boxes.dim_m[k], dtype=np.float64) / 2
            inner[k], outer[k] = count_in_box_band(points, boxes.centroid_m[k], R_box_ref[k], half_m, margin_m[k])
    return inner, outer


def box_corners_world(loader: SequenceLoaderV4, boxes: CuboidColumns) -> np.ndarray:
    """The 8 corners of each box in ``world``, float64 [B,8,3]."""
    R_box_ref = Rotation.from_euler("xyz", boxes.rot_rad).as_matrix()
    xyz_ref = box_corners(R_box_ref, boxes.centroid_m, boxes.dim_m / 2)
    out = np.empty_like(xyz_ref)
    for k, (frame_id, t_us) in enumerate(
        zip(boxes.reference_frame_id, boxes.reference_frame_timestamp_us.tolist(), strict=True)
    ):
        T_ref_world = _T_reference_world(loader, frame_id, t_us)
        out[k] = xyz_ref[k] @ T_ref_world[:3, :3].T + T_ref_world[:3, 3]
    return out
