"""Synthetic scenes: the truth line is where the rendered boundary is; disturbances behave."""

from __future__ import annotations

import numpy as np
import pytest

from horizon.camera import CameraModel
from horizon.synth import (
    DISTURBANCES,
    SceneSpec,
    add_glare,
    add_noise,
    add_sync_stripes,
    apply_disturbance,
    random_spec,
    render_scene,
    render_through_lens,
    shift_colour,
    shift_exposure,
)


def _side_means(img: np.ndarray, truth) -> tuple[float, float]:  # type: ignore[no-untyped-def]
    h, w = img.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w]
    nx, ny = truth.normal
    cx, cy = truth.centre
    d = nx * (xs - cx) + ny * (ys - cy) - truth.rho_px
    grey = img.mean(axis=2)
    return float(grey[d < -3].mean()), float(grey[d > 3].mean())


@pytest.mark.parametrize("roll", [-35.0, 0.0, 20.0, 150.0])
def test_truth_separates_bright_sky_from_ground(roll: float) -> None:
    rng = np.random.default_rng(1)
    img, truth = render_scene(SceneSpec(320, 240, roll, 0.1, clouds=0.0, haze=0.0), rng)
    assert img.shape == (240, 320, 3) and img.dtype == np.uint8
    sky, ground = _side_means(img, truth)
    assert sky > ground + 40
    assert truth.roll_deg == pytest.approx(roll)


def test_same_seed_same_frame() -> None:
    spec = random_spec(np.random.default_rng(7), clutter=True)
    a, _ = render_scene(spec, np.random.default_rng(3))
    b, _ = render_scene(spec, np.random.default_rng(3))
    assert np.array_equal(a, b)


def test_horizon_outside_gives_all_sky_or_all_ground() -> None:
    rng = np.random.default_rng(2)
    sky, truth = render_scene(SceneSpec(160, 120, 0.0, 1.5, haze=0.0), rng)
    assert truth.border_points() is None
    ground, _ = render_scene(SceneSpec(160, 120, 0.0, -1.5, haze=0.0), rng)
    assert sky.mean() > ground.mean() + 50


def test_stripes_cover_whole_rows() -> None:
    img = np.full((120, 160, 3), 100, np.uint8)
    out = add_sync_stripes(img, np.random.default_rng(0), count=2, colour="white")
    flat = (out.mean(axis=(1, 2)) > 220)
    assert flat.any()
    assert (out[flat].std(axis=(1, 2)) < 12).all()
    with pytest.raises(ValueError, match="colour"):
        add_sync_stripes(img, np.random.default_rng(0), colour="red")


def test_noise_strength_is_controlled() -> None:
    img = np.full((120, 160, 3), 128, np.uint8)
    weak = add_noise(img, np.random.default_rng(0), 0.1).astype(float).std()
    strong = add_noise(img, np.random.default_rng(0), 0.8).astype(float).std()
    assert 0 < weak < strong


def test_exposure_colour_glare() -> None:
    img = np.full((60, 80, 3), 100, np.uint8)
    assert shift_exposure(img, 2.0).mean() == pytest.approx(200, abs=1)
    assert shift_colour(img, (1.0, 1.0, 0.5))[..., 2].mean() == pytest.approx(50, abs=1)
    glared = add_glare(img, np.random.default_rng(0), 1.0, centre=(10.0, 10.0))
    assert glared[10, 10].mean() > 250 and glared[55, 75].mean() < glared[10, 10].mean()
    with pytest.raises(ValueError):
        shift_exposure(img, 0.0)


def test_every_named_disturbance_runs() -> None:
    rng = np.random.default_rng(0)
    img, truth = render_scene(SceneSpec(160, 120), rng)
    for name in DISTURBANCES:
        out = apply_disturbance(name, img, rng, truth)
        assert out.shape == img.shape and out.dtype == np.uint8
    with pytest.raises(ValueError, match="unknown disturbance"):
        apply_disturbance("fog", img, rng)


def test_lens_rendering_truth_is_in_undistorted_pixels() -> None:
    cam = CameraModel.from_hfov(320, 240, 100.0, k1=-0.28, k2=0.06)
    img, truth = render_through_lens(SceneSpec(320, 240, 10.0, 0.1, clouds=0.0, haze=0.0), cam, np.random.default_rng(0))
    assert img.shape == (240, 320, 3)
    # sample points just above and below the undistorted line, map them through the lens
    ends = truth.border_points()
    assert ends is not None
    (x0, y0), (x1, y1) = ends
    nx, ny = truth.normal
    for a in (0.2, 0.5, 0.8):
        px, py = x0 + a * (x1 - x0), y0 + a * (y1 - y0)
        above = cam.distort_points(np.array([[px - 6 * nx, py - 6 * ny]]))[0]
        below = cam.distort_points(np.array([[px + 6 * nx, py + 6 * ny]]))[0]
        sky = img[int(round(above[1])), int(round(above[0]))].mean()
        ground = img[int(round(below[1])), int(round(below[0]))].mean()
        assert sky > ground + 40
