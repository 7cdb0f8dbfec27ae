"""Argoverse 2 / TbV ego masks, per log (``--ego-masks estimate|none|DIR``): estimated from a sample
of each camera's own images (:mod:`ncore_convert.transforms.camera.ego_mask`), or the user's PNGs.

The plan carries each estimate at reduced resolution (small to ship to the writing workers); the
base job upsamples it and stores it as the camera's mask named ``ego`` (``contract.EGO_MASK``).
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from functools import partial

import numpy as np
import PIL.Image
from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.run.pool import Job
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources.masks import read_mask_folder
from ncore_convert.sources.reader import Reader, ReadSettings
from ncore_convert.sources.store import ObjectInfo
from ncore_convert.transforms.camera import ego_mask
from ncore_convert.transforms.camera.models import Pinhole
from ncore_convert.transforms.sampling import spread_indices

#: Images decoded per camera that must see the body, spread evenly over the log (or clip window):
#: two halves of 16, each enough for an estimate of its own (the split-log agreement).
SAMPLES = 32
#: Images are decoded at a power-of-two reduction that brings their longer side to about this.
REDUCED_SIDE_PX = 512


@dataclass(frozen=True)
class EgoMask:
    """One camera's ego mask as planned: an estimate at reduced resolution (bool [h,w]) or the
    user's PNG bytes, or neither (no mask); ``meta`` goes into the camera's metadata (``ego_mask``)."""

    meta: dict
    reduced: np.ndarray | None = None
    user_png: bytes | None = None

    def image(self, width: int, height: int) -> PIL.Image.Image | None:
        """The mask to store (None: none): the user's image as given, or the estimate upsampled
        (mode L, 255 = ego)."""
        if self.user_png is not None:
            return PIL.Image.open(io.BytesIO(self.user_png), formats=["PNG"])
        if self.reduced is None:
            return None
        return PIL.Image.fromarray(ego_mask.upsample(self.reduced, width, height).astype(np.uint8) * 255, mode="L")


#: The estimate's rule, for each camera's metadata.
_RULE = (
    "below the silhouette that best follows persistent edges and mirror folds, with the world changing more and"
    " keeping less fixed structure above it, inside the nominal ego box's reach, attached to the bottom border;"
    f" no mask with fewer than {ego_mask.MIN_SAMPLES} distinct views among the sampled images (more are read"
    f" when views repeat), when the world moved less than {ego_mask.MIN_WORLD_STD} grey levels, the region is"
    f" not distinct from the world (max(change ratio - 1, 0) / {ego_mask.CHANGE_RATIO_UNIT - 1:.2f} + structure"
    f" / {ego_mask.STRUCTURE_UNIT} < 1), the silhouette is not persistent (edge +"
    f" {ego_mask.FOLD_WEIGHT / ego_mask.EDGE_WEIGHT:.2f} x fold < {ego_mask.MIN_EDGE}), the mask would cover more"
    f" than {ego_mask.MAX_FRACTION:.0%} of the image, or the log's first and second halves, estimated alone,"
    f" disagree (split IoU < {ego_mask.SPLIT_MIN_IOU} or silhouettes within {ego_mask.SPLIT_ROW_TOLERANCE:.0%} of"
    f" the height in < {ego_mask.SPLIT_MIN_COLUMNS:.0%} of the columns)"
)


def reduction(pinhole: Pinhole) -> int:
    """The power-of-two decode reduction of a camera (2048 px -> 4, TbV's 1024 px -> 2)."""
    return 2 ** max(0, int(math.log2(max(pinhole.resolution_px) / REDUCED_SIDE_PX)))


def reduced_size(pinhole: Pinhole) -> tuple[int, int]:
    """(width, height) of the camera's images decoded at :func:`reduction` (JPEG DCT scaling rounds up)."""
    k = reduction(pinhole)
    return -(-pinhole.resolution_px[0] // k), -(-pinhole.resolution_px[1] // k)


def _prior(
    shape: tuple[int, int], pinhole: Pinhole, T_camera_ego: np.ndarray, box: ego_mask.EgoBox
) -> ego_mask.BodyPrior:
    """The camera's body prior at a reduced size (h, w) of its images."""
    return ego_mask.body_prior(pinhole.scaled(shape[1], shape[0]), T_camera_ego, box)


def _estimate(
    log_dir: UPath,
    camera: str,
    stamps_ns: np.ndarray,
    pinhole: Pinhole,
    T_camera_ego: np.ndarray,
    box: ego_mask.EgoBox,
    require_agreement: bool = True,
    listing: dict[str, ObjectInfo] | None = None,
    reader: Reader | None = None,
) -> EgoMask:
    """One camera's estimate (its images read by ``reader``); ``require_agreement``: as in
    ``ego_mask.estimate`` (False only to measure the agreement test)."""
    scale = reduction(pinhole)
    width, height = reduced_size(pinhole)
    prior = _prior((height, width), pinhole, T_camera_ego, box)
    if not prior.must_see:  # by the calibration, no body along the bottom border: nothing to estimate
        return EgoMask(
            {
                "method": "estimate",
                "decision": "not seen",
                "must_see": False,
                "samples": 0,
                "lower_body_border_fraction": round(prior.lower_border, 3),
                "ego_box_m": [box.length_m, box.width_m, box.height_m],
                "rule": f"not estimated: rays along less than {ego_mask.MUST_SEE_BORDER:.0%} of the bottom"
                " border hit the nominal ego box's lower body",
            }
        )

    def grey(fetched: tuple[UPath, bytes | SourceError]) -> np.ndarray:
        path, data = fetched
        if isinstance(data, SourceError):
            raise data
        return av2.decode_jpeg(path, data, scale, "L").astype(np.float32)

    def decoded(indices: np.ndarray) -> np.ndarray:
        # fetched ahead, decoded in two threads (decoding frees the GIL), so that the log's last
        # camera, alone on the workers, still uses two cores for it
        fetched = av2.read_images(
            log_dir, camera, stamps_ns[indices], listing, keep=True, reader=reader
        )  # copied later
        with ThreadPoolExecutor(2) as threads:
            return np.stack(list(threads.map(grey, fetched)))

    picks = spread_indices(len(stamps_ns), SAMPLES)
    frames = decoded(picks)
    h, w = frames.shape[1:]
    if (h, w) != prior.reach.shape:
        prior = _prior((h, w), pinhole, T_camera_ego, box)
    seen = ego_mask.views(frames, prior)
    if len(seen.distinct) < len(picks) < len(stamps_ns):
        # The car stopped (repeated views carry no evidence): look between the samples too, once,
        # and keep at most SAMPLES of the distinct views, spread over them, in time order.
        more = np.setdiff1d(np.arange(len(stamps_ns)), picks)
        more = more[spread_indices(len(more), SAMPLES)]
        order = np.argsort(np.concatenate([picks, more]))
        picks, frames = np.concatenate([picks, more])[order], np.concatenate([frames, decoded(more)])[order]
        seen = ego_mask.views(frames, prior)
        if len(seen.distinct) > SAMPLES:
            frames = frames[[seen.distinct[i] for i in spread_indices(len(seen.distinct), SAMPLES)]]
            seen = ego_mask.views(frames, prior)
    result = ego_mask.estimate(frames, prior, require_agreement, seen)
    meta = {
        "method": "estimate",
        "decision": result.decision,
        "must_see": prior.must_see,
        "samples": len(picks),
        "distinct_samples": len(seen.distinct),
        "reduced_size_px": [w, h],
        "reach_fraction": round(float(prior.reach.mean()), 5),
        "lower_body_border_fraction": round(prior.lower_border, 3),
        "covered_fraction": round(result.covered_fraction, 5),
        "silhouette_edge": round(result.edge, 3),
        "silhouette_fold": round(result.fold, 3),
        "change_ratio": round(result.change_ratio, 3),
        "structure": round(result.structure, 3),
        "world_std": round(result.world_std, 3),
        "split_iou": round(result.split_iou, 3),
        "split_columns": round(result.split_columns, 3),
        "ego_box_m": [box.length_m, box.width_m, box.height_m],
        "rule": _RULE,
    }
    return EgoMask(meta, reduced=result.mask)


def _estimate_job(*args, reading: ReadSettings, progress=None) -> tuple[EgoMask, dict]:
    """:func:`_estimate` as a ``JobPool`` job (which passes a progress callback: no frames written
    here), with a reader of its own for the log (``reading``), and that reader's counts."""
    with Reader(reading) as reader:
        return _estimate(*args, reader=reader), asdict(reader.counts)


def _agreement(camera: str, meta: dict) -> str:
    """A camera named with its split-log agreement, for a warning."""
    iou, columns = meta["split_iou"], meta["split_columns"]
    return f"{camera} (split IoU {iou:.2f}, silhouette agreeing in {columns:.0%} of columns)"


def plan_ego_masks(
    log_dir: UPath,
    option: str,
    cameras: dict[str, tuple[np.ndarray, Pinhole, np.ndarray]],
    warnings: list[str],
    box: ego_mask.EgoBox,
    run_jobs: Callable[[list[Job]], list] | None = None,
    listing: dict[str, ObjectInfo] | None = None,
    reader: Reader | None = None,
) -> dict[str, EgoMask]:
    """Every camera's ego mask under ``--ego-masks`` ``option`` (``estimate``, ``none`` or a folder).

    Args:
        cameras: camera id -> (its image timestamps in ns [N], its pinhole, T_camera_ego [4,4]).
        warnings: fallbacks are reported here, one line per kind of fallback; a camera that must
            see the body (``ego_mask.BodyPrior.must_see``) but gets no mask is always one.
        box: the nominal ego vehicle of the prior.
        listing: the remote images' sizes and ETags (``LogInputs.files``).
        reader: the log's reader: the estimates read with readers it shares (in other processes
            too), and their counts are added to its own.
        run_jobs: runs the per-camera estimates (``JobPool.run``: the conversion's worker processes,
            idle while a log is planned); None: threads in this process. The result does not
            depend on it.
    """
    if option == "none":
        return {cam: EgoMask({"method": "none"}) for cam in cameras}
    if option != "estimate":
        sizes = {cam: pinhole.resolution_px for cam, (_, pinhole, _) in cameras.items()}
        user = read_mask_folder(UPath(option), sizes, reader)
        return {
            cam: EgoMask({"method": "user", "file": f"{cam}.png"}, user_png=user[cam])
            if cam in user
            else EgoMask({"method": "user", "decision": "no file: no mask"})
            for cam in cameras
        }
    reading = reader.shared() if reader is not None else ReadSettings()
    estimate = partial(_estimate_job, reading=reading)
    jobs = [(estimate, (log_dir, cam, *inputs, box, True, listing)) for cam, inputs in cameras.items()]
    if run_jobs is None:  # threads: JPEG decoding and most array work free the GIL
        with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
            estimated = list(pool.map(lambda job: job[0](*job[1]), jobs))
    else:
        estimated = run_jobs(jobs)
    if reader is not None:
        for _, counts in estimated:
            reader.counts.add(counts)
    masks = dict(zip(cameras, (mask for mask, _ in estimated), strict=True))
    fallbacks: dict[str, list[str]] = {}
    for cam, mask in masks.items():
        decision = mask.meta["decision"]
        if decision != "mask" and (decision != "not seen" or mask.meta["must_see"]):
            fallbacks.setdefault(decision, []).append(cam)
    for decision, cams in fallbacks.items():
        seen = [cam for cam in cams if masks[cam].meta["must_see"]]
        note = f" ({', '.join(seen)} must see the ego body by the calibration and the ego box)" if seen else ""
        named = [_agreement(cam, masks[cam].meta) if decision == "halves disagree" else cam for cam in cams]
        warnings.append(
            f"{log_dir / 'sensors' / 'cameras'}: ego masks not estimated ({decision}) for"
            f" {', '.join(named)}; no ego mask written{note}"
        )
    return masks
