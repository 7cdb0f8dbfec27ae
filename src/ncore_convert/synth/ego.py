"""The synthetic ego body in the AV2 / TbV cameras that see it, and camera pictures around it.

The cameras that see the ego vehicle, as the calibration predicts for a car of AV2's size:
``ring_front_center`` and the two stereo cameras the hood along the bottom of the image,
``ring_rear_left`` / ``ring_rear_right`` the rear corner of the body (trunk lid and flank). The
body is an outline in the ego frame (metres, x forward, y left, z up from the rear-axle origin),
projected with each camera's own calibration; the true mask is every pixel below the projected
outline, so it follows the mounting exactly.

Pictures: the world is a road-like gradient with large random blobs that change from picture to
picture (the world moving past). The light changes as in real logs, by tens of grey levels: the
camera's exposure varies by ±25 % between pictures. With ``shadows``, in 40 % of them a soft-edged
shadow (a building's, a tree's) also darkens part of the picture, body included, by 35-60 %.
Three bodies:

- ``easy``: the paint keeps its texture and only its lighting changes (±5 %, and the shadows).
- ``realistic`` (what real glossy paint does): the paint carries panel shading, a painted logo and
  text; each picture lights it differently (±40 % and a colour cast, with a shade ramp across it);
  it mirrors the moving scene (flipped about the silhouette and compressed, as on a convex panel,
  with 40-80 % of the scene's contrast, strongest at grazing angles near the silhouette); some
  pictures have saturated glare patches; and along stretches of the silhouette the paint takes the
  colour of the world just behind it, so the outline nearly vanishes there.
- ``glossy``: the realistic body with strong reflections: it mirrors 75-95 % of the moving scene's
  contrast, so its pixels change nearly as much as the world's.

``light="night"``: the world at a fifth of its daylight level with the same sensor noise, lit by
street lamps and headlights (saturated spots that move from picture to picture), which the paint
mirrors; the paint's own light drops with the world's.
"""

from __future__ import annotations

import io

import numpy as np
import PIL.Image
import PIL.ImageDraw
import PIL.ImageFilter
import PIL.ImageFont
import pyarrow as pa

from ncore_convert.transforms.camera.models import Pinhole

#: The cameras that see the ego body.
EGO_CAMERAS = ("ring_front_center", "ring_rear_left", "ring_rear_right", "stereo_front_left", "stereo_front_right")
#: Body renderings: still paint, what real paint does, and real paint with strong reflections.
BODIES = ("realistic", "easy", "glossy")
#: Scene light: daylight, or a night scene lit by lamps.
LIGHTS = ("day", "night")
#: Pictures per camera that the frames cycle through (each a different "world"), by default.
N_PICTURES = 16
#: Paint brightness varies by this factor between pictures: the easy body, and the realistic one.
LIGHTING = {"easy": (0.95, 1.05), "realistic": (0.6, 1.4)}
#: Share of the scene's contrast that the paint mirrors: the realistic body, and the glossy one.
REFLECTION = {"realistic": (0.4, 0.8), "glossy": (0.75, 0.95)}
#: Camera exposure changes between pictures (the whole image): tens of grey levels, as in real logs.
EXPOSURE = (0.75, 1.25)
#: Share of pictures with a soft-edged shadow across them, and how much it darkens (body included).
SHADOW_SHARE, SHADOW_DEPTH = 0.4, (0.35, 0.6)
#: A night scene: the world's light level relative to daylight, and the lamps in each picture.
NIGHT_GAIN, NIGHT_LAMPS = 0.2, (3, 7)


def body_outline_m(camera: str) -> np.ndarray:
    """The visible top outline of the ego body for ``camera``, ego frame, metres [K,3], ordered so
    that the region below it in the image is the body."""
    s = np.linspace(-1.0, 1.0, 41)
    if camera in ("ring_front_center", "stereo_front_left", "stereo_front_right"):
        # hood: its rounded front edge ~1 m above the road (the origin is ~0.32 m above it), the
        # sides rising towards the windscreen
        front = np.stack([3.70 - 0.25 * s**2, -0.85 * s, 0.47 - 0.05 * s**2], axis=1)
        left = np.stack([np.linspace(2.4, 3.45, 8), np.full(8, 0.85), np.linspace(0.62, 0.42, 8)], axis=1)
        return np.concatenate([left, front, left[::-1] * [1, -1, 1]])
    side = 1.0 if camera == "ring_rear_left" else -1.0
    flank = np.stack([np.linspace(1.0, -0.9, 30), np.full(30, 0.98 * side), np.full(30, 0.75)], axis=1)
    rear = np.stack([np.full(41, -0.9), 0.98 * side * -s, np.full(41, 0.75)], axis=1)
    return np.concatenate([flank, rear])


