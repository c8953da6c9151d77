"""Sub-pixel refinement of a coarse line on a strip of the frame."""

from __future__ import annotations

import numpy as np
import pytest

from horizon.geometry import OrientedLine
from horizon.refine import refine_line
from horizon.synth import SceneSpec, render_scene


def test_refines_a_rough_line_onto_the_horizon() -> None:
    rng = np.random.default_rng(4)
    img, truth = render_scene(SceneSpec(320, 240, roll_deg=12.0, offset_frac=0.08, haze=0.0), rng)
    rough = OrientedLine.from_roll_offset(14.0, 0.1, 320, 240)
    fisher = np.array([-1.0, 0.2, -0.8]) / 255.0  # bright sky to darker, greener ground
    line = rough
    inliers = []
    for half in (0.07 * 240, 0.025 * 240):
        ref = refine_line(img, line, fisher, half)
        assert ref is not None
        line = ref.line
        inliers.append(ref.inlier_frac)
    assert line.roll_deg == pytest.approx(truth.roll_deg, abs=0.2)
    assert line.offset_frac == pytest.approx(truth.offset_frac, abs=0.003)
    assert inliers[-1] > 0.8


def test_blank_rows_are_not_used() -> None:
    rng = np.random.default_rng(5)
    img, truth = render_scene(SceneSpec(320, 240, roll_deg=0.0, offset_frac=0.0, haze=0.0), rng)
    bad = np.zeros(240, bool)
    bad[100:130] = True  # the horizon row (about 120) hides under a stripe
    img[100:130] = 245
    ref = refine_line(img, truth, np.array([-1.0, 0.2, -0.8]) / 255.0, 0.07 * 240, bad_rows=bad)
    # nothing left that shows the horizon itself: no confident fit on the stripe's border
    assert ref is None or ref.inlier_frac < 0.5 or abs(ref.line.offset_frac - truth.offset_frac) < 0.01


def test_line_outside_the_frame() -> None:
    img = np.zeros((60, 80, 3), np.uint8)
    assert refine_line(img, OrientedLine.from_roll_offset(0, 0.9, 80, 60), np.ones(3), 5.0) is None
