"""Per-log decisions every converter makes the same way for the output's consumers
(docs/consumers.md): the clip window, what ``world -> world_global`` holds, the camera models, and
the cuboids' class names, label source and dynamic tracks."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ncore_convert import contract
from ncore_convert.contract import CameraModel, ClassNames, CuboidLabelSource, WorldGlobalMode
from ncore_convert.converters.common import ConsumerOptions
from ncore_convert.transforms.camera.models import FThetaFit, Pinhole, fit_ftheta
from ncore_convert.transforms.geometry import euler_xyz_from_rotation
from ncore_convert.transforms.objects import classes, dynamic
from ncore_convert.transforms.timebase import clip_window_us


def clip_window(options: ConsumerOptions, reference_us: list[np.ndarray]) -> tuple[int, int] | None:
    """The inclusive µs window of ``--seek-sec/--duration-sec`` over a log whose frames have the
    reference times ``reference_us`` (int arrays, µs); None without a window. WindowError (naming
    the log's duration) when the window is outside the log."""
    if options.seek_sec is None and options.duration_sec is None:
        return None
    times = [t for t in reference_us if len(t)]
    first = min(int(np.min(t)) for t in times)
    last = max(int(np.max(t)) for t in times)
    return clip_window_us(first, last, options.seek_sec, options.duration_sec)


def clip_meta(options: ConsumerOptions, window_us: tuple[int, int]) -> dict:
    """The sequence metadata's ``clip`` record."""
    return {
        "seek_sec": options.seek_sec,
        "duration_sec": options.duration_sec,
        "start_us": int(window_us[0]),
        "end_us": int(window_us[1]),
        "rule": "frames whose reference time (sweep timestamp, image timestamp, frame tick) lies in"
        " [start_us, end_us] are kept whole; cuboids by their timestamp; poses cover the kept frames",
    }


def world_global(
    T_world_dataset_global: np.ndarray, mode: WorldGlobalMode, dataset_global: str
) -> tuple[np.ndarray | None, dict]:
    """What ``world -> world_global`` holds under ``mode``, and the sequence metadata's
    ``world_global`` record, which keeps the dataset's global frame recoverable in every mode.

    Args:
        T_world_dataset_global: world -> the dataset's global frame, float64 [4,4].
        dataset_global: what that frame is (for the metadata).

    Returns:
        the static edge to store (None: no ``world_global`` node), and the metadata record.
    """
    edge = {"localized": T_world_dataset_global, "identity": np.eye(4), "none": None}[mode]
    meta = {
        "mode": mode,
        "dataset_global": dataset_global,
        "T_world_dataset_global": np.asarray(T_world_dataset_global, dtype=np.float64).tolist(),
        "note": {
            "localized": "world_global is the dataset's global frame",
            "identity": "world_global = world; the dataset's global frame is T_world_dataset_global",
            "none": "no world_global node; the dataset's global frame is T_world_dataset_global",
        }[mode],
    }
    return edge, meta


@dataclass(frozen=True)
class CameraSpec:
    """A camera as stored: its pinhole, the model type, and the f-theta fit (``ftheta`` only)."""

    pinhole: Pinhole
    model: CameraModel
    ftheta: FThetaFit | None = None

    def meta(self) -> dict:
        """The camera component metadata's ``camera_model`` record."""
        out: dict = {"type": self.model}
        if self.model == "opencv-pinhole":
            out["note"] = "every distortion coefficient 0: the same rays as the ideal pinhole"
        if self.ftheta is not None:
            out["ftheta_fit"] = self.ftheta.meta()
        return out


def camera_spec(pinhole: Pinhole, model: CameraModel, known: dict[Pinhole, CameraSpec] | None = None) -> CameraSpec:
    """How ``--camera-model`` stores a pinhole camera (the f-theta fit is made here); ``known``: the
    specs made so far, by pinhole (cameras that share one share its fit, made once)."""
    if known is not None and pinhole in known:
        return known[pinhole]
    spec = CameraSpec(pinhole, model, fit_ftheta(pinhole) if model == "ftheta" else None)
    if known is not None:
        known[pinhole] = spec
    return spec


@dataclass(frozen=True)
class CuboidLabels:
    """The cuboids' names and provenance as written.

    Attributes:
        class_ids: the written class name of each observation [M].
        class_map: source class -> written class name, for every source class seen.
        label_source: the NCore ``LabelSource`` member name.
        meta: the cuboids component's metadata.
        dynamic: the ids of the dynamic tracks.
        warnings: one per log for source classes outside the table.
        static_poses: track id -> :func:`dynamic.static_pose` (centre [3], rotation [3,3], size [3])
            of every static track, in the observations' frame.
    """

    class_ids: list[str]
    class_map: dict[str, str]
    label_source: str
    meta: dict
    dynamic: frozenset[str]
    warnings: list[str]
    static_poses: dict[str, tuple[np.ndarray, ...]]


def _motion_meta(
    observations: dynamic.TrackObservations,
    poses: dict[str, tuple[np.ndarray, ...]],
    motion: dict[str, dynamic.TrackMotion],
    frame: str,
) -> dict:
    """The cuboids' metadata on motion: the dynamic tracks with their figures (``motion``), the rule,
    and the static tracks' median boxes (``poses``) in ``frame``."""
    rotations = euler_xyz_from_rotation(np.stack([p[1] for p in poses.values()])) if poses else []
    speeds = (
        "measured speeds (every observation of the track has one) over 1 km/h, else "
        if (observations.speeds_mps is not None)
        else ""
    )
    return {
        contract.DYNAMIC_TRACKS: {t: m.as_meta() for t, m in motion.items() if m.dynamic},
        "dynamic_rule": f"class always dynamic ({', '.join(sorted(classes.ALWAYS_DYNAMIC))}); else {speeds}the box"
        f" centres (median over {dynamic.MEDIAN_WINDOW} observations) moved: net displacement between the medians"
        f" of the first and last {dynamic.END_WINDOW_S:g} s (a quarter of a track shorter than 2 s) >"
        f" {dynamic.NET_DYNAMIC_M:g} m, or a centre more than {dynamic.DEVIATION_DYNAMIC_M:g} m from the track's"
        f" median centre; never: {', '.join(sorted(classes.ALWAYS_STATIC))}",
        contract.STATIC_POSES: {
            "frame": frame,
            "convention": "the median box of each static track's observations, as NCore's BBox3: centroid (m),"
            " dim (length, width, height, m), rot (x-y-z Euler angles, rad) in the frame named here; the"
            " observations themselves are unchanged",
            "tracks": {
                t: {
                    "centroid": [round(float(v), 4) for v in pose[0]],
                    "dim": [round(float(v), 4) for v in pose[2]],
                    "rot": [round(float(v), 6) for v in rot],
                }
                for (t, pose), rot in zip(poses.items(), rotations, strict=True)
            },
        },
    }


def cuboid_labels(
    observations: dynamic.TrackObservations,
    source_classes: list[str],
    table: dict[str, str],
    class_names: ClassNames,
    label_source_option: CuboidLabelSource,
    dataset_label_source: str,
    frame: str,
    where: str,
) -> CuboidLabels:
    """Class names, label source, dynamic tracks and static poses of a log's cuboid observations.

    Args:
        observations: the boxes in the fixed frame named ``frame`` (``world``, ``world_global``).
        source_classes: per observation [M]; table: source class -> NCore class.
        where: the source file or folder, for the warning.
    """
    written, ncore, unmapped = classes.output_classes(source_classes, table, class_names)
    source = classes.label_source(label_source_option, dataset_label_source)
    warnings = []
    if unmapped:
        warnings.append(f"{where}: categories without an NCore class name kept as they are: {', '.join(unmapped)}")
    motion = dynamic.classify_tracks(observations, ncore) if len(observations.track_ids) else {}
    poses = dynamic.static_poses(observations, {t for t, m in motion.items() if not m.dynamic})
    motion_meta = _motion_meta(observations, poses, motion, frame)
    meta = {
        "class_names": class_names,
        "label_source": source,
        "label_source_note": "AUTOLABEL is a compatibility setting for instant-nurec, not a provenance claim"
        if source == "AUTOLABEL" and dataset_label_source != "AUTOLABEL"
        else f"the dataset's labels are {dataset_label_source}",
        contract.SOURCE_CLASS_BY_TRACK: dict(zip(observations.track_ids, source_classes, strict=True)),
        **motion_meta,
    }
    moving = frozenset(motion_meta[contract.DYNAMIC_TRACKS])
    return CuboidLabels(written, dict(zip(source_classes, written, strict=True)), source, meta, moving, warnings, poses)
