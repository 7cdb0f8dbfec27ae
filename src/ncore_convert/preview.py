"""``ncore-convert preview``: pictures of a converted sequence or cooperative scenario.

- Lidar points projected into every camera at one frame, coloured by range. Motion-aware: each
  point is taken to ``world`` at its own timestamp, and projected with the camera's rolling-shutter
  poses (the camera model and poses are NCore's, read through ``SequenceLoaderV4``).
- A bird's-eye view of the lidar with the cuboids and the ego trajectory (``world``, metres).
- For a cooperative scenario (``scenario.json``): every agent in one bird's-eye view of
  ``world_global``; with noise settings, the ground truth and each noisy poses instance side by side.

Figures are drawn on matplotlib's Agg canvas without pyplot (no global state, no display).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from ncore.data.v4 import SequenceLoaderV4
from ncore.impl.data.types import LabelType
from ncore.sensors import camera_model_from_parameters
from upath import UPath

from ncore_convert.contract import DEFAULT_INSTANCE, EGO_MASK
from ncore_convert.validate.coregister import scenario_lidars
from ncore_convert.validate.cuboids import CuboidColumns, read_cuboids
from ncore_convert.validate.poses import T_world_dataset_global, sensor_poses
from ncore_convert.validate.readback import (
    OpenSequence,
    box_corners_world,
    boxes_at,
    open_sequence,
    read_manifest,
    world_points,
)

BEV_HALF_SIZE_M = 60.0  #: the bird's-eye view spans this far around the ego in x and y
SCENARIO_MARGIN_M = 50.0  #: the cooperative view spans the agents plus this much around them
MAX_RANGE_M = 80.0  #: colour scale of the projections
DPI = 100


@dataclass(frozen=True)
class CameraProjection:
    """Lidar points as seen by one camera frame.

    Attributes:
        camera_id, frame: the camera and its frame index; timestamp_us: the frame's end time.
        pixels: image coordinates (x right, y down, px) of the points in the image, float64 [M,2].
        xyz_world_m: the same points in ``world``, float64 [M,3]; range_m: their distance to the camera [M].
        png: the file written.
    """

    camera_id: str
    frame: int
    timestamp_us: int
    pixels: np.ndarray
    xyz_world_m: np.ndarray
    range_m: np.ndarray
    png: UPath


def _nearest_frame(frames_us: np.ndarray, t_us: float) -> int:
    """The frame (of a [N,2] start/end table, µs) whose middle is nearest ``t_us``."""
    return int(np.argmin(np.abs(frames_us.astype(np.float64).mean(axis=1) - t_us)))


def lidar_world_points(loader: SequenceLoaderV4, t_us: float) -> np.ndarray:
    """Every lidar's frame nearest ``t_us``, motion-compensated into ``world``, float64 [N,3]."""
    clouds = [np.zeros((0, 3))]
    for lidar_id in loader.lidar_ids:
        frames_us = loader.get_lidar_sensor(lidar_id).frames_timestamps_us
        clouds.append(world_points(loader, lidar_id, _nearest_frame(frames_us, t_us))[0])
    return np.concatenate(clouds)


def project_into_camera(loader: SequenceLoaderV4, camera_id: str, frame: int, xyz_world_m: np.ndarray):
    """Project world points (float64 [N,3]) into a camera frame with its rolling-shutter poses.

    Returns:
        (image points float64 [M,2], indices into ``xyz_world_m`` of those points [M]).
    """
    camera = loader.get_camera_sensor(camera_id)
    model = camera_model_from_parameters(camera.model_parameters, device="cpu", dtype=torch.float64)
    frame_us = camera.frames_timestamps_us[frame].astype(np.uint64)  # (start, end)
    T_camera_world = sensor_poses(loader, camera_id, "world", frame_us)
    T_world_camera = np.linalg.inv(T_camera_world)  # NCore's projection takes world -> sensor poses
    in_front = np.einsum("ij,nj->ni", T_world_camera[1, :3, :3], xyz_world_m)[:, 2] + T_world_camera[1, 2, 3] > 0.1
    candidates = np.flatnonzero(in_front)
    if not len(candidates):
        return np.zeros((0, 2)), candidates
    result = model.world_points_to_image_points_shutter_pose(
        xyz_world_m[candidates], T_world_camera[0], T_world_camera[1], return_valid_indices=True
    )
    valid = np.atleast_1d(result.valid_indices.cpu().numpy())
    return result.image_points.cpu().numpy().reshape(-1, 2), candidates[valid]


