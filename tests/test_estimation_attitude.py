"""6-D attitude filter: convergence, bias estimation, adaptive trust, causality, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.estimation.attitude import AttitudeFilter, estimate_attitude
from companion.estimation.quat import inclination_error_rad
from companion.evaluation.synthetic import (
    ImuErrors,
    Segment,
    add_imu_errors,
    fixed_wing_flight,
    handheld_motion,
)

FLIGHT_ERRORS = ImuErrors(
    gyro_bias_rad_s=math.radians(0.5),
    gyro_scale=0.005,
    accel_scale=0.003,
    accel_bias_m_s2=0.05,
    vibration_m_s2=0.5,
    seed=7,
)


def _rms_deg(err_rad: np.ndarray) -> float:
    return float(np.degrees(np.sqrt(np.mean(err_rad**2))))


def test_converges_and_tracks_in_straight_flight() -> None:
    tr = fixed_wing_flight([Segment(40.0), Segment(20.0, gamma_deg=5.0), Segment(20.0)])
    imu = add_imu_errors(tr, FLIGHT_ERRORS)
    q = estimate_attitude(imu.gyro_rad_s, imu.accel_m_s2, tr.rate_hz)
    assert q.shape == (len(tr.t_s), 4)
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0)
    err = inclination_error_rad(q, tr.quat)
    settled = tr.t_s > 10.0
    assert _rms_deg(err[settled]) < 0.6
    assert float(np.degrees(err[settled].max())) < 1.5


def test_output_is_causal() -> None:
    tr = handheld_motion(20.0, seed=1)
    imu = add_imu_errors(tr, ImuErrors(seed=2))
    full = estimate_attitude(imu.gyro_rad_s, imu.accel_m_s2, tr.rate_hz)
    cut = 1234
    gyro, accel = imu.gyro_rad_s.copy(), imu.accel_m_s2.copy()
    gyro[cut + 1 :] = 5.0  # change the future only
    accel[cut + 1 :] *= -3.0
    altered = estimate_attitude(gyro, accel, tr.rate_hz)
    assert np.array_equal(full[: cut + 1], altered[: cut + 1])
    assert not np.allclose(full[cut + 1 :], altered[cut + 1 :])


def test_gyro_bias_learnt_at_rest_and_in_motion() -> None:
    tr = handheld_motion(60.0, seed=4)
    errors = ImuErrors(gyro_bias_rad_s=math.radians(1.0), gyro_bias_rw_rad_s_rt_s=0.0, seed=5)
    imu = add_imu_errors(tr, errors)
    filt = AttitudeFilter()
    rest_seen = False
    for k in range(len(tr.t_s)):
        filt.update(imu.gyro_rad_s[k], imu.accel_m_s2[k], 1.0 / tr.rate_hz)
        rest_seen |= filt.at_rest
        if k == int(8.0 * tr.rate_hz):
            # the recording starts with 5-15 s of rest: the bias is measured directly
            assert np.degrees(np.abs(filt.gyro_bias_rad_s - imu.gyro_bias_rad_s[k])).max() < 0.1
    assert rest_seen
    bias_err = np.degrees(np.abs(filt.gyro_bias_rad_s - imu.gyro_bias_rad_s[-1]))
    assert bias_err.max() < 0.15
    assert filt.rejected_samples == 0


def test_handheld_motion_accuracy_and_accel_bias() -> None:
    tr = handheld_motion(90.0, seed=11)
    errors = ImuErrors(gyro_bias_rad_s=math.radians(0.4), gyro_scale=0.005, accel_bias_m_s2=0.1, seed=12)
    imu = add_imu_errors(tr, errors)
    with_bias = estimate_attitude(imu.gyro_rad_s, imu.accel_m_s2, tr.rate_hz)
    without = estimate_attitude(imu.gyro_rad_s, imu.accel_m_s2, tr.rate_hz, accel_bias_std0_m_s2=0.0)
    rms_with = _rms_deg(inclination_error_rad(with_bias, tr.quat))
    rms_without = _rms_deg(inclination_error_rad(without, tr.quat))
    assert rms_with < 0.6
    # estimating the accelerometer bias lowers the tilt floor it would otherwise set
    assert rms_with < rms_without


def test_forward_speed_removes_turn_centripetal_error() -> None:
    tr = fixed_wing_flight([Segment(15.0), Segment(40.0, bank_deg=30.0), Segment(15.0)])
    imu = add_imu_errors(tr, FLIGHT_ERRORS)
    plain = inclination_error_rad(estimate_attitude(imu.gyro_rad_s, imu.accel_m_s2, 100.0), tr.quat)
    compensated = inclination_error_rad(
        estimate_attitude(imu.gyro_rad_s, imu.accel_m_s2, 100.0, forward_speed_m_s=20.0), tr.quat
    )
    turning = (tr.t_s > 20.0) & (tr.t_s < 55.0)
    # without the airspeed a 6-D filter cannot tell a steady turn from a tilt
    assert _rms_deg(plain[turning]) > 5.0
    assert _rms_deg(compensated[turning]) < 2.0


def test_non_finite_samples_are_skipped() -> None:
    tr = fixed_wing_flight([Segment(20.0)])
    imu = add_imu_errors(tr, FLIGHT_ERRORS)
    gyro, accel = imu.gyro_rad_s.copy(), imu.accel_m_s2.copy()
    gyro[500:510] = np.nan
    accel[700] = np.inf
    filt = AttitudeFilter()
    out = np.array([filt.update(g, a, 0.01) for g, a in zip(gyro, accel, strict=True)])
    assert np.isfinite(out).all()
    assert filt.rejected_samples == 11
    assert filt.covariance_resets == 0
    assert np.degrees(inclination_error_rad(out[-1], tr.quat[-1])) < 1.0
    # a non-positive dt is refused too
    before = filt.quaternion
    assert np.array_equal(filt.update(gyro[-1], accel[-1], 0.0), before)
    assert filt.rejected_samples == 12


def test_waits_for_a_usable_first_sample() -> None:
    filt = AttitudeFilter()
    assert np.array_equal(filt.update((0, 0, 0), (0, 0, 0), 0.01), (1.0, 0.0, 0.0, 0.0))
    assert filt.rejected_samples == 1
    q = filt.update((0, 0, 0), (0.0, -9.80665 * math.sin(0.3), -9.80665 * math.cos(0.3)), 0.01)
    assert float(inclination_error_rad(q, (math.cos(0.15), math.sin(0.15), 0.0, 0.0))) < 1e-9


def test_bad_arguments_raise_clear_errors() -> None:
    with pytest.raises(ValueError, match="gyro_rad_s must have shape"):
        estimate_attitude(np.zeros((10, 2)), np.zeros((10, 2)), 100.0)
    with pytest.raises(ValueError, match="accel_m_s2 shape"):
        estimate_attitude(np.zeros((10, 3)), np.zeros((9, 3)), 100.0)
    with pytest.raises(ValueError, match="rate_hz"):
        estimate_attitude(np.zeros((10, 3)), np.zeros((10, 3)), 0.0)
    with pytest.raises(ValueError, match="accel_noise_m_s2"):
        AttitudeFilter(accel_noise_m_s2=-1.0)
    with pytest.raises(TypeError):
        AttitudeFilter(no_such_parameter=1.0)  # type: ignore[call-arg]