def true_mask(
    camera: str, T_camera_ego: np.ndarray, focal_px: float, cx_px: float, cy_px: float, width: int, height: int
) -> np.ndarray:
    """The ego pixels of ``camera`` (bool [H,W]): below the projected body outline. ``T_camera_ego``
    maps camera points (OpenCV axes) to the ego frame; the principal point is av2's (pixel centres
    at integers)."""
    mask = PIL.Image.new("L", (width, height), 0)
    if camera not in EGO_CAMERAS:
        return np.zeros((height, width), dtype=bool)
    T_ego_camera = np.linalg.inv(T_camera_ego)
    xyz = body_outline_m(camera) @ T_ego_camera[:3, :3].T + T_ego_camera[:3, 3]
    xyz = xyz[xyz[:, 2] > 0.05]
    # av2's principal point as is: u, v in av2's and PIL's convention (pixel centres at integers)
    u, v = Pinhole((focal_px, focal_px), (cx_px, cy_px), (width, height)).project(xyz)
    u, v = np.clip(u, -4 * width, 5 * width), np.clip(v, -4 * height, 5 * height)
    polygon = [(float(a), float(b)) for a, b in zip(u, v, strict=True)]
    polygon += [(float(u[-1]), 2.0 * height), (float(u[0]), 2.0 * height)]
    PIL.ImageDraw.Draw(mask).polygon(polygon, fill=255)  # PIL and av2 both put pixel centres at integers
    return np.asarray(mask) > 0


