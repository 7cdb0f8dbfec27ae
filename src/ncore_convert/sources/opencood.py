"""OPV2V and V2XSet (OpenCOOD layout, written by OpenCDA) on disk: small, pure readers.

Layout: ``<root>/<split>/<scenario>/<agent>/<key>.{yaml,pcd}`` and ``<key>_camera{0..3}.png``, plus
``<scenario>/data_protocol.yaml``. Agents are CARLA actor ids: positive for connected vehicles
(CAVs), negative for infrastructure (V2XSet RSUs). Keys are the CARLA frame counter, zero-padded to
6 digits. Everything here is in CARLA's own (left-handed) conventions; nothing knows of NCore.
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass

import numpy as np
import PIL.Image
import yaml
from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.sources.checks import png_defect
from ncore_convert.sources.pcd import read_pcd_with_header, red_from_rgb
from ncore_convert.sources.reader import Reader, reading
from ncore_convert.sources.store import ObjectInfo

SPLITS = {
    "opv2v": ("train", "validate", "test", "test_culvercity"),
    "v2xset": ("train", "validate", "test"),
}
#: Camera folder index -> NCore camera id (OpenCDA mounts: front, right rear, left rear, back).
CAMERAS = ("camera_front", "camera_right_rear", "camera_left_rear", "camera_back")
LIDAR = "lidar_top"
#: A CAV is absent from its own ``vehicles``; OpenCDA's logreplay spawns every CAV as this model
#: (``vehicle.lincoln.mkz_2017``): bounding-box centre offset and half extents, metres.
CAV_BOX_CENTER_M = (0.0040, 0.0, 0.7189)
CAV_BOX_EXTENT_M = (2.4508, 1.0642, 0.7554)

_AGENT = re.compile(r"^-?[0-9]{1,9}$")
_KEY = re.compile(r"^[0-9]{4,9}$")


class _Loader(yaml.CSafeLoader if hasattr(yaml, "CSafeLoader") else yaml.SafeLoader):
    """Safe YAML (no object construction) that also reads ``1e-06`` as a float, as OpenCOOD does."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?|[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\.[0-9_]+(?:[eE][-+][0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


def load_yaml(path: UPath, reader: Reader | None = None) -> dict:
    """Parse a YAML mapping safely (read by ``reader``); SourceError naming the file if it is
    unreadable or not a mapping."""
    with reading(reader) as r:
        return parse_yaml(r.read(UPath(path)), path)


def read_text(path: UPath, data: bytes | None = None, reader: Reader | None = None) -> str:
    """A file's UTF-8 text (what OpenCOOD's YAML files are; ``data``: its bytes, already fetched,
    else read by ``reader``); SourceError naming it otherwise."""
    if data is None:
        with reading(reader) as r:
            data = r.read(UPath(path))
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise SourceError(path, f"not UTF-8 text ({err.reason} at byte {err.start})") from None


