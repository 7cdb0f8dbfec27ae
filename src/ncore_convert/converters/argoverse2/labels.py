"""AV2 / TbV camera labels (``--camera-labels depth``): one ``depth.z@<camera>`` label per camera
frame, from the lidar points of the sweep nearest the frame in time
(:func:`ncore_convert.transforms.camera_labels.depth_z`), written by the lidars' writing job as the
sweeps stream past.

A frame belongs to the sweep whose middle (the median time of its points) is nearest its own time:
each sweep's frames are labelled once the next sweep's middle is known, so two sweeps are held at
most. The views are at the cameras' full resolution, with their ego masks and the annotated boxes
at the frames' times (:mod:`views`).

Without cuboids (TbV), which points move is unknown: every point is then treated as possibly
moving (used only within ``camera_labels.DYNAMIC_DT_US`` of its frame), so the labels are sparser
but never show where a car was 50 ms earlier; the component metadata says so.

A frame more than ``dynamic.HOLD_S`` before the first sweep's points or after the last one's (the
cameras may run on beyond the lidar) gets an empty label (0 everywhere) that says why in its
metadata: there, the moving objects are neither in the points nor in the boxes, and the static
points would label pixels through them.
"""

from __future__ import annotations

import time

import numpy as np

from ncore_convert.converters.argoverse2.plan import LogPlan
from ncore_convert.converters.argoverse2.views import LABEL_SLACK_M, camera_views
from ncore_convert.transforms import camera_labels
from ncore_convert.transforms.dynamic import HOLD_S
from ncore_convert.transforms.timebase import NS_PER_US
from ncore_convert.transforms.visibility import VIEW_MARGIN, in_view
from ncore_convert.writer import CameraLabelStream, SequenceWriter

#: What each depth label's component metadata says of how it was made.
DEPTH_GENERATOR = {
    "generator": "ncore-convert transforms.camera_labels.depth_z",
    "from": "lidar points of the sweep nearest the frame in time (its median point time), both lidars",
    "value": "z in metres (camera frame, OpenCV) of the nearest lidar point the camera sees in the pixel; 0: none",
    "dynamic_points_within_us": camera_labels.DYNAMIC_DT_US,
    "occlusion": "visibility.visible_pixels: depth buffer of the sweep's points and the annotated boxes at the"
    f" frame's time (slack {LABEL_SLACK_M} m)",
    "storage": "RAW, uint32 millimetres (NCore quantization scale 0.001: error <= 0.5 mm)",
}


class DepthLabeller:
    """Writes the depth labels of every camera of ``plan`` through ``writer`` (see the module docstring)."""

    def __init__(self, plan: LogPlan, writer: SequenceWriter) -> None:
        self._plan = plan
        self._unknown_motion = plan.dynamic_boxes is None  # no cuboids: any point may be on a mover
        self._streams: dict[str, CameraLabelStream] = {
            cam: writer.add_camera_label("depth", cam, "EXTERNAL", {}) for cam in plan.camera_ids
        }
        self._usable = {}
        for cam in plan.camera_ids:
            pinhole = plan.cameras[cam].pinhole
            mask = plan.ego_masks[cam].image(*pinhole.resolution_px) if plan.ego_masks else None
            self._usable[cam] = None if mask is None else ~(np.asarray(mask) > 0)
        self._next = {cam: 0 for cam in plan.camera_ids}  # each camera's first frame not labelled yet
        self._held: tuple[np.ndarray, np.ndarray, np.ndarray, float] | None = None  # the previous sweep
        self._first_sweep_us: float | None = None  # the first point time of the first sweep
        self.labels = 0
        self.seconds = 0.0

    def add_sweep(self, xyz_world_m: np.ndarray, timestamps_us: np.ndarray, dynamic: np.ndarray) -> None:
        """One sweep's points (``PointData.xyz_fixed_m``, ``timestamps_us``, ``dynamic``): the held
        sweep labels the frames up to halfway to this one, and this one is held."""
        middle_us = float(np.median(timestamps_us)) if len(timestamps_us) else np.nan
        if self._first_sweep_us is None and len(timestamps_us):
            self._first_sweep_us = float(np.min(timestamps_us))
        if self._held is not None and np.isfinite(middle_us):
            self._label_until((self._held[3] + middle_us) / 2)
        if self._unknown_motion:
            dynamic = np.ones(len(timestamps_us), dtype=bool)
        if np.isfinite(middle_us):
            self._held = (xyz_world_m, timestamps_us, dynamic, middle_us)

    def finish(self) -> None:
        """Label the frames after the last sweep's middle (with it) and set each label's metadata."""
        self._label_until(np.inf)
        meta = dict(DEPTH_GENERATOR)
        if self._unknown_motion:
            meta["moving_objects"] = (
                "unknown (no cuboids): every point is used only within"
                f" {camera_labels.DYNAMIC_DT_US / 1000:g} ms of its frame"
            )
        for stream in self._streams.values():
            stream.set_meta(meta)

    def _label_until(self, end_us: float) -> None:
        """Label, with the held sweep, every camera's unlabelled frames before ``end_us`` (µs)."""
        started = time.perf_counter()
        for cam, stream in self._streams.items():
            stamps_us = self._plan.inputs.image_timestamps_ns[cam] // NS_PER_US
            first, last = self._next[cam], int(np.searchsorted(stamps_us, end_us, side="left"))
            if last <= first:
                continue
            self._next[cam] = last
            pinhole = self._plan.cameras[cam].pinhole
            stamps_ns = self._plan.inputs.image_timestamps_ns[cam][first:last]
            views = camera_views(self._plan, cam, stamps_ns, pinhole, self._usable[cam])
            points = None
            if self._held is not None:  # once per camera and sweep: the points its middle frame may see
                near, _ = in_view(views[len(views) // 2], self._held[0], VIEW_MARGIN)
                points = tuple(a[near] for a in self._held[:3])
            for view in views:
                reason = self._no_measurement(view.timestamp_us)
                if reason:  # still one label per frame: an empty one, saying why
                    depth = np.zeros(pinhole.resolution_px[::-1], np.float32)
                    meta = {"no_measurement": reason}
                else:
                    depth = camera_labels.depth_z(view, *points)
                    meta = {"sweep_median_time_us": round(self._held[3])}
                stream.store_label(depth, view.timestamp_us, meta)
                self.labels += 1
        self.seconds += time.perf_counter() - started

    def _no_measurement(self, t_us: int) -> str:
        """Why the frame at ``t_us`` gets no depth ('' if it does)."""
        if self._held is None:
            return "no lidar sweep with points"
        hold_us = HOLD_S * 1e6
        last_us = float(np.max(self._held[1]))
        if t_us < self._first_sweep_us - hold_us or t_us > last_us + hold_us:
            return f"no lidar sweep within {HOLD_S * 1e3:g} ms: the moving objects are unknown there"
        return ""