def _title(loader: SequenceLoaderV4, what: str, t_us: int) -> str:
    return f"{loader.sequence_id}  |  {what}  |  t = {t_us} µs"


def _camera_frame(camera_id: str, frame: int, lidar_frame: int | None) -> str:
    """A camera frame as the titles name it: with the lidar frame whose time it shows (the ``f<N>``
    of the file names), when it is a preview's."""
    return f"{camera_id} frame {frame}" + (f" (at lidar frame {lidar_frame})" if lidar_frame is not None else "")


def draw_camera(
    loader: SequenceLoaderV4,
    camera_id: str,
    frame: int,
    xyz_world_m: np.ndarray,
    png: UPath,
    lidar_frame: int | None = None,
):
    """The camera image with the projected lidar points coloured by range; returns a CameraProjection.
    ``lidar_frame``: the lidar frame the points are of (named in the title)."""
    camera = loader.get_camera_sensor(camera_id)
    image = camera.get_frame_image_array(frame)
    pixels, index = project_into_camera(loader, camera_id, frame, xyz_world_m)
    frame_us = camera.frames_timestamps_us[frame].astype(np.uint64)
    centre = sensor_poses(loader, camera_id, "world", frame_us[1:])[0][:3, 3]
    range_m = np.linalg.norm(xyz_world_m[index] - centre, axis=1)
    height, width = image.shape[:2]
    fig = Figure(figsize=(12, 12 * height / width + 0.6), dpi=DPI)
    ax = fig.add_axes((0.07, 0.05, 0.82, 0.89))
    ax.imshow(image)
    if (mask := camera.get_mask_images().get(EGO_MASK)) is not None:  # the ego's pixels, shaded
        ego = np.asarray(mask) > 0
        ax.imshow(np.ma.masked_where(~ego, ego), cmap="autumn", alpha=0.35, vmin=0, vmax=1)
        ax.plot([], [], "s", color="orange", alpha=0.5, label=f"ego mask ({ego.mean():.1%})")
    order = np.argsort(-range_m)  # near points drawn last, on top
    dots = ax.scatter(
        pixels[order, 0],
        pixels[order, 1],
        c=range_m[order],
        s=1.5,
        cmap="turbo",
        vmin=0,
        vmax=MAX_RANGE_M,
        linewidths=0,
        label=f"lidar points ({len(index)})",
    )
    ax.set_xlim(0, width)
    ax.set_ylim(height, 0)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    legend = ax.legend(loc="upper right", fontsize=8)
    for handle in legend.legend_handles:
        if hasattr(handle, "set_sizes"):  # the lidar dots
            handle.set_sizes([20])
    fig.colorbar(dots, cax=fig.add_axes((0.91, 0.05, 0.02, 0.89)), label="range from the camera (m)")
    ax.set_title(_title(loader, _camera_frame(camera_id, frame, lidar_frame), int(frame_us[1])), fontsize=10)
    fig.savefig(str(png))
    return CameraProjection(camera_id, frame, int(frame_us[1]), pixels, xyz_world_m[index], range_m, png)


def _label_figure(image: np.ndarray) -> tuple[Figure, object]:
    """A figure with the camera picture (uint8 [H,W,3]) on pixel axes, room right for a colour bar."""
    height, width = image.shape[:2]
    fig = Figure(figsize=(12, 12 * height / width + 0.6), dpi=DPI)
    ax = fig.add_axes((0.07, 0.05, 0.82, 0.89))
    ax.imshow(image)
    ax.set_xlim(0, width)
    ax.set_ylim(height, 0)
    return fig, ax


def _label_at(loader: SequenceLoaderV4, camera_id: str, end_us: int, label_type: LabelType):
    """The camera's label of ``label_type`` at the frame ending at ``end_us`` (None: none there)."""
    found = loader.query_camera_labels(camera_id, label_type=label_type)
    if not found or end_us not in set(found[0].label_timestamps_us.tolist()):
        return None
    return found[0]


