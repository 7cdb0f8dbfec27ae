"""What the synthetic AV2/TbV generator (:mod:`.argoverse2`) is asked for (:class:`SynthConfig`) and
the truth it keeps of a log it wrote (:class:`SynthTruth`, :class:`SweepTruth`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from upath import UPath

from ncore_convert.sources import argoverse2 as av2
from ncore_convert.synth.ego import N_PICTURES
from ncore_convert.synth.scene import Scene

MAX_RANGE_M = 200.0  #: the simulated lidar's and renderer's reach


@dataclass(frozen=True)
class SynthConfig:
    seconds: float = 2.0
    seed: int = 0
    swap_lidar_halves: bool = False
    camera_fps: float = 20.0
    keep_truth: bool = False
    tbv: bool = False  #: write a TbV log (see the module docstring)
    #: a TbV log with an annotations.feather all the same (TbV has none): the converter's handling of one
    tbv_annotations: bool = False
    #: the first part of the log (a fraction, 0..1) in which the cameras' world stands still (the
    #: car parked): every image there is the same picture but for the body's lighting
    parked_fraction: float = 0.0
    #: how the ego body is rendered: ``realistic`` (reflections, lighting, markings, glare,
    #: camouflaged silhouette), ``easy`` (still paint under ±5 % light) or ``glossy`` (realistic,
    #: with strong reflections); see ``synth.ego``
    ego_body: str = "realistic"
    #: the cameras' light: ``day``, or ``night`` (a dark world lit by moving lamps); see ``synth.ego``
    light: str = "day"
    #: moving shadows across the pictures (body included); see ``synth.ego``
    shadows: bool = False
    #: distinct pictures per camera that its images cycle through (the ego-mask tests and sweep use
    #: 32, as many as the estimator samples)
    pictures: int = N_PICTURES
    #: write the images of these cameras only (None: all; every camera is calibrated either way)
    image_cameras: tuple[str, ...] | None = None
    #: write the lidar sweeps and annotations (False: cameras, poses and calibration only, as the
    #: ego-mask sweep benchmark needs)
    sweeps: bool = True
    #: the cameras' pictures: ``pattern`` (a few textured pictures per camera, cycled: cheap) or
    #: ``render`` (each picture ray-cast from the scene the lidar sees at its own time, flat-shaded,
    #: the ego body painted flat: one world, ~0.2 s per picture)
    world: str = "pattern"
    #: every camera's size and focal length divided by this (the same field of view, pixels binned:
    #: ``synth.ego.pictures``): a picture then costs about 1/scale² as much to make, write and
    #: decode. The tests use 4 where no check depends on the pixel count, 2 for the AV2 ego-mask logs
    #: (docs/tests.md says which keep the real size, and why)
    camera_scale: int = 1
    #: vehicles, pedestrians and cyclists shaped inside their boxes, and cyclists on the road
    #: (``synth.shapes``; ``synth.scene.make_scene``)
    shapes: bool = False
    #: a car just ahead of the ego and one alongside it, at its speed (``synth.scene.make_scene``)
    close_range: bool = False
    #: nothing moves through a standing object: parked cars stand clear of the moving cars, pedestrians
    #: who would walk through one are left out (``synth.scene.make_scene``). False writes the old
    #: overlapping traffic (cars through parked cars), for a test that wants fused objects on purpose
    clear_paths: bool = True

    @property
    def cameras(self) -> tuple[str, ...]:
        return av2.RING_CAMERAS if self.tbv else av2.CAMERAS


@dataclass
class SweepTruth:
    """Simulated raw returns of one sweep, in the feather file's row order.

    Attributes:
        unit: 0 for up_lidar, 1 for down_lidar, int8 [N]; laser_number: as written, uint8 [N].
        direction_sensor: unit ray directions in the unit's own frame at firing time, float64 [N,3].
        distance_m: true range, float64 [N].
        time_ns: absolute firing time, int64 [N].
        box_index: the scene box each return hit (index into ``scene.boxes``), -1 for the ground, int64 [N].
    """

    timestamp_ns: int
    offset_ns: np.ndarray
    unit: np.ndarray | None = None
    laser_number: np.ndarray | None = None
    direction_sensor: np.ndarray | None = None
    distance_m: np.ndarray | None = None
    time_ns: np.ndarray | None = None
    box_index: np.ndarray | None = None


@dataclass
class SynthTruth:
    log_dir: UPath
    log_id: str
    t0_ns: int
    scene: Scene
    T_sensor_ego: dict[str, np.ndarray]
    sweeps: list[SweepTruth] = field(default_factory=list)
    image_paths: list[UPath] = field(default_factory=list)
    n_cuboids: int = 0
    ego_masks: dict[str, np.ndarray] = field(default_factory=dict)  #: camera -> true ego pixels, bool [H,W]
    #: camera -> (focal length, cx, cy) in px, AV2's convention (pixel centres at integers)
    intrinsics: dict[str, tuple[float, float, float]] = field(default_factory=dict)

    @property
    def n_images(self) -> int:
        return len(self.image_paths)

    def T_ego_city(self, timestamps_ns: np.ndarray) -> np.ndarray:
        return self.scene.ego.T_ego_city((np.asarray(timestamps_ns) - self.t0_ns) * 1e-9)

    def sweep_returns(self, k: int, moving_mps: float = 0.2) -> dict[str, np.ndarray]:
        """Sweep ``k``'s returns as the lidar measured them (a log written with ``keep_truth``): ``xyz_m``
        (city frame) and ``origin_m`` (where the unit was as it fired), float64 [N,3]; ``unit`` and
        ``beam`` (laser_number), [N]; ``moving``: the object it hit moved faster than ``moving_mps``
        at the return's own time, bool [N]."""
        sweep = self.sweeps[k]
        t_s = (sweep.time_ns - self.t0_ns) * 1e-9
        T_ego_city = self.scene.ego.T_ego_city(t_s)
        xyz_m, origin_m = np.zeros((len(t_s), 3)), np.zeros((len(t_s), 3))
        for u, unit in enumerate(av2.LIDARS):
            m = sweep.unit == u
            T = T_ego_city[m] @ self.T_sensor_ego[unit]
            local = sweep.direction_sensor[m] * sweep.distance_m[m, None]
            xyz_m[m] = np.einsum("nij,nj->ni", T[:, :3, :3], local) + T[:, :3, 3]
            origin_m[m] = T[:, :3, 3]
        speed = np.zeros(len(t_s))
        for b in np.unique(sweep.box_index[sweep.box_index >= 0]):
            m = sweep.box_index == b
            speed[m] = self.scene.boxes[b].speed_mps(t_s[m])
        return {
            "xyz_m": xyz_m,
            "origin_m": origin_m,
            "unit": sweep.unit,
            "beam": sweep.laser_number,
            "moving": speed > moving_mps,
        }
