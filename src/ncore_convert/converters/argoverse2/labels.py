"""AV2 / TbV camera labels (``--camera-labels``), one per camera frame and kind.

Depth (:class:`DepthLabeller`): ``depth.z@<camera>``, from the lidar points of the sweep nearest the
frame in time (:func:`ncore_convert.transforms.camera.labels.depth_z`), written by depth-label
jobs of a few cameras each as they stream the sweeps (``convert.log_jobs``).

Boxes (:class:`BoxLabeller`): ``mask.dynamic@<camera>`` and ``segmentation.instance@<camera>``, from
which annotated box each pixel shows at the frame's time
(:func:`ncore_convert.transforms.camera.labels.box_index`), written by the camera's own writing job.

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

from ncore_convert import contract
from ncore_convert.converters.argoverse2.plan import LogPlan
from ncore_convert.converters.argoverse2.views import LABEL_SLACK_M, camera_views, usable_pixels
from ncore_convert.transforms.camera import labels as camera_labels
from ncore_convert.transforms.camera.visibility import VIEW_MARGIN, in_view
from ncore_convert.transforms.objects.dynamic import HOLD_S
from ncore_convert.transforms.timebase import NS_PER_US, floor_us
from ncore_convert.writer import CameraLabelStream, SequenceWriter

#: What each depth label's component metadata says of how it was made.
DEPTH_GENERATOR = {
    "generator": "ncore-convert transforms.camera_labels.depth_z",
    "from": "lidar points of the sweep nearest the frame in time (its median point time), both lidars",
    "value": "z in metres (camera frame, OpenCV) of the nearest lidar point the camera sees in the pixel; 0: none",
    "dynamic_points_within_us": camera_labels.DYNAMIC_DT_US,
    "occlusion": "visibility.visible_pixels: depth buffer of the sweep's points and the annotated boxes at the"
    f" frame's time (slack {LABEL_SLACK_M} m)",
}


class DepthLabeller:
    """Writes the depth labels of ``camera_ids`` of ``plan`` through ``writer`` (see the module docstring)."""

    def __init__(self, plan: LogPlan, writer: SequenceWriter, camera_ids: list[str]) -> None:
        self._plan = plan
        self._unknown_motion = plan.dynamic_boxes is None  # no cuboids: any point may be on a mover
        self._streams: dict[str, CameraLabelStream] = {
            cam: writer.add_camera_label("depth", cam, "EXTERNAL", {}) for cam in camera_ids
        }
        self._usable = {cam: usable_pixels(plan, cam, plan.cameras[cam].pinhole) for cam in camera_ids}
        self._next = {cam: 0 for cam in camera_ids}  # each camera's first frame not labelled yet
        # the previous sweep: points, times, dynamic, spacing (or None), median and last point time
        self._held: tuple | None = None
        self._first_sweep_us: float | None = None  # the first point time of the first sweep
        self.labels = 0
        self.seconds = 0.0

    def add_sweep(
        self,
        xyz_world_m: np.ndarray,
        timestamps_us: np.ndarray,
        dynamic: np.ndarray,
        spacing_m: np.ndarray | None = None,
    ) -> None:
        """One sweep's points (``PointData.xyz_fixed_m``, ``timestamps_us``, ``dynamic``,
        ``spacing_m``): the held sweep labels the frames up to halfway to this one, and this one is
        held."""
        middle_us = float(np.median(timestamps_us)) if len(timestamps_us) else np.nan
        if self._first_sweep_us is None and len(timestamps_us):
            self._first_sweep_us = float(np.min(timestamps_us))
        if self._held is not None and np.isfinite(middle_us):
            self._label_until((self._held[4] + middle_us) / 2)
        if self._unknown_motion:
            dynamic = np.ones(len(timestamps_us), dtype=bool)
        if np.isfinite(middle_us):
            self._held = (xyz_world_m, timestamps_us, dynamic, spacing_m, middle_us, float(np.max(timestamps_us)))

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
                points = tuple(None if a is None else a[near] for a in self._held[:4])
            for view in views:
                reason = self._no_measurement(view.timestamp_us)
                if reason:  # still one label per frame: an empty one, saying why
                    depth = np.zeros(pinhole.resolution_px[::-1], np.float32)
                    meta = {"no_measurement": reason}
                else:
                    depth = camera_labels.depth_z(view, *points)
                    meta = {"sweep_median_time_us": round(self._held[4])}
                stream.store_label(depth, view.timestamp_us, meta)
                self.labels += 1
        self.seconds += time.perf_counter() - started

    def _no_measurement(self, t_us: int) -> str:
        """Why the frame at ``t_us`` gets no depth ('' if it does)."""
        if self._held is None:
            return "no lidar sweep with points"
        hold_us = HOLD_S * 1e6
        if t_us < self._first_sweep_us - hold_us or t_us > self._held[5] + hold_us:
            return f"no lidar sweep within {HOLD_S * 1e3:g} ms: the moving objects are unknown there"
        return ""


#: What the box labels' component metadata says of how they were made.
BOX_GENERATOR = {
    "generator": "ncore-convert transforms.camera_labels.box_index",
    "from": "the annotated boxes at the frame's time: a static track's median box, a moving track's box"
    f" interpolated between its observations (up to {HOLD_S * 1e3:g} ms beyond its ends)",
    "pixel": "the box the ray through the pixel's centre meets first (nearest box first where boxes overlap);"
    " none on the ego body (the camera's ego mask)",
    "not_known": "surfaces other than the boxes (walls, poles, vegetation) do not hide a box; a box over-covers"
    " its object's true shape",
}
#: ``mask.dynamic``: which boxes count.
DYNAMIC_RULE = (
    "1 where the box shown is a dynamic track's (transforms.objects.dynamic: moved beyond annotation noise, or an"
    " always-dynamic class); 0 elsewhere"
)


def instance_table(plan: LogPlan) -> tuple[np.ndarray, dict[str, dict]]:
    """The sequence's instance index of every track of ``plan.solids`` (int [S+T], 1 upwards, by
    sorted track id: the same in every camera), and the table index -> track id, class and whether
    it is dynamic, as ``segmentation.instance``'s metadata holds it."""
    track_ids = plan.solids.track_ids
    order = np.argsort(track_ids, kind="stable")
    index = np.empty(len(track_ids), dtype=np.int64)
    index[order] = np.arange(1, len(track_ids) + 1)
    if len(track_ids) > np.iinfo(np.uint16).max:
        raise ValueError(f"{len(track_ids)} tracks: more than a uint16 instance label holds")
    labels = plan.cuboid_labels
    classes = dict(zip(plan.inputs.annotations.track_uuids, labels.class_ids, strict=True))
    table = {
        str(int(index[k])): {"track_id": str(tid), "class_id": classes[tid], "dynamic": tid in labels.dynamic}
        for k, tid in enumerate(track_ids)
    }
    return index, dict(sorted(table.items(), key=lambda item: int(item[0])))


