"""Image-aligned labels of camera frames, for NCore's camera-labels component: sparse z-depth from
lidar points (``depth.z``).

A depth label holds, per pixel, the camera-frame z (metres, OpenCV frame: z forward) of the nearest
lidar point that the camera sees there, 0 where no point does. The points are the lidar's, where
it saw them, in the fixed (world) frame:

- a static point is still there at the camera's time, so it is taken from whichever sweep is at
  hand and projected with the camera's pose at the frame's time;
- a point on a moving object (``dynamic``) only from within ``DYNAMIC_DT_US`` of the frame: the
  object moves, and elsewhere its points would label pixels it no longer covers;
- only the points the camera sees (:func:`visibility.visible_pixels`: in front of the camera, not on
  the ego body, not behind a nearer point of the picture or a labelled box at the frame's time),
  so a pixel never shows a surface the lidar saw through a foreground object from its own viewpoint.
"""

from __future__ import annotations

import numpy as np

from ncore_convert.transforms.visibility import CameraView, visible_pixels

#: A point on a moving object labels only a frame this close to its own time (µs): at 15 m/s the
#: object moves 7.5 cm in that time.
DYNAMIC_DT_US = 5_000


def depth_z(view: CameraView, xyz_world_m: np.ndarray, timestamps_us: np.ndarray, dynamic: np.ndarray) -> np.ndarray:
    """The depth label of ``view`` (see the module docstring).

    Args:
        view: the camera frame; its pinhole's resolution is the label's.
        xyz_world_m: lidar points where the lidar saw them, fixed frame, float64 [N,3].
        timestamps_us: each point's own time, int [N].
        dynamic: the points on moving objects (``dynamic_flag``), bool [N].

    Returns:
        float32 [height,width]: z in metres of the nearest visible point per pixel, 0 where none.
    """
    width, height = view.pinhole.resolution_px
    image = np.zeros((height, width), dtype=np.float32)
    dt_us = np.abs(np.asarray(timestamps_us, dtype=np.int64) - int(view.timestamp_us))
    usable = np.flatnonzero(~np.asarray(dynamic, dtype=bool) | (dt_us <= DYNAMIC_DT_US))
    if not len(usable):
        return image
    rows, cols, lines = visible_pixels(view, xyz_world_m[usable])
    T = view.T_world_camera
    z_m = xyz_world_m[usable[rows]] @ T[2, :3] + T[2, 3]
    pixel = lines * width + cols
    order = np.lexsort((z_m, pixel))  # by pixel, nearest first
    first = order[np.r_[True, pixel[order][1:] != pixel[order][:-1]]] if len(order) else order
    image.reshape(-1)[pixel[first]] = z_m[first]
    return image
