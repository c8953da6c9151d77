"""Synthetic sky/ground frames at a known attitude, and the thesis's video disturbances.

Scenes are rendered upright on a canvas larger than the frame (sky with a haze gradient and
clouds, a ground plane in perspective made of fields, optional roads and buildings that draw
strong straight lines), then rotated to the wanted roll and cropped, so the true horizon is exact.
Every random choice comes from the ``numpy.random.Generator`` passed in, so a seed reproduces a
frame.

The disturbances reproduce what the thesis saw on its radio video link (chapter 6.2.3) at a
controlled strength: random transmission noise, white or black stripes from lost vertical sync,
exposure and colour changes, glare when facing the sun, and radial lens distortion. They work on
any BGR frame, real or synthetic.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from horizon.camera import CameraModel
from horizon.geometry import OrientedLine

__all__ = [
    "SceneSpec",
    "render_scene",
    "random_spec",
    "add_noise",
    "add_sync_stripes",
    "shift_exposure",
    "shift_colour",
    "add_glare",
    "distort_frame",
    "render_through_lens",
    "DISTURBANCES",
    "apply_disturbance",
]

Image = NDArray[np.uint8]


@dataclass(frozen=True)
class SceneSpec:
    """What to render. ``offset_frac`` is measured like the detectors report it (vertical,
    at the image centre, fraction of height, positive below); a value beyond about +-1 puts the
    horizon outside the frame (all sky when positive, all ground when negative)."""

    width: int = 320
    height: int = 240
    roll_deg: float = 0.0
    offset_frac: float = 0.0
    clouds: float = 0.5
    haze: float = 0.3
    roads: int = 0
    buildings: int = 0
    hfov_deg: float = 60.0


def random_spec(
    rng: np.random.Generator,
    width: int = 320,
    height: int = 240,
    max_roll_deg: float = 45.0,
    max_offset_frac: float = 0.35,
    clutter: bool = False,
) -> SceneSpec:
    """A plausible random attitude and scene; ``clutter`` adds roads and buildings."""
    return SceneSpec(
        width=width,
        height=height,
        roll_deg=float(rng.uniform(-max_roll_deg, max_roll_deg)),
        offset_frac=float(rng.uniform(-max_offset_frac, max_offset_frac)),
        clouds=float(rng.uniform(0.0, 0.8)),
        haze=float(rng.uniform(0.0, 0.7)),
        roads=int(rng.integers(1, 4)) if clutter else 0,
        buildings=int(rng.integers(1, 6)) if clutter else 0,
        hfov_deg=float(rng.uniform(50.0, 90.0)),
    )


def render_scene(spec: SceneSpec, rng: np.random.Generator) -> tuple[Image, OrientedLine]:
    """Render one BGR frame and return it with its true horizon line."""
    w, h = spec.width, spec.height
    if w < 8 or h < 8:
        raise ValueError(f"synthetic frame must be at least 8x8 pixels, got {w}x{h}")
    side = int(math.ceil(math.hypot(w, h))) + 8
    cos_r = math.cos(math.radians(spec.roll_deg))
    # perpendicular distance of the horizon below the centre (upright canvas), in pixels
    rho_px = spec.offset_frac * h * cos_r
    if abs(cos_r) < 1e-6:
        rho_px = 0.0
    canvas_c = (side - 1) / 2.0
    horizon_y = canvas_c + rho_px
    focal_px = (w / 2.0) / math.tan(math.radians(spec.hfov_deg) / 2.0)

    canvas = _render_upright(side, horizon_y, focal_px, spec, rng)

    # rotate the upright canvas counter-clockwise by the roll and crop the frame from its middle
    rot = cv2.getRotationMatrix2D((canvas_c, canvas_c), spec.roll_deg, 1.0)
    rot[0, 2] -= canvas_c - (w - 1) / 2.0
    rot[1, 2] -= canvas_c - (h - 1) / 2.0
    frame = cv2.warpAffine(canvas, rot, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    truth = OrientedLine(90.0 - spec.roll_deg, rho_px, w, h)
    return np.asarray(frame, np.uint8), truth


def _render_upright(
    side: int, horizon_y: float, focal_px: float, spec: SceneSpec, rng: np.random.Generator
) -> Image:
    ys = np.arange(side, dtype=np.float32)[:, None]
    xs = np.arange(side, dtype=np.float32)[None, :] - (side - 1) / 2.0
    d = ys - horizon_y  # > 0 below the horizon

    # --- sky: a gradient from a pale horizon to a deeper zenith colour, with clouds
    zenith = np.array(rng.choice([[200, 140, 90], [210, 170, 130], [185, 175, 170]]), np.float32)
    zenith += rng.uniform(-15, 15, 3).astype(np.float32)
    pale = np.array([235, 228, 222], np.float32) + rng.uniform(-12, 12, 3).astype(np.float32)
    up = np.clip(-d / (0.8 * side), 0.0, 1.0) ** 0.6
    sky = pale[None, None, :] * (1.0 - up[..., None]) + zenith[None, None, :] * up[..., None]
    sky = np.broadcast_to(sky, (side, side, 3)).copy()
    if spec.clouds > 0:
        cloud = _smooth_noise(rng, side, cells=6) + 0.5 * _smooth_noise(rng, side, cells=14)
        cover = np.clip((cloud - (1.2 - spec.clouds)) * 3.0, 0.0, 1.0)[..., None]
        shade = rng.uniform(215, 250)
        sky = sky * (1 - cover) + shade * cover

    # --- ground: perspective fields sampled from a random patchwork texture
    depth_k = focal_px * 1.0  # camera height 1 unit; depth = k / d
    below = np.maximum(d, 0.5)
    z = depth_k / below  # distance along the ground
    gx = xs * z / focal_px
    tex = _field_texture(rng, 256)
    tex_scale = 256.0 / 40.0  # 40 units of ground per texture repeat
    map_x = (gx * tex_scale).astype(np.float32)
    map_y = np.broadcast_to((z * tex_scale).astype(np.float32), map_x.shape).copy()
    ground = cv2.remap(tex, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    ground = ground.astype(np.float32)
    mean_col = tex.reshape(-1, 3).mean(axis=0)
    # far fields blur into their average colour, then into the haze
    far = np.clip(z / 60.0, 0.0, 1.0)[..., None]
    ground = ground * (1 - far) + mean_col[None, None, :] * far
    if spec.haze > 0:
        haze_px = 2.0 + spec.haze * 0.08 * side
        veil = np.exp(-np.maximum(d, 0.0) / haze_px)[..., None] * spec.haze
        ground = ground * (1 - veil) + pale[None, None, :] * veil
    fine = rng.normal(0.0, 6.0, (side, side, 1)).astype(np.float32)
    ground += fine

    is_ground = (d >= 0)[..., None]
    img = np.where(is_ground, ground, sky)
    # anti-alias the boundary row
    frac = np.clip(d + 0.5, 0.0, 1.0)[..., None]
    img = sky * (1 - frac) + np.where(is_ground, ground, sky) * frac
    out = np.clip(img, 0, 255).astype(np.uint8)

    _draw_roads(out, rng, spec.roads, horizon_y, depth_k, focal_px)
    _draw_buildings(out, rng, spec.buildings, horizon_y, depth_k)
    return out


def _smooth_noise(rng: np.random.Generator, side: int, cells: int) -> NDArray[np.float32]:
    small = rng.random((cells, cells)).astype(np.float32)
    return np.asarray(cv2.resize(small, (side, side), interpolation=cv2.INTER_CUBIC), np.float32)


def _field_texture(rng: np.random.Generator, size: int) -> Image:
    palette = np.array(
        [[40, 110, 70], [50, 130, 90], [60, 95, 80], [70, 120, 140], [45, 80, 60], [90, 150, 150],
         [35, 70, 45], [80, 140, 110]],
        np.float32,
    )
    tex = np.empty((size, size, 3), np.float32)
    tex[:] = palette[int(rng.integers(len(palette)))]
    for _ in range(40):
        x0, y0 = rng.integers(0, size, 2)
        fw, fh = rng.integers(size // 16, size // 4, 2)
        col = palette[int(rng.integers(len(palette)))] + rng.uniform(-12, 12, 3)
        tex[y0 : y0 + fh, x0 : x0 + fw] = col
    tex += rng.normal(0.0, 8.0, tex.shape).astype(np.float32)
    return np.clip(tex, 0, 255).astype(np.uint8)


def _draw_roads(
    img: Image, rng: np.random.Generator, count: int, horizon_y: float, depth_k: float, focal_px: float
) -> None:
    side = img.shape[0]
    for i in range(count):
        colour = (200, 200, 205) if rng.random() < 0.6 else (60, 62, 65)
        if i % 2 == 0:
            # a road parallel to the horizon: the hardest distractor for a Hough maximum
            dist = rng.uniform(0.06, 0.35) * side
            y = int(round(horizon_y + dist))
            thick = max(2, int(round(dist / 12.0)))
            cv2.line(img, (0, y), (side - 1, y), colour, thick, cv2.LINE_AA)
        else:
            # a road running away from the camera, converging on a point of the horizon
            vx = rng.uniform(0.2, 0.8) * side
            bx = rng.uniform(-0.5, 1.5) * side
            cv2.line(img, (int(vx), int(horizon_y) + 2), (int(bx), side - 1), colour, 4, cv2.LINE_AA)


def _draw_buildings(
    img: Image, rng: np.random.Generator, count: int, horizon_y: float, depth_k: float
) -> None:
    side = img.shape[0]
    for _ in range(count):
        dist = rng.uniform(0.04, 0.4) * side
        base_y = horizon_y + dist
        scale = dist / (0.2 * side)
        bw = rng.uniform(20, 60) * scale
        bh = rng.uniform(10, 30) * scale
        x0 = rng.uniform(0.15, 0.85) * side
        wall = tuple(int(c) for c in rng.uniform(150, 245, 3))
        roof = tuple(int(c) for c in rng.uniform(30, 200, 3))
        p = np.array(
            [[x0, base_y], [x0 + bw, base_y], [x0 + bw, base_y - bh], [x0, base_y - bh]], np.int32
        )
        cv2.fillPoly(img, [p], wall, cv2.LINE_AA)
        r = np.array(
            [[x0 - 2, base_y - bh], [x0 + bw + 2, base_y - bh], [x0 + bw + 2, base_y - 1.3 * bh],
             [x0 - 2, base_y - 1.3 * bh]],
            np.int32,
        )
        cv2.fillPoly(img, [r], roof, cv2.LINE_AA)


# ---------------------------------------------------------------------------------------------
# disturbances


def add_noise(img: Image, rng: np.random.Generator, strength: float = 0.5) -> Image:
    """Analogue transmission noise at a falling signal-to-noise ratio: grain, chroma noise,
    impulsive 'snow' and short horizontal streaks. ``strength`` 0..1 (1 = barely usable)."""
    s = float(np.clip(strength, 0.0, 1.0))
    h, w = img.shape[:2]
    out = img.astype(np.float32)
    out += rng.normal(0.0, 45.0 * s, (h, w, 1)).astype(np.float32)
    out += rng.normal(0.0, 15.0 * s, (h, w, 3)).astype(np.float32)
    # snow: isolated white and black dots
    n_dots = int(0.04 * s * h * w)
    ys = rng.integers(0, h, n_dots)
    xs = rng.integers(0, w, n_dots)
    out[ys, xs] = rng.choice([0.0, 255.0], n_dots)[:, None]
    # streaks: short horizontal dashes from lost line sync
    for _ in range(int(30 * s * h / 240)):
        y = int(rng.integers(0, h))
        x = int(rng.integers(0, w))
        length = int(rng.integers(w // 20, w // 4))
        out[y, x : x + length] += rng.choice([-90.0, 90.0])
    return np.clip(out, 0, 255).astype(np.uint8)


def add_sync_stripes(
    img: Image,
    rng: np.random.Generator,
    count: int = 2,
    colour: str = "white",
    height_frac: tuple[float, float] = (0.02, 0.07),
) -> Image:
    """Full-width bands from a lost vertical sync: near-saturated white (or black) rows with a
    little noise and a soft one-pixel edge, at random heights."""
    if colour not in ("white", "black"):
        raise ValueError(f"stripe colour must be 'white' or 'black', got {colour!r}")
    h, w = img.shape[:2]
    out = img.astype(np.float32)
    level = 245.0 if colour == "white" else 12.0
    for _ in range(count):
        band = max(2, int(round(rng.uniform(*height_frac) * h)))
        y0 = int(rng.integers(0, max(1, h - band)))
        y1 = min(h, y0 + band)
        noise = rng.normal(0.0, 5.0, (y1 - y0, w, 1)).astype(np.float32)
        out[y0:y1] = level + noise
        for y, a in ((y0 - 1, 0.5), (y1, 0.5)):
            if 0 <= y < h:
                out[y] = (1 - a) * out[y] + a * level
    return np.clip(out, 0, 255).astype(np.uint8)


def shift_exposure(img: Image, gain: float = 1.5, gamma: float = 1.0) -> Image:
    """Brightness/contrast change as an auto-exposure swing does it: gain, gamma, clipping."""
    if gain <= 0 or gamma <= 0:
        raise ValueError(f"exposure gain and gamma must be positive, got {gain}, {gamma}")
    lut = np.clip(255.0 * ((np.arange(256) / 255.0) ** gamma) * gain, 0, 255).astype(np.uint8)
    return np.asarray(cv2.LUT(img, lut), np.uint8)


def shift_colour(
    img: Image, gains_bgr: tuple[float, float, float] = (1.2, 1.0, 0.8), saturation: float = 1.0
) -> Image:
    """White-balance drift (per-channel gains) and a saturation change."""
    out = img.astype(np.float32) * np.array(gains_bgr, np.float32)[None, None, :]
    if saturation != 1.0:
        grey = out.mean(axis=2, keepdims=True)
        out = grey + (out - grey) * saturation
    return np.clip(out, 0, 255).astype(np.uint8)


def add_glare(
    img: Image,
    rng: np.random.Generator,
    strength: float = 0.7,
    centre: tuple[float, float] | None = None,
) -> Image:
    """Looking toward the sun: a saturated disc, a wide bloom that washes out contrast, and a
    row of flare ghosts through the image centre."""
    h, w = img.shape[:2]
    s = float(np.clip(strength, 0.0, 1.0))
    if centre is None:
        centre = (float(rng.uniform(0.1, 0.9) * w), float(rng.uniform(0.05, 0.6) * h))
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    r = np.hypot(xx - centre[0], yy - centre[1]) / max(w, h)
    bloom = s * (255.0 * np.exp(-((r / 0.25) ** 2)) + 120.0 * np.exp(-r / 0.5))
    out = img.astype(np.float32) + bloom[..., None]
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    for k in (0.4, 0.9, 1.4):
        gx = centre[0] + (cx - centre[0]) * 2 * k
        gy = centre[1] + (cy - centre[1]) * 2 * k
        rad = int(max(3, 0.03 * w * (1 + k)))
        ghost = np.zeros((h, w), np.float32)
        cv2.circle(ghost, (int(gx), int(gy)), rad, 60.0 * s, -1, cv2.LINE_AA)
        out += ghost[..., None] * np.array([1.0, 0.9, 0.7], np.float32)
    return np.clip(out, 0, 255).astype(np.uint8)


def distort_frame(img: Image, camera: CameraModel, margin_px: tuple[int, int] = (0, 0)) -> Image:
    """What the lens makes of an ideal pinhole frame: each output pixel (distorted) takes the
    colour of the ideal pixel the lens maps onto it.

    A barrel lens sees more than the pinhole frame of the same focal length, so ``img`` may be
    rendered ``margin_px`` (x, y) larger on every side; the output is the camera's size.
    """
    mx, my = margin_px
    h, w = img.shape[0] - 2 * my, img.shape[1] - 2 * mx
    if h <= 0 or w <= 0:
        raise ValueError(f"margins {margin_px} leave nothing of a {img.shape[1]}x{img.shape[0]} frame")
    cam = camera.scaled_to(w, h)
    yy, xx = np.mgrid[0:h, 0:w]
    pts = np.column_stack([xx.ravel(), yy.ravel()]).astype(np.float64)
    src = cam.undistort_points(pts)
    map_x = (src[:, 0] + mx).reshape(h, w).astype(np.float32)
    map_y = (src[:, 1] + my).reshape(h, w).astype(np.float32)
    out = cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return np.asarray(out, np.uint8)


def render_through_lens(
    spec: SceneSpec, camera: CameraModel, rng: np.random.Generator
) -> tuple[Image, OrientedLine]:
    """Render a scene as seen through ``camera`` (size ``spec.width`` x ``spec.height``, its focal
    length overriding ``spec.hfov_deg``); the truth is in undistorted pixel coordinates, which
    is where detectors given the camera report the line."""
    # rendered at twice the size and reduced at the end: a barrel lens squeezes the edges of
    # the view, which would alias a one-sample-per-pixel rendering
    w, h = 2 * spec.width, 2 * spec.height
    cam = camera.scaled_to(w, h)
    # the whole border, not just the corners: with k2 > 0 an edge's middle can reach further
    tx, ty = np.linspace(0.0, w - 1.0, 65), np.linspace(0.0, h - 1.0, 49)
    border = np.concatenate(
        [
            np.column_stack([tx, np.zeros_like(tx)]),
            np.column_stack([tx, np.full_like(tx, h - 1.0)]),
            np.column_stack([np.zeros_like(ty), ty]),
            np.column_stack([np.full_like(ty, w - 1.0), ty]),
        ]
    )
    und = cam.undistort_points(border)
    mx = int(math.ceil(max(0.0, -und[:, 0].min(), und[:, 0].max() - (w - 1)))) + 2
    my = int(math.ceil(max(0.0, -und[:, 1].min(), und[:, 1].max() - (h - 1)))) + 2
    big_w, big_h = w + 2 * mx, h + 2 * my
    hfov = math.degrees(2.0 * math.atan((big_w / 2.0) / cam.fx_px))
    # the same line through the same centre: perpendicular distance kept, height fraction rescaled
    big_spec = replace(
        spec, width=big_w, height=big_h, offset_frac=spec.offset_frac * h / big_h, hfov_deg=hfov
    )
    big, big_truth = render_scene(big_spec, rng)
    truth = big_truth.translated(mx, my, w, h).scaled(spec.width, spec.height)
    frame = distort_frame(big, cam, (mx, my))
    small = cv2.resize(frame, (spec.width, spec.height), interpolation=cv2.INTER_AREA)
    return np.asarray(small, np.uint8), truth


# ---------------------------------------------------------------------------------------------
# named disturbances for the benchmark and tests

Disturbance = Callable[[Image, np.random.Generator, "OrientedLine | None"], Image]


def _random_exposure(img: Image, rng: np.random.Generator, truth: OrientedLine | None) -> Image:
    if rng.random() < 0.5:
        return shift_exposure(img, float(rng.uniform(1.3, 1.8)), float(rng.uniform(0.8, 1.3)))
    return shift_exposure(img, float(rng.uniform(0.45, 0.7)), float(rng.uniform(0.8, 1.4)))


def _random_colour(img: Image, rng: np.random.Generator, truth: OrientedLine | None) -> Image:
    gains = tuple(float(g) for g in rng.uniform(0.7, 1.3, 3))
    return shift_colour(img, (gains[0], gains[1], gains[2]), float(rng.uniform(0.3, 1.6)))


def _random_glare(img: Image, rng: np.random.Generator, truth: OrientedLine | None) -> Image:
    centre = None
    if truth is not None:
        # the sun is in the sky: somewhere above the horizon, not far from it
        ends = truth.border_points()
        if ends is not None:
            (x0, y0), (x1, y1) = ends
            a = float(rng.uniform(0.1, 0.9))
            nx, ny = truth.normal
            up = float(rng.uniform(0.05, 0.35)) * img.shape[0]
            centre = (x0 + a * (x1 - x0) - nx * up, y0 + a * (y1 - y0) - ny * up)
    return add_glare(img, rng, float(rng.uniform(0.4, 0.8)), centre)


DISTURBANCES: dict[str, Disturbance] = {
    "clean": lambda img, rng, truth: img,
    "noise": lambda img, rng, truth: add_noise(img, rng, float(rng.uniform(0.3, 0.6))),
    "stripes": lambda img, rng, truth: add_sync_stripes(img, rng, 2, "white"),
    "black-stripes": lambda img, rng, truth: add_sync_stripes(img, rng, 2, "black"),
    "exposure": _random_exposure,
    "colour": _random_colour,
    "glare": _random_glare,
}


def apply_disturbance(
    name: str, img: Image, rng: np.random.Generator, truth: OrientedLine | None = None
) -> Image:
    """Apply one named disturbance (see :data:`DISTURBANCES`) at a random strength drawn from
    ``rng``; ``truth``, when known, keeps the sun of ``glare`` in the sky."""
    try:
        fn = DISTURBANCES[name]
    except KeyError:
        raise ValueError(
            f"unknown disturbance {name!r}; choose from {', '.join(DISTURBANCES)}"
        ) from None
    return fn(img, rng, truth)
