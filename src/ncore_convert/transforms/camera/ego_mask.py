"""The ego vehicle's pixels in a camera, estimated from the camera's own images and its calibration.

Real car bodies are glossy: their pixels mirror the moving scene, change brightness and colour with
sun and shade, carry logos and glare, and can match the road or sky at the silhouette. A still-pixel
test sees only the darkest, least reflective part of them. What stays fixed is the **geometry**:
the body is one region under a silhouette that sits at the same pixels in every frame, attached to
the image border that faces the car, inside where a car of the vehicle's size can be. The estimate
is built from cues that hold for that geometry, on greyscale frames sampled across the log and
decoded at reduced resolution:

1. **Prior** (:func:`body_prior`, from the calibration and a nominal ego box): the body can only be
   on rays that hit the box (``reach``); a camera whose rays hit the box's lower body (up to
   ``LOWER_BODY_FRACTION`` of its height: hood and trunk level) along at least
   ``MUST_SEE_BORDER`` of its bottom border must see the body.
2. **Motion**: repeated views (a stopped car, :func:`distinct_views`) are dropped, and at least
   ``MIN_SAMPLES`` distinct ones must remain; the world must have moved (median temporal standard
   deviation outside the reach of at least ``MIN_WORLD_STD`` grey levels, once each frame's
   exposure is divided out); else (parked, a static scene) no mask and a warning.
3. **Persistent edges**: the gradient of the log image (a brightness change multiplies an image,
   so it leaves log gradients alone) keeps its orientation across frames at the silhouette and at
   painted markings, while the world's edges move through: per pixel, the coherence of the
   frames' gradient orientations (doubled angles, so a silhouette whose contrast flips sign between
   a brighter and a darker background still counts).
4. **Change energy**: how much fine structure changes between frames, after removing each frame's
   smooth brightness change (lighting, shade, colour casts). Reflections on paint are the scene
   mirrored and attenuated, so the body changes less than the world above it; a robust quantile
   over frames keeps glare in a few frames from counting.
5. **Fixed structure** (:func:`_fixed_structure`): the persistent-edge strength averaged along the
   rows, above the world's own level. A body keeps structure at fixed pixels (markings, panel gaps,
   shading, and the streaks of a grazing reflection, which run across the silhouette); the world
   moving past keeps none. Next to a grazing silhouette the paint mirrors the scene just behind it,
   compressed, and changes as much as the world: there this cue holds where the change energy fails.
6. **Mirror folds** (:func:`mirror_folds`): glossy paint at a grazing angle is a mirror, so right
   under the silhouette it shows the world just above it, flipped: each frame's column profile
   folds there (the row differences below are those above, reversed in sign). The world moves
   through but the fold stays at the same rows, even where the body's colour matches the road or
   sky behind it and no edge is left. The fold line sits 1.5 rows above the first body row; that
   offset was chosen on our synthetic bodies among 0.5, 1 and 1.5 rows, so it is a tuned figure.
7. **Silhouette** (dynamic programming over the image columns): per column, the row where the body
   begins (or none), minimising the log change energy claimed as body relative to the world's just
   above the reach (clipped to ``COST_CLIP``) minus ``STRUCTURE_WEIGHT`` x the fixed structure,
   minus a silhouette bonus (``EDGE_WEIGHT`` x the persistent-edge strength plus ``FOLD_WEIGHT`` x
   the fold score over ``FOLD_FLOOR``), plus ``JUMP_COST`` per row of jump between neighbouring
   columns; inside the reach only. Dips narrower than ``DIP_FRACTION`` of the width are filled.
   The body is everything below.
8. **Decision**: the mask is kept when it covers at least ``MIN_FRACTION`` and at most
   ``MAX_FRACTION`` of the image, differs from the world (it changes ``CHANGE_RATIO_UNIT`` times
   less than the world above the silhouette, or keeps ``STRUCTURE_UNIT`` fixed structure, or a mix:
   the two fractions add to at least 1; else "not seen": what a camera without a body gives) and
   its silhouette is persistent: the mean edge strength plus ``FOLD_WEIGHT / EDGE_WEIGHT`` x the
   mean fold score along it reaches ``MIN_EDGE``. Otherwise no mask, with the reason; for a camera
   that must see the body, a warning (the caller's).
9. **Split-log agreement** (:func:`split_agreement`): the first and second halves of the frames
   (disjoint stretches of road, each estimated alone, steps 3-7) must give the same body: an IoU of
   at least ``SPLIT_MIN_IOU`` and silhouettes within ``SPLIT_ROW_TOLERANCE`` of the image height
   in at least ``SPLIT_MIN_COLUMNS`` of the columns. The body stays where it is in every frame; a
   piece of world that looked fixed (a textureless stretch, a shadow, a reflection that matched)
   does so in one stretch of road, not in both. Each half needs ``MIN_SAMPLES / 2`` distinct
   frames: with fewer (9 and 10 in a half-parked log of the sweep) a chance persistence can fool
   both halves alike. A cue that misleads the whole log in the same way is not caught by this.
10. The mask is upsampled to the camera's resolution (bilinear, then a threshold at one half).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import PIL.Image
from scipy import ndimage

from ncore_convert.contract import EGO_BOX_M
from ncore_convert.transforms.camera.ego_cues import Cues, change_energy, cues, mirror_folds, persistent_edges
from ncore_convert.transforms.camera.models import Pinhole
from ncore_convert.transforms.objects.boxes import slab_span

MIN_WORLD_STD = 4.0  #: grey levels: below this, the world did not move enough to tell the body from it
MIN_FRACTION = 0.005  #: of the image: a smaller region is not a car body
MAX_FRACTION = 0.30  #: of the image: a larger "body" is the scene standing still
MIN_SAMPLES = 24  #: fewer (distinct) sampled images than this leave a half too few (12) to tell fixed from moving
SPLIT_MIN_IOU = 0.9  #: the two halves' bodies must overlap this much (IoU) ...
SPLIT_MIN_COLUMNS = 0.9  #: ... and their silhouettes agree in this share of the columns ...
SPLIT_ROW_TOLERANCE = 0.01  #: ... to within this share of the image height
LOWER_BODY_FRACTION = 2 / 3  #: hood and trunk lid sit at about two thirds of a car's roof height
MUST_SEE_BORDER = 0.45  #: share of the bottom border on the lower body that makes a camera see the body
EDGE_WEIGHT = 20.0  #: silhouette bonus per unit of persistent-edge strength
JUMP_COST = 2.0  #: per row of silhouette change between neighbouring columns
COST_CLIP = 0.5  #: a single pixel's change energy counts at most this much either way
REFERENCE_BAND_PX = 12  #: rows (reduced) of world above the reach, and of either side of the silhouette
DIP_FRACTION = 0.1  #: of the image width: narrower dips in the silhouette are filled
MIN_EDGE = 0.25  #: mean persistent-edge strength a silhouette needs
CHANGE_RATIO_UNIT = 1.05  #: a body that changes this much less than the world above it ...
STRUCTURE_UNIT = 0.1  #: ... or keeps this much fixed structure (or a mix: the two add) is not the world
STRUCTURE_WEIGHT = 2.0  #: per pixel, what claiming fixed structure (persistent edges) as body earns
STRUCTURE_SIGMA_PX = (0.7, 4.0)  #: (rows, columns): the structure is averaged along the silhouette
STRUCTURE_MARGIN = 1.5  #: times the world's own persistent-edge level counts as no structure
WORLD_SAMPLE_PIXELS = 20000  #: world pixels (evenly strided) behind the exposure and motion figures ...
FOLD_FLOOR = 0.1  #: a fold score the world reaches by chance (its median is ~0)
FOLD_WEIGHT = 12.0  #: silhouette bonus per unit of fold score above the floor
REPEAT_PIXELS = 2000  #: ... and the fewer of them compared to tell a repeated view


@dataclass(frozen=True)
class EgoBox:
    """The nominal ego vehicle: a box around the rear-axle origin (metres, ego frame x forward,
    y left, z up). The default is AV2's car (a Ford Fusion Hybrid: about 4.9 x 1.9 x 1.5 m, the
    rear axle ~1.05 m ahead of the rear bumper, the origin ~0.32 m above the road)."""

    length_m: float = EGO_BOX_M[0]
    width_m: float = EGO_BOX_M[1]
    height_m: float = EGO_BOX_M[2]
    rear_overhang_m: float = 1.05
    origin_height_m: float = 0.32

    @property
    def dims_m(self) -> tuple[float, float, float]:
        """(length, width, height) in metres: what ``--ego-box-m`` sets."""
        return (self.length_m, self.width_m, self.height_m)

    def bounds(self, height_fraction: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners in the ego frame [3] of the box, or of its lower part."""
        lo = np.array([-self.rear_overhang_m, -self.width_m / 2, -self.origin_height_m])
        hi = np.array(
            [
                self.length_m - self.rear_overhang_m,
                self.width_m / 2,
                self.height_m * height_fraction - self.origin_height_m,
            ]
        )
        return lo, hi


