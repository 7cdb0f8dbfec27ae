"""Camera models a pinhole camera can be stored as: the ideal pinhole itself, an OpenCV pinhole with
zero distortion (identical rays), or an f-theta model fitted to the pinhole's angle -> radius mapping.

Image conventions are NCore's: pixel (0, 0) is the top-left *corner* of the top-left pixel, so the
centre of pixel (i, j) is (i + 0.5, j + 0.5). NCore's f-theta model alone stores its principal point
in the pixel-*centre* convention (it adds 0.5 internally); :func:`fit_ftheta` converts.

The f-theta fit (NCore ``FThetaCameraModel``):

    image_point = A @ (delta(theta) * u) + principal_point,   A = [[c, d], [e, 1]],  u = unit xy of the ray

An ideal pinhole maps a ray at angle theta from the optical axis to ``(fx tan(theta) ux, fy tan(theta) uy)``,
so with ``c = fx / fy`` (``d = e = 0``) the f-theta model reproduces it exactly when
``delta(theta) = fy tan(theta)``. The *reference* polynomial is the backward one,
``theta = bw(r) ~ atan(r / fy)`` (``r`` the radius after undoing ``A``): atan is far better
conditioned for a degree-5 polynomial than tan, which matters for wide cameras (OPV2V's 100° HFOV).
The forward polynomial ``fw(theta) ~ fy tan(theta)`` is only the start of NCore's Newton inversion
of ``bw``. Both are least-squares fits over the radii of every pixel centre (weighted by how many
pixel centres share a radius), refined towards the worst error by iterative re-weighting.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Polynomial degree of both f-theta polynomials (NCore stores at most 6 coefficients: degree 5).
FTHETA_DEGREE = 5
#: Radius bins of the fit (pixel centres are binned by their radius from the principal point).
FIT_BINS = 4000
#: Re-weighting rounds that trade median error for worst error.
REWEIGHT_ROUNDS = 10
#: ``max_angle`` is the largest pixel-corner angle times this (a ray just outside the image projects).
MAX_ANGLE_MARGIN = 1.02
#: Radii on which the fit's error is computed exactly (see :func:`projection_errors_px`).
RADIAL_SAMPLES = 65536
#: Newton iterations of the projection, as NCore's ``FThetaCameraModel`` runs them.
NEWTON_ITERATIONS = 3


@dataclass(frozen=True)
class Pinhole:
    """An ideal pinhole camera.

    Attributes:
        focal_length_px: (fx, fy), pixels.
        principal_point_px: (cx, cy), pixels, NCore pixel-corner convention.
        resolution_px: (width, height).
    """

    focal_length_px: tuple[float, float]
    principal_point_px: tuple[float, float]
    resolution_px: tuple[int, int]

    def project(self, xyz_camera_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image coordinates (u, v), px, float64 [N] each, of points in the camera frame (OpenCV: x
        right, y down, z forward), float [N,3], z > 0 (the caller culls the points behind)."""
        (fx, fy), (cx, cy) = self.focal_length_px, self.principal_point_px
        z = xyz_camera_m[:, 2]
        return fx * xyz_camera_m[:, 0] / z + cx, fy * xyz_camera_m[:, 1] / z + cy

    def scaled(self, width_px: int, height_px: int) -> Pinhole:
        """The same camera for its images resized to (width_px, height_px) (e.g. decoded with JPEG DCT
        scaling): focal length and principal point scaled per axis."""
        sx, sy = width_px / self.resolution_px[0], height_px / self.resolution_px[1]
        (fx, fy), (cx, cy) = self.focal_length_px, self.principal_point_px
        return Pinhole((fx * sx, fy * sy), (cx * sx, cy * sy), (width_px, height_px))

    def image_rays(self, u_px: np.ndarray, v_px: np.ndarray) -> np.ndarray:
        """The rays through image points (``u_px``, ``v_px``: px, float, any one shape), in the camera
        frame with z = 1, float64 [...,3]: the inverse of :meth:`project`."""
        (fx, fy), (cx, cy) = self.focal_length_px, self.principal_point_px
        u, v = np.asarray(u_px, dtype=np.float64), np.asarray(v_px, dtype=np.float64)
        return np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)

    def pixel_rays(self, step_px: int = 1) -> np.ndarray:
        """The rays through the centres of every ``step_px``-th pixel's ``step_px`` square, in the camera
        frame with z = 1, float64 [H,W,3] (H, W: the rows and columns sampled)."""
        width, height = self.resolution_px
        u, v = np.meshgrid(np.arange(0, width, step_px) + step_px / 2, np.arange(0, height, step_px) + step_px / 2)
        return self.image_rays(u, v)


