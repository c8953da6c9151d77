"""Quaternion helpers and the synthetic-flight generator the estimator tests rely on."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from companion.estimation.quat import (
    GRAVITY_M_S2,
    heading_error_rad,
    inclination_error_rad,
    quat_conjugate,
    quat_from_accel,
    quat_from_euler,
    quat_from_rotvec,
    quat_from_rotvec_f,
    quat_multiply,
    quat_multiply_f,
    quat_normalise,
    quat_rotate,
    quat_to_euler,
    quat_to_rotmat,
    quat_to_rotvec,
    roll_pitch_from_accel,
    rotmat_f,
    skew,
    wrap_pi,
)
from companion.evaluation.synthetic import (
    ImuErrors,
    Segment,
    add_imu_errors,
    fixed_wing_flight,
    gps_fixes,
    handheld_motion,
)

angles = st.floats(-math.pi + 1e-3, math.pi - 1e-3)
pitches = st.floats(-1.5, 1.5)


@settings(max_examples=200, deadline=None)
@given(angles, pitches, angles)
def test_euler_round_trip(roll: float, pitch: float, yaw: float) -> None:
    q = quat_from_euler(roll, pitch, yaw)
    assert np.isclose(np.linalg.norm(q), 1.0)
    back = quat_to_euler(q)
    assert np.allclose(wrap_pi(back - (roll, pitch, yaw)), 0.0, atol=1e-7)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1.8, 1.8), min_size=3, max_size=3))
def test_rotvec_exp_log_round_trip(rv: list[float]) -> None:
    assume(np.linalg.norm(rv) < math.pi - 1e-3)  # the log map returns angles up to pi
    q = quat_from_rotvec(rv)
    assert np.allclose(quat_to_rotvec(q), rv, atol=1e-9)
    # the float variant used by the filters agrees with the array one
    assert np.allclose(quat_from_rotvec_f(*rv), q, atol=1e-12)


def test_small_rotvec_is_exact() -> None:
    q = quat_from_rotvec_f(1e-9, -2e-9, 3e-9)
    assert q[0] == pytest.approx(1.0)
    assert np.allclose(q[1:], (0.5e-9, -1e-9, 1.5e-9), rtol=1e-12)


def test_rotation_matrix_conventions() -> None:
    # yaw 90 deg: body x (forward) points east
    q = quat_from_euler(0.0, 0.0, math.pi / 2)
    assert np.allclose(quat_rotate(q, (1.0, 0.0, 0.0)), (0.0, 1.0, 0.0), atol=1e-12)
    # pitch up 90 deg: body x points up (NED -z)
    q = quat_from_euler(0.0, math.pi / 2, 0.0)
    assert np.allclose(quat_rotate(q, (1.0, 0.0, 0.0)), (0.0, 0.0, -1.0), atol=1e-12)
    # roll right 90 deg: body y (right wing) points down
    q = quat_from_euler(math.pi / 2, 0.0, 0.0)
    assert np.allclose(quat_rotate(q, (0.0, 1.0, 0.0)), (0.0, 0.0, 1.0), atol=1e-12)
    r = quat_to_rotmat(quat_from_euler(0.3, -0.2, 2.0))
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.allclose(rotmat_f(*quat_from_euler(0.3, -0.2, 2.0)), r, atol=1e-12)


def test_multiply_matches_matrices() -> None:
    a = quat_from_euler(0.1, 0.2, 0.3)
    b = quat_from_euler(-0.4, 0.5, -0.6)
    ab = quat_multiply(a, b)
    assert np.allclose(quat_to_rotmat(ab), quat_to_rotmat(a) @ quat_to_rotmat(b), atol=1e-12)
    assert np.allclose(quat_multiply_f(*a, *b), ab, atol=1e-12)
    assert np.allclose(quat_multiply(a, quat_conjugate(a)), (1.0, 0.0, 0.0, 0.0), atol=1e-12)
    assert quat_normalise(-2.0 * a)[0] > 0.0


def test_skew_is_cross_product() -> None:
    a, b = np.array((1.0, -2.0, 0.5)), np.array((0.3, 0.7, -1.1))
    assert np.allclose(skew(a) @ b, np.cross(a, b))


def test_accel_levelling() -> None:
    q_true = quat_from_euler(0.4, -0.3, 1.0)
    f_body = quat_to_rotmat(q_true).T @ np.array((0.0, 0.0, -GRAVITY_M_S2))
    roll, pitch = roll_pitch_from_accel(f_body)
    assert roll == pytest.approx(0.4)
    assert pitch == pytest.approx(-0.3)
    assert float(inclination_error_rad(quat_from_accel(f_body), q_true)) < 1e-9


def test_error_metrics_separate_tilt_and_heading() -> None:
    base = quat_from_euler(0.3, 0.1, 0.5)
    turned = quat_multiply(quat_from_rotvec((0.0, 0.0, 0.2)), base)  # about NED down
    assert float(inclination_error_rad(turned, base)) < 1e-12
    assert float(heading_error_rad(turned, base)) == pytest.approx(0.2)
    tilted = quat_multiply(quat_from_rotvec((0.05, 0.0, 0.0)), base)  # about north
    assert float(inclination_error_rad(tilted, base)) == pytest.approx(0.05)
    assert abs(float(heading_error_rad(tilted, base))) < 2e-3


def _strapdown(traj_gyro: np.ndarray, traj_accel: np.ndarray, q0, v0, p0, dt):  # type: ignore[no-untyped-def]
    q, v, p = np.array(q0), np.array(v0), np.array(p0)
    g = np.array((0.0, 0.0, GRAVITY_M_S2))
    for k in range(1, len(traj_gyro)):
        q_mid = quat_multiply(q, quat_from_rotvec(traj_gyro[k] * dt / 2))
        a = quat_rotate(q_mid, traj_accel[k]) + g
        p = p + v * dt + 0.5 * a * dt * dt
        v = v + a * dt
        q = quat_multiply(q, quat_from_rotvec(traj_gyro[k] * dt))
    return q, v, p


def test_fixed_wing_imu_is_consistent_with_truth() -> None:
    """Integrating the ideal IMU reproduces the truth: the generator adds no error of its own."""
    tr = fixed_wing_flight([Segment(5.0), Segment(10.0, bank_deg=30.0, gamma_deg=5.0)])
    q, v, p = _strapdown(tr.gyro_rad_s, tr.accel_m_s2, tr.quat[0], tr.vel_ned_m_s[0], tr.pos_ned_m[0], 0.01)
    assert float(inclination_error_rad(q, tr.quat[-1])) < 1e-8
    assert np.linalg.norm(v - tr.vel_ned_m_s[-1]) < 1e-3
    assert np.linalg.norm(p - tr.pos_ned_m[-1]) < 5e-3
    # a steady level coordinated turn: no lateral specific force, load factor 1/cos(bank)
    tr = fixed_wing_flight([Segment(5.0, bank_deg=30.0)], alpha_deg=0.0)
    mid = len(tr.t_s) // 2
    assert abs(tr.accel_m_s2[mid, 1]) < 1e-3
    assert np.linalg.norm(tr.accel_m_s2[mid]) == pytest.approx(
        GRAVITY_M_S2 / math.cos(math.radians(30.0)), rel=2e-3
    )


def test_handheld_and_error_models() -> None:
    tr = handheld_motion(20.0, seed=3)
    assert np.isfinite(tr.quat).all()
    assert np.allclose(np.linalg.norm(tr.quat, axis=1), 1.0)
    # it starts at rest
    assert np.linalg.norm(tr.gyro_rad_s[10]) < 1e-6
    imu = add_imu_errors(tr, ImuErrors(seed=1))
    resid = imu.gyro_rad_s - tr.gyro_rad_s - imu.gyro_bias_rad_s
    assert resid.std() == pytest.approx(ImuErrors().gyro_noise_rad_s_rt_hz * 10.0, rel=0.1)
    gps = gps_fixes(tr, rate_hz=10.0, latency_s=0.2)
    assert len(gps.t_valid_s) == 201
    assert np.allclose(gps.t_report_s - gps.t_valid_s, 0.2)
