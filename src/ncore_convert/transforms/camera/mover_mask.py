"""``mask.dynamic`` without boxes (TbV): where the movers a lidar itself found (``dynamic_flag`` from
``transforms.lidar.free_space``) may be at a camera frame's time."""

from __future__ import annotations

import numpy as np

from ncore_convert.transforms.camera.labels import footprints
from ncore_convert.transforms.camera.visibility import MIN_DEPTH_M, CameraView


def mover_mask(view: CameraView, xyz_world_m: np.ndarray, spacing_m: np.ndarray, ground_z_m: np.ndarray) -> np.ndarray:
    """``mask.dynamic`` from the points a lidar itself saw move (no boxes: TbV), bool [height,width].

    A mover is drawn where its points were at their own times. Each point draws its footprint (its
    spacing, across and along the lidar's rows, as the camera sees it at its depth: the object's
    surface between neighbouring returns) down to the ground under it: a mover stands on the ground,
    and the lidar, above the cameras, does not see the lower body of a car close by that they see.
    The caller hands over the movers' points measured within a sweep of the frame, less
    ``DYNAMIC_DT_US``: a point measured at the frame's time stands alone, and one measured before
    (after) it joins the same object's points a sweep later (earlier). An object moving steadily
    lies, at the frame's time, between where the two sweeps saw it; drawn at both places it is
    covered at the frame's time whenever it is longer than it moves in a sweep (a car at 15 m/s:
    1.5 m). The mask then over-covers by up to that much: recall first.

    Args:
        view: the camera frame; its ``usable`` pixels bound the mask.
        xyz_world_m: the movers' points, fixed frame (z up), float64 [N,3].
        spacing_m: the lidar's spacing between neighbouring returns at each, across and along its
            rows, m [N,2].
        ground_z_m: the ground's height under each, fixed frame, m [N].
    """
    width, height = view.pinhole.resolution_px
    T = view.T_world_camera
    foot_m = np.column_stack([xyz_world_m[:, :2], np.minimum(ground_z_m, xyz_world_m[:, 2])])
    top, foot = (p @ T[:3, :3].T + T[:3, 3] for p in (xyz_world_m, foot_m))
    ahead = (top[:, 2] > MIN_DEPTH_M) & (foot[:, 2] > MIN_DEPTH_M)
    (u0, v0), (u1, v1) = view.pinhole.project(top[ahead]), view.pinhole.project(foot[ahead])
    size_px = spacing_m[ahead] / top[ahead, 2:3] * np.asarray(view.pinhole.focal_length_px)
    ok = np.isfinite(u0) & np.isfinite(v0) & np.isfinite(u1) & np.isfinite(v1)
    # each point's footprint stretched from it to its foot: one centred between them, as much larger
    reach_px = np.abs(np.stack([u1 - u0, v1 - v0], axis=1))
    centre_u, centre_v = (u0 + u1) / 2.0, (v0 + v1) / 2.0
    mask = footprints(centre_u[ok], centre_v[ok], (size_px + reach_px)[ok], (height, width))
    return mask if view.usable is None else mask & view.usable
