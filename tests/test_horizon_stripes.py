"""Sync-stripe rows: found where painted, not in flat sky or haze."""

from __future__ import annotations

import numpy as np

from horizon.stripes import inpaint_rows, stripe_rows


def _scene(h: int = 80, w: int = 107, horizon: int = 40, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.empty((h, w), np.float64)
    img[:horizon] = np.linspace(170, 215, horizon)[:, None]
    img[horizon:] = 90
    img += rng.normal(0, 8, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def test_white_and_black_bands_are_found() -> None:
    img = _scene()
    img[20:24] = 246
    img[55:58] = 10
    flags = stripe_rows(img)
    assert flags[20:24].all() and flags[55:58].all()
    assert flags.sum() == 7


def test_blended_edge_rows_and_bottom_band() -> None:
    img = _scene()
    img[30:34] = 245
    img[29] = 226  # half-covered rows from resampling
    img[34] = 230
    img[77:80] = 244
    flags = stripe_rows(img)
    assert flags[30:34].all() and flags[77:].all()


def test_flat_sky_and_haze_ramp_are_not_stripes() -> None:
    img = _scene()
    img[:25] = 254  # over-exposed sky from the top
    img[36:40] = np.array([236, 227, 214, 187])[:, None]  # sky fading into haze
    assert not stripe_rows(img).any()


def test_inpaint_removes_the_band_edges() -> None:
    img = _scene()
    img[20:24] = 246
    flags = stripe_rows(img)
    out = inpaint_rows(img, flags)
    grad = np.abs(np.diff(out.astype(float).mean(axis=1)))
    assert grad[17:25].max() < 15
    assert np.array_equal(out[:18], img[:18])
