"""Hough transforms over point lists: the thesis's all-angle vote and the oriented vote."""

from __future__ import annotations

import math

import numpy as np
import pytest

from horizon.hough import (
    HoughSpace,
    find_peaks,
    global_maximum,
    support_of,
    vote_all_angles,
    vote_oriented,
)


def _points_on(theta: float, rho: float, w: int, h: int, n: int = 80) -> np.ndarray:
    cx, cy = (w - 1) / 2, (h - 1) / 2
    t = np.linspace(-60, 60, n)
    x = cx + rho * math.cos(theta) - t * math.sin(theta)
    y = cy + rho * math.sin(theta) + t * math.cos(theta)
    return np.column_stack([x, y])


def test_all_angle_vote_finds_the_line() -> None:
    space = HoughSpace(160, 120)
    theta, rho = math.radians(80.0), 12.0
    acc = vote_all_angles(space, _points_on(theta, rho, 160, 120))
    peak = global_maximum(space, acc)
    assert peak is not None
    assert peak.theta_rad == pytest.approx(theta, abs=math.radians(1.0))
    assert peak.rho_px == pytest.approx(rho, abs=1.0)
    assert peak.votes >= 70


def test_points_outside_do_not_pile_up_at_the_edge() -> None:
    # a far point (after distortion correction) votes only for the few lines through it that
    # cross the image, not into the outermost distance bins
    space = HoughSpace(40, 30)
    acc = vote_all_angles(space, np.array([[500.0, 500.0]] * 50))
    assert acc[0].sum() + acc[-1].sum() == 0
    assert 0 < acc.sum() <= 50 * 8


def test_oriented_vote_and_several_peaks() -> None:
    space = HoughSpace(160, 120, n_theta=90)
    lines = [(math.radians(90.0), -20.0), (math.radians(60.0), 25.0)]
    pts = np.vstack([_points_on(t, r, 160, 120) for t, r in lines])
    normals = np.concatenate([np.full(80, t) for t, _ in lines])
    acc = vote_oriented(space, pts, normals, np.ones(len(pts)))
    peaks = find_peaks(space, acc, 4)
    found = {(round(math.degrees(p.theta_rad)), round(p.rho_px)) for p in peaks[:2]}
    assert any(abs(t - 90) <= 2 and abs(r + 20) <= 1 for t, r in found)
    assert any(abs(t - 60) <= 2 and abs(r - 25) <= 1 for t, r in found)
    # the same line with the opposite normal has the same support
    s = support_of(space, acc, np.radians([90.0, 270.0]), np.array([-20.0, 20.0]))
    assert s[0] == pytest.approx(s[1]) and s[0] > 0


def test_vertical_line_wraps_without_a_duplicate_peak() -> None:
    space = HoughSpace(100, 100, n_theta=90)
    pts = _points_on(math.radians(0.5), 10.0, 100, 100)
    acc = vote_oriented(space, pts, np.full(len(pts), math.radians(0.5)), np.ones(len(pts)))
    peaks = find_peaks(space, acc, 5, min_fraction=0.5)
    assert len(peaks) == 1


def test_empty_inputs() -> None:
    space = HoughSpace(50, 40)
    empty = np.zeros((0, 2))
    assert global_maximum(space, vote_all_angles(space, empty)) is None
    assert find_peaks(space, vote_oriented(space, empty, np.zeros(0), np.zeros(0)), 3) == []
