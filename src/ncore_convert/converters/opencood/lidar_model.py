"""OPV2V / V2XSet: each agent's lidar model, decided at planning (docs/lidar-model.md): from its
``data_protocol.yaml`` block when a few of its frames fit it, else measured from the points, else none
(raw rays only), with the metadata that says which and why."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ncore_convert.converters.opencood.records import AgentPlan, OpenCoodOptions
from ncore_convert.errors import SourceError
from ncore_convert.sources import opencood as src
from ncore_convert.sources.reader import Reader
from ncore_convert.transforms import carla
from ncore_convert.transforms.lidar import carla as carla_lidar
from ncore_convert.transforms.lidar.rays import MIN_RANGE_M
from ncore_convert.transforms.sampling import spread_indices

#: Frames per agent checked against its protocol lidar block.
MODEL_FRAMES = 3
#: The data disagree with the protocol when the 99th percentile of the distance to the nearest
#: laser exceeds this (real OPV2V: 0.0007 deg, the float32 floor about 0.003 deg) ...
RING_TOLERANCE_DEG = 0.02
#: ... or the distance to the nearest azimuth column (or the frames' grid phases) this, in columns.
COLUMN_TOLERANCE = 0.25


def with_lidar_model(
    agent: AgentPlan,
    protocol: src.Protocol,
    options: OpenCoodOptions,
    scenario: str,
    warnings: list[str],
    reader: Reader,
) -> AgentPlan:
    """The agent's lidar model: from its protocol block (the CAVs', or its infrastructure unit's)
    when a few of its frames fit it; else, when the block is missing, unusable or disagrees with the
    data (a warning says which), measured from the points (``carla_lidar.fit_from_points``); else,
    or with ``--lidar-model-source none``, raw rays only."""
    if not agent.lidar_ids:
        return agent
    if options.lidar_model_source == "none":
        return replace(agent, lidar_model_meta={"lidar_model_source": "none"})
    directions = _model_frames(agent, reader)
    if not directions:
        return _no_model(agent, scenario, "no readable lidar frame to derive it from", warnings)
    block = protocol.lidar_of(agent.agent_id)
    spec, why = None, "data_protocol.yaml has no lidar block for this agent"
    if block:
        try:
            spec = carla_lidar.CarlaLidarSpec.from_protocol(block, protocol.fixed_delta_seconds)
            carla_lidar.model(spec, 0.0)  # one revolution per tick, else ValueError
        except ValueError as err:
            spec, why = None, f"data_protocol.yaml: {err}"
    if spec is not None:
        fit = carla_lidar.fit_to_data(directions, spec)
        if _fits(fit):
            return _modelled(agent, spec, fit, "protocol", len(directions), {})
        why = f"the lidar data disagree with data_protocol.yaml: {_figures(fit, spec)}"
    try:
        measured = carla_lidar.fit_from_points(directions, protocol.fixed_delta_seconds, spec)
    except ValueError as err:
        return _no_model(agent, scenario, f"{why}; not measurable from the points either ({err})", warnings)
    if not _fits(measured.fit):
        figures = _figures(measured.fit, measured.spec)
        return _no_model(
            agent, scenario, f"{why}; the grid measured from the points does not fit either: {figures}", warnings
        )
    found = measured.spec
    warnings.append(
        f"{agent.agent_dir}: scenario {scenario}: {why}; lidar model from the points: {found.channels} lasers"
        f" {found.upper_fov_deg:+.3f} to {found.lower_fov_deg:+.3f} deg, {found.points_per_channel} columns"
        f" (ring residual {measured.fit.ring_residual_deg:.4f} deg, column residual {measured.fit.column_residual:.3f})"
    )
    extra = {
        "protocol_disagreement": why,
        "protocol_said": {k: block[k] for k in carla_lidar.PROTOCOL_KEYS if k in block} if block else None,
        "fov_source": measured.fov_source,
        "rings_with_returns": measured.rings_seen,
        "ring_step_deg": round(measured.ring_step_deg, 6),
        "ring_grid_residual_deg": round(measured.ring_grid_residual_deg, 6),
    }
    return _modelled(agent, found, measured.fit, "points", len(directions), extra)


def _model_frames(agent: AgentPlan, reader: Reader) -> list[np.ndarray]:
    """Unit rays (right-handed lidar frame, [N,3]) of a few of the agent's frames (unreadable ones
    are left out here and reported when the frame is written)."""
    directions = []
    for key in [agent.keys[i] for i in spread_indices(len(agent.keys), MODEL_FRAMES)]:
        try:
            sweep = src.fetch_points(agent.agent_dir, key, agent.files, reader)
        except SourceError:
            continue
        xyz = carla.points_right_handed(sweep.xyz_m.astype(np.float64))
        distance = np.linalg.norm(xyz, axis=1)
        ok = np.isfinite(distance) & (distance >= MIN_RANGE_M)
        if ok.any():
            directions.append(xyz[ok] / distance[ok, None])
    return directions


def _fits(fit: carla_lidar.DataFit) -> bool:
    return (
        fit.ring_residual_deg <= RING_TOLERANCE_DEG
        and fit.column_residual <= COLUMN_TOLERANCE
        and fit.phase_spread_columns <= COLUMN_TOLERANCE
    )


def _figures(fit: carla_lidar.DataFit, spec: carla_lidar.CarlaLidarSpec) -> str:
    return (
        f"ring residual {fit.ring_residual_deg:.4f} deg (limit {RING_TOLERANCE_DEG}), column residual"
        f" {fit.column_residual:.3f} and phase spread {fit.phase_spread_columns:.3f} columns (limit"
        f" {COLUMN_TOLERANCE}) against {spec.channels} channels x {spec.points_per_channel} columns"
    )


def _modelled(
    agent: AgentPlan, spec: carla_lidar.CarlaLidarSpec, fit: carla_lidar.DataFit, source: str, frames: int, extra: dict
) -> AgentPlan:
    """The agent with the model of ``spec`` at the fitted phase, and its metadata (``source``:
    ``protocol`` or ``points``; ``extra``: what the points fit adds)."""
    derivation = {
        "protocol": "CARLA ray-cast lidar from data_protocol.yaml (channels, upper_fov, lower_fov, rotation_frequency,"
        " points_per_second, world.fixed_delta_seconds); azimuth phase from the data",
        "points": "CARLA ray-cast lidar measured from the points: lasers = clusters of elevation on a uniform grid"
        " (step and top laser by a line through their medians), columns = 360 deg over the step between a laser's"
        " neighbouring returns (refined to the best-fitting count), one revolution per tick, phase from the data",
    }[source]
    meta = {
        "lidar_model_source": "empirical",
        "lidar_model": {
            "model_source": source,
            "derivation": derivation,
            "protocol_block": "rsu_list" if src.is_infrastructure(agent.agent_id) else "single_cav_list",
            "rows": spec.channels,
            "upper_fov_deg": round(spec.upper_fov_deg, 6),
            "lower_fov_deg": round(spec.lower_fov_deg, 6),
            "columns": spec.points_per_channel,
            "column_step_deg": 360.0 / spec.points_per_channel,
            "column0_azimuth_deg": round(float(np.degrees(fit.phase_rad)), 6),
            "spinning_direction": "cw (CARLA's azimuth increases in its left-handed frame)",
            "checked_frames": frames,
            "ring_residual_p99_deg": round(fit.ring_residual_deg, 6),
            "column_residual_p99": round(fit.column_residual, 6),
            "phase_spread_columns": round(fit.phase_spread_columns, 6),
            **extra,
            "frame_time": "every ray of a frame has the tick's timestamp and the frame spans [t, t]: NCore's"
            " column time (column / (n_columns - 1) of the frame) is the tick for every column, as CARLA casts"
            " all of a tick's rays against one world state",
            "element_assignment": "row: nearest laser elevation; column: nearest azimuth of the grid",
        },
    }
    return replace(agent, lidar_model=carla_lidar.model(spec, fit.phase_rad), lidar_model_meta=meta)


def _no_model(agent: AgentPlan, scenario: str, why: str, warnings: list[str]) -> AgentPlan:
    warnings.append(f"{agent.agent_dir}: scenario {scenario}: no lidar model ({why}); raw rays only")
    return replace(agent, lidar_model_meta={"lidar_model_source": "none", "lidar_model_fallback": why})