@dataclass(frozen=True)
class FThetaFit:
    """An f-theta model fitted to a :class:`Pinhole`, in NCore ``FThetaCameraModelParameters`` terms.

    Attributes:
        principal_point_px: (cx, cy), pixel-*centre* convention (the pinhole's minus 0.5), float32.
        pixeldist_to_angle: backward (reference) polynomial, radians per pixel power, float32 [6].
        angle_to_pixeldist: forward polynomial, pixels per radian power, float32 [6].
        max_angle_rad: largest ray angle that projects.
        linear_cde: (c, d, e) of the linear term, float32 [3].
        max_error_px, median_error_px: over every pixel centre, the distance between the pinhole's
            projection (the pixel centre itself) and the f-theta projection of the same ray.
    """

    principal_point_px: np.ndarray
    pixeldist_to_angle: np.ndarray
    angle_to_pixeldist: np.ndarray
    max_angle_rad: float
    linear_cde: np.ndarray
    max_error_px: float
    median_error_px: float

    def meta(self) -> dict:
        """The fit's figures, as stored in the camera's metadata."""
        return {
            "reference_polynomial": "pixeldist_to_angle (fitted to atan(r / fy))",
            "degree": FTHETA_DEGREE,
            "max_reprojection_error_px": round(self.max_error_px, 5),
            "median_reprojection_error_px": round(self.median_error_px, 5),
            "measured_over": "every pixel centre: the pinhole ray through it, projected by the f-theta model",
        }


