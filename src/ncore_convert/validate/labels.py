"""Checks of a camera's labels (NCore's camera-labels component, ``--camera-labels``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ncore.data.v4 import SequenceLoaderV4
from ncore.impl.data.types import LabelCategory

from ncore_convert import contract
from ncore_convert.transforms.camera.models import FTheta, Pinhole
from ncore_convert.transforms.objects.boxes import box_edges, near_plane_crossings
from ncore_convert.transforms.objects.dynamic import HOLD_S
from ncore_convert.transforms.sampling import spread_indices
from ncore_convert.validate.cuboids import CuboidColumns
from ncore_convert.validate.poses import sensor_poses
from ncore_convert.validate.readback import box_corners_world
from ncore_convert.validate.report import Report

#: Labels decoded per label component: the first, the last and evenly spread ones between.
DECODED_SAMPLE = 8
#: How far (px) a mask pixel may lie outside the rectangle of its box's projected corners (rounding,
#: and a stored f-theta model's bend of the box's edges between its corners).
BOX_MARGIN_PX = 2.0
#: Per-label metadata of a mask whose moving objects are unknown (the dynamic mask is all 1 there).
UNKNOWN_KEY = "moving_objects_unknown"


def check_camera_labels(
    report: Report, loader: SequenceLoaderV4, camera_id: str, held: HeldBoxes | None = None
) -> None:
    """Every label component of ``camera_id``: one label per camera frame, at the frame's end time;
    a sample of ``DECODED_SAMPLE`` decoded through the library has the camera's size; depth is
    finite and >= 0 (0: no measurement); a mask's pixels lie within the projections of the boxes
    they name (``held``: the sequence's cuboids, :func:`held_boxes`, made once per sequence): an
    instance's within its track's, a dynamic pixel's
    within a dynamic track's (not a ``mask.dynamic`` made from the lidar's own movers: it names no box)."""
    camera = loader.get_camera_sensor(camera_id)
    frames_end_us = np.sort(camera.frames_timestamps_us[:, 1])
    width, height = (int(v) for v in camera.model_parameters.resolution)
    found = loader.query_camera_labels(camera_id)
    instances = _instance_tables(found)
    projection = stored_camera(camera.model_parameters)
    for labels in found:
        # a mask made from the lidar's own movers (TbV) names no box to lie within
        from_boxes = (labels.labels_generic_meta_data or {}).get("generator") != contract.MOVER_MASK_GENERATOR
        boxes_checked = held is not None and projection is not None and from_boxes
        descriptor = labels.label_descriptor
        category = descriptor.label_type.category
        name = f"camera {camera_id}: label {descriptor.default_instance_name}"
        stamps_us = np.sort(labels.label_timestamps_us)
        report.add(
            f"{name}: one per camera frame",
            np.array_equal(stamps_us, frames_end_us),
            f"{len(stamps_us)} labels for {len(frames_end_us)} frames"
            f" ({len(np.setdiff1d(frames_end_us, stamps_us))} frames without one,"
            f" {len(np.setdiff1d(stamps_us, frames_end_us))} labels at no frame's end time)",
        )
        problems, labelled, outside = [], [], []
        for i in spread_indices(len(stamps_us), DECODED_SAMPLE):
            ts = int(stamps_us[i])
            try:
                handle = labels.get_label(ts)
                data = handle.get_data()
            except Exception as err:  # noqa: BLE001 - any failure to decode is the finding
                problems.append(f"{ts}: does not decode ({type(err).__name__})")
                continue
            if data.shape[:2] != (height, width):
                problems.append(f"{ts}: {data.shape[1]}x{data.shape[0]} px")
            elif category == LabelCategory.DEPTH and not np.all(np.isfinite(data) & (data >= 0)):
                problems.append(f"{ts}: depth not finite and >= 0 everywhere")
            elif category == LabelCategory.MASK and not np.all((data == 0) | (data == 1)):
                problems.append(f"{ts}: mask values other than 0 and 1")
            else:
                labelled.append(float(np.count_nonzero(data)) / data.size)
                if category in (LabelCategory.MASK, LabelCategory.SEGMENTATION) and boxes_checked:
                    if UNKNOWN_KEY not in (handle.generic_meta_data or {}):
                        outside += _outside_boxes(loader, camera_id, projection, data, category, instances, held, ts)
        report.add(
            f"{name}: decodes, the camera's size, valid values",
            not problems,
            "; ".join(problems[:3])
            or f"{len(labelled)} labels decoded ({width}x{height}), median {np.median(labelled):.2%} of pixels set",
        )
        if category in (LabelCategory.MASK, LabelCategory.SEGMENTATION) and held is not None and from_boxes:
            report.add(
                f"{name}: within the projected boxes",
                not outside,
                "; ".join(outside[:3])
                or (
                    f"every set pixel of {len(labelled)} labels within its boxes' projection"
                    if boxes_checked
                    else f"not checked: the camera is stored as {type(camera.model_parameters).__name__},"
                    " and the check projects distortion-free pinholes and the converter's f-theta models"
                ),
            )


def _instance_tables(found: list) -> dict[int, dict]:
    """The instance index -> {track_id, class_id, dynamic} table of the camera's instance labels ({}: none)."""
    for labels in found:
        if labels.label_descriptor.label_type.category == LabelCategory.SEGMENTATION:
            table = (labels.labels_generic_meta_data or {}).get("instances", {})
            return {int(k): v for k, v in table.items()}
    return {}


