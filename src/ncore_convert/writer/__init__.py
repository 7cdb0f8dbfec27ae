"""The one place that talks to the nvidia-ncore V4 writer (this package; ``labels.py``: how camera
labels are stored).

Converters hand over plain numpy arrays and Python values; this module builds the NCore types,
registers the components under their default instance names, and writes the sequence-meta JSON and
the cooperative ``scenario.json``. Frame ids are passed by keyword. The names it writes that
readers look up again are defined in :mod:`ncore_convert.contract`.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import PIL.Image
from ncore.data.v4 import (
    CameraLabelsComponent,
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
from ncore.impl.data.types import (
    BBox3,
    CuboidTrackObservation,
    FThetaCameraModelParameters,
    IdealPinholeCameraModelParameters,
    LabelSource,
    OpenCVPinholeCameraModelParameters,
    RowOffsetStructuredSpinningLidarModelParameters,
    ShutterType,
)
from ncore.impl.data.v4.components import SequenceMeta
from upath import UPath

from ncore_convert.contract import (
    DEFAULT_INSTANCE,
    MANIFEST,
    MAP_GROUND_HEIGHT,
    MAP_META,
    MAP_VECTOR_JSON,
    CameraModel,
    Profile,
    ScenarioManifest,
    StoreType,
    camera_label_id,
)
from ncore_convert.storage import flush_to_disk
from ncore_convert.transforms.camera.models import FThetaFit, Pinhole
from ncore_convert.transforms.lidar.model import SpinningLidarModel
from ncore_convert.transforms.lidar.rays import RayBundle
from ncore_convert.writer.labels import CameraLabelStream, label_descriptor
from ncore_convert.writer.parts import component_groups


@dataclass(frozen=True)
class Cuboids:
    """Cuboid track observations, columnar. Boxes are centred, in ``reference_frame_id`` at ``timestamps_us``.

    Attributes:
        track_ids, class_ids: lists of str [M].
        timestamps_us: int [M], observation and reference-frame time, microseconds.
        centroids_m: box centres, float64 [M,3]; dims_m: (length, width, height), float64 [M,3].
        euler_xyz_rad: extrinsic xyz Euler angles of the box frame, float64 [M,3].
    """

    track_ids: list[str]
    class_ids: list[str]
    timestamps_us: np.ndarray
    centroids_m: np.ndarray
    dims_m: np.ndarray
    euler_xyz_rad: np.ndarray
    reference_frame_id: str = "rig"

    def __len__(self) -> int:
        return len(self.track_ids)


class _SensorStream:
    """A sensor component writer; its component-level metadata can be set after the frames."""

    def __init__(self, writer: CameraSensorComponent.Writer | LidarSensorComponent.Writer) -> None:
        self._writer = writer

    def set_meta(self, generic_meta_data: dict) -> None:
        """Replace the component-level metadata (written at finalize)."""
        self._writer.set_generic_data({}, generic_meta_data)


class CameraStream(_SensorStream):
    """Frames of one camera. Image bytes are stored as given (no re-encode)."""

    def store_frame(self, image_bytes: bytes, image_format: str, timestamps_us: tuple[int, int]) -> None:
        """Store one encoded image with its (start, end) exposure times in microseconds."""
        self._writer.store_frame(
            image_binary_data=image_bytes,
            image_format=image_format,
            frame_timestamps_us=np.array(timestamps_us, dtype=np.uint64),
            generic_data={},
            generic_meta_data={},
        )


class LidarStream(_SensorStream):
    """Frames of one lidar, stored as single-return ray bundles."""

    def store_frame(
        self,
        rays: RayBundle,
        generic_meta_data: dict,
        model_element: np.ndarray | None = None,
        generic_data: dict[str, np.ndarray] | None = None,
    ) -> None:
        """Store one frame; ``model_element`` is uint16 [N,2] (row, column) of the lidar's model, or None;
        ``generic_data``: per-point arrays [N] (e.g. ``contract.DYNAMIC_FLAG``, int8)."""
        self._writer.store_frame(
            direction=rays.direction,
            timestamp_us=rays.timestamp_us,
            model_element=model_element,
            distance_m=rays.distance_m[None, :],
            intensity=rays.intensity[None, :],
            frame_timestamps_us=rays.frame_timestamps_us,
            generic_data=generic_data or {},
            generic_meta_data=generic_meta_data,
        )


def camera_model_parameters(pinhole: Pinhole, model: CameraModel, ftheta: FThetaFit | None = None):
    """NCore's camera model parameters of a global-shutter camera (see :meth:`SequenceWriter.store_camera`)."""
    common = {"resolution": np.array(pinhole.resolution_px, dtype=np.uint64), "shutter_type": ShutterType.GLOBAL}
    pinhole_terms = {
        "principal_point": np.array(pinhole.principal_point_px, dtype=np.float32),
        "focal_length": np.array(pinhole.focal_length_px, dtype=np.float32),
    }
    if model == "ideal-pinhole":
        params = IdealPinholeCameraModelParameters(**common, **pinhole_terms)
    elif model == "opencv-pinhole":
        params = OpenCVPinholeCameraModelParameters(
            **common,
            **pinhole_terms,
            radial_coeffs=np.zeros(6, dtype=np.float32),
            tangential_coeffs=np.zeros(2, dtype=np.float32),
            thin_prism_coeffs=np.zeros(4, dtype=np.float32),
        )
    else:
        params = FThetaCameraModelParameters(
            **common,
            principal_point=ftheta.principal_point_px,
            reference_poly=FThetaCameraModelParameters.PolynomialType.PIXELDIST_TO_ANGLE,
            pixeldist_to_angle_poly=ftheta.pixeldist_to_angle,
            angle_to_pixeldist_poly=ftheta.angle_to_pixeldist,
            max_angle=ftheta.max_angle_rad,
            linear_cde=ftheta.linear_cde,
        )
    return params


