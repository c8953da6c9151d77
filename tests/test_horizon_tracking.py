"""Temporal tracking: confidence grows with agreement, decays without, never overrules."""

from __future__ import annotations

import numpy as np
import pytest

from horizon.geometry import wrap_deg
from horizon.synth import SceneSpec, render_scene
from horizon.tracking import HorizonTracker


def _frame(roll: float, offset: float = 0.05, seed: int = 0) -> np.ndarray:
    img, _ = render_scene(SceneSpec(320, 240, roll, offset, clouds=0.3, roads=1), np.random.default_rng(seed))
    return img


def test_confidence_rises_on_a_steady_sequence_and_follows_motion() -> None:
    tr = HorizonTracker()
    confidences = []
    for i in range(8):
        est = tr.update(_frame(2.0 * i))
        assert est.found and est.roll_deg is not None
        assert abs(wrap_deg(est.roll_deg - 2.0 * i)) < 0.5
        confidences.append(tr.confidence)
    assert confidences[-1] > confidences[0]
    assert confidences[-1] > 0.7
    predicted = tr.predicted_line()
    assert predicted is not None and predicted.roll_deg == pytest.approx(16.0, abs=1.5)


def test_missing_horizon_decays_to_single_frame_mode() -> None:
    tr = HorizonTracker()
    for _ in range(5):
        tr.update(_frame(0.0))
    blank = np.zeros((240, 320, 3), np.uint8)
    for _ in range(10):
        assert not tr.update(blank).found
    assert tr.predicted_line() is None  # confidence ran out: back to single frames
    est = tr.update(_frame(30.0))
    assert est.found and est.roll_deg is not None and abs(est.roll_deg - 30.0) < 0.5


def test_a_jump_is_reported_with_lowered_quality() -> None:
    tr = HorizonTracker()
    for _ in range(6):
        tr.update(_frame(0.0))
    single = HorizonTracker().update(_frame(25.0, seed=3))
    jumped = tr.update(_frame(25.0, seed=3))
    assert jumped.found and jumped.roll_deg is not None
    assert abs(jumped.roll_deg - 25.0) < 0.5  # the detector is not overruled
    assert jumped.quality < single.quality


def test_reset_on_frame_size_change() -> None:
    tr = HorizonTracker()
    tr.update(_frame(0.0))
    img, _ = render_scene(SceneSpec(160, 120, 5.0, 0.0), np.random.default_rng(1))
    assert tr.update(img).found