def parse_yaml(raw: bytes | str, path: object) -> dict:
    """Parse YAML text as OpenCOOD does (safely; ``1e-06`` is a float); SourceError naming ``path``
    if it is not valid YAML or not a mapping."""
    try:
        data = yaml.load(raw, Loader=_Loader)  # noqa: S506 - _Loader is a SafeLoader
    except yaml.YAMLError as err:
        raise SourceError(path, f"not valid YAML ({str(err).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise SourceError(path, "expected a YAML mapping")
    return data


def is_infrastructure(agent_id: str) -> bool:
    return int(agent_id) < 0


def agent_kind(agent_id: str) -> str:
    """ "infrastructure" (negative id) or "cav" (connected vehicle, positive id)."""
    return "infrastructure" if is_infrastructure(agent_id) else "cav"


def scenario_dir(root: UPath, split: str, scenario: str) -> UPath:
    """A scenario's folder: ``<root>/<split>/<scenario>``."""
    return UPath(root) / split / scenario


def list_scenarios(root: UPath, split: str, reader: Reader | None = None) -> list[str]:
    """Sorted scenario folder names of a split (SourceError if the split folder is missing)."""
    split_dir = UPath(root) / split
    with reading(reader) as r:
        if not r.is_folder(split_dir):
            raise SourceError(split_dir, "split folder not found")
        return r.folder_names(split_dir, "scenario folder")


def list_agents(scenario_dir: UPath, reader: Reader | None = None) -> list[str]:
    """Agent folder names (CARLA actor ids as strings), sorted numerically (one listing)."""
    with reading(reader) as r:
        if not r.is_folder(scenario_dir):
            raise SourceError(scenario_dir, "scenario folder not found")
        names = r.folder_names(scenario_dir, None)  # actor ids, checked below
    bad = [n for n in names if not is_agent_id(n)]
    if bad:
        raise SourceError(scenario_dir / bad[0], "agent folder names must be integer actor ids")
    if not names:
        raise SourceError(scenario_dir, "no agent folders")
    return sorted(names, key=int)


def is_agent_id(name: str) -> bool:
    """An agent folder's name: a CARLA actor id (negative: infrastructure)."""
    return bool(_AGENT.match(name))


def opencood_order(agent_ids: list[str]) -> list[str]:
    """OpenCOOD's scenario-database order (``basedataset.py``): agent folders by *string* sort, with
    a leading infrastructure id moved to the end; e.g. ['650', '1732', '-1'] -> ['1732', '650', '-1']."""
    order = sorted(agent_ids)
    if is_infrastructure(order[0]):
        order = order[1:] + order[:1]
    return order


def opencood_ego(agent_ids: list[str]) -> str:
    """OpenCOOD's ego: the first agent of :func:`opencood_order`."""
    return opencood_order(agent_ids)[0]


def list_frame_keys(
    agent_dir: UPath, listing: dict[str, ObjectInfo] | None = None, reader: Reader | None = None
) -> list[str]:
    """Frame keys of an agent: the stems of ``<key>.yaml`` (``*_additional.yaml`` and others skipped);
    a remote folder is listed once, its files' sizes and ETags added to ``listing``."""
    with reading(reader) as r:
        names = r.file_names(agent_dir, listing)
    stems = (name[: -len(".yaml")] for name in names if name.endswith(".yaml"))
    return sorted((stem for stem in stems if _KEY.match(stem)), key=int)


@dataclass(frozen=True)
class Protocol:
    """What the converter uses of a scenario's ``data_protocol.yaml`` (OpenCDA's scenario config).

    Attributes:
        fixed_delta_seconds: the CARLA tick, ``world.fixed_delta_seconds``, seconds.
        cav_lidar: the first CAV's ``sensing.perception.lidar`` block (empty if absent).
        rsu_lidars: each infrastructure unit's (``scenario.rsu_list``) lidar block, in list order;
            agent ``-k`` is the k-th (empty blocks where absent).
    """

    fixed_delta_seconds: float
    cav_lidar: dict
    rsu_lidars: tuple[dict, ...] = ()
    text: str | None = None  #: the file's text as it is (stored for the OpenCOOD export); None: no file

    def lidar_of(self, agent_id: str) -> dict:
        """The lidar block of an agent: its infrastructure unit's (negative ids), else the CAVs'."""
        if is_infrastructure(agent_id):
            k = -int(agent_id) - 1
            return self.rsu_lidars[k] if k < len(self.rsu_lidars) else {}
        return self.cav_lidar


#: The CARLA tick of OPV2V and V2XSet (OpenCDA's ``world.fixed_delta_seconds``), used when a scenario
#: has no ``data_protocol.yaml``: OpenCOOD's 10 Hz frames are every second tick, keys step by 2.
DEFAULT_TICK_S = 0.05


def protocol_path(scenario_dir: UPath) -> UPath:
    return UPath(scenario_dir) / "data_protocol.yaml"


def read_protocol(scenario_dir: UPath, reader: Reader | None = None) -> Protocol:
    """Read ``data_protocol.yaml`` (SourceError naming it without a plausible tick; its existence
    from the scenario folder's listing, never a HEAD); a scenario without one gets
    :data:`DEFAULT_TICK_S` and no lidar blocks (``text`` None)."""
    path = protocol_path(scenario_dir)
    with reading(reader) as r:
        if not r.exists(path):
            return Protocol(DEFAULT_TICK_S, {})
        text = read_text(path, reader=r)
    protocol = parse_yaml(text, path)
    try:
        dt = float(protocol["world"]["fixed_delta_seconds"])
    except (KeyError, TypeError, ValueError):
        raise SourceError(path, "no numeric world.fixed_delta_seconds") from None
    if not 0.0 < dt <= 1.0:
        raise SourceError(path, f"world.fixed_delta_seconds {dt} is not a plausible CARLA tick")

    def lidar_block(unit) -> dict:
        try:
            return dict(unit["sensing"]["perception"]["lidar"])
        except (KeyError, IndexError, TypeError, ValueError):
            return {}

    scenario = protocol.get("scenario") if isinstance(protocol, dict) else None
    scenario = scenario if isinstance(scenario, dict) else {}
    cavs, rsus = scenario.get("single_cav_list"), scenario.get("rsu_list")
    cav = cavs[0] if isinstance(cavs, list) and cavs else {}
    rsus = rsus if isinstance(rsus, list) else []
    return Protocol(dt, lidar_block(cav), tuple(lidar_block(unit) for unit in rsus), text)


@dataclass(frozen=True)
class Vehicles:
    """Vehicles of one agent's frame, columnar, CARLA world (left-handed), metres and degrees.

    Attributes:
        actor_ids: int64 [M]; location: actor origin [M,3]; angle: (roll, yaw, pitch) [M,3];
        center: box-centre offset in the actor frame [M,3]; extent: half length, width, height [M,3];
        speed_kmh: CARLA's speed of each vehicle [M] (km/h, no direction), NaN where the entry has none.
    """

    actor_ids: np.ndarray
    location: np.ndarray
    angle: np.ndarray
    center: np.ndarray
    extent: np.ndarray
    speed_kmh: np.ndarray

    def __len__(self) -> int:
        return len(self.actor_ids)


@dataclass(frozen=True)
class AgentFrame:
    """One agent's ``<key>.yaml``: poses ``[x, y, z, roll, yaw, pitch]`` (m, deg, CARLA world).

    Attributes:
        lidar_pose: [6]; true_ego_pos: [6]; camera_cords: {camera index: [6]};
        camera_intrinsic: {camera index: K [3,3]}; vehicles: the labelled vehicles;
        ego_speed_kmh: the agent's own speed (km/h; NaN when the file has none).
    """

    path: UPath
    lidar_pose: np.ndarray
    true_ego_pos: np.ndarray
    camera_cords: dict[int, np.ndarray]
    camera_intrinsic: dict[int, np.ndarray]
    vehicles: Vehicles
    ego_speed_kmh: float = float("nan")


def _vector(path: UPath, data: dict, key: str, size: int, where: str = "") -> np.ndarray:
    """``data[key]`` as float64 [size], or SourceError naming the file, ``where`` and the key."""
    try:
        value = np.asarray(data[key], dtype=np.float64).reshape(-1)  # a 3x3 matrix comes flat
    except KeyError:
        raise SourceError(path, f"{where}missing key {key!r}") from None
    except (TypeError, ValueError):
        raise SourceError(path, f"{where}{key!r} is not numeric") from None
    if value.shape != (size,) or not np.all(np.isfinite(value)):
        raise SourceError(path, f"{where}{key!r} must be {size} finite numbers, got {data[key]!r}"[:200])
    return value


def _vehicles(path: UPath, table: object) -> Vehicles:
    if table is None:
        table = {}
    if not isinstance(table, dict):
        raise SourceError(path, "'vehicles' is not a mapping")
    columns: dict[str, list] = {"location": [], "angle": [], "center": [], "extent": []}
    ids, speeds = [], []
    for actor, entry in table.items():
        try:
            ids.append(int(actor))
        except (TypeError, ValueError):
            raise SourceError(path, f"vehicle id {actor!r} is not an integer") from None
        if not isinstance(entry, dict):
            raise SourceError(path, f"vehicle {actor}: not a mapping")
        for name, column in columns.items():
            column.append(_vector(path, entry, name, 3, where=f"vehicle {actor}: "))
        speeds.append(_vector(path, entry, "speed", 1, where=f"vehicle {actor}: ")[0] if "speed" in entry else np.nan)
    shape = (len(ids), 3)
    return Vehicles(
        np.array(ids, dtype=np.int64),
        *(np.array(c, dtype=np.float64).reshape(shape) for c in columns.values()),
        np.array(speeds, dtype=np.float64),
    )


def yaml_path(agent_dir: UPath, key: str) -> UPath:
    return agent_dir / f"{key}.yaml"


def read_agent_frame(agent_dir: UPath, key: str, raw: bytes | None = None, reader: Reader | None = None) -> AgentFrame:
    """Read ``<agent_dir>/<key>.yaml`` (``raw``: its bytes, already fetched, else read by ``reader``;
    SourceError naming the file on a missing key or bad value)."""
    path = yaml_path(agent_dir, key)
    data = load_yaml(path, reader) if raw is None else parse_yaml(raw, path)
    cords, intrinsic = {}, {}
    for index in range(len(CAMERAS)):
        entry = data.get(f"camera{index}")
        if entry is None:
            continue
        if not isinstance(entry, dict):
            raise SourceError(path, f"'camera{index}' is not a mapping")
        cords[index] = _vector(path, entry, "cords", 6, where=f"camera{index}: ")
        intrinsic[index] = _vector(path, entry, "intrinsic", 9, where=f"camera{index}: ").reshape(3, 3)
    return AgentFrame(
        path=path,
        lidar_pose=_vector(path, data, "lidar_pose", 6),
        true_ego_pos=_vector(path, data, "true_ego_pos", 6),
        camera_cords=cords,
        camera_intrinsic=intrinsic,
        vehicles=_vehicles(path, data.get("vehicles")),
        ego_speed_kmh=_vector(path, data, "ego_speed", 1)[0] if "ego_speed" in data else float("nan"),
    )


def pcd_path(agent_dir: UPath, key: str) -> UPath:
    return agent_dir / f"{key}.pcd"


def camera_path(agent_dir: UPath, key: str, index: int) -> UPath:
    return agent_dir / f"{key}_camera{index}.png"


def read_png(agent_dir: UPath, key: str, index: int, data: bytes | None = None, reader: Reader | None = None) -> bytes:
    """The encoded bytes of ``<key>_camera<index>.png`` (``data``: already fetched, else read by
    ``reader``), checked to be a complete PNG (SourceError naming the file if it is missing,
    unreadable, not a PNG or cut short)."""
    path = camera_path(agent_dir, key, index)
    if data is None:
        with reading(reader) as r:
            data = r.read(path)
    if (defect := png_defect(data)) is not None:
        raise SourceError(path, defect)
    return data


def fetch_png(agent_dir: UPath, key: str, index: int, listing: dict | None, reader: Reader) -> bytes:
    """:func:`read_png`, the file fetched by its folder's ``listing`` entry and kept for the
    scenario's later jobs (:meth:`Reader.read`)."""
    return read_png(agent_dir, key, index, reader.read(camera_path(agent_dir, key, index), listing, keep=True))


def decode_png_rgb(data: bytes) -> np.ndarray:
    """A PNG read by :func:`read_png`, decoded: uint8 [height,width,3]."""
    with PIL.Image.open(io.BytesIO(data), formats=["PNG"]) as image:
        return np.asarray(image.convert("RGB"))


#: The fourth field of the lidar PCDs OpenCDA writes: Open3D's packed colour with the intensity in
#: red (OPV2V, V2XSet), or the intensity as a float.
PCD_INTENSITY_FIELDS = ("rgb", "intensity")


@dataclass(frozen=True)
class Sweep:
    """A lidar frame as its PCD holds it, in the CARLA lidar frame (left-handed: x forward, y right, z up).

    Attributes:
        xyz_m: float32 [N,3], file order; intensity: float32 [N] in [0, 1] (``rgb``: red / 255);
        field: the PCD's intensity field (``rgb`` or ``intensity``); binary: ``DATA binary``.
    """

    xyz_m: np.ndarray
    intensity: np.ndarray
    field: str
    binary: bool

    @property
    def layout(self) -> str:
        """E.g. ``"x y z rgb ascii"``: what the OpenCOOD export writes back."""
        return f"x y z {self.field} {'binary' if self.binary else 'ascii'}"


def read_points(agent_dir: UPath, key: str, data: bytes | None = None, reader: Reader | None = None) -> Sweep:
    """``<key>.pcd``: x, y, z and the intensity (``data``: its bytes, already fetched, else read by
    ``reader``; SourceError naming the file if it lacks them)."""
    path = pcd_path(agent_dir, key)
    header, columns = read_pcd_with_header(path, data, reader)
    missing = [f for f in ("x", "y", "z") if f not in columns]
    field = next((f for f in PCD_INTENSITY_FIELDS if f in columns), None)
    if missing or field is None:
        lacks = missing + ([] if field else ["rgb or intensity"])
        raise SourceError(path, f"PCD lacks field(s) {', '.join(lacks)}")
    xyz = np.stack([columns["x"], columns["y"], columns["z"]], axis=1).astype(np.float32, copy=False)
    if field == "rgb":
        intensity = red_from_rgb(columns["rgb"]).astype(np.float32) / np.float32(255.0)
    else:
        intensity = columns["intensity"].astype(np.float32, copy=False)
        outside = ~((intensity >= 0.0) & (intensity <= 1.0))  # CARLA's are in [0, 1]; NaN is outside too
        if outside.any():
            bad = intensity[outside][0]
            raise SourceError(path, f"PCD intensity {bad} outside [0, 1] (CARLA's ray-cast intensity)")
    return Sweep(xyz, intensity, field, header.data == "binary")


def fetch_points(agent_dir: UPath, key: str, listing: dict | None, reader: Reader) -> Sweep:
    """:func:`read_points`, the file fetched by its folder's ``listing`` entry and kept for the
    scenario's later jobs (:meth:`Reader.read`)."""
    return read_points(agent_dir, key, reader.read(pcd_path(agent_dir, key), listing, keep=True))


def png_size(data: bytes) -> tuple[int, int]:
    """(width, height) of a PNG read by :func:`read_png`, from its header."""
    with PIL.Image.open(io.BytesIO(data[:64]), formats=["PNG"]) as image:
        return image.size


def key_timestamps_us(keys: list[str], fixed_delta_seconds: float) -> np.ndarray:
    """Frame keys (CARLA frame counters) -> µs since the simulation's frame 0, int64 [N]."""
    return np.round(np.array([int(k) for k in keys], dtype=np.float64) * fixed_delta_seconds * 1e6).astype(np.int64)
