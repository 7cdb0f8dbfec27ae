"""Per-point ``rgb`` of AV2 and TbV lidar frames (``--lidar-rgb``): the camera frames around each sweep,
with the cameras' poses at their own times, their ego masks and the annotated boxes at their times
(solid occluders), handed to
:func:`ncore_convert.transforms.camera.colours.point_colours`. Images are decoded in colour at the
ego-mask estimator's reduction (2048 px -> 512 px), only when a point takes its colour from them,
and once per log (a small cache carries them to the next sweep)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ncore_convert.converters.argoverse2.masks import reduced_size, reduction
from ncore_convert.converters.argoverse2.plan import LogPlan
from ncore_convert.converters.argoverse2.views import camera_views, usable_pixels
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources.reader import Reader
from ncore_convert.transforms.camera.colours import DYNAMIC_DT_US, ColourFrame, point_colours
from ncore_convert.transforms.timebase import NS_PER_US

#: Camera frames this far (µs) beyond a sweep's first and last point are candidates: a 20 Hz
#: camera has a frame within 25 ms of any time (TbV's 20 Hz ring cameras too).
FRAME_MARGIN_US = 30_000


#: Which pixel a point's ``rgb`` is (``transforms.lidar.frames.point_data_notes``).
COLOURS_TAKEN_FROM = (
    "camera pixel it projects to in the frame nearest its own time (occlusion by a depth buffer of the sweep's"
    " points and by the annotated boxes, never from ego pixels, points on dynamic tracks only from a frame within"
    f" {DYNAMIC_DT_US / 1000:g} ms)"
)


class SweepColours:
    """The cameras of one log as colour sources (see the module docstring)."""

    def __init__(self, plan: LogPlan, reader: Reader) -> None:
        self._plan, self._reader = plan, reader
        self._cameras = {}
        for cam in plan.camera_ids:
            full = plan.cameras[cam].pinhole
            pinhole = full.scaled(*reduced_size(full))
            self._cameras[cam] = (reduction(full), pinhole, usable_pixels(plan, cam, pinhole))
        self._decode = lru_cache(maxsize=4 * max(1, len(self._cameras)))(self._read)

    def _read(self, cam: str, timestamp_ns: int) -> np.ndarray:
        inputs = self._plan.inputs
        path = av2.image_path(inputs.log_dir, cam, timestamp_ns)
        return av2.decode_jpeg(path, self._reader.read(path, inputs.files), self._cameras[cam][0], "RGB")

    def frames(self, t_lo_us: int, t_hi_us: int) -> list[ColourFrame]:
        """Every camera frame from ``t_lo_us - FRAME_MARGIN_US`` to ``t_hi_us + FRAME_MARGIN_US``."""
        out = []
        for cam, (_, pinhole, usable) in self._cameras.items():
            stamps_ns = self._plan.inputs.image_timestamps_ns[cam]
            lo = np.searchsorted(stamps_ns, (t_lo_us - FRAME_MARGIN_US) * NS_PER_US)
            hi = np.searchsorted(stamps_ns, (t_hi_us + FRAME_MARGIN_US) * NS_PER_US, side="right")
            picked = stamps_ns[lo:hi]
            views = camera_views(self._plan, cam, picked, pinhole, usable)
            for ts, view in zip(picked.tolist(), views, strict=True):
                out.append(ColourFrame.of(view, lambda cam=cam, ts=ts: self._decode(cam, ts)))
        return out

    def colours(
        self,
        xyz_world_m: np.ndarray,
        timestamps_us: np.ndarray,
        dynamic: np.ndarray,
        spacing_m: np.ndarray | None = None,
    ) -> tuple[np.ndarray, ...]:
        """:func:`point_colours` of a sweep's points (arguments as there) from the frames around it."""
        if not len(xyz_world_m):
            return np.zeros((0, 3), np.uint8), np.zeros(0, bool)
        t_us = np.asarray(timestamps_us, dtype=np.int64)
        return point_colours(xyz_world_m, t_us, dynamic, self.frames(int(t_us.min()), int(t_us.max())), spacing_m)
