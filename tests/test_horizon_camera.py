"""Camera model: radial distortion through the look-up table, attitude from the horizon, files."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from horizon.camera import CameraError, CameraModel
from horizon.geometry import OrientedLine


def _cam() -> CameraModel:
    return CameraModel(320, 240, 200.0, 205.0, 161.0, 118.0, k1=-0.25, k2=0.05)


def test_undistort_matches_opencv() -> None:
    cam = _cam()
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(0, 319, 200), rng.uniform(0, 239, 200)])
    ours = cam.undistort_points(pts)
    dist = np.array([cam.k1, cam.k2, 0.0, 0.0, cam.k3])
    ref = cv2.undistortPoints(
        pts.reshape(-1, 1, 2), cam.matrix(), dist, P=cam.matrix(),
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12),
    ).reshape(-1, 2)
    assert np.max(np.abs(ours - ref)) < 0.02


def test_distort_undoes_undistort() -> None:
    cam = _cam()
    pts = np.array([[0.0, 0.0], [319.0, 239.0], [160.0, 120.0], [10.0, 200.0]])
    assert np.allclose(cam.distort_points(cam.undistort_points(pts)), pts, atol=0.01)


def test_no_distortion_is_identity() -> None:
    cam = CameraModel.from_hfov(320, 240, 60.0)
    pts = np.array([[1.0, 2.0], [300.0, 200.0]])
    assert np.array_equal(cam.undistort_points(pts), pts)


def test_folding_lens_is_refused() -> None:
    with pytest.raises(CameraError, match="folds back"):
        CameraModel(320, 240, 100.0, 100.0, 160.0, 120.0, k1=-0.9)


def test_pitch_sign_nose_up_moves_horizon_down() -> None:
    cam = CameraModel.from_hfov(320, 240, 90.0)  # f = 160 px
    f = cam.fx_px
    below = OrientedLine.from_roll_offset(0.0, (f * math.tan(math.radians(10.0))) / 240, 320, 240)
    roll, pitch = cam.attitude_deg(below)
    assert pitch == pytest.approx(10.0, abs=1e-6) and roll == pytest.approx(0.0, abs=1e-9)
    above = OrientedLine.from_roll_offset(0.0, -(f * math.tan(math.radians(5.0))) / 240, 320, 240)
    assert cam.attitude_deg(above)[1] == pytest.approx(-5.0, abs=1e-6)


def test_pitch_independent_of_roll() -> None:
    cam = CameraModel.from_hfov(640, 480, 70.0)
    d = cam.fx_px * math.tan(math.radians(8.0))
    for roll in (-40.0, 0.0, 25.0):
        line = OrientedLine.from_roll_offset(roll, d / math.cos(math.radians(roll)) / 480, 640, 480)
        r, p = cam.attitude_deg(line)
        assert r == pytest.approx(roll, abs=1e-6)
        assert p == pytest.approx(8.0, abs=1e-6)


def test_scaled_camera_gives_same_attitude() -> None:
    cam = CameraModel.from_hfov(640, 480, 70.0)
    line = OrientedLine.from_roll_offset(12.0, 0.1, 640, 480)
    assert cam.attitude_deg(line) == pytest.approx(cam.attitude_deg(line.scaled(320, 240)), abs=1e-6)


def test_load_json_and_toml(tmp_path: Path) -> None:
    j = tmp_path / "cam.json"
    j.write_text(json.dumps({"width": 320, "height": 240, "fx": 200, "fy": 200, "cx": 160, "cy": 120, "k1": -0.1}))
    assert CameraModel.load(j).k1 == -0.1
    t = tmp_path / "cam.toml"
    t.write_text("width = 640\nheight = 480\nhfov_deg = 90.0\n")
    assert CameraModel.load(t).fx_px == pytest.approx(320.0)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ('{"width": 320, "height": 240}', "missing field 'fx'"),
        ('{"width": 320, "height": 240, "hfov_deg": "wide"}', "'hfov_deg' must be a number"),
        ('{"width": 320, "height": 240, "hfov_deg": 200}', "field of view"),
        ("[1, 2]", "top level"),
        ('{"width": 320,\n "height": }', "line 2"),
    ],
)
def test_bad_camera_files_name_the_problem(tmp_path: Path, text: str, match: str) -> None:
    p = tmp_path / "bad.json"
    p.write_text(text)
    with pytest.raises(CameraError, match=match) as info:
        CameraModel.load(p)
    assert str(p) in str(info.value)


def test_missing_camera_file(tmp_path: Path) -> None:
    with pytest.raises(CameraError, match="cannot read"):
        CameraModel.load(tmp_path / "nope.json")
