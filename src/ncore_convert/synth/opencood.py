"""Synthetic OPV2V / V2XSet scenarios, written the way OpenCDA writes them, with known truth.

Everything is built in CARLA's own conventions, independently of :mod:`ncore_convert.transforms.carla`:
a left-handed world (z up, +y 90° clockwise from +x seen from above), poses
``[x, y, z, roll, yaw, pitch]`` in degrees with ``R = Rz(yaw) · Ry(-pitch) · Rx(-roll)``, UE4
camera axes (x optical axis, y right, z up). On disk: ``<root>/<split>/<scenario>/<agent>/`` with
6-digit frame keys stepping by 2 from an odd, non-zero first key, per-frame YAML, ASCII PCD
(x y z rgb, the intensity in the packed red channel), 800x600 PNGs and ``data_protocol.yaml``.

The scene: a curved road with CAVs (positive actor ids) and other vehicles driving on it, parked
vehicles, pillars (static landmarks) and building fronts; V2XSet adds infrastructure units
(negative ids) with a lidar on a pole and four cameras pitched down 35°. The lidar is a 64-channel
CARLA ray-cast lidar (all points at the tick). The cameras see the same world as the lidar: each
picture is ray-cast from the scene (flat colours: a checkered ground, a colour per vehicle, red
pillars, brown buildings, sky). A pillar whose centre's pixel and the 8 around it show the pillar is
a marker: the truth keeps where its centre projects.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import yaml
from upath import UPath

from ncore_convert.sources import opencood as src
from ncore_convert.sources.pcd import write_pcd
from ncore_convert.synth.carla import (
    FOCAL_PX,
    HEIGHT,
    PILLAR_DIMS_M,
    PILLAR_RGB,
    RENDER_STEP,
    WIDTH,
    carla_pose_list,
    carla_pose_matrix,
    carla_rotation,
    project_ue4,
    render_png,
    shows_around,
)
from ncore_convert.synth.opencood_traffic import (
    Actor,
    Road,
    actor_box,
    actor_pose,
    clear_of,
    clear_of_cavs,
    close_to,
)
from ncore_convert.synth.raycast import BUILDING_RGB, cast_rays, own_colour, surface_rgb
from ncore_convert.synth.scene import Box, Scene

LIDAR_CHANNELS, UPPER_FOV_DEG, LOWER_FOV_DEG, LIDAR_RANGE_M = 64, 2.0, -25.0, 120.0
#: The infrastructure units' lidar (V2XSet): channels, upper_fov, lower_fov; its own protocol block.
RSU_LIDAR = (32, 0.0, -40.0)
#: Lidar mount on a CAV (vehicle frame, m), and the height of an infrastructure lidar above ground.
CAV_LIDAR_M = (-0.5, 0.0, 1.9)
RSU_LIDAR_HEIGHT_M = 4.5
#: OpenCDA camera mounts (vehicle frame): x, y, z (m), yaw (deg); pitch 0 on a CAV, -35° on an RSU.
CAMERA_MOUNTS = ((2.5, 0.0, 1.0, 0.0), (0.0, 0.3, 1.8, 100.0), (0.0, -0.3, 1.8, -100.0), (-2.0, 0.0, 1.5, 180.0))
RSU_CAMERA_PITCH_DEG = -35.0


@dataclass(frozen=True)
class SynthConfig:
    dataset: str = "opv2v"  #: "opv2v" or "v2xset"
    frames: int = 10
    seed: int = 0
    cavs: int = 2
    infrastructure: int | None = None  #: None: 1 for V2XSet, 0 for OPV2V
    split: str = "test"
    first_key: int = 69
    key_step: int = 2
    fixed_delta_seconds: float = 0.05
    lidar_columns: int = 720  #: azimuth samples per channel and tick (one tick is one revolution)
    lidar_noise_stddev: float = 0.0  #: CARLA's noise_stddev: range noise along each ray, m
    lidar_dropoff_rate: float = 0.0  #: CARLA's dropoff_general_rate: share of points dropped at random
    keep_truth: bool = False
    lidar_channels: int = LIDAR_CHANNELS  #: the CAVs' simulated lasers (a real V2XSet scenario: 32)
    #: keys of the CAVs' protocol lidar block written over what was simulated (a protocol dumped by
    #: another run, as real V2XSet has): e.g. (("channels", 64),); the data keep the simulated lidar
    protocol_lidar: tuple[tuple[str, float], ...] = ()
    protocol: bool = True  #: write data_protocol.yaml (False: a scenario without one)
    #: share of the points moved onto a 0.1 m grid in x (where one float32 step moves a point across a voxel edge)
    grid_share: float = 0.0
    pcd_fields: str = "rgb"  #: the PCD's fourth field: "rgb" (Open3D's packed colour) or "intensity" (float)
    pcd_binary: bool = False  #: DATA binary instead of ascii
    cameras: bool = True  #: False: lidar and YAML only (no PNGs, no camera entries), for lidar-only tests
    #: the pictures are ray-cast at one ray per render_step x render_step pixels (2: CARLA's look at
    #: half resolution; tests that do not read pixels use 8, 16 times fewer rays)
    render_step: int = RENDER_STEP
    #: vehicles shaped inside their boxes (``synth.shapes``: body, cabin, wheels, mirrors)
    shapes: bool = False
    #: a car queued just ahead of the first CAV (0.3-1.0 m from its front camera) and one alongside
    #: it (1-2 m from its side), at its speed
    close_range: bool = False
    #: the YAMLs as OpenCDA writes them (seen on the real agent, issue 73): CARLA's float32 values
    #: for every pose, location, angle and size (the camera extrinsics computed from them), block
    #: style, ``predicted_ego_pos`` with zero roll and pitch and its yaw in [0, 360); False: exact
    #: doubles in flow style, as the generator wrote them before (``bench/fingerprints.py`` pins it)
    opencda_format: bool = True

    @property
    def n_infrastructure(self) -> int:
        return self.infrastructure if self.infrastructure is not None else int(self.dataset == "v2xset")


@dataclass
class AgentTruth:
    """Per frame key: CARLA lidar pose [6], the actor id hit by each stored point (-1 ground,
    -2 pillar, -3 building), the stored intensity (uint8), the true colour of each point's surface
    (:func:`synth.raycast.surface_rgb`, uint8 [N,3]) and the marker pixels {camera index: {pillar index:
    (u, v)}}: where each pillar's centre projects, if the picture shows that pillar there.
    Point arrays only with ``keep_truth``."""

    agent_id: str
    lidar_pose: dict[str, list[float]] = field(default_factory=dict)
    hit_actor: dict[str, np.ndarray] = field(default_factory=dict)
    intensity_u8: dict[str, np.ndarray] = field(default_factory=dict)
    n_points: dict[str, int] = field(default_factory=dict)
    markers: dict[str, dict[int, dict[int, tuple[float, float]]]] = field(default_factory=dict)
    point_rgb: dict[str, np.ndarray] = field(default_factory=dict)  #: the true colour of each point's surface
    #: per frame key: the scene the agent's sensors see at the tick (its own vehicle left out), with
    #: the actor id of each scene box (-2 pillar, -3 building), int [B]
    scenes: dict[str, tuple[Scene, np.ndarray]] = field(default_factory=dict)
    #: per frame key: each camera's pose (camera index -> UE4 camera -> CARLA world, [4,4])
    T_cam_world: dict[str, dict[int, np.ndarray]] = field(default_factory=dict)


@dataclass
class ScenarioTruth:
    scenario_dir: UPath
    scenario: str
    keys: list[str]
    fixed_delta_seconds: float
    pillars_m: np.ndarray  #: pillar centres, CARLA world [P,3]; sizes PILLAR_DIMS_M, yaw 0
    agents: dict[str, AgentTruth]
    actor_speed_mps: dict[int, float] = field(default_factory=dict)  #: every actor (CAVs included)


def lidar_block(config: SynthConfig, channels: int, upper_fov: float, lower_fov: float) -> dict:
    """A ``sensing.perception.lidar`` block that matches the simulated lidar: one revolution per tick,
    and ``points_per_second`` with a fractional share per channel and tick that CARLA rounds to
    ``lidar_columns`` (as OPV2V's 1,300,000 / 20 / 64 = 1015.6 rounds to 1016)."""
    dt = config.fixed_delta_seconds
    return {
        "channels": channels,
        "range": LIDAR_RANGE_M,
        "upper_fov": upper_fov,
        "lower_fov": lower_fov,
        "rotation_frequency": round(1.0 / dt, 9),
        "points_per_second": round((config.lidar_columns - 0.375) * channels / dt, 3),
        "noise_stddev": config.lidar_noise_stddev,
        "dropoff_general_rate": config.lidar_dropoff_rate,
        "dropoff_intensity_limit": 1.0,
        "dropoff_zero_intensity": 0.0,
    }


def _lidar_rays(block: dict, dt: float) -> np.ndarray:
    """Unit directions of one tick of CARLA's ray-cast lidar in its (left-handed) frame
    [channels * n, 3], laser by laser: n = round(pps * dt / channels) azimuths from -180 deg, evenly
    over the tick's sweep (one revolution)."""
    channels = int(block["channels"])
    n = int(np.floor(block["points_per_second"] * dt / channels + 0.5))
    elevation = np.radians(np.linspace(block["upper_fov"], block["lower_fov"], channels))
    azimuth = np.radians(-180.0 + np.arange(n) * (360.0 * block["rotation_frequency"] * dt) / n)
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)


