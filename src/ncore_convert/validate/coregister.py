"""Cooperative scenarios: do the agents co-register in ``world_global``?

At a few frames every agent shares, each agent's lidar points are taken to ``world_global``
through its own sequence's pose graph (default poses). Structure above the ground (ground: the
lowest point of each GROUND_CELL_M cell) that both agents see (within OVERLAP_RANGE_M of both
lidars) must land on the other agent's points as well as under any nearby wrong registration (shifts of
0.5-2 m, yaws of 1-5 degrees about the agent's lidar) does: the fraction of structure points within
MATCH_M of the other agent's must be at least MIN_RATIO of the best alternative's. This makes the
test independent of point density and viewpoint (a roadside unit sees roofs a car sees the sides
of). Ground is left out because a horizontal shift of a flat ground still lands on ground.

The agents are compared at the same frame end, but not at the same instant: each ray has its own
time in a sweep, and two lidars sweep a moving car at different phases (a car at 10 m/s moves 1 m
in a 100 ms sweep), so the movers' points would pull towards a wrong registration. Points whose
stored ``dynamic_flag`` is 1 (inside a moving track's box grown by 0.5 m) are therefore left out; a
sequence without the flag is compared whole, and the line says so.

Each fraction is a sample of the scan columns that hit shared structure: the points of one column
lie on one surface and rise and fall together. The comparison decides only when both agents'
shared structure is dense (median horizontal spacing of its columns at most MAX_SPACING_M, finer
than the smallest alternative shift); a few sparse columns (a low-resolution lidar far away) are
too few independent samples, and the line says it was not decisive.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ncore.data.v4 import SequenceLoaderV4
from scipy.spatial import cKDTree
from upath import UPath

from ncore_convert import contract
from ncore_convert.contract import ScenarioManifest
from ncore_convert.sources import opencood as ocd
from ncore_convert.transforms.sampling import spread_indices
from ncore_convert.validate.readback import open_sequence, read_manifest, world_points
from ncore_convert.validate.report import Report

FRAMES = 3  #: common frames compared, spread over the scenario
OVERLAP_RANGE_M = 50.0
GROUND_CELL_M = 2.0
ABOVE_GROUND_M = 0.3
MATCH_M = 0.3  #: a point lands on the other agent's structure within this distance
SHIFTS_M = (0.5, 1.0, 2.0)  #: alternative registrations: shifts ...
YAWS_DEG = (1.0, 2.0, 5.0)  #: ... and yaws about the agent's lidar
MIN_RATIO = 0.85  #: the registration must score at least this fraction of the best alternative
MIN_POINTS = 200  #: fewer shared structure points than this: not decisive
MAX_SPACING_M = 0.2  #: sparser shared structure than this (median horizontal point spacing) is not decisive


@dataclass(frozen=True)
class AgentLidar:
    """One agent's lidar as a sequence holds it."""

    agent_id: str
    sequence_json: UPath
    loader: SequenceLoaderV4
    lidar_id: str

    def static_points(self, frame_end_us: int) -> tuple[np.ndarray, np.ndarray, bool]:
        """The frame's points in ``world_global`` (float64 [N,3]) without those flagged dynamic, the
        lidar's position there (float64 [3]), and whether the frame carried the flag."""
        frame = self.frame_ending_at(frame_end_us)
        xyz_m, origin_m = world_points(self.loader, self.lidar_id, frame, "world_global")
        source = self.loader.get_point_clouds_source(self.lidar_id)
        if not source.has_pc_generic_data(frame, contract.DYNAMIC_FLAG):
            return xyz_m, origin_m, False
        dynamic = np.asarray(source.get_pc_generic_data(frame, contract.DYNAMIC_FLAG)) == 1
        if len(dynamic) != len(xyz_m):  # "dynamic_flag per ray" reports the mismatch
            return xyz_m, origin_m, False
        return xyz_m[~dynamic], origin_m, True

    def frame_ends_us(self) -> np.ndarray:
        return self.loader.get_lidar_sensor(self.lidar_id).frames_timestamps_us[:, 1]

    def frame_ending_at(self, frame_end_us: int) -> int:
        return int(np.flatnonzero(self.frame_ends_us() == frame_end_us)[0])


