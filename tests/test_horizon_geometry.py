"""Oriented horizon lines: roll/offset conventions, clipping to the image, rescaling."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from horizon.geometry import OrientedLine, wrap_deg


def test_level_horizon_below_centre() -> None:
    line = OrientedLine.from_roll_offset(0.0, 0.25, 480, 480)
    ends = line.border_points()
    assert ends is not None
    (x1, y1), (x2, y2) = ends
    assert (x1, x2) == pytest.approx((0.0, 479.0))
    assert y1 == pytest.approx(239.5 + 120.0) and y2 == pytest.approx(y1)
    assert line.roll_deg == pytest.approx(0.0)
    assert line.offset_frac == pytest.approx(0.25)


def test_matches_dataset_convention() -> None:
    # a row of the development set's gt.csv: right end higher = positive roll
    line = OrientedLine.from_points((0.0, 382.704253), (479.0, 131.624913), 480, 480)
    assert line.roll_deg == pytest.approx(27.662359, abs=1e-5)
    assert line.offset_frac == pytest.approx(0.036801, abs=1e-6)


def test_sky_side_is_part_of_the_line() -> None:
    up = OrientedLine.from_roll_offset(10.0, 0.1, 320, 240)
    down = up.flipped()
    assert down.roll_deg == pytest.approx(wrap_deg(10.0 + 180.0))
    assert down.offset_frac == pytest.approx(up.offset_frac)
    # the sky (top-left corner here) is on the negative side of the upright line
    assert up.signed_distance(0, 0) < 0 < down.signed_distance(0, 0)
    e_up, e_down = up.border_points(), down.border_points()
    assert e_up is not None and e_down is not None
    assert e_up[0] == pytest.approx(e_down[1]) and e_up[1] == pytest.approx(e_down[0])


def test_line_outside_image_has_no_border_points() -> None:
    assert OrientedLine.from_roll_offset(0.0, 0.8, 320, 240).border_points() is None
    assert OrientedLine.from_roll_offset(0.0, 0.8, 320, 240).ground_fraction() == 0.0
    assert OrientedLine.from_roll_offset(0.0, -0.8, 320, 240).ground_fraction() == pytest.approx(1.0)


def test_ground_fraction_of_centre_line() -> None:
    assert OrientedLine.from_roll_offset(30.0, 0.0, 320, 240).ground_fraction() == pytest.approx(0.5)


def test_vertical_line_has_no_offset() -> None:
    line = OrientedLine(0.0, 10.0, 100, 100)
    assert math.isnan(line.offset_frac)


@settings(max_examples=60, deadline=None)
@given(
    roll=st.floats(-80, 80),
    offset=st.floats(-0.45, 0.45),
    w=st.integers(16, 2000),
    h=st.integers(16, 2000),
)
def test_roll_offset_round_trip_through_points(roll: float, offset: float, w: int, h: int) -> None:
    line = OrientedLine.from_roll_offset(roll, offset, w, h)
    back = OrientedLine.from_points(*line._two_points(), w, h)
    assert back.roll_deg == pytest.approx(roll, abs=1e-6)
    assert back.offset_frac == pytest.approx(offset, abs=1e-6)


@settings(max_examples=40, deadline=None)
@given(roll=st.floats(-60, 60), offset=st.floats(-0.3, 0.3))
def test_scaling_keeps_the_scene_line(roll: float, offset: float) -> None:
    line = OrientedLine.from_roll_offset(roll, offset, 480, 480)
    half = line.scaled(240, 240)
    assert half.roll_deg == pytest.approx(roll, abs=1e-6)
    assert half.offset_frac == pytest.approx(offset, abs=1e-6)
    # a crop keeps pixel positions: the same pixel is on the same side
    crop = line.rebased(400, 300)
    for x, y in ((10, 10), (300, 200), (50, 290)):
        assert math.copysign(1, crop.signed_distance(x, y)) == math.copysign(1, line.signed_distance(x, y))


def test_two_equal_points_are_rejected() -> None:
    with pytest.raises(ValueError, match="two distinct points"):
        OrientedLine.from_points((3.0, 4.0), (3.0, 4.0), 10, 10)