def _yaml(data: dict, config: SynthConfig) -> bytes:
    style = False if config.opencda_format else None  # OpenCDA's: block style
    return yaml.dump(data, Dumper=getattr(yaml, "CSafeDumper", yaml.SafeDumper), default_flow_style=style).encode()


def _floats(values) -> list[float]:
    return [float(v) for v in np.ravel(values)]


def _float32(values) -> np.ndarray:
    """``values`` as CARLA holds them (float32: its transforms, locations, extents), float64 [...]."""
    return np.asarray(values, dtype=np.float32).astype(np.float64)


def _carla(values, config: SynthConfig) -> list[float]:
    """Values as OpenCDA writes them (:func:`_float32`), or exact (``config.opencda_format`` False)."""
    return _floats(_float32(values) if config.opencda_format else values)


def _float32_actor(actor: Actor) -> Actor:
    """``actor`` with CARLA's float32 sizes (its bounding box's extent and centre)."""
    return replace(actor, extent_m=tuple(_float32(actor.extent_m)), center_m=tuple(_float32(actor.center_m)))


def _predicted(true_ego: list[float], rng: np.random.Generator, config: SynthConfig) -> list[float]:
    """``predicted_ego_pos``: the true pose with GPS-like noise on x, y and yaw; as OpenCDA writes it,
    roll and pitch 0 and the yaw in [0, 360), as the real agent's files have it (the sample in
    ../shared/reference/opencood.md, another OpenCDA run, has them nonzero and its yaw below -180:
    the converter reads neither)."""
    noisy = np.array(true_ego) + rng.normal(0, 0.05, 6) * [1, 1, 0, 0, 1, 0]
    if config.opencda_format:
        noisy[[3, 5]], noisy[4] = 0.0, noisy[4] % 360.0
    return _carla(noisy, config)