def draw_depth_label(
    loader: SequenceLoaderV4, camera_id: str, frame: int, png: UPath, lidar_frame: int | None = None
) -> bool:
    """The camera image with its ``depth.z`` label of that frame over it, each labelled pixel
    coloured by its depth on the scale of the lidar projections; False (nothing written) when the
    camera has no depth label at the frame's end time."""
    camera = loader.get_camera_sensor(camera_id)
    end_us = int(camera.frames_timestamps_us[frame, 1])
    labels = _label_at(loader, camera_id, end_us, LabelType.DEPTH_Z_M)
    if labels is None:
        return False
    depth = labels.get_label(end_us).get_data()
    fig, ax = _label_figure(camera.get_frame_image_array(frame))
    lines, cols = np.nonzero(depth)
    order = np.argsort(-depth[lines, cols])  # near pixels drawn last, on top
    dots = ax.scatter(
        cols[order] + 0.5,
        lines[order] + 0.5,
        c=depth[lines[order], cols[order]],
        s=1.5,
        cmap="turbo",
        vmin=0,
        vmax=MAX_RANGE_M,
        linewidths=0,
    )
    fig.colorbar(dots, cax=fig.add_axes((0.91, 0.05, 0.02, 0.89)), label="label depth z (m)")
    name = labels.label_descriptor.default_instance_name
    what = f"{_camera_frame(name, frame, lidar_frame)}: {len(lines)} pixels labelled"
    ax.set_title(_title(loader, what, end_us), fontsize=10)
    fig.savefig(str(png))
    return True


def draw_mask_labels(
    loader: SequenceLoaderV4, camera_id: str, frame: int, png: UPath, lidar_frame: int | None = None
) -> bool:
    """The camera image with its ``segmentation.instance`` label of that frame over it (each
    instance in a colour of its own) and its ``mask.dynamic`` outlined in red; False (nothing
    written) when the camera has neither at the frame's end time."""
    camera = loader.get_camera_sensor(camera_id)
    end_us = int(camera.frames_timestamps_us[frame, 1])
    instances = _label_at(loader, camera_id, end_us, LabelType.SEGMENTATION_INSTANCE)
    dynamic = _label_at(loader, camera_id, end_us, LabelType.MASK_DYNAMIC)
    if instances is None and dynamic is None:
        return False
    fig, ax = _label_figure(camera.get_frame_image_array(frame))
    what = []
    if instances is not None:
        index = instances.get_label(end_us).get_data().astype(np.int64)
        colours = np.random.default_rng(0).uniform(0.2, 1.0, (int(index.max()) + 1, 4))
        colours[:, 3], colours[0] = 0.5, 0.0  # half transparent; 0 (no box) clear
        ax.imshow(colours[index], interpolation="nearest")
        what.append(f"{len(np.unique(index)) - 1} instances")
    if dynamic is not None:
        mask = dynamic.get_label(end_us).get_data() > 0
        if mask.any() and not mask.all():
            ax.contour(mask, levels=[0.5], colors="red", linewidths=1.0)
        what.append(f"dynamic {mask.mean():.1%} of pixels" + (" (movers unknown: all 1)" if mask.all() else ""))
    title = f"{_camera_frame(camera_id + ' masks', frame, lidar_frame)}: {', '.join(what)}"
    ax.set_title(_title(loader, title, end_us), fontsize=10)
    fig.savefig(str(png))
    return True


def _footprint(corners: np.ndarray) -> np.ndarray:
    """The bottom rectangle of a box's corners ([8,3], as box_corners_world orders them), closed, [5,2]."""
    return corners[[0, 2, 6, 4, 0], :2]


