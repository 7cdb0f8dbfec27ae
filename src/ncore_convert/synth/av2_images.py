"""The synthetic AV2/TbV cameras' images (:mod:`.argoverse2`): a few textured pictures per camera,
cycled and made unique per frame (``world="pattern"``), or each picture ray-cast from the scene at
its own time (``world="render"``), with the ego body where the camera sees it."""

from __future__ import annotations

import io

import numpy as np
import PIL.Image

from ncore_convert.sources import argoverse2 as av2
from ncore_convert.synth.av2_config import MAX_RANGE_M, SynthConfig, SynthTruth
from ncore_convert.synth.ego import pictures as ego_pictures
from ncore_convert.synth.raycast import box_colours, render
from ncore_convert.transforms.camera.models import Pinhole


def _unique_jpeg(template: bytes, comment: str) -> bytes:
    """Make a template unique per frame by inserting a JPEG comment (COM) segment after SOI."""
    payload = comment.encode()
    return template[:2] + b"\xff\xfe" + (len(payload) + 2).to_bytes(2, "big") + payload + template[2:]


RENDER_STEP = 4  #: rendered pictures are ray-cast at 1/4 of their size, each ray's colour over 4x4 pixels
BODY_RGB = (60, 60, 70)  #: the ego body in rendered pictures


def _write_rendered_images(truth: SynthTruth, cam_ns: dict[str, np.ndarray], cams: dict, config: SynthConfig) -> None:
    """Every camera's pictures rendered from the scene at their own times (``world="render"``),
    with the ego body painted flat where the camera sees it."""
    step = max(1, int(round(20.0 / config.camera_fps)))
    box_rgb = box_colours(truth.scene)
    for cam, stamps in cam_ns.items():
        _, width, height = cams[cam]
        for i, ts in enumerate(stamps[::step]):
            t_s = (int(ts) - truth.t0_ns) * 1e-9
            T_camera_city = truth.scene.ego.T_ego_city(np.array([t_s]))[0] @ truth.T_sensor_ego[cam]
            f, cx, cy = truth.intrinsics[cam]  # AV2's principal point: pixel centres at integers
            rgb, _ = render(
                truth.scene,
                box_rgb,
                T_camera_city,
                Pinhole((f, f), (cx + 0.5, cy + 0.5), (width, height)),
                RENDER_STEP,
                t_s,
                MAX_RANGE_M,
                with_index=False,
            )
            if cam in truth.ego_masks:
                rgb[truth.ego_masks[cam]] = BODY_RGB
            path = av2.image_path(truth.log_dir, cam, int(ts))
            if i == 0:
                path.parent.mkdir(parents=True, exist_ok=True)
            out = io.BytesIO()
            PIL.Image.fromarray(rgb).save(out, format="JPEG", quality=92)
            path.write_bytes(out.getvalue())
            truth.image_paths.append(path)


def write_images(
    truth: SynthTruth, cam_ns: dict[str, np.ndarray], cams: dict, rng: np.random.Generator, config: SynthConfig
) -> None:
    """Every camera's images: a few pictures per camera (``synth.ego.pictures``: the world changing,
    the ego body where the camera sees it) cycled in order, each made unique by a JPEG comment; in
    the parked part of the log (``config.parked_fraction``) always the first picture."""
    if config.image_cameras is not None:
        cam_ns = {cam: stamps for cam, stamps in cam_ns.items() if cam in config.image_cameras}
    if config.world == "render":
        _write_rendered_images(truth, cam_ns, cams, config)
        return
    parked_all = config.parked_fraction >= 1.0
    parked_until_ns = truth.t0_ns + int(config.parked_fraction * config.seconds * 1e9)
    step = max(1, int(round(20.0 / config.camera_fps)))
    # as many pictures as a camera shows (at most config.pictures); cameras without the body share them per size
    count = {cam: min(config.pictures, len(stamps[::step])) for cam, stamps in cam_ns.items()}
    shared_count: dict[tuple[int, int], int] = {}
    for cam in cam_ns:
        if cam not in truth.ego_masks:
            size = tuple(cams[cam][1:])
            shared_count[size] = max(shared_count.get(size, 0), count[cam])
    shared: dict[tuple[int, int], list[bytes]] = {}
    for cam, stamps in cam_ns.items():
        _, width, height = cams[cam]
        if cam in truth.ego_masks:
            variants = ego_pictures(
                rng,
                width,
                height,
                truth.ego_masks[cam],
                parked_all,
                config.ego_body,
                count[cam],
                config.light,
                config.shadows,
                config.camera_scale,
            )
        else:
            if (width, height) not in shared:
                shared[(width, height)] = ego_pictures(
                    rng,
                    width,
                    height,
                    None,
                    parked_all,
                    count=shared_count[(width, height)],
                    light=config.light,
                    shadows=config.shadows,
                    binning=config.camera_scale,
                )
            variants = shared[(width, height)]
        for i, ts in enumerate(stamps[::step]):
            path = av2.image_path(truth.log_dir, cam, int(ts))
            if i == 0:
                path.parent.mkdir(parents=True, exist_ok=True)
            picture = 0 if ts < parked_until_ns else i % len(variants)
            path.write_bytes(_unique_jpeg(variants[picture], f"{cam} {ts}"))
            truth.image_paths.append(path)
