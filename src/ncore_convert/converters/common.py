"""What every dataset converter shares: the dataset record the CLI runs, sensor selection, and the
counters of a conversion."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any

from upath import UPath

from ncore_convert.contract import (
    PRESET_DEFAULTS,
    PRESETS,
    CameraModel,
    ClassNames,
    CuboidLabelSource,
    Preset,
    WorldGlobalMode,
)
from ncore_convert.transforms.lidar.frames import LidarCounts, StoredRays


@dataclass(frozen=True)
class Dataset:
    """One dataset command, as the CLI runs it (``options``: the dataset's options dataclass).

    Attributes:
        options: the options dataclass, built from the command's keyword arguments.
        noun: what one unit of work is called ("log", "scenario").
        ids_dir: ``(root, options)`` -> the folder the ids are listed from (for messages).
        list_ids: ``(root, options)`` -> every id available (SourceError if the layout is wrong).
        input_dir: ``(root, options, id)`` -> the id's source folder.
        check_sensors: ``(options)`` -> None, or ValueError naming an unknown sensor id.
        convert: ``(root, sequence_dir, id, *, options, pool, progress)`` -> a summary with
            ``line()``, ``warnings`` and ``validation``; a module-level function, shipped to workers.
    """

    options: Callable[..., Any]
    noun: str
    ids_dir: Callable[[UPath, Any], UPath]
    list_ids: Callable[[UPath, Any], list[str]]
    input_dir: Callable[[UPath, Any, str], UPath]
    check_sensors: Callable[[Any], None]
    convert: Callable[..., Any]


@dataclass(frozen=True, kw_only=True)
class ConsumerOptions:
    """Options every dataset command shares that shape the output for its consumers
    (docs/consumers.md): the preset, camera model, class names, label source, clip window,
    world_global, lidar colours.

    The options a preset sets (``PRESET_DEFAULTS``) are None until resolved: an option left None
    takes the preset's value, else its default; one given explicitly wins. So
    ``Argoverse2Options(preset="3dgut")`` is what ``--preset 3dgut`` converts, from the library
    as from the command line.
    """

    preset: Preset = "ncore"
    camera_model: CameraModel | None = None
    class_names: ClassNames = "ncore"
    cuboid_label_source: CuboidLabelSource | None = None
    seek_sec: float | None = None  #: time skipped from the start of the log, s
    duration_sec: float | None = None  #: time kept from there, s (None: to the end)
    world_global_mode: WorldGlobalMode | None = None
    lidar_rgb: bool | None = None  #: per-point ``rgb`` from the cameras on every lidar frame

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; known: {list(PRESETS)}")
        for name, default in PRESET_DEFAULTS.items():
            if getattr(self, name) is None:
                object.__setattr__(self, name, PRESETS[self.preset].get(name, default))


def select_sensors(requested: tuple[str, ...] | None, known: tuple[str, ...], kind: str) -> list[str]:
    """Resolve a sensor selection (None = all) against the dataset's sensor names."""
    if requested is None:
        return list(known)
    unknown = sorted(set(requested) - set(known))
    if unknown:
        raise ValueError(f"unknown {kind} id(s) {unknown}; known: {list(known)}")
    return [s for s in known if s in requested]


class Tally:
    """Mixin for counter dataclasses: :meth:`add` adds up (numbers) or concatenates (lists) the
    fields of the dataclass that derives from Tally directly, so its subclasses (a whole-log
    summary, a job result) can carry other fields."""

    def add(self, other: Tally) -> None:
        counted = next(c for c in type(self).__mro__ if Tally in c.__bases__)
        for f in fields(counted):
            mine, theirs = getattr(self, f.name), getattr(other, f.name)
            if isinstance(mine, dict):  # counts by name (a reader's requests)
                setattr(self, f.name, {k: mine.get(k, 0) + theirs.get(k, 0) for k in mine | theirs})
            else:
                setattr(self, f.name, mine + theirs)


@dataclass
class Counts(Tally):
    """What a conversion, or one writer part of it, produced; both datasets' summaries derive from
    it. Seconds are per-process path times."""

    frames: int = 0  #: lidar frames (AV2: sweeps; OPV2V/V2XSet: every agent's frames)
    points: int = 0
    points_not_stored: int = 0
    images: int = 0
    cuboids: int = 0
    maps: int = 0
    lidar_seconds: float = 0.0  #: read + decompensate + write of all lidar frames
    dynamic_flag_seconds: float = 0.0  #: of which: dynamic_flag of every frame
    colour_seconds: float = 0.0  #: of which: per-point rgb of every frame (decoding included)
    camera_seconds: float = 0.0  #: read + write of all images
    camera_labels: int = 0  #: camera labels written (``--camera-labels``)
    label_seconds: float = 0.0  #: making and storing the camera labels
    warnings: list[str] = field(default_factory=list)
    reads: dict[str, int] = field(default_factory=dict)  #: input requests and bytes (``sources.reader.ReadCounts``)


class LidarStore:
    """One lidar's stream as every converter fills it: each frame stored with its metadata, model
    elements and generic data, and counted; at the end, the lidar's figures in its metadata and in
    the conversion's :class:`Counts`, and a warning for the points not stored.

    Args:
        stream: the writer's lidar stream (``SequenceWriter.add_lidar``).
        coloured: the points are coloured (``--lidar-rgb`` with cameras): the metadata gets the
            coloured-point count.
    """

    def __init__(self, stream, coloured: bool) -> None:
        self.stream, self.coloured, self.tally = stream, coloured, LidarCounts()

    def store(self, frame: StoredRays, frame_meta: dict, generic_data: dict | None = None) -> None:
        """Store one frame (``generic_data`` default: the frame's own) and count it."""
        self.tally.add(frame)
        generic = frame.generic if generic_data is None else generic_data
        self.stream.store_frame(frame.rays, frame_meta, model_element=frame.model_elements, generic_data=generic)

    def finish(self, meta: dict, counts: Counts, where: str, kept: str = "") -> None:
        """Set the lidar's last metadata (``meta`` and the coloured-point count), add its figures to
        ``counts``, and warn of its points not stored (``where``: the lidar or its folder; ``kept``:
        where they are kept instead, if anywhere)."""
        self.stream.set_meta({**meta, **({"rgb_coloured_points": self.tally.coloured} if self.coloured else {})})
        counts.points += self.tally.stored
        counts.points_not_stored += self.tally.not_stored
        if self.tally.not_stored:
            counts.warnings.append(
                f"{where}: {self.tally.not_stored} lidar points at zero range or with non-finite coordinates"
                f" not stored as rays{f' ({kept})' if kept else ''}"
            )
