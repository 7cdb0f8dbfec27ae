"""AV2 / TbV camera frames as :class:`~ncore_convert.transforms.camera.visibility.CameraView`: each
camera's pose at the frame's own time, its ego mask and the annotated boxes at that time as solid
occluders. Lidar colours and camera labels all take their frames from here."""

from __future__ import annotations

import numpy as np
import PIL.Image

from ncore_convert.converters.argoverse2.plan import LogPlan
from ncore_convert.transforms.camera.models import Pinhole
from ncore_convert.transforms.camera.visibility import CameraView
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
