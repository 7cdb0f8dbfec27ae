"""AV2 / TbV camera labels (``--camera-labels``), one per camera frame and kind, written by label jobs
(one per worker, sharing the cameras) as they stream the sweeps (``convert.log_jobs``, :class:`FrameLabeller`):

- ``depth.z@<camera>``: from the lidar points of the sweep nearest the frame in time
  (:func:`ncore_convert.transforms.camera.labels.depth_z`);
- ``mask.dynamic@<camera>`` and ``segmentation.instance@<camera>``: which annotated object each pixel
  shows at the frame's time, each box cut to where the lidar shows its object
  (:func:`ncore_convert.transforms.camera.labels.box_index`): a vehicle from every sweep of its track
  (a first pass, :meth:`FrameLabeller.gather`; ``objects.track_shapes``), any other object from the
  sweep nearest the frame.

A frame belongs to the sweep whose middle (the median time of its points) is nearest its own time:
each sweep's frames are labelled once the next sweep's middle is known, so two sweeps are held at
most. The views are at the cameras' full resolution, with their ego masks and the annotated boxes
at the frames' times (:mod:`views`).

Without cuboids (TbV), which points move comes from the lidar itself (``--dynamic-source lidar``, the
default there; ``transforms.lidar.free_space``): the points it saw move, and those it could not
judge, label depth only within ``camera_labels.DYNAMIC_DT_US`` of their frame, the others (of the
sweep nearest the frame and the sweeps either side) at any time, and the movers' points near the
frame hide what lies behind them; ``mask.dynamic``
draws the movers the sweeps before and after the frame saw (:func:`mover_mask`). With
``--dynamic-source annotations`` (no flags), every point is treated as possibly moving, so the depth
labels are sparser but never show where a car was 50 ms earlier; the component metadata says so.

A frame more than ``dynamic.HOLD_S`` before the first sweep's points or after the last one's (the
cameras may run on beyond the lidar) gets an empty depth label (0 everywhere) and masks of whole
boxes, each saying why in its metadata: there, the moving objects are neither in the points nor in
the boxes, and the static points would label pixels through them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ncore_convert import contract
from ncore_convert.converters.argoverse2.plan import LogPlan
from ncore_convert.converters.argoverse2.views import LABEL_SLACK_M, camera_views, usable_pixels
from ncore_convert.transforms.camera import labels as camera_labels
from ncore_convert.transforms.camera.mover_mask import mover_mask
from ncore_convert.transforms.camera.visibility import VIEW_MARGIN, in_view
from ncore_convert.transforms.lidar.free_space import ground_clearance_m
from ncore_convert.transforms.lidar.range_image import RangeImage
from ncore_convert.transforms.lidar.vlp32c import SPIN_RATE_HZ
from ncore_convert.transforms.objects.cores import VEHICLE
from ncore_convert.transforms.objects.dynamic import HOLD_S
from ncore_convert.transforms.objects.track_shapes import TrackShapes
from ncore_convert.transforms.timebase import NS_PER_US, floor_us
from ncore_convert.writer import CameraLabelStream, SequenceWriter

#: Where the lidars were during a sweep: the rig's pose at this many times of it, between them linear.
ORIGIN_KNOTS = 11
#: What each depth label's component metadata says of how it was made.
DEPTH_GENERATOR = {
    "generator": "ncore-convert transforms.camera_labels.depth_z",
    "from": "lidar points of the sweep nearest the frame in time (its median point time), both lidars",
    "value": "z in metres (camera frame, OpenCV) of the nearest lidar point the camera sees in the pixel; 0: none",
    "dynamic_points_within_us": camera_labels.DYNAMIC_DT_US,
    "occlusion": "visibility.visible_pixels: depth buffer of the sweep's points and the annotated boxes at the"
    f" frame's time (slack {LABEL_SLACK_M} m)",
}


#: What the box labels' component metadata says of how they were made.
BOX_GENERATOR = {
    "generator": "ncore-convert transforms.camera_labels.box_index",
    "from": "the annotated boxes at the frame's time: a static track's median box, a moving track's box"
    f" interpolated between its observations (up to {HOLD_S * 1e3:g} ms beyond its ends)",
    "pixel": "the object the ray through the pixel's centre meets first (nearest box first where boxes overlap);"
    " none on the ego body (the camera's ego mask)",
    "not_known": "surfaces other than the boxes (walls, poles, vegetation) do not hide an object; a mask may"
    " over-cover its object where the points do not show the box empty",
}
#: ``mask.dynamic``: which boxes count.
DYNAMIC_RULE = (
    "1 where the box shown is a dynamic track's (transforms.objects.dynamic: moved beyond annotation noise, or an"
    " always-dynamic class); 0 elsewhere"
)


#: ``mask.dynamic`` without boxes (TbV, ``--dynamic-source lidar``): what its metadata says.
LIDAR_MOVERS = {
    "generator": contract.MOVER_MASK_GENERATOR,
    "from": "the points the lidar itself saw move (dynamic_flag from lidar free space) of the sweep nearest the"
    " frame and the sweeps either side, each drawn where it was at its own time, grown by the lidar's spacing"
    " there, if measured within a sweep period (less 5 ms) of the frame: a mover is drawn where the sweeps"
    " before and after the frame saw it",
    "value": "1 where a mover may be (it over-covers by up to what the mover moves in a sweep: recall first);"
    " 0 elsewhere, which includes the movers the lidar missed (dynamic_flag_unknown, hidden parts)",
}
#: The lidar's sweep period (µs): how far from a frame a mover's point may be drawn (``mover_mask``).
SWEEP_PERIOD_US = 1e6 / SPIN_RATE_HZ
#: The lidar's widest steps between neighbouring returns, across and along its rows (rad): a point's
#: footprint where no lidar model gives its own.
WIDEST_STEPS_RAD = np.radians([0.2, 4.0])


def _spacing_or_widest(xyz_world_m: np.ndarray, origins_m: np.ndarray, spacing_m: np.ndarray | None) -> np.ndarray:
    """``spacing_m`` (m [N,2]) or, where not known (None), each point's range from where the lidar was
    (``origins_m`` [N,3]) times ``WIDEST_STEPS_RAD``."""
    if spacing_m is not None:
        return spacing_m
    return np.linalg.norm(xyz_world_m - origins_m, axis=1)[:, None] * WIDEST_STEPS_RAD


@dataclass(frozen=True)
class _SweepPoints:
    """What a sweep lends the frames near it, with the lidar's movers: its movers' points (xyz, fixed
    frame [M,3]; times, µs [M]; spacing, m [M,2]; the ground's height under each, m [M]) and its static
    points (xyz [S,3], spacing [S,2]): neither flagged nor unknown."""

    movers: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    statics: tuple[np.ndarray, np.ndarray]


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


class FrameLabeller:
    """Writes the labels of ``camera_ids`` of ``plan`` (every kind of ``plan.label_kinds``) through
    ``writer`` (see the module docstring)."""

    def __init__(self, plan: LogPlan, writer: SequenceWriter, camera_ids: list[str]) -> None:
        self._plan = plan
        # without cuboids (TbV), the movers the lidar itself found (--dynamic-source lidar) or, without
        # those, none: then any point may be on a mover
        self._lidar_movers = plan.label_movers_from_lidar
        self._unknown_motion = plan.dynamic_boxes is None and not self._lidar_movers
        # with the lidar's movers: the sweep before the held one, the held one and the next one
        self._around: list[_SweepPoints | None] = [None, None, None]
        self._kinds = [kind for kind in contract.CAMERA_LABEL_KINDS if kind in plan.label_kinds]
        self._streams: dict[tuple[str, str], CameraLabelStream] = {
            (kind, cam): writer.add_camera_label(kind, cam, "EXTERNAL", {})
            for cam in camera_ids
            for kind in self._kinds
        }
        self._cameras = list(camera_ids)
        self._usable = {cam: usable_pixels(plan, cam, plan.cameras[cam].pinhole) for cam in camera_ids}
        self._next = {cam: 0 for cam in camera_ids}  # each camera's first frame not labelled yet
        # the previous sweep: points, times, dynamic, spacing (or None), where the lidar was, median and
        # last point time
        self._held: tuple | None = None
        self._first_sweep_us: float | None = None  # the first point time of the first sweep
        self._covers: dict = {}
        self._sight: RangeImage | None = None
        self.shapes: TrackShapes | None = None  # the static vehicles' shapes from every sweep (gather)
        mounts = [plan.inputs.T_sensor_ego[u][:3, 3] for u in plan.lidar_ids]
        self._lidar_rig_m = np.mean(mounts, axis=0) if mounts else np.zeros(3)  # the units' middle, rig frame
        if self._lidar_movers:
            self._box_meta = {"dynamic": {**LIDAR_MOVERS, "sweep_period_us": SWEEP_PERIOD_US}}
        elif any(kind in contract.BOX_LABEL_KINDS for kind in self._kinds):
            self._instance, table = instance_table(plan)
            self._dynamic = np.array([tid in plan.cuboid_labels.dynamic for tid in plan.solids.track_ids], dtype=bool)
            annotated_us = floor_us(plan.inputs.annotations.timestamps_ns)
            self._span_us = (int(annotated_us.min()), int(annotated_us.max()))  # the annotated sweeps' times
            box_meta = {**BOX_GENERATOR, "masks": camera_labels.MASKS_MADE}
            self.shapes = TrackShapes()
            self._box_meta = {
                "dynamic": {**box_meta, "value": DYNAMIC_RULE},
                "instance": {**box_meta, "value": "instance index (0: no box)", "instances": table},
            }
        self.labels = 0
        self.seconds = 0.0

    def gather(self, xyz_world_m: np.ndarray, timestamps_us: np.ndarray, spacing_m: np.ndarray | None = None) -> None:
        """The first pass, before any :meth:`add_sweep`: one sweep's evidence of the vehicles' shapes
        (``PointData.xyz_fixed_m``, ``timestamps_us``, ``spacing_m``; :mod:`objects.track_shapes`). A
        static track's one median box pools every sweep; a moving track's annotated boxes, at each
        point's time along the track, pool the sweeps whose points agree once registered to it
        (annotations jitter by centimetres from sweep to sweep)."""
        if self.shapes is None or not len(timestamps_us):
            return
        middle_us = int(np.median(timestamps_us))
        tracks, T_box_world, half_m, velocity_mps = self._plan.solids.moving_at(middle_us)
        vehicles = np.flatnonzero(self._plan.solids.kind[tracks] == VEHICLE)
        tracks = tracks[vehicles]
        origins = self._lidar_origins(timestamps_us)
        self.shapes.gather(
            self._plan.solids.track_ids[tracks].tolist(),
            T_box_world[vehicles],
            half_m[vehicles],
            xyz_world_m,
            _spacing_or_widest(xyz_world_m, origins, spacing_m),
            origins,
            RangeImage(xyz_world_m, origins),
            velocity_mps[vehicles],
            (np.asarray(timestamps_us, np.int64) - middle_us) * 1e-6,
            register=tracks >= len(self._plan.solids.static_T_box_frame),
            time_us=middle_us,
        )

    def add_sweep(
        self,
        xyz_world_m: np.ndarray,
        timestamps_us: np.ndarray,
        dynamic: np.ndarray,
        spacing_m: np.ndarray | None = None,
        unknown: np.ndarray | None = None,
    ) -> None:
        """One sweep's points (``PointData.xyz_fixed_m``, ``timestamps_us``, ``dynamic``,
        ``spacing_m``, ``unknown``): the held sweep labels the frames up to halfway to this one, and
        this one is held. A point whose motion the lidar could not judge (``unknown``) labels depth as
        a mover's does (only near its time)."""
        middle_us = float(np.median(timestamps_us)) if len(timestamps_us) else np.nan
        if self._first_sweep_us is None and len(timestamps_us):
            self._first_sweep_us = float(np.min(timestamps_us))
        sweep = None
        if self._lidar_movers:
            spacing = _spacing_or_widest(xyz_world_m, self._lidar_origins(timestamps_us), spacing_m)
            ground_z_m = xyz_world_m[:, 2] - ground_clearance_m(xyz_world_m)
            still = ~dynamic if unknown is None else ~dynamic & ~unknown
            sweep = _SweepPoints(
                (xyz_world_m[dynamic], timestamps_us[dynamic], spacing[dynamic], ground_z_m[dynamic]),
                (xyz_world_m[still], spacing[still]),
            )
        if self._held is not None and np.isfinite(middle_us):
            self._around[2] = sweep
            self._label_until((self._held[5] + middle_us) / 2)
        if self._unknown_motion:
            dynamic = np.ones(len(timestamps_us), dtype=bool)
        elif unknown is not None:
            dynamic = dynamic | unknown
        if np.isfinite(middle_us):
            self._around = [self._around[1], sweep, None]
            self._covers, self._sight = {}, None  # the held sweep's cover maps and range image
            origins = self._lidar_origins(timestamps_us)
            self._held = (
                xyz_world_m,
                timestamps_us,
                dynamic,
                spacing_m,
                origins,
                middle_us,
                float(np.max(timestamps_us)),
            )

    def _lidar_origins(self, timestamps_us: np.ndarray) -> np.ndarray:
        """Where the lidars were (the middle of the units) as they measured points at ``timestamps_us``
        [N], world frame, float64 [N,3]."""
        return self._plan.T_rig_world.positions_at(self._lidar_rig_m, timestamps_us, ORIGIN_KNOTS)

    def finish(self) -> None:
        """Label the frames after the last sweep's middle (with it) and set each label's metadata."""
        self._label_until(np.inf)
        depth_meta = dict(DEPTH_GENERATOR)
        if self._lidar_movers:
            depth_meta["from"] += (
                "; and the static points (neither dynamic_flag nor dynamic_flag_unknown) of the sweeps either side;"
                " the points the lidar saw move or could not judge only within dynamic_points_within_us"
            )
        elif self._unknown_motion:
            depth_meta["moving_objects"] = (
                "unknown (no cuboids): every point is used only within"
                f" {camera_labels.DYNAMIC_DT_US / 1000:g} ms of its frame"
            )
        for (kind, _), stream in self._streams.items():
            stream.set_meta(depth_meta if kind == "depth" else self._box_meta[kind])

    def _label_until(self, end_us: float) -> None:
        """Label, with the held sweep, every camera's unlabelled frames before ``end_us`` (µs)."""
        started = time.perf_counter()
        for cam in self._cameras:
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
                middle = views[len(views) // 2]
                near, _ = in_view(middle, self._held[0], VIEW_MARGIN)
                points = tuple(None if a is None else a[near] for a in self._held[:5])
                if self._lidar_movers:
                    points = self._with_statics_around(middle, points)
            for view in views:
                reason = self._no_measurement(view.timestamp_us)
                movers = None if reason else self._movers_near(view.timestamp_us)
                for kind in self._kinds:
                    if kind == "depth":
                        self._store_depth(cam, view, points, reason, movers)
                if self._lidar_movers and "dynamic" in self._kinds:
                    self._store_lidar_movers(cam, view, reason, movers)
                elif any(kind in contract.BOX_LABEL_KINDS for kind in self._kinds):
                    self._store_boxes(cam, view, None if reason else points, reason)
        self.seconds += time.perf_counter() - started

    def _store_depth(self, cam: str, view, points: tuple | None, reason: str, movers: tuple | None) -> None:
        """The depth label of one frame from the held ``points``; ``movers`` (:meth:`_movers_near`)
        hide what lies behind them."""
        if reason:  # still one label per frame: an empty one, saying why
            depth = np.zeros(view.pinhole.resolution_px[::-1], np.float32)
            meta = {"no_measurement": reason}
        else:
            hiding = None if movers is None else movers[:2]
            depth = camera_labels.depth_z(view, *points[:4], hiding=hiding)
            meta = {"sweep_median_time_us": round(self._held[5])}
        self._streams["depth", cam].store_label(depth, view.timestamp_us, meta)
        self.labels += 1

    def _with_statics_around(self, view, points: tuple) -> tuple:
        """The held sweep's ``points`` (xyz, times, dynamic, spacing; origins) and the static points of
        the sweeps before and after it that ``view`` may see: a static point is still there at the
        frame's time, whichever sweep saw it (three sweeps' points: about 2.5x the labelled pixels of
        the held sweep's alone, and fewer occlusion errors: the denser points hide more of what lies
        behind them; docs/motion.md). The origins are left out (None): only box labels read them, and
        there are none with the lidar's movers."""
        xyz, times_us, dynamic, spacing = points[:4]
        for other in (self._around[0], self._around[2]):
            if other is None or spacing is None:
                continue
            still_m, still_spacing = other.statics
            near, _ = in_view(view, still_m, VIEW_MARGIN)
            xyz, spacing = np.concatenate([xyz, still_m[near]]), np.concatenate([spacing, still_spacing[near]])
            times_us = np.concatenate([times_us, np.full(len(near), view.timestamp_us, times_us.dtype)])
            dynamic = np.concatenate([dynamic, np.zeros(len(near), bool)])
        return xyz, times_us, dynamic, spacing, None

    def _movers_near(self, t_us: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The lidar's movers' points of the sweeps around the held one measured within a sweep of
        ``t_us`` (less ``camera_labels.DYNAMIC_DT_US``), fixed frame [M,3], their spacing [M,2] and the
        ground's height under them [M]: where a mover may be at that time
        (:func:`mover_mask`). None: no lidar movers."""
        if not self._lidar_movers:
            return None
        around = [a.movers for a in self._around if a is not None]
        xyz, times_us, spacing, ground_z_m = (np.concatenate([a[k] for a in around]) for k in range(4))
        near = np.abs(times_us - t_us) < SWEEP_PERIOD_US - camera_labels.DYNAMIC_DT_US
        return xyz[near], spacing[near], ground_z_m[near]

    def _store_lidar_movers(self, cam: str, view, reason: str, movers: tuple | None) -> None:
        """``mask.dynamic`` of one frame from the movers the lidar found in the sweeps around it
        (``movers``: :meth:`_movers_near`, :func:`mover_mask`); all 1 where there is no sweep near it
        (``reason``)."""
        width, height = view.pinhole.resolution_px
        if not reason and None in (self._around[0], self._around[2]) and len(self._plan.sweep_timestamps_ns) > 1:
            # the first sweep's frames before its middle, the last one's after it: no sweep on one side
            before = self._around[0] is None and view.timestamp_us < self._held[5]
            if before or (self._around[2] is None and view.timestamp_us > self._held[5]):
                reason = "no sweep on one side of the frame: where a mover is at its time is not bracketed"
        if reason:
            mask, meta = np.ones((height, width), bool), {"moving_objects_unknown": reason}
        else:
            mask = mover_mask(view, *movers)
            meta = {"sweep_median_time_us": round(self._held[5])}
        self._streams["dynamic", cam].store_label(mask, view.timestamp_us, meta)
        self.labels += 1

    def _store_boxes(self, cam: str, view, points: tuple | None, reason: str) -> None:
        """The box labels of one frame: each object where the held sweep's ``points`` show it (None:
        whole boxes; ``reason`` says why)."""
        tracks, T_box_world, half_m = self._plan.solids.tracks_at(view.timestamp_us)
        kinds = self._plan.solids.kind[tracks]
        if points is None:
            picture = camera_labels.box_index(view, T_box_world, half_m)
            meta = {"masks_from": f"whole boxes: {reason}"}
        else:
            at_frame = camera_labels.points_at_frame(view, *points)
            keys = self._plan.solids.track_ids[tracks].tolist()
            if self._sight is None:  # once per sweep: where its lines of sight passed
                self._sight = RangeImage(self._held[0], self._held[4])
            picture = camera_labels.box_index(
                view, T_box_world, half_m, kinds, *at_frame, self._covers, keys, self._sight, self.shapes
            )
            meta = {"sweep_median_time_us": round(self._held[5])}
        instance, dynamic, shown = camera_labels.box_labels(picture, self._instance[tracks], self._dynamic[tracks])
        if unknown := self._unknown(view.timestamp_us):
            meta["moving_objects_unknown"] = unknown
        for kind in self._kinds:
            if kind == "dynamic":  # where the movers are unknown, any pixel may show one: all 1
                label = np.ones_like(dynamic) if unknown else dynamic
                self._streams[kind, cam].store_label(label, view.timestamp_us, meta)
            elif kind == "instance":
                self._streams[kind, cam].store_label(instance, view.timestamp_us, {"instances_shown": shown, **meta})
            else:
                continue
            self.labels += 1

    def _no_measurement(self, t_us: int) -> str:
        """Why the frame at ``t_us`` gets no lidar evidence ('' if it does)."""
        if self._held is None:
            return "no lidar sweep with points"
        hold_us = HOLD_S * 1e6
        if t_us < self._first_sweep_us - hold_us or t_us > self._held[6] + hold_us:
            return f"no lidar sweep within {HOLD_S * 1e3:g} ms: the moving objects are unknown there"
        return ""

    def _unknown(self, t_us: int) -> str:
        """Why the moving objects at ``t_us`` are unknown ('' if known): no annotations within
        ``HOLD_S`` (the cameras may run on beyond the annotated sweeps)."""
        if self._span_us[0] - HOLD_S * 1e6 <= t_us <= self._span_us[1] + HOLD_S * 1e6:
            return ""
        return f"no annotations within {HOLD_S * 1e3:g} ms: the static boxes only (mask.dynamic: all 1)"