def scenario_lidars(manifest_path: UPath, manifest: ScenarioManifest) -> list[AgentLidar]:
    """Every written agent's lidar, from ``scenario.json`` (either layout), the OpenCOOD ego first."""
    folder = UPath(manifest_path).parent
    loaders: dict[str, SequenceLoaderV4] = {}  # one per sequence: the scenario layout shares one
    lidars = []
    for agent in manifest.agents:
        if not agent.written or ocd.LIDAR not in agent.sensors:
            continue
        sequence = folder / manifest.sequence_of(agent)
        if str(sequence) not in loaders:
            loaders[str(sequence)] = open_sequence(sequence).loader
        lidar_id = manifest.prefix_of(agent) + ocd.LIDAR
        lidars.append(AgentLidar(str(agent.agent_id), sequence, loaders[str(sequence)], lidar_id))
    ego = str(manifest.ego_agent_id)
    return sorted(lidars, key=lambda a: a.agent_id != ego)


def structure_mask(xyz_m: np.ndarray) -> np.ndarray:
    """Points more than ABOVE_GROUND_M above the lowest point of their GROUND_CELL_M cell, bool [N]
    (``xyz_m``: float64 [N,3], z up)."""
    cells = np.floor(xyz_m[:, :2] / GROUND_CELL_M).astype(np.int64)
    _, cell = np.unique(cells, axis=0, return_inverse=True)
    ground = np.full(cell.max() + 1 if len(cell) else 0, np.inf)
    np.minimum.at(ground, cell, xyz_m[:, 2])
    return xyz_m[:, 2] > ground[cell] + ABOVE_GROUND_M


def horizontal_spacing_m(xyz_m: np.ndarray) -> float:
    """Median distance (m) from each point's ground position to the nearest other one, float64 [N,3] in;
    points stacked in one vertical scan column count once (a lidar's rows are close, its columns not)."""
    columns = np.unique(np.round(xyz_m[:, :2] / 0.05).astype(np.int64), axis=0) * 0.05
    if len(columns) < 2:
        return float("inf")
    return float(np.median(cKDTree(columns).query(columns, k=2)[0][:, 1]))


def _alternatives() -> list[tuple[str, np.ndarray]]:
    """Nearby wrong registrations of one agent: (label, 4x4 about the agent's lidar) for shifts of
    SHIFTS_M in 8 directions and yaws of ±YAWS_DEG."""
    out = []
    for r in SHIFTS_M:
        for k in range(8):
            T = np.eye(4)
            T[:2, 3] = r * np.cos(k * np.pi / 4), r * np.sin(k * np.pi / 4)
            out.append((f"{T[0, 3]:+.1f} m x, {T[1, 3]:+.1f} m y", T))
    for deg in YAWS_DEG:
        for sign in (1, -1):
            T = np.eye(4)
            c, s = np.cos(np.radians(sign * deg)), np.sin(np.radians(sign * deg))
            T[:2, :2] = [[c, -s], [s, c]]
            out.append((f"{sign * deg:+g} deg yaw", T))
    return out


ALTERNATIVES = _alternatives()


@dataclass(frozen=True)
class Peak:
    """How well agent A's shared structure lands on B's as registered, against nearby alternatives."""

    overlap: float  #: fraction of A's shared structure points within MATCH_M of one of B's
    best_alternative: float  #: the same fraction under the best alternative registration
    best_label: str
    points: int
    spacing_m: float  #: median horizontal spacing of the sparser agent's shared structure columns

    @property
    def decisive(self) -> bool:
        return self.spacing_m <= MAX_SPACING_M

    @property
    def ratio(self) -> float:
        return self.overlap / self.best_alternative if self.best_alternative > 0 else np.inf


