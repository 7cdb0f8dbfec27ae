"""Image-aligned labels of camera frames, for NCore's camera-labels component: sparse z-depth from
lidar points (``depth.z``), and which labelled box each pixel shows (``mask.dynamic`` and
``segmentation.instance`` are made from :func:`box_index`).

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

from dataclasses import dataclass

import numpy as np

from ncore_convert.transforms.camera.visibility import CameraView, box_pictures, visible_pixels
from ncore_convert.transforms.objects.boxes import slab_span

#: A point on a moving object labels only a frame this close to its own time (µs): at 15 m/s the
#: object moves 7.5 cm in that time.
DYNAMIC_DT_US = 5_000


def depth_z(
    view: CameraView,
    xyz_world_m: np.ndarray,
    timestamps_us: np.ndarray,
    dynamic: np.ndarray,
    spacing_m: np.ndarray | None = None,
) -> np.ndarray:
    """The depth label of ``view`` (see the module docstring).

    Args:
        view: the camera frame; its pinhole's resolution is the label's.
        xyz_world_m: lidar points where the lidar saw them, fixed frame, float64 [N,3].
        timestamps_us: each point's own time, int [N].
        dynamic: the points on moving objects (``dynamic_flag``), bool [N].
        spacing_m: the lidar's spacing between neighbouring returns at each point, across and along its
            rows, m [N,2] (None: not known; see :func:`visibility.visible_pixels`).

    Returns:
        float32 [height,width]: z in metres of the nearest visible point per pixel, 0 where none.
    """
    width, height = view.pinhole.resolution_px
    image = np.zeros((height, width), dtype=np.float32)
    dt_us = np.abs(np.asarray(timestamps_us, dtype=np.int64) - int(view.timestamp_us))
    usable = np.flatnonzero(~np.asarray(dynamic, dtype=bool) | (dt_us <= DYNAMIC_DT_US))
    if not len(usable):
        return image
    stale = np.ones(len(xyz_world_m), bool)
    stale[usable] = False  # a mover's points from other times: where its object is, not what a pixel shows
    spacing = None if spacing_m is None else spacing_m[usable]
    dt_s = (view.timestamp_us - np.asarray(timestamps_us, dtype=np.int64)[stale]) * 1e-6
    stale_spacing = None if spacing_m is None else spacing_m[stale]
    rows, cols, lines = visible_pixels(view, xyz_world_m[usable], spacing, xyz_world_m[stale], dt_s, stale_spacing)
    T = view.T_world_camera
    z_m = xyz_world_m[usable[rows]] @ T[2, :3] + T[2, 3]
    pixel = lines * width + cols
    order = np.lexsort((z_m, pixel))  # by pixel, nearest first
    first = order[np.r_[True, pixel[order][1:] != pixel[order][:-1]]] if len(order) else order
    image.reshape(-1)[pixel[first]] = z_m[first]
    return image


@dataclass(frozen=True)
class BoxPicture:
    """Which box each pixel of a camera frame shows (:func:`box_index`).

    Attributes:
        index: int32 [height,width], an index into the boxes, or -1.
        shown: the boxes that hold a pixel, sorted, int [S].
        rectangles: each shown box's pixels lie in rows ``r0:r1`` and columns ``c0:c1`` of it,
            int [S,4] (r0, r1, c0, c1).
    """

    index: np.ndarray
    shown: np.ndarray
    rectangles: np.ndarray


def box_index(view: CameraView, T_box_world: np.ndarray, half_m: np.ndarray) -> BoxPicture:
    """Which box each pixel of ``view`` shows: the box whose surface the ray through the pixel's
    centre meets first (nearest box first where boxes overlap), -1 where it meets none or the pixel
    is not usable (the ego body). Boxes hide each other; nothing else does (the labels know no
    other surface). A box the camera is inside is left out.

    Args:
        view: the camera frame; its pinhole's resolution is the result's.
        T_box_world: box -> fixed frame, float64 [K,4,4]; half_m: half sizes, float64 [K,3], m.
    """
    width, height = view.pinhole.resolution_px
    index = np.full((height, width), -1, dtype=np.int32)
    pictures = box_pictures(view, T_box_world, half_m)
    u_lo, u_hi, v_lo, v_hi = pictures.rectangle_px
    candidates = np.flatnonzero(pictures.in_view)
    rectangles = np.zeros((len(candidates), 4), dtype=np.int64)
    rectangles[:, 0], rectangles[:, 1] = np.maximum(v_lo[candidates], 0), np.minimum(v_hi[candidates], height - 1) + 1
    rectangles[:, 2], rectangles[:, 3] = np.maximum(u_lo[candidates], 0), np.minimum(u_hi[candidates], width - 1) + 1
    nearest_m = np.full((height, width), np.inf, dtype=np.float32)
    (fx, fy), (cx, cy) = view.pinhole.focal_length_px, view.pinhole.principal_point_px
    R_camera_world = view.T_world_camera[:3, :3].T  # camera axes in the fixed frame
    for k, (r0, r1, c0, c1) in zip(candidates, rectangles.tolist(), strict=True):
        # the ray through pixel (col, row) is x(col) X + y(row) Y + Z in camera axes (z = 1, so the
        # ray parameter at a hit is its z-depth); in the box's axes each coordinate is a sum of a
        # column term and a row term
        M = T_box_world[k, :3, :3].T @ R_camera_world  # camera axes -> box axes
        x = ((np.arange(c0, c1) + 0.5 - cx) / fx).astype(np.float32)
        y = ((np.arange(r0, r1) + 0.5 - cy) / fy).astype(np.float32)
        steps = [(M[axis, 2] + M[axis, 0] * x)[None, :] + (M[axis, 1] * y)[:, None] for axis in range(3)]  # [rows,cols]
        enter, leave = slab_span(pictures.origin_m[k], steps, -half_m[k], half_m[k], 0.0, np.float32)
        window = nearest_m[r0:r1, c0:c1]
        hit = (enter <= leave) & (enter < window)
        window[hit] = enter[hit]
        index[r0:r1, c0:c1][hit] = k
    if view.usable is not None:
        index[~view.usable] = -1
    # the boxes still holding a pixel of their rectangle once every box is in
    held = [
        i
        for i, (k, (r0, r1, c0, c1)) in enumerate(zip(candidates, rectangles.tolist(), strict=True))
        if np.any(index[r0:r1, c0:c1] == k)
    ]
    return BoxPicture(index, candidates[held], rectangles[held])


def box_labels(picture: BoxPicture, instance_of_box: np.ndarray, dynamic_of_box: np.ndarray):
    """``segmentation.instance`` and ``mask.dynamic`` of a :func:`box_index` picture, written box
    by box within their rectangles.

    Args:
        instance_of_box: each box's instance index, int [K] (1 upwards); dynamic_of_box: each box's
            track moves, bool [K].

    Returns:
        uint16 [H,W] instance indices (0: none); bool [H,W] dynamic; the instances shown, sorted list.
    """
    instance = np.zeros(picture.index.shape, np.uint16)
    dynamic = np.zeros(picture.index.shape, bool)
    for k, (r0, r1, c0, c1) in zip(picture.shown.tolist(), picture.rectangles.tolist(), strict=True):
        own = picture.index[r0:r1, c0:c1] == k
        instance[r0:r1, c0:c1][own] = instance_of_box[k]
        if dynamic_of_box[k]:
            dynamic[r0:r1, c0:c1] |= own
    return instance, dynamic, sorted(int(instance_of_box[k]) for k in picture.shown)