@dataclass(frozen=True)
class BodyPrior:
    """Where the body can be in one camera and whether the camera must see it.

    Attributes:
        reach: pixels whose rays hit the nominal ego box, bool [h,w].
        lower_border: share of the bottom border whose rays hit the box's lower body.
        must_see: ``lower_border >= MUST_SEE_BORDER``.
    """

    reach: np.ndarray
    lower_border: float

    @property
    def must_see(self) -> bool:
        return self.lower_border >= MUST_SEE_BORDER


@dataclass(frozen=True)
class EgoMaskEstimate:
    """The estimate for one camera, and the figures it was decided on.

    Attributes:
        mask: ego pixels at the reduced resolution, bool [h,w]; None when no mask is written.
        decision: ``"mask"``, ``"not seen"`` (no body), or a fallback: ``"too few images"``,
            ``"too little motion"``, ``"too few distinct images"``, ``"implausible coverage"``,
            ``"no persistent silhouette"``, ``"halves disagree"``.
    """

    mask: np.ndarray | None
    decision: str
    covered_fraction: float = 0.0  #: the share of the image the mask covers (0 without one)
    world_std: float = 0.0  #: the median temporal standard deviation outside the reach (grey levels)
    edge: float = 0.0  #: mean persistent-edge strength along the silhouette (0..1)
    fold: float = 0.0  #: mean mirror-fold score along the silhouette, over ``FOLD_FLOOR`` (``mirror_folds``)
    change_ratio: float = 0.0  #: the world's change energy above the silhouette over the body's below it
    structure: float = 0.0  #: the median fixed structure (:func:`_fixed_structure`) below the silhouette
    #: the agreement of the log's two halves (:func:`split_agreement`); 0 when the estimate stopped before it
    split_iou: float = 0.0
    split_columns: float = 0.0