def _scenario_name(rng: np.random.Generator) -> str:
    day, hour, minute, second = rng.integers(1, 29), rng.integers(0, 24), rng.integers(0, 60), rng.integers(0, 60)
    return f"2021_08_{day:02d}_{hour:02d}_{minute:02d}_{second:02d}"


def _protocol(config: SynthConfig, cav_spawns: list[list[float]], rsu_spawns: list[list[float]]) -> dict:
    def sensing(lidar: dict) -> dict:
        return {"perception": {"camera_num": 4, "lidar": lidar}, "localization": {"gnss": {"noise_alt_stddev": 0.005}}}

    cav = sensing(lidar_block(config, config.lidar_channels, UPPER_FOV_DEG, LOWER_FOV_DEG))
    protocol = {
        "world": {
            "client_port": 2000,
            "fixed_delta_seconds": config.fixed_delta_seconds,
            "seed": config.seed,
            "sync_mode": True,
            "weather": {"sun_altitude_angle": 15, "cloudiness": 0, "fog_density": 0},
        },
        "vehicle_base": {"sensing": cav},
        "scenario": {"single_cav_list": [{"spawn_position": s, "sensing": cav} for s in cav_spawns]},
    }
    if rsu_spawns:
        rsu = sensing(lidar_block(config, *RSU_LIDAR))
        protocol["scenario"]["rsu_list"] = [{"spawn_position": s, "sensing": rsu} for s in rsu_spawns]
    return protocol


