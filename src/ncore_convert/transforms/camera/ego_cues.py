"""The ego-mask estimator's per-pixel cues (:mod:`ncore_convert.transforms.camera.ego_mask`, steps 3-5): from
greyscale frames sampled across a log, at reduced resolution, the sums a silhouette is found from:
persistent edge orientation, mirror folds (glossy paint reflects the world just above it, flipped)
and fine-change energy with each frame's lighting divided out. Sums over frames, so that the cues
of two halves of a log add up to the whole's (the split-log agreement).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

LOG_OFFSET = 16.0  #: grey levels added before the log, so that dark noise does not dominate
LIGHT_SIGMA_PX = 4.0  #: brightness changes smoother than this (reduced pixels) are lighting, not motion
SMOOTH_TRUNCATE = 2.0  #: Gaussian smoothing is a scale, not a shape: cut at 2 sigma (95 % of the weight)
FOLD_PAIRS = 2  #: row differences compared on either side of a mirror fold
FOLD_SIGMA_PX = 2.0  #: along the row, over which a fold's anticorrelation is pooled


def _log_frames(frames: np.ndarray) -> np.ndarray:
    """Log grey levels of frames float32 [N,h,w], 0 at mid-grey, float32 [N,h,w] (the gradients and
    fold sums that follow stay in float32)."""
    logs = frames + np.float32(LOG_OFFSET)
    np.log(logs, out=logs)
    logs -= np.float32(np.log(LOG_OFFSET + 128.0))
    return logs


@dataclass(frozen=True)
class Cues:
    """What a set of frames says about each pixel, as sums over the frames, so that the cues of two
    disjoint sets add up to those of both (:meth:`__add__`); all at the reduced resolution.

    Attributes:
        frames: how many frames were summed.
        orientation: sum of the log-image gradients with doubled angles, complex64 [h,w].
        gradient_energy: sum of their magnitudes, float32 [h,w].
        folds: sums over frames of the mirrored row-difference products and of the two sides'
            energies (:func:`mirror_folds`), float32 [3,h,w].
        change: each frame's fine-change energy (:func:`change_energy`), float32 [N,h,w].
    """

    frames: int
    orientation: np.ndarray
    gradient_energy: np.ndarray
    folds: np.ndarray
    change: np.ndarray

    def __add__(self, other: Cues) -> Cues:
        return Cues(
            self.frames + other.frames,
            self.orientation + other.orientation,
            self.gradient_energy + other.gradient_energy,
            self.folds + other.folds,
            np.concatenate([self.change, other.change]),
        )


def cues(frames: np.ndarray) -> Cues:
    """The :class:`Cues` of greyscale frames, float32 [N,h,w] (grey levels)."""
    log_frames = _log_frames(frames)
    gx, gy = _sobel(log_frames)
    xx, yy, xy = (np.einsum("nyx,nyx->yx", a, b) for a, b in ((gx, gx), (gy, gy), (gx, gy)))
    # The sum of (gx + i gy)^2, the doubled angle (a contrast whose sign flips keeps its
    # orientation), and of its magnitude.
    return Cues(
        len(frames), (xx - yy + 2j * xy).astype(np.complex64), xx + yy, _fold_sums(log_frames), _change_frames(frames)
    )


def persistent_edges(c: Cues) -> np.ndarray:
    """Per pixel, how consistently the frames' gradients keep one orientation (0..1), float32 [h,w]."""
    total = ndimage.gaussian_filter(c.gradient_energy, 1.0)
    summed = c.orientation
    consistent = ndimage.gaussian_filter(summed.real, 1.0) ** 2 + ndimage.gaussian_filter(summed.imag, 1.0) ** 2
    coherence = np.sqrt(consistent) / (total + 1e-12)
    floor = 1.0 / np.sqrt(c.frames)  # random orientations average to about this
    mean_energy = c.gradient_energy / c.frames
    noise = np.median(mean_energy)  # a pixel this weak is flat: its orientation is noise
    significant = 1.0 - np.exp(-mean_energy / (0.5 * noise + 1e-12))
    return (np.clip((coherence - floor) / (1.0 - floor), 0.0, 1.0) * significant).astype(np.float32)


