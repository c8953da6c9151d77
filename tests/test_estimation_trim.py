"""The IMU board's trim: samples in board axes come out in airframe axes before the filter."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.core.state import ImuSample
from companion.estimation.fusion import EstimatorCore
from companion.estimation.thread import EstimatorThread
from companion.sim.imu_model import rotation_matrix


def _core(**trim: float) -> EstimatorCore:
    params = {spec.name.removeprefix("EST_"): float(spec.default)
              for spec in EstimatorThread.declare_params("EST")}
    params.update(trim)
    return EstimatorCore(params, (47.0, 8.0, 500.0))


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_a_board_turned_on_one_axis_is_turned_back(axis: int) -> None:
    """The simulator's mounting convention (part = M body) undone by the matching trim."""
    angle = math.radians(3.0)
    rotvec = [0.0, 0.0, 0.0]
    rotvec[axis] = angle
    m = np.array(rotation_matrix((rotvec[0], rotvec[1], rotvec[2])))
    body_rates, body_accel = np.array([0.1, -0.2, 0.3]), np.array([1.0, 2.0, -9.0])
    part = ImuSample(0, 0, tuple(m @ body_rates), tuple(m @ body_accel))  # type: ignore[arg-type]
    names = ("TRIM_ROLL", "TRIM_PITCH", "TRIM_YAW")
    core = _core(**{names[axis]: angle})
    (back,) = core._to_body([part])
    assert np.allclose(back.rates_rad_s, body_rates, atol=1e-12)
    assert np.allclose(back.accel_m_s2, body_accel, atol=1e-12)
    # without the trim the board's axes are taken for the airframe's
    (raw,) = _core()._to_body([part])
    assert not np.allclose(raw.accel_m_s2, body_accel, atol=1e-3)


def test_trim_change_applies_to_the_next_samples() -> None:
    core = _core()
    level = ImuSample(0, 0, (0.0, 0.0, 0.0), (0.0, 0.0, -9.80665))
    core.update_params({"TRIM_PITCH": math.radians(2.0)})
    (s,) = core._to_body([level])
    # a board pitched up by 2 deg reads gravity partly along its x axis: turned back, the
    # airframe sees it 2 deg the other way
    assert math.degrees(math.atan2(s.accel_m_s2[0], -s.accel_m_s2[2])) == pytest.approx(-2.0)
