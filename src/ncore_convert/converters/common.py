"""What every dataset converter shares: the dataset record the CLI runs, sensor selection, and the
counters of a conversion."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

from upath import UPath

from ncore_convert.contract import PRESETS, CameraModel, ClassNames, CuboidLabelSource, Preset, WorldGlobalMode


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


#: The consumer options a preset may set (``contract.PRESETS``), and their values under none.
PRESET_DEFAULTS: dict[str, object] = {
    "camera_model": "ideal-pinhole",
    "cuboid_label_source": "auto",
    "world_global_mode": "localized",
    "lidar_rgb": False,
}


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
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))
