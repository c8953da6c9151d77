"""The IMU's temperature lets the filter's biases follow a warm-up (`Eskf.set_temperature`).

A consumer MEMS gyro's bias moves with its temperature by a coefficient no datasheet pins down;
after switch-on the part warms by some 20 C within minutes. The filter is not told the
coefficient, only the temperature the IMU's slow block carries: while it changes, the bias may
move faster. Checked: the variance grows by exactly what the coefficient says and only while
the temperature moves (noise below `TEMP_STEP_C` does not count); bad readings are refused and
counted; and on a SITL flight with the realistic consumer part warming up (20 -> 40 C) the
estimator's inclination error is smaller with the temperature than without.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.estimation.eskf import IDX_ACCEL_BIAS, IDX_GYRO_BIAS, TEMP_SPAN_C, TEMP_STEP_C, Eskf
from companion.evaluation.sitl import (
    EskfOptions,
    FlightSpec,
    filter_errors,
    record_flight,
    run_eskf,
)

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
    assert g1 - g0 == pytest.approx(GYRO_TC**2 * TEMP_SPAN_C * 1.0, rel=1e-6)
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
