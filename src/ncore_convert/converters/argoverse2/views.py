"""AV2 / TbV camera frames as :class:`~ncore_convert.transforms.camera.visibility.CameraView`: each
camera's pose at the frame's own time, its ego mask and the annotated boxes at that time as solid
occluders. Lidar colours and camera labels all take their frames from here."""

from __future__ import annotations

import numpy as np
import PIL.Image

from ncore_convert.converters.argoverse2.plan import LogPlan
from ncore_convert.transforms.camera.models import Pinhole
from ncore_convert.transforms.camera.visibility import CameraView, box_pictures
from ncore_convert.transforms.geometry import invert_se3
from ncore_convert.transforms.timebase import NS_PER_US

#: How far an annotated box may be off its object: a parked car's annotations wander 0.1-1.4 m on the
#: real sample, and their median (the static box) is nearer; a box does not hide points this close to it.
LABEL_SLACK_M = 0.5


def camera_views(
    plan: LogPlan, camera_id: str, stamps_ns: np.ndarray, pinhole: Pinhole, usable: np.ndarray | None
) -> list[CameraView]:
    """The views of ``camera_id``'s frames at ``stamps_ns`` (int [K]), their pixels those of
    ``pinhole`` (``usable``: bool [height,width] at that resolution, False on the ego body; None: all)."""
    if not len(stamps_ns):
        return []
    traj = plan.T_rig_world
    stamps_us = np.asarray(stamps_ns) // NS_PER_US  # the frames' stored times: the pose a reader gets
    T_rig_world = traj.interpolate(traj.relative_seconds(stamps_us * NS_PER_US))
    T_camera_world = T_rig_world @ plan.inputs.T_sensor_ego[camera_id]
    views = []
    for t_us, T in zip(stamps_us.tolist(), T_camera_world, strict=True):
        solids, velocity, kind = None, None, None
        if plan.solids is not None:
            T_box, half, velocity, kind = plan.solids.solids_at(t_us)
            solids = (T_box, half)
        views.append(CameraView(camera_id, t_us, invert_se3(T), pinhole, usable, solids, LABEL_SLACK_M, velocity, kind))
    return views


def usable_pixels(plan: LogPlan, camera_id: str, pinhole: Pinhole) -> np.ndarray | None:
    """The pixels of ``camera_id`` at ``pinhole``'s resolution that show the world: False where its
    ego mask (resized, nearest pixel) marks the ego body, bool [height,width]; None without a mask."""
    full = plan.cameras[camera_id].pinhole
    mask = plan.ego_masks[camera_id].image(*full.resolution_px) if plan.ego_masks else None
    if mask is None:
        return None
    return ~(np.asarray(mask.resize(pinhole.resolution_px, PIL.Image.NEAREST)) > 0)


#: How many frames of a camera :func:`label_work` looks at, spread over the log.
WORK_SAMPLE_FRAMES = 8
#: A camera frame's label work grows by this for every whole picture its boxes' pictures cover: on a
#: 2 s synthetic log a camera's three labels took 5.0 s + 11.6 s x the covered share (5.7-15.1 s).
WORK_PER_COVER = 2.3


def label_work(plan: LogPlan, camera_id: str) -> float:
    """How much work ``camera_id``'s labels are, in frames' worth of a frame without boxes: its frames,
    each weighted by 1 + ``WORK_PER_COVER`` x the share of its picture that the labelled boxes'
    pictures cover (their bounding rectangles, summed; ``WORK_SAMPLE_FRAMES`` frames looked at).
    Masks cost by the pixels of the objects' pictures, and cameras that face the traffic or a row of
    parked cars take several times those that do not."""
    stamps_ns = plan.inputs.image_timestamps_ns[camera_id]
    if plan.solids is None or not len(stamps_ns):
        return float(len(stamps_ns))
    pinhole = plan.cameras[camera_id].pinhole
    width, height = pinhole.resolution_px
    sample = stamps_ns[np.linspace(0, len(stamps_ns) - 1, min(WORK_SAMPLE_FRAMES, len(stamps_ns))).astype(int)]
    covered = []
    for view in camera_views(plan, camera_id, sample, pinhole, None):
        pictures = box_pictures(view, *view.solids)
        u_lo, u_hi, v_lo, v_hi = (a[pictures.in_view] for a in pictures.rectangle_px)
        columns = np.clip(u_hi, 0, width - 1) - np.clip(u_lo, 0, width - 1) + 1
        rows = np.clip(v_hi, 0, height - 1) - np.clip(v_lo, 0, height - 1) + 1
        covered.append(float(np.sum(columns * rows)) / (width * height))
    return len(stamps_ns) * (1.0 + WORK_PER_COVER * float(np.mean(covered)))