def _smooth_field(rng: np.random.Generator, width: int, height: int, cell_px: int) -> np.ndarray:
    """A random field in [-1, 1] that varies over about ``cell_px`` pixels, float32 [H,W]."""
    coarse = rng.uniform(-1, 1, (height // cell_px + 2, width // cell_px + 2)).astype(np.float32)
    image = PIL.Image.fromarray(coarse, mode="F").resize((width, height), PIL.Image.BILINEAR)
    return np.clip(pixels(image), -1, 1)


def pixels(image: PIL.Image.Image) -> np.ndarray:
    """The pixels of a one-band ``image`` as a read-only array [H,W]: a view through Pillow's Arrow
    export where its rows are one block of memory (no copy; ``np.asarray`` copies them through the
    raw encoder, ~18 ms for an AV2 picture), else a copy."""
    try:
        flat = pa.array(image).to_numpy(zero_copy_only=True)
    except ValueError:  # rows in several blocks (images over Pillow's block size)
        return np.asarray(image)
    return flat.reshape(image.height, image.width)


class _RealisticBody:
    """What stays fixed on a realistic body (its paint, markings, the silhouette's geometry) and
    what each picture changes (light, colour cast, reflections, glare, camouflaged stretches)."""

    def __init__(self, rng: np.random.Generator, mask: np.ndarray, body: str = "realistic", binning: int = 1) -> None:
        height, width = mask.shape
        self.rng, self.binning = rng, binning
        self.top = np.where(mask.any(axis=0), mask.argmax(axis=0), height).astype(np.float32)  # silhouette row
        self.r0 = int(self.top.min()) if mask.any() else height  # the body's rows: r0 and below
        rows = np.arange(height, dtype=np.float32)[:, None]
        depth = np.clip(rows - self.top, 0, None)  # px below the silhouette
        extent = max(float((height - self.top[self.top < height]).max(initial=1.0)), 1.0)
        self.depth = depth / extent  # 0 at the silhouette, ~1 at the deepest body row
        base = rng.uniform(50, 190)  # dark to white paint
        shading = 25 * _smooth_field(rng, width, height, 96 // binning) - 35 * self.depth  # curvature: darker below
        markings = PIL.Image.new("L", (width, height), 0)
        draw = PIL.ImageDraw.Draw(markings)
        cols = np.flatnonzero(self.top < height)
        if len(cols):
            cx = float(rng.uniform(np.percentile(cols, 30), np.percentile(cols, 70)))
            cy = float(np.median(self.top[cols]) + 0.45 * extent)
            r = 0.18 * extent
            draw.ellipse([cx - r, cy - r, cx + r, cy + r], outline=255, width=max(2, int(r / 6)))  # a logo
            font = PIL.ImageFont.load_default(size=max(10, int(0.12 * extent)))
            draw.text((cx + 1.3 * r, cy - 0.5 * r), "SELF-DRIVING TEST", fill=255, font=font)  # text
            gap = [(float(x), float(self.top[x] + 0.7 * extent)) for x in cols[::8]]  # a panel gap
            draw.line(gap, fill=160, width=max(1, 3 // binning))
        ink = np.asarray(markings, dtype=np.float32) / 255.0
        self.paint = np.clip(base + shading - 0.7 * base * ink + 60 * ink * (base < 100), 5, 250)
        lo, hi = REFLECTION[body]
        self.reflect = (lo + (hi - lo) * np.exp(-3 * self.depth)).astype(np.float32)
        self.compress = rng.uniform(1.5, 3.0)  # a convex panel minifies its mirror image
        # Stretches of the silhouette whose paint takes the colour of the world behind it.
        self.camouflage = np.zeros(width, dtype=np.float32)
        if len(cols):
            for _ in range(2):
                span = int(0.15 * len(cols))
                start = int(rng.integers(cols[0], max(cols[0] + 1, cols[-1] - span)))
                self.camouflage[start : start + span] = 1.0
        self.band = (np.clip(1.0 - self.depth / 0.25, 0, 1) * self.camouflage[None, :])[self.r0 :]
        self.paint, self.reflect = self.paint[self.r0 :], self.reflect[self.r0 :]

    def render(self, world: np.ndarray, light_gain: float = 1.0) -> np.ndarray:
        """The body's rows (``r0`` and below) of one picture over ``world`` (grey, float32 [H,W]),
        the paint lit at ``light_gain`` times daylight."""
        height, width = world.shape
        rng = self.rng
        rows = np.arange(self.r0, height, dtype=np.float32)[:, None]
        source = np.clip(self.top - self.compress * (rows - self.top), 0, height - 1).astype(np.int64)
        mirrored = np.take_along_axis(world, source, axis=0)  # flipped about the silhouette, compressed
        ramp_dir = rng.uniform(0, 2 * np.pi)
        u = np.linspace(-1, 1, width, dtype=np.float32)[None, :]
        v = np.linspace(-1, 1, height, dtype=np.float32)[self.r0 :, None]
        ramp = 1 + 0.15 * (np.cos(ramp_dir) * u + np.sin(ramp_dir) * v)
        light = light_gain * rng.uniform(*LIGHTING["realistic"]) * ramp
        behind = np.take_along_axis(world, np.clip(self.top - 3, 0, height - 1).astype(np.int64)[None, :], axis=0)
        lit = self.paint * light * (1 - self.band) + behind * self.band  # the silhouette matches the world here
        grey = (1 - self.reflect) * lit + self.reflect * mirrored
        if rng.random() < 0.5:  # glare: saturated patches where the sun catches the paint
            glare = PIL.Image.new("L", (width, height - self.r0), 0)
            cols = np.flatnonzero(self.top < height)
            for _ in range(int(rng.integers(1, 3))):
                x = float(rng.choice(cols))
                y = float(rng.uniform(self.top[int(x)], height)) - self.r0
                r = float(rng.uniform(0.02, 0.06)) * max(width, height)
                PIL.ImageDraw.Draw(glare).ellipse([x - r, y - 0.5 * r, x + r, y + 0.5 * r], fill=255)
            glare = np.asarray(glare.filter(PIL.ImageFilter.GaussianBlur(6 / self.binning)), dtype=np.float32) / 255.0
            grey = grey * (1 - glare) + 255.0 * glare
        return grey


def _shadow(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """A soft-edged shadow across a picture: the light's factor per pixel (1 in the sun), float32
    [H,W]; its edge at a random angle and place, blurred over 3-8 % of the width."""
    angle = rng.uniform(0, 2 * np.pi)
    x = np.arange(width, dtype=np.float32)[None, :] - rng.uniform(0, width)
    y = np.arange(height, dtype=np.float32)[:, None] - rng.uniform(0, height)
    soft = rng.uniform(0.03, 0.08) * width
    inside = np.clip((np.float32(np.cos(angle)) * x + np.float32(np.sin(angle)) * y) / soft + 0.5, 0, 1)
    return 1 - np.float32(rng.uniform(*SHADOW_DEPTH)) * inside


def _lamps(rng: np.random.Generator, width: int, height: int, binning: int) -> np.ndarray:
    """Street lamps and headlights in a night picture: saturating spots in the upper 60 % of the
    picture, added grey levels, float32 [H,W] (``binning``: as in :func:`pictures`)."""
    spots = PIL.Image.new("L", (width, height), 0)
    draw = PIL.ImageDraw.Draw(spots)
    for _ in range(int(rng.integers(*NIGHT_LAMPS))):
        x, y, r = rng.uniform(0, width), rng.uniform(0, 0.6 * height), rng.uniform(0.005, 0.02) * width
        draw.ellipse([x - r, y - r, x + r, y + r], fill=255)
    return 1.5 * np.asarray(spots.filter(PIL.ImageFilter.GaussianBlur(4 / binning)), dtype=np.float32)


def pictures(
    rng: np.random.Generator,
    width: int,
    height: int,
    mask: np.ndarray | None,
    parked: bool,
    body: str = "realistic",
    count: int = N_PICTURES,
    light: str = "day",
    shadows: bool = False,
    binning: int = 1,
) -> list[bytes]:
    """``count`` JPEGs of one camera (~0.45 MB each at AV2 resolutions): a different world in each
    (the same one when ``parked``), the body (``mask``, or none) rendered as ``body`` (one of
    ``BODIES``) in ``light`` (one of ``LIGHTS``), with moving ``shadows`` or not. The first ``k``
    pictures do not depend on ``count``. ``binning``: the camera is a full-size one whose pixels are
    binned ``binning`` x ``binning`` (``SynthConfig.camera_scale``): the same world in its field of
    view (blobs, shading and blurs in pixels divided by it) and its sensor noise divided by it, as
    averaging that many pixels does (what the ego-mask estimator sees of a full-size picture that it
    decodes at reduced size)."""
    v = np.linspace(0, 1, height, dtype=np.float32)[:, None]
    road = np.where(v < 0.45, 150 + 80 * v, 90 - 40 * (v - 0.45))
    world_seed = int(rng.integers(2**62))
    realistic = _RealisticBody(rng, mask, body, binning) if mask is not None and body != "easy" else None
    if mask is not None and realistic is None:
        paint = 70 + 25 * _smooth_field(rng, width, height, 64 // binning) + 40 * np.clip(1.2 - v, 0, 1)
    cast = np.array([0, 5, 12], dtype=np.float32)  # a blue cast, growing down the picture
    night = NIGHT_GAIN if light == "night" else 1.0
    out = []
    for _ in range(count):
        world_rng = np.random.default_rng(world_seed) if parked else rng  # parked: the same world each time
        # in place, but the same float32 operations in the same order as the plain expressions
        grey = _smooth_field(world_rng, width, height, 48 // binning)
        grey *= 45
        grey += 20 * _smooth_field(world_rng, width, height, max(1, 9 // binning))  # the world's blobs
        noise = rng.standard_normal((height, width), dtype=np.float32)
        if binning != 1:
            noise /= binning
        grey += road
        grey *= rng.uniform(*EXPOSURE) * night
        if light == "night":
            grey += _lamps(world_rng, width, height, binning)
        shade = _shadow(rng, width, height) if shadows and rng.random() < SHADOW_SHARE else None
        grey += 5 * noise
        if realistic is not None:
            r0 = realistic.r0
            gains = rng.uniform(0.9, 1.1, 3).astype(np.float32)  # the body's colour cast
            rendered = realistic.render(grey, night) + 2 * noise[r0:]
        elif mask is not None:
            grey = np.where(mask, night * paint * rng.uniform(*LIGHTING["easy"]) + 2 * noise, grey)
        if shade is not None:  # the shadow falls on the world and the body alike
            grey *= shade
            if realistic is not None:
                rendered *= shade[r0:]
        planes = []
        for c in range(3):  # channel by channel, as contiguous planes that PIL interleaves
            if realistic is not None:
                channel = grey.copy()
                channel[r0:] = np.where(mask[r0:], rendered * gains[c], grey[r0:])  # float32, as stored
                channel += cast[c] * v
            else:
                channel = grey + cast[c] * v
            planes.append(PIL.Image.fromarray(np.clip(channel, 0, 255, out=channel).astype(np.uint8)))
        buf = io.BytesIO()
        PIL.Image.merge("RGB", planes).save(buf, format="JPEG", quality=80)
        out.append(buf.getvalue())
    return out