class BoxLabeller:
    """Writes ``camera_id``'s box labels (``plan.job_label_ids(camera_id)``) through ``writer``, one
    per frame (see the module docstring)."""

    def __init__(self, plan: LogPlan, writer: SequenceWriter, camera_id: str) -> None:
        self._plan, self._camera_id = plan, camera_id
        self._kinds = [kind for kind in plan.label_kinds if kind in contract.BOX_LABEL_KINDS]
        self._streams = {kind: writer.add_camera_label(kind, camera_id, "EXTERNAL", {}) for kind in self._kinds}
        self._instance, table = instance_table(plan)
        self._dynamic = np.array([tid in plan.cuboid_labels.dynamic for tid in plan.solids.track_ids], dtype=bool)
        annotated_us = floor_us(plan.inputs.annotations.timestamps_ns)
        self._span_us = (int(annotated_us.min()), int(annotated_us.max()))  # the annotated sweeps' times
        self._pinhole = plan.cameras[camera_id].pinhole
        self._usable = usable_pixels(plan, camera_id, self._pinhole)
        self._meta = {
            "dynamic": {**BOX_GENERATOR, "value": DYNAMIC_RULE},
            "instance": {**BOX_GENERATOR, "value": "instance index (0: no box)", "instances": table},
        }
        self.labels = 0
        self.seconds = 0.0

    def label_frames(self, stamps_ns: np.ndarray) -> None:
        """Label the frames at ``stamps_ns`` (int [K])."""
        started = time.perf_counter()
        for view in camera_views(self._plan, self._camera_id, stamps_ns, self._pinhole, self._usable):
            tracks, T_box_world, half_m = self._plan.solids.tracks_at(view.timestamp_us)
            picture = camera_labels.box_index(view, T_box_world, half_m)
            instance, dynamic, shown = camera_labels.box_labels(picture, self._instance[tracks], self._dynamic[tracks])
            meta = {"moving_objects_unknown": unknown} if (unknown := self._unknown(view.timestamp_us)) else {}
            for kind, stream in self._streams.items():
                if kind == "dynamic":  # where the movers are unknown, any pixel may show one: all 1
                    stream.store_label(np.ones_like(dynamic) if unknown else dynamic, view.timestamp_us, meta)
                else:
                    stream.store_label(instance, view.timestamp_us, {"instances_shown": shown, **meta})
                self.labels += 1
        self.seconds += time.perf_counter() - started

    def _unknown(self, t_us: int) -> str:
        """Why the moving objects at ``t_us`` are unknown ('' if known): no annotations within
        ``HOLD_S`` (the cameras may run on beyond the annotated sweeps)."""
        if self._span_us[0] - HOLD_S * 1e6 <= t_us <= self._span_us[1] + HOLD_S * 1e6:
            return ""
        return f"no annotations within {HOLD_S * 1e3:g} ms: the static boxes only (mask.dynamic: all 1)"

    def finish(self) -> None:
        """Set each kind's component metadata."""
        for kind, stream in self._streams.items():
            stream.set_meta(self._meta[kind])