def draw_bev(loader: SequenceLoaderV4, cuboids: CuboidColumns, t_us: int, xyz: np.ndarray, png: UPath) -> None:
    """Bird's-eye view of ``world`` around the ego at ``t_us``: the lidar points (world, float64 [N,3])
    by height, the cuboids of that sweep, the ego trajectory."""
    T_rig_world = sensor_poses(loader, "rig", "world", np.array([t_us]))[0]
    pose_times = np.unique(
        np.concatenate([loader.get_lidar_sensor(s).frames_timestamps_us[:, 1] for s in loader.lidar_ids])
    )
    trajectory = sensor_poses(loader, "rig", "world", pose_times)[:, :2, 3]
    near = np.all(np.abs(xyz[:, :2] - T_rig_world[:2, 3]) < BEV_HALF_SIZE_M, axis=1)
    fig = Figure(figsize=(10, 9.4), dpi=DPI)
    ax = fig.add_axes((0.08, 0.06, 0.78, 0.86))
    dots = ax.scatter(
        xyz[near, 0],
        xyz[near, 1],
        c=xyz[near, 2] - T_rig_world[2, 3],
        s=0.3,
        cmap="viridis",
        vmin=-2.0,
        vmax=3.0,
        linewidths=0,
        label="lidar points",
    )
    frame_end = int(t_us)
    lidar0 = loader.get_lidar_sensor(loader.lidar_ids[0]).frames_timestamps_us
    f = _nearest_frame(lidar0, t_us)
    boxes = boxes_at(cuboids, int(lidar0[f, 0]), int(lidar0[f, 1]))
    outlines = [_footprint(corners) for corners in box_corners_world(loader, boxes)]
    ax.add_collection(LineCollection(outlines, colors="red", linewidths=1.0, label=f"cuboids ({len(boxes)})"))
    ax.plot(trajectory[:, 0], trajectory[:, 1], "-", color="orange", lw=1.5, label="ego trajectory")
    heading_deg = np.degrees(np.arctan2(T_rig_world[1, 0], T_rig_world[0, 0]))
    ax.plot(*T_rig_world[:2, 3], marker=(3, 0, heading_deg - 90), ms=10, color="black", ls="none", label="ego now")
    ax.set_xlim(T_rig_world[0, 3] - BEV_HALF_SIZE_M, T_rig_world[0, 3] + BEV_HALF_SIZE_M)
    ax.set_ylim(T_rig_world[1, 3] - BEV_HALF_SIZE_M, T_rig_world[1, 3] + BEV_HALF_SIZE_M)
    ax.set_aspect("equal")
    ax.set_xlabel("x world (m)")
    ax.set_ylabel("y world (m)")
    ax.grid(alpha=0.3)
    legend = ax.legend(loc="upper right", fontsize=8)
    for handle in legend.legend_handles:
        if hasattr(handle, "set_sizes"):  # the lidar dots
            handle.set_sizes([20])  # the points' legend dot, readable
    fig.colorbar(dots, cax=fig.add_axes((0.88, 0.06, 0.02, 0.86)), label="height above the ego origin (m)")
    ax.set_title(_title(loader, "bird's-eye view", frame_end), fontsize=10)
    fig.savefig(str(png))


@dataclass(frozen=True)
class Preview:
    """What ``preview_sequence`` wrote: the bird's-eye view and one projection per camera."""

    bev: UPath
    cameras: list[CameraProjection]
    depth_labels: list[UPath]  #: ``<stem>_<camera>_depth.png`` for the cameras with depth labels
    mask_labels: list[UPath]  #: ``<stem>_<camera>_masks.png`` for the cameras with mask labels