def registration_peak(a_xyz: np.ndarray, a_origin: np.ndarray, b_xyz: np.ndarray, b_origin: np.ndarray) -> Peak | None:
    """Agent A's structure on agent B's, as registered and under each of ALTERNATIVES.

    Args:
        a_xyz, b_xyz: the agents' points at one instant, world_global, float64 [N,3] (z up).
        a_origin, b_origin: the lidars' positions, world_global, float64 [3].

    Returns:
        None when either agent has fewer than MIN_POINTS shared structure points.
    """
    structure = structure_mask(np.concatenate([a_xyz, b_xyz]))
    a_struct, b_struct = a_xyz[structure[: len(a_xyz)]], b_xyz[structure[len(a_xyz) :]]

    def shared(xyz: np.ndarray) -> np.ndarray:
        near_a = np.linalg.norm(xyz - a_origin, axis=1) <= OVERLAP_RANGE_M
        return xyz[near_a & (np.linalg.norm(xyz - b_origin, axis=1) <= OVERLAP_RANGE_M)]

    a_shared, b_shared = shared(a_struct), shared(b_struct)
    if len(a_shared) < MIN_POINTS or len(b_shared) < MIN_POINTS:
        return None
    spacing = max(horizontal_spacing_m(b_shared), horizontal_spacing_m(a_shared))
    if spacing > MAX_SPACING_M:  # too few independent columns to resolve the alternatives
        return Peak(float("nan"), float("nan"), "", len(a_shared), spacing)
    tree = cKDTree(b_shared)
    local = a_shared - a_origin

    def overlap(T: np.ndarray) -> float:
        moved = local @ T[:3, :3].T + T[:3, 3] + a_origin
        return float(np.mean(tree.query(moved, k=1, distance_upper_bound=MATCH_M)[0] <= MATCH_M))

    scores = [(overlap(T), label) for label, T in ALTERNATIVES]
    best, label = max(scores)
    return Peak(overlap(np.eye(4)), best, label, len(a_shared), spacing)


def check_coregistration(manifest_path: UPath) -> Report:
    """Compare every agent with the OpenCOOD ego (or the first agent, when the ego was not written)
    at FRAMES common frames."""
    report = Report(str(manifest_path))
    try:
        lidars = scenario_lidars(manifest_path, read_manifest(manifest_path))
    except Exception as err:  # noqa: BLE001 - any failure to open is the finding
        report.add("co-registration: sequences open", False, f"{type(err).__name__}: {err}".splitlines()[0])
        return report
    if len(lidars) < 2:
        report.add("co-registration", True, f"{len(lidars)} agent(s) with a lidar: nothing to compare")
        return report
    reference = lidars[0]
    for other in lidars[1:]:
        common = np.intersect1d(reference.frame_ends_us(), other.frame_ends_us())
        name = f"co-registration: agent {other.agent_id} on agent {reference.agent_id}"
        if not len(common):
            report.add(name, False, "no common frame time")
            continue
        picks = common[spread_indices(len(common), FRAMES)]
        peaks, flagged = [], True
        for t in picks:
            a_xyz, a_origin, a_flagged = other.static_points(int(t))
            b_xyz, b_origin, b_flagged = reference.static_points(int(t))
            flagged &= a_flagged and b_flagged
            if (peak := registration_peak(a_xyz, a_origin, b_xyz, b_origin)) is not None:
                peaks.append(peak)
        movers = "dynamic points left out" if flagged else "no dynamic_flag: moving objects compared too"
        if not peaks:
            report.add(name, True, f"fewer than {MIN_POINTS} shared structure points ({movers}): not decisive")
            continue
        if not any(p.decisive for p in peaks):
            spacing = min(p.spacing_m for p in peaks)
            report.add(
                name,
                True,
                f"shared structure too sparse to decide (column spacing {spacing:.2f} m > {MAX_SPACING_M} m; {movers})",
            )
            continue
        peaks = [p for p in peaks if p.decisive]
        worst = min(peaks, key=lambda p: p.ratio)
        report.add(
            name,
            worst.ratio >= MIN_RATIO,
            f"{worst.overlap:.0%} of {worst.points} shared structure points land within {MATCH_M} m;"
            f" best nearby alternative ({worst.best_label}) {worst.best_alternative:.0%}"
            f" (worst of {len(peaks)} frame(s); must be >= {MIN_RATIO:.0%} of it; {movers})",
        )
    return report
