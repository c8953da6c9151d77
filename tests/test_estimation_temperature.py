"""The IMU's temperature lets the filter's biases follow a warm-up (`Eskf.set_temperature`).

A consumer MEMS gyro's bias moves with its temperature by a coefficient no datasheet pins down;
after switch-on the part warms by some 20 C within minutes. The filter is not told the
coefficient, only the temperature the IMU's slow block carries: while it changes, the bias may
move faster, and the gyro's coefficient is estimated, so a drift seen early in the warm-up is
predicted later. Checked: the variance grows by exactly what the model says and only while the
temperature moves (noise below `TEMP_STEP_C` does not count); a gyro warming at rest with a
coefficient the filter is not told has that coefficient learnt and its bias followed; a
parameter change restarts the coefficient; bad readings are refused and counted; and on a
SITL flight with the realistic consumer part warming up (20 -> 40 C) the estimator's
inclination error is smaller with the temperature than without.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.estimation.eskf import Eskf
from companion.estimation.eskf_state import (
    GYRO_TEMP_RESIDUAL,
    IDX_ACCEL_BIAS,
    IDX_GYRO_BIAS,
    IDX_GYRO_TEMP,
    TEMP_SPAN_C,
    TEMP_STEP_C,
)
from companion.evaluation.sitl import FlightSpec, record_flight
from companion.evaluation.sitl_estimator import EskfOptions, run_eskf
from companion.evaluation.sitl_scoring import filter_errors

GYRO_TC = 5e-4  # rad/s/C
ACCEL_TC = 1.5e-3  # m/s^2/C


def started() -> Eskf:
    f = Eskf(gyro_bias_temp_rad_s_per_c=GYRO_TC, accel_bias_temp_m_s2_per_c=ACCEL_TC,
             cov_period_s=0.01)
    f.initialise((0.0, 0.0, -9.80665), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0),
                 yaw_rad=0.0)
    return f


def bias_var_after(f: Eskf, temperature_c: float) -> tuple[float, float]:
    """The gyro and accel bias variances (x axis) after one covariance period at rest."""
    f.set_temperature(temperature_c)
    f.predict((0.0, 0.0, 0.0), (0.0, 0.0, -9.80665), 0.01)
    p = f.covariance
    return float(p[IDX_GYRO_BIAS.start, IDX_GYRO_BIAS.start]), \
        float(p[IDX_ACCEL_BIAS.start, IDX_ACCEL_BIAS.start])


def test_bias_variance_grows_with_the_temperature_change_and_only_then() -> None:
    steady, moving = started(), started()
    for f in (steady, moving):
        bias_var_after(f, 20.0)  # the first reading is the reference
    g0, a0 = bias_var_after(steady, 20.0)
    g1, a1 = bias_var_after(moving, 21.0)
    # the gyro: what a straight line leaves, as a walk in temperature, plus the coefficient's
    # own uncertainty times the change (squared)
    assert g1 - g0 == pytest.approx((GYRO_TEMP_RESIDUAL * GYRO_TC)**2 * TEMP_SPAN_C * 1.0
                                    + GYRO_TC**2 * 1.0**2, rel=1e-6)
    assert a1 - a0 == pytest.approx(ACCEL_TC**2 * TEMP_SPAN_C * 1.0, rel=1e-6)
    # a change below the step (quantisation, sensor noise) adds nothing, however often
    before = bias_var_after(steady, 20.0)
    for k in range(50):
        after = bias_var_after(steady, 20.0 + (TEMP_STEP_C * 0.9 if k % 2 else 0.0))
    assert after[0] - before[0] < 1e-3 * GYRO_TC**2 * TEMP_SPAN_C


def test_without_a_coefficient_the_temperature_changes_nothing() -> None:
    a = Eskf(cov_period_s=0.01)
    b = Eskf(cov_period_s=0.01)
    for f in (a, b):
        f.initialise((0.0, 0.0, -9.80665), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0),
                     yaw_rad=0.0)
    for t_c in (20.0, 25.0, 30.0):
        a.set_temperature(t_c)
        for f in (a, b):
            f.predict((0.0, 0.0, 0.0), (0.0, 0.0, -9.80665), 0.01)
    assert np.array_equal(a.covariance, b.covariance)


def test_a_gyro_warming_at_rest_has_its_coefficient_learnt_and_its_bias_followed() -> None:
    """At rest, level, heading known, GPS at 10 Hz: the x and y gyro biases show as tilt, so
    their drift with temperature (a coefficient the filter is not told, 2x its prior's
    1-sigma, opposite signs) is learnt while the part warms 20 -> 30 C, and then predicted:
    when the part warms on by 5 C the bias error stays under 5 % of the drift."""
    true_k = np.array((2.0 * GYRO_TC, -2.0 * GYRO_TC, 0.0))
    b0 = np.array((0.002, -0.001, 0.0))
    f = Eskf(gyro_bias_temp_rad_s_per_c=GYRO_TC, cov_period_s=0.01)
    f.initialise((0.0, 0.0, -9.80665), b0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), yaw_rad=0.0)

    def fly(t0_c: float, t1_c: float, seconds: int) -> None:
        for k in range(seconds * 100):
            temp = t0_c + (t1_c - t0_c) * k / (seconds * 100)
            if k % 100 == 0:
                f.set_temperature(round(temp, 2))  # the slow block, once a second
            gyro = b0 + true_k * (temp - 20.0)
            assert f.predict(tuple(gyro.tolist()), (0.0, 0.0, -9.80665), 0.01)
            if k % 10 == 9:
                assert f.update_gps((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.5, 0.05).accepted

    fly(20.0, 30.0, 300)
    st = f.state()
    np.testing.assert_allclose(st.gyro_temp_rad_s_per_c[:2], true_k[:2], rtol=0.2)
    learnt_std = np.sqrt(np.diagonal(f.covariance)[IDX_GYRO_TEMP][:2])
    assert (learnt_std < 0.5 * GYRO_TC).all(), learnt_std  # from 1-sigma GYRO_TC
    fly(30.0, 35.0, 60)
    drift = np.abs(true_k[:2]) * 15.0
    err = np.abs(f.state().gyro_bias_rad_s[:2] - (b0 + true_k * 15.0)[:2])
    assert (err < 0.05 * drift).all(), (err, drift)  # a random walk alone: 0.11-0.16


def test_a_parameter_change_restarts_the_coefficient() -> None:
    f = started()
    f.set_temperature(20.0)
    assert f.set_gyro_bias_temp(2 * GYRO_TC)
    var = np.diagonal(f.covariance)[IDX_GYRO_TEMP]
    np.testing.assert_allclose(var, (2 * GYRO_TC) ** 2)
    assert not f.covariance[IDX_GYRO_TEMP, IDX_GYRO_BIAS].any()  # uncoupled from the bias
    assert f.set_gyro_bias_temp(0.0)
    before = f.covariance[IDX_GYRO_BIAS, IDX_GYRO_BIAS].copy()
    f.set_temperature(25.0)  # no coefficient: the temperature no longer widens the gyro bias
    f.predict((0.0, 0.0, 0.0), (0.0, 0.0, -9.80665), 0.01)
    after = f.covariance[IDX_GYRO_BIAS, IDX_GYRO_BIAS]
    assert np.allclose(after, before, rtol=1e-3, atol=1e-10)
    for bad in (math.nan, -1e-3):
        assert not f.set_gyro_bias_temp(bad)
    assert f.rejected_inputs == 2


@pytest.mark.parametrize("bad", [math.nan, math.inf, 1e6, "warm", None])
def test_bad_temperatures_are_refused_and_counted(bad: object) -> None:
    f = started()
    f.set_temperature(bad)  # type: ignore[arg-type]
    assert f.rejected_inputs == 1
    assert f.state().faults == 0


def test_a_warming_consumer_imu_is_followed_better_with_its_temperature() -> None:
    """Realistic consumer part (20 -> 40 C warm-up, about 1 deg/s of gyro bias drift 1-sigma),
    moderate turbulence, 0.15 s of untold GPS latency, a seed the defaults were not set on."""
    rec = record_flight(FlightSpec(aircraft="c172p", seed=31, duration_s=150.0,
                                   gps_latency_s=0.15))
    assert rec.imu_temperature_c[-1] - rec.imu_temperature_c[0] > 7.0  # it does warm up

    def incl_rmse_deg(opts: EskfOptions) -> float:
        run = run_eskf(rec, opts)
        err = filter_errors(rec, run.quat, run=run)
        s = run.start_tick + 3000
        return float(np.degrees(np.sqrt(np.nanmean(err.inclination_rad[s:] ** 2))))

    with_t = incl_rmse_deg(EskfOptions())
    without = incl_rmse_deg(EskfOptions(params={"GB_TEMP": 0.0, "AB_TEMP": 0.0}))
    assert with_t < 0.92 * without, (with_t, without)