def _outside_boxes(
    loader: SequenceLoaderV4,
    camera_id: str,
    camera: Pinhole | FTheta,
    data: np.ndarray,
    category: LabelCategory,
    instances: dict[int, dict],
    held: HeldBoxes,
    ts: int,
) -> list[str]:
    """What of a mask label (``data`` [H,W], of the camera frame ending at ``ts``, µs) lies outside the rectangle
    of the projected corners of every observation of the track(s) it names, grown by
    ``BOX_MARGIN_PX`` (and of its ends carried on ``HOLD_S`` along its end segments, as the labels
    hold them): an instance's pixels outside its own track's; a dynamic mask's outside every
    dynamic track's (every track's without an instance table). A box crossing the plane of the
    camera is cut ``CUT_Z_M`` ahead of it (:func:`_in_front`), its edges sampled (an f-theta
    picture of a straight edge bends). ``camera``: :func:`stored_camera`'s projection."""
    if category == LabelCategory.SEGMENTATION:
        groups = {k: [instances.get(k, {}).get("track_id")] for k in np.unique(data[data > 0]).tolist()}
        unnamed = [k for k, tracks in groups.items() if tracks == [None]]
        if unnamed:
            return [f"{ts}: instance(s) {unnamed[:5]} not in the instance table"]
    else:
        dynamic = [v["track_id"] for v in instances.values() if v.get("dynamic")] if instances else None
        groups = {1: dynamic if dynamic is not None else sorted(set(held.track_id.tolist()))}
    allowed = {k: np.zeros(data.shape[:2], bool) for k in groups}
    end_us = np.array([ts], dtype=np.uint64)
    T_world_camera = np.linalg.inv(sensor_poses(loader, camera_id, "world", end_us)[0])
    for k, tracks in groups.items():
        rows = np.flatnonzero(np.isin(held.track_id, tracks))
        if not len(rows):
            continue
        points, owner = _in_front(held.corners_world_m[rows], T_world_camera)
        if not len(points):
            continue
        pixels = np.stack(camera.project(points), axis=1)
        if not np.all(np.isfinite(pixels)):  # beyond an f-theta's reach: unbounded
            allowed[k][:] = True
            continue
        for box in np.unique(owner):
            u, v = pixels[owner == box, 0], pixels[owner == box, 1]
            c0, c1 = int(max(np.floor(u.min() - BOX_MARGIN_PX), 0)), int(max(np.ceil(u.max() + BOX_MARGIN_PX), 0))
            r0, r1 = int(max(np.floor(v.min() - BOX_MARGIN_PX), 0)), int(max(np.ceil(v.max() + BOX_MARGIN_PX), 0))
            allowed[k][r0:r1, c0:c1] = True
    found = []
    for k in groups:
        stray = np.count_nonzero((data == k) & ~allowed[k])
        if stray:
            what = f"instance {k}" if category == LabelCategory.SEGMENTATION else "dynamic pixels"
            found.append(f"{ts}: {stray} px of {what} outside the projected boxes")
    return found