def preview_sequence(sequence_json: UPath, out_dir: UPath, frame: int | None = None) -> Preview:
    """Write ``<sequence_id>_f<frame>_bev.png`` and ``<sequence_id>_f<frame>_<camera>.png`` in ``out_dir``.

    Args:
        frame: index of the first lidar's frame to show (default: the middle one); each camera shows
            its frame nearest in time.
    """
    sequence = open_sequence(sequence_json)
    loader = sequence.loader
    if not loader.lidar_ids:
        raise ValueError(f"{sequence_json}: the sequence has no lidar to preview")
    frames_us = loader.get_lidar_sensor(loader.lidar_ids[0]).frames_timestamps_us
    frame = len(frames_us) // 2 if frame is None else frame
    if not 0 <= frame < len(frames_us):
        raise ValueError(f"{sequence_json}: frame {frame} outside 0..{len(frames_us) - 1}")
    out_dir = UPath(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = f"{loader.sequence_id}_f{frame:04d}"
    t_mid = float(frames_us[frame].astype(np.float64).mean())
    xyz = lidar_world_points(loader, t_mid)
    cuboids = read_cuboids(sequence.reader) or CuboidColumns.from_stored([])
    draw_bev(loader, cuboids, int(frames_us[frame, 1]), xyz, out_dir / f"{stem}_bev.png")
    projections, labels, masks = [], [], []
    for camera_id in loader.camera_ids:
        camera_frame = _nearest_frame(loader.get_camera_sensor(camera_id).frames_timestamps_us, t_mid)
        png = out_dir / f"{stem}_{camera_id}.png"
        projections.append(draw_camera(loader, camera_id, camera_frame, xyz, png, lidar_frame=frame))
        if draw_depth_label(loader, camera_id, camera_frame, out_dir / f"{stem}_{camera_id}_depth.png", frame):
            labels.append(out_dir / f"{stem}_{camera_id}_depth.png")
        if draw_mask_labels(loader, camera_id, camera_frame, out_dir / f"{stem}_{camera_id}_masks.png", frame):
            masks.append(out_dir / f"{stem}_{camera_id}_masks.png")
    return Preview(out_dir / f"{stem}_bev.png", projections, labels, masks)


def _scenario_footprints(loader: SequenceLoaderV4, cuboids: CuboidColumns | None, agent, t_us: int) -> list[np.ndarray]:
    """The footprints ([5,2] each, ``world_global``) of an agent's sequence's ``cuboids`` at its
    lidar frame ending at ``t_us`` (``agent``: a ``validate.coregister`` scenario lidar)."""
    if cuboids is None:
        return []
    start_us, end_us = loader.get_lidar_sensor(agent.lidar_id).frames_timestamps_us[agent.frame_ending_at(t_us)]
    corners = box_corners_world(loader, boxes_at(cuboids, int(start_us), int(end_us)))
    T_world_global = T_world_dataset_global(loader)
    return [_footprint(c @ T_world_global[:3, :3].T + T_world_global[:3, 3]) for c in corners]


def preview_scenario(manifest_path: UPath, out_dir: UPath, frame: int | None = None) -> UPath:
    """Every agent of a cooperative scenario in one bird's-eye view of ``world_global``; with noise
    settings, one panel per poses instance (ground truth first). Returns the PNG written."""
    manifest = read_manifest(manifest_path)
    instances = [DEFAULT_INSTANCE] + [s.poses_instance for s in manifest.noise_settings]
    agents = scenario_lidars(UPath(manifest_path), manifest)
    if not agents:
        raise ValueError(f"{manifest_path}: no agent with a lidar")
    common = agents[0].frame_ends_us()
    for agent in agents[1:]:
        common = np.intersect1d(common, agent.frame_ends_us())
    if not len(common):
        raise ValueError(f"{manifest_path}: the agents share no frame time")
    frame = len(common) // 2 if frame is None else frame
    if not 0 <= frame < len(common):
        raise ValueError(f"{manifest_path}: frame {frame} outside 0..{len(common) - 1} (frames all agents share)")
    t_us = int(common[frame])
    fig = Figure(figsize=(8 * len(instances), 8.4), dpi=DPI, layout="constrained")
    colours = [f"C{i}" for i in range(10)]
    cuboids: dict[str, CuboidColumns | None] = {}  # per sequence, whatever its poses instance
    for panel, instance in enumerate(instances):
        ax = fig.add_subplot(1, len(instances), panel + 1)
        positions, drawn = [], 0
        sequences: dict[str, OpenSequence] = {}  # the scenario layout: one sequence for every agent
        for k, agent in enumerate(agents):
            key = str(agent.sequence_json)
            if key not in sequences:
                sequences[key] = open_sequence(agent.sequence_json, instance)
            if key not in cuboids:
                cuboids[key] = read_cuboids(sequences[key].reader)
            loader = sequences[key].loader
            xyz, origin = world_points(loader, agent.lidar_id, agent.frame_ending_at(t_us), "world_global")
            ends_us = agent.frame_ends_us().astype(np.uint64)
            track = sensor_poses(loader, agent.lidar_id, "world_global", ends_us)
            colour = colours[k % len(colours)]
            positions.append(origin[:2])
            ax.scatter(xyz[::2, 0], xyz[::2, 1], s=0.2, color=colour, linewidths=0, alpha=0.6)
            footprints = _scenario_footprints(loader, cuboids[key], agent, t_us)
            ax.add_collection(LineCollection(footprints, colors=colour, linewidths=0.8))
            drawn += len(footprints)
            ax.plot(track[:, 0, 3], track[:, 1, 3], "-", color=colour, lw=1.2)
            ax.plot(origin[0], origin[1], "o", color=colour, mec="black", ms=8, label=f"agent {agent.agent_id}")
        centre = np.mean(positions, axis=0)
        half = np.max(np.abs(np.array(positions) - centre)) + SCENARIO_MARGIN_M
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_aspect("equal")
        ax.set_xlabel("x world_global (m)")
        ax.set_ylabel("y world_global (m)")
        ax.grid(alpha=0.3)
        ax.plot([], [], "-", color="black", lw=0.8, label=f"cuboids, each agent's ({drawn})")
        ax.legend(loc="upper right", fontsize=8, title="points, trajectory, lidar now")
        label = "ground truth poses" if instance == DEFAULT_INSTANCE else f"noisy poses: {instance}"
        ax.set_title(f"{manifest.scenario}  |  {label}  |  t = {t_us} µs", fontsize=10)
    out_dir = UPath(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    png = out_dir / f"{manifest.scenario}_f{frame:04d}_agents_bev.png"
    fig.savefig(str(png))
    return png