def _rays_hit_box(origin: np.ndarray, directions: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Whether rays from ``origin`` [3] along ``directions`` [...,3] (ego frame) hit the box [lo, hi]."""
    near, far = slab_span(origin, np.moveaxis(directions, -1, 0), lo, hi, 0.0)
    return far >= near


def body_prior(pinhole: Pinhole, T_camera_ego: np.ndarray, box: EgoBox) -> BodyPrior:
    """The body prior of one camera at the reduced resolution.

    Args:
        pinhole: the camera at the reduced image size (``Pinhole.scaled``); T_camera_ego: camera
            (OpenCV) -> ego [4,4]; box: the vehicle.
    """
    rays = pinhole.pixel_rays() @ T_camera_ego[:3, :3].T
    origin = T_camera_ego[:3, 3]
    reach = _rays_hit_box(origin, rays, *box.bounds())
    lower = _rays_hit_box(origin, rays[-1], *box.bounds(LOWER_BODY_FRACTION))
    return BodyPrior(reach, float(lower.mean()))


def silhouette(cost_body: np.ndarray, bonus: np.ndarray, reach: np.ndarray, jump_cost: float) -> np.ndarray:
    """Per column, the first body row (``h``: no body in that column), int [w]: the minimum of
    the summed ``cost_body`` of the rows claimed, minus the ``bonus`` of the first one, plus
    ``jump_cost`` per row of change between neighbouring columns (dynamic programming, exact).

    Args:
        cost_body: what claiming each pixel as body costs, float [h,w] (negative: body-like).
        bonus: what a silhouette through each pixel earns, float [h,w]. reach: where the body
            can be, bool [h,w].
    """
    h, w = cost_body.shape
    claimed = np.vstack([np.cumsum(cost_body[::-1], axis=0)[::-1], np.zeros((1, w))])  # [h+1,w]: rows c.. h-1
    earned = np.vstack([bonus, np.zeros((1, w))])
    allowed = np.vstack([reach, np.ones((1, w), dtype=bool)])
    allowed[:-1] &= np.flip(np.logical_and.accumulate(np.flip(reach, 0), axis=0), 0)  # reach from c down
    data = np.where(allowed, claimed - earned, np.inf)
    rows = np.arange(h + 1, dtype=np.float64)
    slope = jump_cost * rows
    total = np.empty((w, h + 1))
    total[0] = data[:, 0]
    down, up = np.empty(h + 1), np.empty(h + 1)
    for x in range(1, w):  # the L1 distance transform of the previous column, in two sweeps
        prev = total[x - 1]
        np.minimum.accumulate(np.subtract(prev, slope, out=down), out=down)
        down += slope
        np.minimum.accumulate(np.add(prev, slope, out=up)[::-1], out=up[::-1])
        up -= slope
        np.minimum(down, up, out=total[x])
        total[x] += data[:, x]
    path = np.empty(w, dtype=np.int64)
    path[-1] = int(np.argmin(total[-1]))
    for x in range(w - 1, 0, -1):
        path[x - 1] = int(np.argmin(total[x - 1] + jump_cost * np.abs(rows - path[x])))
    return path


@dataclass(frozen=True)
class Outline:
    """One set of cues' silhouette: per column of the crop, the first body row (``h``: none), int
    [w], the body below it, bool [h,w], and the figures the decision reads."""

    top: np.ndarray
    body: np.ndarray
    figures: dict


def _outline(c: Cues, reach: np.ndarray) -> Outline:
    """The silhouette (:func:`silhouette`) that cues ``c`` of the crop give inside ``reach`` [h,w]."""
    edge = persistent_edges(c)
    change = change_energy(c)
    cost = np.clip(np.log(np.maximum(change, 1e-3) / _world_reference(change, reach)), -COST_CLIP, COST_CLIP)
    structure = _fixed_structure(edge, reach)
    cost -= STRUCTURE_WEIGHT * structure  # < 0: changes less, keeps more structure, than the world
    fold = np.clip(mirror_folds(c) - FOLD_FLOOR, 0.0, None)
    bonus = EDGE_WEIGHT * edge + FOLD_WEIGHT * fold
    top = silhouette(cost, bonus, reach, jump_cost=JUMP_COST)
    # A silhouette is smooth: a dip narrower than DIP_FRACTION of the image (where the paint
    # matched the world behind it, so neither cue saw the outline) is filled from its sides.
    top = ndimage.grey_opening(top, size=max(3, int(DIP_FRACTION * len(top))), mode="nearest")
    h = reach.shape[0]
    on = top < h
    edge_on, fold_on = (float(np.mean(cue[top[on], np.flatnonzero(on)])) if on.any() else 0.0 for cue in (edge, fold))
    below = np.arange(h)[:, None] >= top[None, :]
    fixed = float(np.median(structure[below])) if below.any() else 0.0
    body = ndimage.binary_opening(below, structure=np.ones((3, 3))) & reach
    return Outline(
        top, body, {"edge": edge_on, "fold": fold_on, "change_ratio": _change_ratio(change, top), "structure": fixed}
    )


def split_agreement(first: Outline, second: Outline, height_px: int) -> tuple[float, float]:
    """How two independent estimates of one body agree: the IoU of their bodies, and the share of
    the columns either claims whose first body rows lie within ``SPLIT_ROW_TOLERANCE`` of the
    image height (``height_px``) of each other (a column one claims and the other not disagrees)."""
    union = (first.body | second.body).sum()
    iou = float((first.body & second.body).sum() / union) if union else 0.0
    h = first.body.shape[0]
    claimed = (first.top < h) | (second.top < h)
    close = np.abs(first.top - second.top) <= max(1.0, SPLIT_ROW_TOLERANCE * height_px)
    columns = float(close[claimed].mean()) if claimed.any() else 0.0
    return iou, columns


class Views(NamedTuple):
    """What the frames of a log show of the world (:func:`views`)."""

    samples: np.ndarray  #: the world's exposure-normalised grey levels (:func:`world_samples`), [N,K]
    distinct: list[int]  #: the frames that are not repeated views (:func:`distinct_views`)


def views(frames: np.ndarray, prior: BodyPrior) -> Views:
    """The :class:`Views` of frames float32 [N,h,w] (grey levels at the prior's resolution)."""
    samples = world_samples(frames, prior)
    return Views(samples, distinct_views(samples))


def world_samples(frames: np.ndarray, prior: BodyPrior) -> np.ndarray:
    """The world's grey levels in each frame, with each frame's exposure divided out: an even
    stride of the pixels outside the prior's reach (a median needs no more), float [N,K].

    Args:
        frames: float32 [N,h,w] grey levels at the prior's resolution.
    """
    world = ~prior.reach if (~prior.reach).any() else np.ones_like(prior.reach)
    picked = np.flatnonzero(world.ravel())[:: max(1, int(world.sum()) // WORLD_SAMPLE_PIXELS)]
    samples = frames.reshape(len(frames), -1)[:, picked]  # [N, <= 2 x WORLD_SAMPLE_PIXELS]
    levels = np.median(samples, axis=1)  # each frame's exposure: not motion
    return samples * (np.median(levels) / np.maximum(levels, 1.0))[:, None]


def distinct_views(samples: np.ndarray) -> list[int]:
    """The frames whose world (:func:`world_samples`, [N,K]) differs from that of every earlier
    kept frame by a median of at least ``MIN_WORLD_STD`` grey levels, in order (the first always).

    A stopped car gives the same view again: such repeats carry no evidence and would make the
    world look fixed.
    """
    compared = samples[:, :: max(1, samples.shape[1] // REPEAT_PIXELS)]
    kept = [0]
    for i in range(1, len(samples)):
        if np.median(np.abs(compared[i] - compared[kept]), axis=1).min() >= MIN_WORLD_STD:
            kept.append(i)
    return kept


def estimate(
    frames: np.ndarray, prior: BodyPrior, require_agreement: bool = True, seen: Views | None = None
) -> EgoMaskEstimate:
    """Estimate the ego pixels from greyscale frames sampled across a log (in time order).

    The estimate from all the frames is kept only when the two halves of the log, estimated
    alone, agree on it (:func:`split_agreement`): the body is the same in both, the world is not.

    Args:
        frames: float32 [N,h,w], grey levels 0..255, at reduced resolution, in time order.
        prior: the camera's :func:`body_prior` at that resolution.
        require_agreement: False only to measure what the agreement test prevents (the sweep):
            the mask from all the frames is kept whatever the halves say.
        seen: the frames' :func:`views`, when the caller has them already.
    """
    if len(frames) < MIN_SAMPLES:
        return EgoMaskEstimate(None, "too few images")
    if not prior.reach.any():
        return EgoMaskEstimate(None, "not seen")
    samples, kept = seen or views(frames, prior)
    world_std = float(np.median(samples.std(axis=0)))
    if world_std >= MIN_WORLD_STD and len(kept) < MIN_SAMPLES:
        return EgoMaskEstimate(None, "too few distinct images", world_std=world_std)
    if world_std < MIN_WORLD_STD:
        return EgoMaskEstimate(None, "too little motion", world_std=world_std)
    # Only the reach and a band above it (the world's reference) matter from here on.
    r0 = max(0, int(np.flatnonzero(prior.reach.any(axis=1))[0]) - 2 * REFERENCE_BAND_PX)
    crop, reach = frames[kept, r0:], prior.reach[r0:]
    half = len(kept) // 2  # the log's first and second halves: disjoint stretches of road
    first, second = cues(crop[:half]), cues(crop[half:])
    outline = _outline(first + second, reach)
    mask = np.vstack([np.zeros((r0, reach.shape[1]), dtype=bool), outline.body])
    covered = float(mask.mean())
    figures = {"covered_fraction": covered, "world_std": world_std, **outline.figures}
    ratio, fixed = figures["change_ratio"], figures["structure"]
    # A body may change more than the world (reflections): only a lower change is evidence.
    if covered < MIN_FRACTION or max(ratio - 1.0, 0.0) / (CHANGE_RATIO_UNIT - 1.0) + fixed / STRUCTURE_UNIT < 1.0:
        return EgoMaskEstimate(None, "not seen", **figures)
    if covered > MAX_FRACTION:
        return EgoMaskEstimate(None, "implausible coverage", **figures)
    if figures["edge"] + FOLD_WEIGHT / EDGE_WEIGHT * figures["fold"] < MIN_EDGE:  # the silhouette's evidence
        return EgoMaskEstimate(None, "no persistent silhouette", **figures)
    iou, columns = split_agreement(_outline(first, reach), _outline(second, reach), frames.shape[1])
    figures.update(split_iou=iou, split_columns=columns)
    if require_agreement and (iou < SPLIT_MIN_IOU or columns < SPLIT_MIN_COLUMNS):
        return EgoMaskEstimate(None, "halves disagree", **figures)
    return EgoMaskEstimate(mask, "mask", **figures)


def _fixed_structure(edge: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """Per pixel, how much more persistent structure surrounds it than the world just above the
    reach holds, float32 [h,w]: ~0 on the world, up to ~1 on a body.

    The persistent-edge strength (:func:`persistent_edges`) is averaged along the rows (a body's
    structure, and the world's lack of it, run along the silhouette) but hardly across them, so
    the step at the silhouette stays sharp; the world's own level (noise, a rare edge that stays)
    is measured above the reach, where the body cannot be, and ``STRUCTURE_MARGIN`` times it
    counts as none.

    Args:
        edge: persistent-edge strength 0..1, float32 [h,w]; reach: the prior's reach, bool [h,w].
    """
    density = ndimage.gaussian_filter(edge, STRUCTURE_SIGMA_PX)
    world = _world_reference(density, reach)
    return (density - STRUCTURE_MARGIN * world) / (1.0 - world)


def _world_reference(change: np.ndarray, reach: np.ndarray, band_px: int = REFERENCE_BAND_PX) -> np.ndarray:
    """Per column, the world's level of a cue ``change`` [h,w] (change energy, fixed structure) just
    above the reach (the body cannot be there), [1,w]; columns without such a band take the median
    over all of them."""
    h, w = change.shape
    top = np.where(reach.any(axis=0), reach.argmax(axis=0), h)
    band = np.median(_rows_from(change, top, np.arange(w), -np.arange(1, band_px + 1)), axis=0)
    fine = top >= band_px
    fallback = float(np.median(band[fine])) if fine.any() else float(np.median(change))
    return np.where(fine, band, fallback)[None, :]


def _change_ratio(change: np.ndarray, top: np.ndarray, band_px: int = REFERENCE_BAND_PX) -> float:
    """Median change energy in a band above the silhouette over that in a band below it."""
    h = change.shape[0]
    on = np.flatnonzero((top < h) & (top >= band_px))
    if not len(on):
        return 0.0
    above = _rows_from(change, top[on], on, -np.arange(1, band_px + 1))
    below = _rows_from(change, top[on], on, np.arange(band_px))
    return float(np.median(above) / max(float(np.median(below)), 1e-6))


def _rows_from(values: np.ndarray, rows: np.ndarray, cols: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """``values`` [h,w] at rows ``rows + offset`` (clipped to the image) of columns ``cols`` [K],
    [len(offsets), K]."""
    picked = np.clip(rows[None, :] + offsets[:, None], 0, values.shape[0] - 1)
    return values[picked, cols[None, :]]


def upsample(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """A reduced-resolution mask at the camera's resolution, bool [height,width] (bilinear, then > 1/2)."""
    image = PIL.Image.fromarray(mask.astype(np.uint8) * 255).resize((width, height), PIL.Image.BILINEAR)
    return np.asarray(image) >= 128