@dataclass(frozen=True)
class HeldBoxes:
    """The sequence's cuboids as the labels hold them (:func:`held_boxes`): corners in ``world``,
    float64 [B,8,3], and each box's track id, str [B]."""

    corners_world_m: np.ndarray
    track_id: np.ndarray


def held_boxes(loader: SequenceLoaderV4, boxes: CuboidColumns) -> HeldBoxes:
    """Every observation's box (``box_corners_world``), and each track's first and last box carried
    ``HOLD_S`` on along its end segment (a moving box is labelled that long beyond its
    observations). Made once per sequence: the corners take a pose look-up per observation."""
    corners = box_corners_world(loader, boxes)
    held, tracks = [corners], [np.asarray(boxes.track_id, dtype=object)]
    for track in np.unique(boxes.track_id):
        rows = np.flatnonzero(boxes.track_id == track)
        rows = rows[np.argsort(boxes.timestamp_us[rows], kind="stable")]
        if len(rows) < 2:
            continue
        for end, neighbour in ((rows[0], rows[1]), (rows[-1], rows[-2])):
            dt_us = abs(int(boxes.timestamp_us[end]) - int(boxes.timestamp_us[neighbour]))
            if dt_us:
                step_m = corners[end].mean(axis=0) - corners[neighbour].mean(axis=0)
                held.append(corners[end][None] + step_m * (HOLD_S * 1e6 / dt_us))
                tracks.append(np.array([track], dtype=object))
    return HeldBoxes(np.concatenate(held), np.concatenate(tracks))


#: The plane ahead of the camera (m, camera z) that boxes are cut at before projecting: the part of
#: a box behind it is not in the picture.
CUT_Z_M = 0.2
#: Where along each box edge the outline is sampled (the corners included).
EDGE_SAMPLES = np.linspace(0.0, 1.0, 9)


def _in_front(corners_world_m: np.ndarray, T_world_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The outline of each box's part ahead of the camera: its edges' samples (``EDGE_SAMPLES``,
    corners included) beyond ``CUT_Z_M`` and where its edges cross that plane, in the camera frame
    (float64 [P,3]), and the box each point outlines, int [P]. The picture of a box lies within the
    rectangle of these points' projections (to the sampling, for a camera that bends edges)."""
    xyz = corners_world_m @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]  # [B,8,3] camera frame
    start, end = box_edges(xyz)
    along = start[:, :, None] + EDGE_SAMPLES[None, None, :, None] * (end - start)[:, :, None]  # [B,12,S,3]
    on_plane, crossing = near_plane_crossings(xyz, CUT_Z_M)
    points = np.concatenate([along[along[..., 2] > CUT_Z_M], on_plane[crossing]])
    owner = np.concatenate([np.nonzero(along[..., 2] > CUT_Z_M)[0], np.nonzero(crossing)[0]])
    return points, owner


def stored_camera(parameters) -> Pinhole | FTheta | None:
    """The stored camera as a projection (``.project(xyz_camera_m) -> (u, v)``): a :class:`Pinhole`
    when it is stored as a distortion-free pinhole (NCore's ideal pinhole, or an OpenCV pinhole whose
    coefficients are all 0); an :class:`FTheta` for an f-theta model with the pixel-distance ->
    angle reference polynomial (the converter's); else None."""
    width, height = (int(v) for v in parameters.resolution)
    if getattr(parameters, "external_distortion_parameters", None) is not None:
        return None
    if hasattr(parameters, "pixeldist_to_angle_poly"):
        if parameters.reference_poly.name != "PIXELDIST_TO_ANGLE":
            return None
        return FTheta(
            tuple(float(v) for v in parameters.principal_point),
            np.asarray(parameters.pixeldist_to_angle_poly, np.float64),
            np.asarray(parameters.angle_to_pixeldist_poly, np.float64),
            tuple(float(v) for v in parameters.linear_cde),
            float(parameters.max_angle),
            (width, height),
        )
    if not hasattr(parameters, "focal_length"):
        return None
    for name in ("radial_coeffs", "tangential_coeffs", "thin_prism_coeffs"):
        if np.any(np.asarray(getattr(parameters, name, 0.0)) != 0):
            return None
    (fx, fy), (cx, cy) = (float(v) for v in parameters.focal_length), (float(v) for v in parameters.principal_point)
    return Pinhole((fx, fy), (cx, cy), (width, height))
