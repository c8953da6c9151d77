"""The detectors on synthetic frames: accuracy, the thesis's failure cases, honest answers."""

from __future__ import annotations

import numpy as np
import pytest

from horizon import HorizonEstimate, detect
from horizon.baseline import BaselineDetector
from horizon.camera import CameraModel
from horizon.detector import create_detector, method_names
from horizon.geometry import OrientedLine, wrap_deg
from horizon.robust import RobustDetector
from horizon.synth import (
    SceneSpec,
    add_noise,
    add_sync_stripes,
    random_spec,
    render_scene,
    render_through_lens,
)


def _errors(est: HorizonEstimate, truth: OrientedLine) -> tuple[float, float]:
    assert est.found and est.roll_deg is not None and est.offset_frac is not None
    return abs(wrap_deg(est.roll_deg - truth.roll_deg)), abs(est.offset_frac - truth.offset_frac)


def _scenes(n: int, seed: int, clutter: bool = False) -> list[tuple[np.ndarray, OrientedLine]]:
    rng = np.random.default_rng(seed)
    return [render_scene(random_spec(rng, clutter=clutter), rng) for _ in range(n)]


@pytest.mark.parametrize("method", ["baseline", "robust"])
def test_clean_frames(method: str) -> None:
    det = create_detector(method)
    for img, truth in _scenes(6, 1):
        roll_err, off_err = _errors(det.detect(img), truth)
        assert roll_err < (2.0 if method == "baseline" else 0.3)
        assert off_err < (0.02 if method == "baseline" else 0.005)


def test_estimate_fields_are_consistent() -> None:
    img, truth = _scenes(1, 2)[0]
    est = detect(img)
    assert est.method == "robust" and est.found and 0.0 < est.quality <= 1.0
    assert est.pitch_deg is None  # no intrinsics, no pitch
    assert est.p1 is not None and est.p2 is not None and est.line is not None
    assert OrientedLine.from_points(est.p1, est.p2, 320, 240).roll_deg == pytest.approx(est.roll_deg)
    assert (est.width, est.height) == (320, 240)


def test_sync_stripes_beat_the_baseline_but_not_robust() -> None:
    rng = np.random.default_rng(11)
    base, best = BaselineDetector(), RobustDetector()
    base_gross = best_gross = 0
    for img, truth in _scenes(8, 3):
        striped = add_sync_stripes(img, rng, 2, "white")
        b = base.detect(striped)
        if not b.found or _errors(b, truth)[0] > 10 or _errors(b, truth)[1] > 0.1:
            base_gross += 1
        r_err, o_err = _errors(best.detect(striped), truth)
        best_gross += int(r_err > 10 or o_err > 0.1)
    assert best_gross == 0
    assert base_gross >= 4


def test_noise_and_clutter() -> None:
    rng = np.random.default_rng(5)
    det = RobustDetector()
    for img, truth in _scenes(6, 4, clutter=True):
        roll_err, off_err = _errors(det.detect(add_noise(img, rng, 0.6)), truth)
        assert roll_err < 2.0 and off_err < 0.03


def test_upside_down() -> None:
    img, truth = render_scene(SceneSpec(320, 240, 170.0, 0.05, clouds=0.2), np.random.default_rng(0))
    roll_err, _ = _errors(detect(img), truth)
    assert roll_err < 1.0


@pytest.mark.parametrize("offset", [1.6, -1.6])
def test_no_horizon_in_sky_or_ground(offset: float) -> None:
    img, _ = render_scene(SceneSpec(320, 240, 10.0, offset, clouds=0.0, roads=0), np.random.default_rng(1))
    est = detect(img)
    assert not est.found
    assert est.roll_deg is None and est.p1 is None and 0.0 <= est.quality < 0.35


def test_no_horizon_in_lost_signal() -> None:
    img = np.random.default_rng(0).integers(0, 256, (240, 320, 3)).astype(np.uint8)
    assert not detect(img).found
    assert not detect(np.zeros((240, 320, 3), np.uint8)).found
    assert not detect(np.zeros((240, 320, 3), np.uint8), method="baseline").found


def test_lens_distortion_is_corrected_on_points() -> None:
    cam = CameraModel.from_hfov(320, 240, 100.0, k1=-0.28, k2=0.06)
    rng = np.random.default_rng(2)
    for roll in (-25.0, 15.0):
        img, truth = render_through_lens(SceneSpec(320, 240, roll, 0.12, haze=0.1), cam, rng)
        for method, tol in (("baseline", 2.0), ("robust", 0.5)):
            roll_err, off_err = _errors(create_detector(method, cam).detect(img), truth)
            assert roll_err < tol and off_err < 0.02


def test_pitch_with_intrinsics() -> None:
    cam = CameraModel.from_hfov(320, 240, 60.0)
    img, truth = render_scene(SceneSpec(320, 240, 5.0, 0.2, hfov_deg=60.0), np.random.default_rng(3))
    est = detect(img, camera=cam)
    assert est.pitch_deg is not None
    assert est.pitch_deg == pytest.approx(cam.attitude_deg(truth)[1], abs=0.3)
    assert est.pitch_deg > 0  # horizon below the centre: nose up


def test_grey_input_and_odd_sizes() -> None:
    img, truth = render_scene(SceneSpec(333, 201, 8.0, -0.1), np.random.default_rng(9))
    grey = img.mean(axis=2).astype(np.uint8)
    for frame in (img, grey):
        roll_err, off_err = _errors(detect(frame), truth)
        assert roll_err < 1.0 and off_err < 0.01


def test_bad_frames_and_names() -> None:
    with pytest.raises(ValueError, match="uint8"):
        detect(np.zeros((10, 10, 3), np.float32))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="too small"):
        detect(np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(ValueError, match="3 channels"):
        detect(np.zeros((20, 20, 4), np.uint8))
    with pytest.raises(ValueError, match="unknown horizon method"):
        detect(np.zeros((20, 20, 3), np.uint8), method="magic")
    assert {"baseline", "robust", "best"} <= set(method_names())
    assert create_detector("best").name == "robust"