def _observations(cuboids: Cuboids, source: LabelSource) -> Iterator[CuboidTrackObservation]:
    for i in range(len(cuboids)):
        ts = int(cuboids.timestamps_us[i])
        yield CuboidTrackObservation(
            track_id=str(cuboids.track_ids[i]),
            class_id=str(cuboids.class_ids[i]),
            timestamp_us=ts,
            reference_frame_id=cuboids.reference_frame_id,
            reference_frame_timestamp_us=ts,
            bbox3=BBox3(
                centroid=tuple(float(v) for v in cuboids.centroids_m[i]),
                dim=tuple(float(v) for v in cuboids.dims_m[i]),
                rot=tuple(float(v) for v in cuboids.euler_xyz_rad[i]),
            ),
            source=source,
        )


class SequenceWriter:
    """Writes the component stores of one NCore V4 sequence, or a disjoint part of them.

    Files: ``<output_dir>/<sequence_id>.ncore4*.zarr[.itar]``. Several writers with the same
    sequence arguments may write different jobs (see ``writer.parts.independent_parts``), e.g. one
    per process; :func:`write_sequence_meta` joins their parts into ``<sequence_id>.json``.
    With ``base=True`` the writer owns the poses, intrinsics, masks and cuboids components, which
    are always written (empty masks and cuboids when there are none).
    """

    def __init__(
        self,
        output_dir: UPath,
        sequence_id: str,
        interval_us: tuple[int, int],
        generic_meta_data: dict,
        camera_ids: list[str],
        lidar_ids: list[str],
        store_type: StoreType = "itar",
        profile: Profile = "separate-sensors",
        base: bool = True,
        poses_meta: dict | None = None,
        extra_pose_instances: dict[str, dict] | None = None,
        label_ids: list[str] = (),
    ) -> None:
        """
        Args:
            interval_us: inclusive (start, end) of the sequence in microseconds.
            camera_ids, lidar_ids: all sensors of the sequence (they fix the store layout).
            extra_pose_instances: instance name -> metadata of further ``PosesComponent`` instances
                next to ``default`` (e.g. a trajectory with simulated GPS error). Each holds the
                whole pose graph: the static edges are written to every instance.
            label_ids: all camera labels of the sequence (``contract.camera_label_id``; they fix
                the store layout too).
        """
        self._groups = component_groups(camera_ids, lidar_ids, profile, label_ids)
        self._writer = SequenceComponentGroupsWriter(
            output_dir_path=output_dir,
            store_base_name=sequence_id,
            sequence_id=sequence_id,
            sequence_timestamp_interval_us=HalfClosedInterval.from_start_end(int(interval_us[0]), int(interval_us[1])),
            generic_meta_data=generic_meta_data,
            store_type=store_type,
        )
        self._base = base
        if base:
            register = self._writer.register_component_writer
            groups = self._groups
            self._poses = {
                name: register(PosesComponent.Writer, name, groups.poses_component_group, meta)
                for name, meta in {DEFAULT_INSTANCE: poses_meta or {}, **(extra_pose_instances or {})}.items()
            }
            self._intrinsics = register(IntrinsicsComponent.Writer, DEFAULT_INSTANCE, groups.intrinsics_component_group)
            self._masks = register(MasksComponent.Writer, DEFAULT_INSTANCE, groups.masks_component_group)
            self._cuboids = register(
                CuboidsComponent.Writer, DEFAULT_INSTANCE, groups.cuboid_track_observations_component_group
            )

    def _require_base(self) -> None:
        if not self._base:
            raise RuntimeError("poses, intrinsics, masks and cuboids are written by the base writer")

    def store_trajectory(
        self,
        timestamps_us: np.ndarray,
        T_rig_world: np.ndarray,
        T_world_world_global: np.ndarray | None,
        *,
        rig_frame: str = "rig",
        instance: str = DEFAULT_INSTANCE,
        covers_sequence: bool = True,
    ) -> None:
        """Store ``rig->world`` (dynamic, float32) in one poses instance and ``world->world_global``
        (static, float64) in every instance.

        Args:
            timestamps_us: int [N >= 2], strictly increasing, within the sequence interval; from its
                start to its end unless ``covers_sequence`` is False (a rig that is not there all
                along, e.g. an agent of a cooperative scenario with fewer frames than the others).
            T_rig_world: [N,4,4], stored as float32.
            T_world_world_global: [4,4], stored as float64; None when another call stores it
                (several rigs in one sequence, or a further poses instance).
            rig_frame: the moving frame's name ("rig", or e.g. "agent1732_rig").
            instance: the ``PosesComponent`` instance of the dynamic edge.
        """
        self._require_base()
        self._poses[instance].store_dynamic_pose(
            rig_frame,
            "world",
            T_rig_world.astype(np.float32),
            np.asarray(timestamps_us, dtype=np.uint64),
            require_sequence_time_coverage=covers_sequence,
        )
        if T_world_world_global is not None:
            for poses in self._poses.values():
                poses.store_static_pose("world", "world_global", T_world_world_global.astype(np.float64))

    def store_pose_data(self, instance: str, arrays: dict[str, np.ndarray]) -> None:
        """Add named arrays to a poses instance's component-level generic data (written at finalize)."""
        self._require_base()
        self._poses[instance].set_generic_data(arrays)

    def store_map(self, vector_map_json: bytes, ground_height_m: np.ndarray, meta: dict) -> None:
        """Attach an HD map to the poses component (which holds ``world_global``) as generic data.

        Args:
            vector_map_json: the vector map file's bytes, stored as uint8 [B] (``MAP_VECTOR_JSON``).
            ground_height_m: ground height raster [H,W], stored with its dtype (``MAP_GROUND_HEIGHT``).
            meta: JSON-able description (frame, Sim(2), lookup rule), stored as ``MAP_META``.
        """
        self._require_base()
        self._poses[DEFAULT_INSTANCE].set_generic_data(
            {MAP_VECTOR_JSON: np.frombuffer(vector_map_json, dtype=np.uint8), MAP_GROUND_HEIGHT: ground_height_m},
            {MAP_META: meta},
        )

    def store_extrinsic(self, sensor_id: str, T_sensor_rig: np.ndarray, *, rig_frame: str = "rig") -> None:
        """Store a static sensor->rig extrinsic [4,4] (float32) in every poses instance."""
        self._require_base()
        for poses in self._poses.values():
            poses.store_static_pose(sensor_id, rig_frame, T_sensor_rig.astype(np.float32))

    def store_camera(
        self,
        camera_id: str,
        pinhole: Pinhole,
        model: CameraModel,
        ftheta: FThetaFit | None = None,
        masks: dict[str, PIL.Image.Image] | None = None,
    ) -> None:
        """Store a global-shutter camera model (OpenCV camera frame) and the camera's masks (by name,
        e.g. ``contract.EGO_MASK``; none by default), PNG-encoded by the library.

        Args:
            pinhole: the camera as an ideal pinhole (NCore pixel-corner convention).
            model: ``ideal-pinhole`` (NCore ``IdealPinholeCameraModelParameters``), ``opencv-pinhole``
                (``OpenCVPinholeCameraModelParameters``, every distortion coefficient 0: the same rays),
                or ``ftheta`` (``FThetaCameraModelParameters`` from ``ftheta``, the fit to ``pinhole``).
        """
        self._require_base()
        params = camera_model_parameters(pinhole, model, ftheta)
        self._intrinsics.store_camera_intrinsics(camera_id, params)
        self._masks.store_camera_masks(camera_id, masks or {})

    def store_lidar_model(self, lidar_id: str, model: SpinningLidarModel) -> None:
        """Store a lidar's structured model as NCore ``RowOffsetStructuredSpinningLidarModelParameters``."""
        self._require_base()
        self._intrinsics.store_lidar_intrinsics(
            lidar_id,
            RowOffsetStructuredSpinningLidarModelParameters(
                spinning_frequency_hz=float(model.spinning_frequency_hz),
                spinning_direction=model.spinning_direction,
                n_rows=len(model.row_elevations_rad),
                n_columns=len(model.column_azimuths_rad),
                row_elevations_rad=model.row_elevations_rad.astype(np.float32),
                column_azimuths_rad=model.column_azimuths_rad.astype(np.float32),
                row_azimuth_offsets_rad=model.row_azimuth_offsets_rad.astype(np.float32),
            ),
        )

    def add_camera(self, camera_id: str, generic_meta_data: dict) -> CameraStream:
        """Register a camera component; its frames are stored through the returned stream."""
        writer = self._writer.register_component_writer(
            CameraSensorComponent.Writer,
            camera_id,
            self._groups.camera_component_groups.get(camera_id),
            generic_meta_data,
        )
        return CameraStream(writer)

    def add_lidar(self, lidar_id: str, generic_meta_data: dict) -> LidarStream:
        """Register a lidar component; its frames are stored through the returned stream."""
        writer = self._writer.register_component_writer(
            LidarSensorComponent.Writer, lidar_id, self._groups.lidar_component_groups.get(lidar_id), generic_meta_data
        )
        return LidarStream(writer)

    def add_camera_label(self, kind: str, camera_id: str, source: str, generic_meta_data: dict) -> CameraLabelStream:
        """Register one camera's labels of ``kind`` (``contract.CAMERA_LABEL_KINDS``) from the NCore
        ``LabelSource`` named ``source``; they are stored through the returned stream."""
        label_id = camera_label_id(kind, camera_id)
        writer = self._writer.register_component_writer(
            CameraLabelsComponent.Writer,
            label_id,
            self._groups.camera_labels_component_groups.get(label_id),
            generic_meta_data,
            descriptor=label_descriptor(kind, camera_id, source),
        )
        return CameraLabelStream(writer, kind)

    def store_cuboids(self, cuboids: Cuboids | None, source: str = "EXTERNAL", meta: dict | None = None) -> None:
        """Store all cuboid observations (an empty component when there are none), tagged with the
        NCore ``LabelSource`` named ``source``; ``meta``: the component's generic metadata.

        The library keeps every observation in one JSON attribute, so this costs memory in
        proportion to the number of observations; they are handed over one at a time (a
        generator) so that only the library's own copy is held.
        """
        self._require_base()
        self._cuboids.store_observations(_observations(cuboids, LabelSource[source]) if cuboids is not None else [])
        if meta:
            self._cuboids.set_generic_data({}, meta)

    def finalize(self, with_meta: bool = True) -> SequenceMeta | None:
        """Close this writer's stores and flush them to disk. With ``with_meta``, return the library's
        sequence meta of these stores (component summaries and md5 checksums, computed here so parts
        hash in parallel)."""
        paths = self._writer.finalize()
        for path in paths:  # on disk now, overlapping the other writers' work
            flush_to_disk(path)
        if not with_meta or not paths:
            return None
        meta = SequenceComponentGroupsReader(paths).get_sequence_meta()
        order = [path.name for path in paths]  # the reader lists stores in load-completion order
        return dataclasses.replace(
            meta, component_stores=sorted(meta.component_stores, key=lambda s: order.index(s.path))
        )


def write_sequence_meta(output_dir: UPath, sequence_id: str, parts: list[SequenceMeta]) -> UPath:
    """Join the sequence metas of the writer parts into ``<output_dir>/<sequence_id>.json``.

    Stores are listed in part order, so the file does not depend on which process finished first.
    """
    stores = [store for part in parts for store in part.component_stores]
    for part in parts[1:]:
        if dataclasses.replace(part, component_stores=[]) != dataclasses.replace(parts[0], component_stores=[]):
            raise ValueError(f"{sequence_id}: writer parts disagree on the sequence properties")
    meta = dataclasses.replace(parts[0], component_stores=stores)
    path = output_dir / f"{sequence_id}.json"
    path.write_text(json.dumps(meta.to_dict(), indent=2))
    flush_to_disk(path)
    return path


def write_scenario_manifest(output_dir: UPath, manifest: ScenarioManifest) -> UPath:
    """Write ``<output_dir>/scenario.json`` (the last file of a scenario) and flush it to disk."""
    path = output_dir / MANIFEST
    path.write_text(json.dumps(manifest.to_dict(), indent=2))
    flush_to_disk(path)
    return path
