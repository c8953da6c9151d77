"""Sky/ground statistics: the separation score of candidate lines."""

from __future__ import annotations

import math

import numpy as np
import pytest

from horizon.skyground import SkyGroundStats


def _two_colour(w: int = 40, h: int = 30, row: int = 12, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.empty((h, w, 3), np.float64)
    img[:row] = (210, 180, 150)
    img[row:] = (60, 110, 70)
    img += rng.normal(0, 6, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def _level(row: int, h: int) -> tuple[float, float]:
    # a line between rows row-1 and row, normal pointing down
    return math.pi / 2, row - 0.5 - (h - 1) / 2


def test_true_split_scores_highest() -> None:
    img = _two_colour()
    stats = SkyGroundStats(img)
    rows = [4, 8, 12, 16, 24]
    t = np.full(len(rows), math.pi / 2)
    rho = np.array([_level(r, 30)[1] for r in rows])
    sp = stats.evaluate(t, rho)
    assert int(np.argmax(sp.separation)) == 2
    assert sp.separation[2] > 0.9
    assert sp.grey_neg[2] > sp.grey_pos[2]  # sky (negative side, above) is brighter
    assert sp.positive_share[2] == pytest.approx(18 / 30, abs=0.02)
    # Fisher direction points from sky to ground colours: ground is greener than it is blue
    f = sp.fisher_bgr[2]
    assert f @ (np.array([60, 110, 70]) - np.array([210, 180, 150])) > 0


def test_invariant_to_linear_colour_change() -> None:
    img = _two_colour().astype(np.float64)
    mix = np.array([[0.5, 0.2, 0.1], [0.1, 0.6, 0.1], [0.0, 0.2, 0.7]])
    other = np.clip(img @ mix.T + 10, 0, 255).astype(np.uint8)
    t = np.array([math.pi / 2, math.pi / 3])
    rho = np.array([_level(12, 30)[1], 3.0])
    a = SkyGroundStats(img.astype(np.uint8)).evaluate(t, rho).separation
    b = SkyGroundStats(other).evaluate(t, rho).separation
    assert a == pytest.approx(b, abs=0.03)


def test_noise_has_no_split() -> None:
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (30, 40, 3)).astype(np.uint8)
    sp = SkyGroundStats(img).evaluate(np.array([math.pi / 2, 1.0]), np.array([0.0, 4.0]))
    assert np.all(sp.separation < 0.1)


def test_line_outside_separates_nothing_and_grey_frames_stay_finite() -> None:
    grey = np.full((30, 40, 3), 128, np.uint8)
    grey[15:] = 60
    sp = SkyGroundStats(grey).evaluate(np.array([math.pi / 2, math.pi / 2]), np.array([100.0, -0.5]))
    assert sp.separation[0] == 0.0
    assert np.isfinite(sp.separation).all() and sp.separation[1] > 0.9


def test_weights_remove_rows() -> None:
    img = _two_colour()
    img[20:23] = 255  # a stripe in the ground
    weights = np.ones((30, 40))
    weights[20:23] = 0.0
    t, rho = _level(12, 30)
    with_w = SkyGroundStats(img, weights).evaluate(np.array([t]), np.array([rho])).separation[0]
    without = SkyGroundStats(img).evaluate(np.array([t]), np.array([rho])).separation[0]
    assert with_w > without


def test_texture_feature_tells_smooth_sky_from_textured_ground() -> None:
    img = np.full((30, 40, 3), 250, np.uint8)  # over-exposed: sky and a road both white
    texture = np.zeros((30, 40), np.float32)
    texture[12:] = np.random.default_rng(0).uniform(20, 60, (18, 40))
    texture[20:23] = 0.0  # the flat road
    t = np.full(2, math.pi / 2)
    rho = np.array([_level(12, 30)[1], _level(23, 30)[1]])
    sp = SkyGroundStats(img, texture=texture).evaluate(t, rho)
    assert sp.separation[0] > sp.separation[1]
    assert sp.texture_pos[0] > sp.texture_neg[0]