def _sobel(images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Sobel gradients (d/dx, d/dy) of images [N,h,w], as ``scipy.ndimage.sobel`` gives them
    (mirrored borders), by slicing: the filter's 3x3 taps on a padded copy."""
    p = np.pad(images, ((0, 0), (1, 1), (1, 1)), mode="symmetric")
    across_rows = p[:, 1:-1] * 2  # [N,h,w+2]
    across_rows += p[:, :-2]
    across_rows += p[:, 2:]
    across_cols = p[:, :, 1:-1] * 2  # [N,h+2,w]
    across_cols += p[:, :, :-2]
    across_cols += p[:, :, 2:]
    return across_rows[:, :, 2:] - across_rows[:, :, :-2], across_cols[:, 2:] - across_cols[:, :-2]


def _fold_sums(log_frames: np.ndarray) -> np.ndarray:
    """For :func:`mirror_folds`: per first body row, the sums over frames of the mirrored row
    differences' products and of each side's energy, float32 [3,h,w]."""
    diff = np.diff(log_frames, axis=1)  # [N,h-1,w]: row y+1 minus row y
    energy = np.einsum("nyx,nyx->yx", diff, diff)  # [h-1,w]: each row difference's, over the frames
    h = log_frames.shape[1]
    sums = np.zeros((3, h, log_frames.shape[2]), dtype=np.float32)  # product, energy above, energy below
    for j in range(FOLD_PAIRS):
        # For first body row t: the difference j rows above the fold line (diff[t-3-j]) against
        # its mirror j rows below it (diff[t-1+j]); the line sits 1.5 rows above t.
        rows = slice(3 + j, h - j)
        sums[0, rows] += np.einsum("nyx,nyx->yx", diff[:, : h - 3 - 2 * j], diff[:, 2 + 2 * j :])
        sums[1, rows] += energy[: h - 3 - 2 * j]
        sums[2, rows] += energy[2 + 2 * j :]
    return sums


def mirror_folds(c: Cues) -> np.ndarray:
    """Per pixel taken as the first body row of its column, how consistently the frames' vertical
    log-gradients reverse across a line 1.5 rows above it (-1..1; ~0 on the world),
    float32 [h,w].

    Glossy paint at a grazing angle is a mirror: right under the silhouette it shows the world just
    above it, flipped. Each frame's column profile then folds at the silhouette: the row
    differences below it are those above it, reversed in sign (and compressed). The world moves
    through, but the fold stays at the same rows, even where the mirror leaves no edge at all. The
    score is the anticorrelation, over frames and ``FOLD_SIGMA_PX`` along the row, of the row
    differences mirrored about the fold line (``FOLD_PAIRS`` of them).
    """
    sums = ndimage.gaussian_filter1d(c.folds, FOLD_SIGMA_PX, axis=2)
    return (-sums[0] / np.sqrt(sums[1] * sums[2] + 1e-12)).astype(np.float32)


def _change_frames(frames: np.ndarray) -> np.ndarray:
    """Each frame's fine-change energy (:func:`change_energy`) at half the resolution (2x2 bins: a
    regional cue, smoothed over more than that), float32 [N,ceil(h/2),ceil(w/2)]: its fine
    structure's departure from the frames' median once its smooth brightness change is divided out."""
    frames = _binned(frames)
    median = _over_frames(frames, 0.5)
    sigma = LIGHT_SIGMA_PX / 2
    smooth = {"sigma": (0, sigma, sigma), "truncate": SMOOTH_TRUNCATE}
    lit = ndimage.gaussian_filter(median, sigma, truncate=SMOOTH_TRUNCATE) + 1.0
    change = frames - ndimage.gaussian_filter(frames, **smooth) / lit * median
    fine = change - ndimage.gaussian_filter(change, **smooth)
    return ndimage.gaussian_filter(fine**2, (0, 1.25, 1.25), truncate=SMOOTH_TRUNCATE).astype(np.float32)


def _binned(frames: np.ndarray) -> np.ndarray:
    """Frames [N,h,w] averaged over 2x2 pixel bins (an odd last row or column repeated),
    float32 [N,ceil(h/2),ceil(w/2)]."""
    h, w = frames.shape[1:]
    p = np.pad(frames, ((0, 0), (0, h % 2), (0, w % 2)), mode="edge")
    return (p[:, 0::2, 0::2] + p[:, 1::2, 0::2] + p[:, 0::2, 1::2] + p[:, 1::2, 1::2]) * np.float32(0.25)


def change_energy(c: Cues) -> np.ndarray:
    """Per pixel, how much fine structure changes between frames once each frame's smooth
    brightness change (lighting, shade, exposure) is divided out, grey levels, float32 [h,w]: the
    75 % quantile over frames, so glare in a few frames does not count; computed on 2x2 bins and
    brought back to the full grid bilinearly.

    Linear grey levels, not logs: a reflection adds the scene scaled by the paint's reflectance,
    so on a dark glossy body it is small in grey levels although large relative to the paint.
    """
    binned = np.sqrt(_over_frames(c.change, 0.75))
    h, w = c.gradient_energy.shape
    full = ndimage.zoom(binned, (2, 2), order=1, mode="nearest", grid_mode=True)[:h, :w]
    return full.astype(np.float32)


def _over_frames(values: np.ndarray, q: float) -> np.ndarray:
    """The ``q`` quantile over the frames of ``values`` [N,h,w], [h,w], as ``np.quantile`` gives
    it (linear interpolation), from one sort (a few times faster for a handful of frames)."""
    ordered = np.sort(values, axis=0)
    position = q * (len(values) - 1)
    lo = int(position)
    hi = min(lo + 1, len(values) - 1)
    return ordered[lo] + (position - lo) * (ordered[hi] - ordered[lo])