@dataclass(frozen=True)
class FTheta:
    """An f-theta camera as NCore stores it (``FThetaCameraModelParameters`` with the
    pixel-distance -> angle reference polynomial), for projecting points.

    Attributes:
        principal_point_px: (cx, cy), NCore's pixel-*centre* convention for this model.
        pixeldist_to_angle: backward (reference) polynomial [6]; angle_to_pixeldist: forward [6].
        linear_cde: (c, d, e) of the linear term; max_angle_rad: the largest ray angle that projects.
        resolution_px: (width, height).
    """

    principal_point_px: tuple[float, float]
    pixeldist_to_angle: np.ndarray
    angle_to_pixeldist: np.ndarray
    linear_cde: tuple[float, float, float]
    max_angle_rad: float
    resolution_px: tuple[int, int]

    def project(self, xyz_camera_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image coordinates (u, v), px, NCore's pixel-corner convention (as :meth:`Pinhole.project`),
        float64 [N] each, of camera-frame points (OpenCV axes) [N,3]; NaN beyond ``max_angle_rad``.
        The radius solves the reference polynomial by Newton from the forward one, as NCore does."""
        xyz = np.asarray(xyz_camera_m, dtype=np.float64)
        rho = np.hypot(xyz[:, 0], xyz[:, 1])
        theta = np.arctan2(rho, xyz[:, 2])
        bw = np.asarray(self.pixeldist_to_angle, np.float64)
        r = _inverse(bw, np.asarray(self.angle_to_pixeldist, np.float64), theta)
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(rho > 0, r / rho, 0.0)
        scale = np.where(theta <= self.max_angle_rad, scale, np.nan)
        px, py = xyz[:, 0] * scale, xyz[:, 1] * scale
        c, d, e = self.linear_cde
        cx, cy = self.principal_point_px
        return c * px + d * py + cx + 0.5, e * px + py + cy + 0.5


def _pixel_offsets(pinhole: Pinhole) -> tuple[np.ndarray, np.ndarray]:
    """Offsets of every pixel centre from the principal point, after undoing the linear term:
    (dx / c, dy) with c = fx / fy. Returns x [W] and y [H], float64."""
    (fx, fy), (cx, cy), (width, height) = pinhole.focal_length_px, pinhole.principal_point_px, pinhole.resolution_px
    return (np.arange(width) + 0.5 - cx) * (fy / fx), np.arange(height) + 0.5 - cy


def _radii(pinhole: Pinhole) -> np.ndarray:
    """Radius of every pixel centre (linear term undone), float64 [H,W]."""
    x, y = _pixel_offsets(pinhole)
    return np.sqrt(x[None, :] ** 2 + y[:, None] ** 2)


def _lstsq_odd_free(variable: np.ndarray, target: np.ndarray, weight: np.ndarray, scale: float) -> np.ndarray:
    """Coefficients c_0..c_5 (c_0 = 0) of sum_k c_k v^k fitted to ``target`` in weighted least squares,
    solved in the scaled variable v / scale for conditioning. float64 [6]."""
    powers = np.arange(1, FTHETA_DEGREE + 1)
    design = (variable[:, None] / scale) ** powers[None, :]
    coef, *_ = np.linalg.lstsq(design * weight[:, None], target * weight, rcond=None)
    return np.concatenate([[0.0], coef / scale**powers])


def _polyval(coef: np.ndarray, x: np.ndarray) -> np.ndarray:
    """sum_k coef[k] x^k (Horner), float64."""
    out = np.zeros_like(x)
    for c in coef[::-1]:
        out = out * x + c
    return out


def _inverse(bw: np.ndarray, fw: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """r with bw(r) = theta, by Newton from fw(theta) (what NCore's projection computes)."""
    dbw = bw[1:] * np.arange(1, len(bw))
    r = _polyval(fw, theta)
    for _ in range(NEWTON_ITERATIONS):
        r = r - (_polyval(bw, r) - theta) / _polyval(dbw, r)
    return r


def projection_errors_px(pinhole: Pinhole, bw: np.ndarray, fw: np.ndarray) -> np.ndarray:
    """For every pixel centre: the distance (px) between it and the f-theta projection (polynomials
    ``bw`` reference, ``fw`` start) of the pinhole ray through it. float64 [H*W].

    The radial error depends on the radius alone: it is computed exactly on ``RADIAL_SAMPLES`` radii
    up to the farthest pixel centre and interpolated to each pixel centre's radius (the spacing is
    below 0.03 px, where the error changes by far less than 1e-6 px), then mapped back through the
    linear term along the pixel's direction."""
    fx, fy = pinhole.focal_length_px
    x, y = _pixel_offsets(pinhole)
    r = _radii(pinhole)
    radii = np.linspace(0.0, float(r.max()), RADIAL_SAMPLES)
    radial_error = np.abs(_inverse(bw, fw, np.arctan(radii / fy)) - radii)
    errors = np.interp(r, radii, radial_error)
    if fx != fy:
        with np.errstate(invalid="ignore", divide="ignore"):
            errors *= np.where(r > 0, np.hypot(x[None, :] * fx / fy, y[:, None]) / r, 1.0)
    return errors.ravel()


def fit_ftheta(pinhole: Pinhole) -> FThetaFit:
    """Fit an f-theta model to ``pinhole`` over its whole image (see the module docstring)."""
    fx, fy = pinhole.focal_length_px
    (cx, cy), (width, height) = pinhole.principal_point_px, pinhole.resolution_px
    counts, edges = np.histogram(_radii(pinhole), bins=FIT_BINS)
    used = counts > 0
    r = (0.5 * (edges[1:] + edges[:-1]))[used]
    weight = np.sqrt(counts[used].astype(np.float64))
    scale = float(r.max())
    theta = np.arctan(r / fy)
    px_per_rad = (fy**2 + r**2) / fy  # d r / d theta: angle errors -> pixels
    bw_weight = weight * px_per_rad
    for _ in range(REWEIGHT_ROUNDS):
        bw = _lstsq_odd_free(r, theta, bw_weight, scale)
        error_px = np.abs(_polyval(bw, r) - theta) * px_per_rad
        bw_weight = bw_weight * np.sqrt(1.0 + error_px / max(float(np.median(error_px)), 1e-12))
    fw = _lstsq_odd_free(theta, r, weight, float(theta.max()))
    bw32, fw32 = bw.astype(np.float32), fw.astype(np.float32)
    errors = projection_errors_px(pinhole, bw32.astype(np.float64), fw32.astype(np.float64))
    corners_x = np.array([0.0 - cx, width - cx]) * (fy / fx)
    corners_y = np.array([0.0 - cy, height - cy])
    corner_r = float(np.sqrt((np.abs(corners_x).max()) ** 2 + (np.abs(corners_y).max()) ** 2))
    return FThetaFit(
        principal_point_px=np.array([cx - 0.5, cy - 0.5], dtype=np.float32),
        pixeldist_to_angle=bw32,
        angle_to_pixeldist=fw32,
        max_angle_rad=float(np.arctan(corner_r / fy) * MAX_ANGLE_MARGIN),
        linear_cde=np.array([fx / fy, 0.0, 0.0], dtype=np.float32),
        max_error_px=float(errors.max()),
        median_error_px=float(np.median(errors)),
    )