def write_scenario(split_dir: UPath, config: SynthConfig, scenario_seed: int = 0) -> ScenarioTruth:
    """Write one scenario into ``split_dir``; return its truth."""
    rng = np.random.default_rng([config.seed, scenario_seed])
    road = Road(
        np.array([rng.uniform(-300, 300), rng.uniform(-400, 400)]),
        float(rng.uniform(-180, 180)),
        float(rng.choice([-1, 1]) * rng.uniform(1 / 600, 1 / 300)),
    )
    ids = rng.choice(np.arange(100, 9999), size=config.cavs + 12, replace=False).tolist()
    lincoln = (src.CAV_BOX_EXTENT_M, src.CAV_BOX_CENTER_M)
    cavs = [
        Actor(ids[i], 1.75 * (i % 2), -8.0 + 14.0 * i, 8.0, *lincoln, int(rng.integers(60, 250)))
        for i in range(config.cavs)
    ]
    others = []
    for j in range(config.cavs, config.cavs + 12):
        moving = j % 3 != 0
        extent = (float(rng.uniform(2.0, 2.6)), float(rng.uniform(0.9, 1.1)), float(rng.uniform(0.7, 0.9)))
        lane = float(rng.choice([-1.75, 0.0, 1.75])) if moving else float(rng.choice([-5.0, 6.5]))
        others.append(
            Actor(
                ids[j],
                lane,
                float(rng.uniform(-60, 80)),
                float(rng.uniform(4, 12)) if moving else 0.0,
                extent,
                (0.0, 0.0, extent[2]),
                int(rng.integers(20, 250)),
            )
        )
    span_s = config.frames * config.key_step * config.fixed_delta_seconds
    others = clear_of_cavs(others, cavs, span_s)
    if config.close_range:
        close_rng = np.random.default_rng([config.seed, scenario_seed, 1])  # the rest of the scenario unchanged
        free = np.setdiff1d(np.arange(100, 9999), ids)
        close = close_to(cavs[0], CAMERA_MOUNTS[0][0], close_rng.choice(free, 2, replace=False).tolist(), close_rng)
        others = clear_of(others, close, span_s) + close
    if config.opencda_format:  # CARLA's actors: float32 sizes, the boxes the lidar hits and the YAML labels
        cavs, others = ([_float32_actor(a) for a in actors] for actors in (cavs, others))
    pillars, buildings = [], []
    for s in np.arange(-40.0, 80.0, 9.0):
        for side in (-1, 1):
            xyz, yaw = road.at(float(s) + rng.uniform(-2, 2), side * 8.5)
            pillars.append(xyz + np.array([0, 0, PILLAR_DIMS_M[2] / 2]))
            xyz_b, yaw_b = road.at(float(s), side * 18.0)
            buildings.append(
                Box(
                    xyz_b + np.array([0, 0, 6.0]),
                    np.zeros(3),
                    carla_rotation(np.array([0, yaw_b, 0])),
                    np.array([9.0, 5.0, 12.0]),
                    "BUILDING",
                    "",
                    int(rng.integers(10, 40)),
                )
            )
    pillar_boxes = [Box(p, np.zeros(3), np.eye(3), np.array(PILLAR_DIMS_M), "PILLAR", "", 230) for p in pillars]
    rsu_positions = [road.at(25.0 + 30.0 * k, -11.0)[0] for k in range(config.n_infrastructure)]

    scenario = _scenario_name(rng)
    scenario_dir = split_dir / scenario
    keys = [f"{config.first_key + config.key_step * i:06d}" for i in range(config.frames)]
    agent_ids = [str(c.actor_id) for c in cavs] + [str(-(k + 1)) for k in range(config.n_infrastructure)]
    truth = ScenarioTruth(
        scenario_dir,
        scenario,
        keys,
        config.fixed_delta_seconds,
        np.array(pillars),
        {a: AgentTruth(a) for a in agent_ids},
        {act.actor_id: act.speed_mps for act in cavs + others},
    )
    for a in agent_ids:
        (scenario_dir / a).mkdir(parents=True, exist_ok=True)
    protocol = _protocol(config, [], [[0.0] * 6] if config.n_infrastructure else [])
    rays = {
        False: _lidar_rays(protocol["vehicle_base"]["sensing"]["perception"]["lidar"], config.fixed_delta_seconds),
        True: _lidar_rays(
            protocol["scenario"]["rsu_list"][0]["sensing"]["perception"]["lidar"], config.fixed_delta_seconds
        )
        if config.n_infrastructure
        else None,
    }
    K = [[FOCAL_PX, 0.0, WIDTH / 2], [0.0, FOCAL_PX, HEIGHT / 2], [0.0, 0.0, 1.0]]
    tick0 = config.first_key * config.fixed_delta_seconds
    cav_spawns = [_floats(actor_pose(road, c, 0.0, False)) for c in cavs]
    rsu_spawns = [_floats([*p[:2], RSU_LIDAR_HEIGHT_M, 0, 0, 0]) for p in rsu_positions]
    written = _protocol(config, cav_spawns, rsu_spawns)
    for cav in written["scenario"]["single_cav_list"]:
        cav["sensing"]["perception"]["lidar"] = {**cav["sensing"]["perception"]["lidar"], **dict(config.protocol_lidar)}
    if config.protocol:
        (scenario_dir / "data_protocol.yaml").write_bytes(_yaml(written, config))

    for key in keys:
        t_s = int(key) * config.fixed_delta_seconds - tick0
        vehicle_pose = {c.actor_id: actor_pose(road, c, t_s, True) for c in cavs + others}
        if config.opencda_format:  # CARLA's float32 actor transforms
            vehicle_pose = {a: _float32(p) for a, p in vehicle_pose.items()}
        T_vehicle = {a: carla_pose_matrix(p) for a, p in vehicle_pose.items()}
        actor_boxes = [actor_box(T_vehicle[c.actor_id], c, "VEHICLE", config.shapes) for c in cavs + others]
        actors = cavs + others
        for agent_id in agent_ids:
            infra = int(agent_id) < 0
            if infra:
                position = rsu_positions[-int(agent_id) - 1]
                T_lidar_world = np.eye(4)
                T_lidar_world[:3, 3] = [position[0], position[1], RSU_LIDAR_HEIGHT_M]
                T_base_world = T_lidar_world  # camera offsets are added to the RSU (lidar) position
                pitch, own = RSU_CAMERA_PITCH_DEG, None
                true_ego = _carla([*position[:2], RSU_LIDAR_HEIGHT_M, 0, 0, 0], config)
            else:
                own = int(agent_id)
                T_base_world = T_vehicle[own]
                T_lidar_world = T_base_world @ carla_pose_matrix(np.array([*CAV_LIDAR_M, 0, 0, 0]))
                pitch = 0.0
                true_ego = _carla(vehicle_pose[own], config)
            boxes = [b for b, act in zip(actor_boxes, actors, strict=True) if act.actor_id != own]
            box_actor = [act.actor_id for act in actors if act.actor_id != own]
            scene = Scene(None, boxes + pillar_boxes + buildings)
            box_rgb = np.array(
                [own_colour(a) for a in box_actor] + [PILLAR_RGB] * len(pillar_boxes) + [BUILDING_RGB] * len(buildings),
                dtype=np.uint8,
            )
            rays_lidar = rays[infra]
            origins = np.broadcast_to(T_lidar_world[:3, 3], rays_lidar.shape)
            directions = rays_lidar @ T_lidar_world[:3, :3].T
            no_time = np.zeros(len(rays_lidar))
            rng_m, intensity, index = cast_rays(origins, directions, no_time, scene, LIDAR_RANGE_M, ground_z_m=0.0)
            hit = np.isfinite(rng_m)
            if config.lidar_dropoff_rate:  # drop-off leaves holes in the grid
                hit &= rng.random(len(hit)) >= config.lidar_dropoff_rate
            if config.lidar_noise_stddev:  # range noise moves points along their rays
                rng_m = rng_m + rng.normal(0.0, config.lidar_noise_stddev, len(rng_m))
            xyz = (rays_lidar[hit] * rng_m[hit, None]).astype(np.float32)
            if config.grid_share:  # a few points exactly on round coordinates (x = k * 0.1 m as float32)
                on_grid = rng.random(len(xyz)) < config.grid_share
                xyz[on_grid, 0] = (np.round(xyz[on_grid, 0].astype(np.float64) * 10.0) / 10.0).astype(np.float32)
            intensity = intensity[hit]
            lookup = np.array(box_actor + [-2] * len(pillar_boxes) + [-3] * len(buildings) + [-1], dtype=np.int64)
            hit_actor = lookup[index[hit]]  # index -1 (ground) takes the last entry
            stored = intensity if config.pcd_fields == "rgb" else intensity.astype(np.float32) / np.float32(255.0)
            write_pcd(scenario_dir / agent_id / f"{key}.pcd", xyz, stored, config.pcd_fields, config.pcd_binary)
            # labels: vehicles hit by >= 1 ray within range, except the agent itself (OpenCDA)
            seen = set(hit_actor[hit_actor >= 0].tolist())
            vehicles = {}
            for act in actors:
                if act.actor_id in seen:
                    p = vehicle_pose[act.actor_id]
                    vehicles[act.actor_id] = {
                        "location": _carla(p[:3], config),
                        "angle": _carla(p[3:], config),
                        "center": _carla(act.center_m, config),
                        "extent": _carla(act.extent_m, config),
                        "speed": float(act.speed_mps * 3.6),
                    }
            lidar_pose = _carla(carla_pose_list(T_lidar_world), config)
            frame = {
                "lidar_pose": lidar_pose,
                "true_ego_pos": true_ego,
                "predicted_ego_pos": _predicted(true_ego, rng, config),
                "ego_speed": 0.0 if infra else 8.0 * 3.6,
                "vehicles": vehicles,
            }
            if config.dataset == "v2xset":
                frame["RSU"] = infra
            if not infra:
                frame["plan_trajectory"] = [[*_floats(road.at(s, 0.0)[0][:2]), 28.8] for s in (10.0, 20.0)]
            markers: dict[int, dict[int, tuple[float, float]]] = {}
            for index_cam, (mx, my, mz, yaw) in enumerate(CAMERA_MOUNTS if config.cameras else ()):
                T_cam_world = T_base_world @ carla_pose_matrix(np.array([mx, my, mz, 0.0, yaw, pitch]))
                uv, front = project_ue4(T_cam_world, truth.pillars_m)
                png, shows = render_png(scene, box_rgb, T_cam_world, config.render_step)
                (scenario_dir / agent_id / f"{key}_camera{index_cam}.png").write_bytes(png)
                inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < WIDTH) & (uv[:, 1] >= 0) & (uv[:, 1] < HEIGHT)
                visible = [p for p in np.flatnonzero(inside) if shows_around(shows, uv[p], len(boxes) + p)]
                markers[index_cam] = {int(p): (float(uv[p, 0]), float(uv[p, 1])) for p in visible}
                cords = _carla(carla_pose_list(T_cam_world), config)
                # lidar -> camera: OpenCDA's, from the poses as written (CARLA's float32 transforms)
                T_cam, T_lidar = (
                    (T_cam_world, T_lidar_world)
                    if not config.opencda_format
                    else (
                        carla_pose_matrix(np.array(cords)),
                        carla_pose_matrix(np.array(lidar_pose)),
                    )
                )
                extrinsic = np.linalg.inv(T_cam) @ T_lidar
                frame[f"camera{index_cam}"] = {
                    "cords": cords,
                    "intrinsic": [list(r) for r in K],
                    "extrinsic": [_floats(row) for row in extrinsic],
                }
            (scenario_dir / agent_id / f"{key}.yaml").write_bytes(_yaml(frame, config))
            agent_truth = truth.agents[agent_id]
            agent_truth.lidar_pose[key] = frame["lidar_pose"]
            agent_truth.n_points[key] = len(xyz)
            agent_truth.markers[key] = markers
            if config.keep_truth:
                agent_truth.hit_actor[key] = hit_actor
                agent_truth.intensity_u8[key] = intensity
                xyz_world = xyz.astype(np.float64) @ T_lidar_world[:3, :3].T + T_lidar_world[:3, 3]
                agent_truth.point_rgb[key] = surface_rgb(box_rgb, index[hit], xyz_world, np.ones(len(xyz), bool))
                agent_truth.scenes[key] = (scene, lookup[:-1])
                agent_truth.T_cam_world[key] = {
                    i: T_base_world @ carla_pose_matrix(np.array([mx, my, mz, 0.0, yaw, pitch]))
                    for i, (mx, my, mz, yaw) in enumerate(CAMERA_MOUNTS if config.cameras else ())
                }
    return truth


def write_dataset(root: UPath, config: SynthConfig, scenarios: int = 1) -> list[ScenarioTruth]:
    """``scenarios`` scenarios under ``<root>/<split>/``."""
    return [write_scenario(UPath(root) / config.split, config, k) for k in range(scenarios)]
