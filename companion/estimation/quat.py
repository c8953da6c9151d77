"""Quaternion and rotation helpers shared by the attitude filter, the ESKF and their tests.

Conventions (the whole estimation package uses them):

* quaternions are ``(w, x, y, z)``, Hamilton product, and rotate *body-frame* vectors into the
  NED navigation frame: ``v_ned = R(q) @ v_body``;
* Euler angles are the aerospace Z-Y-X sequence (yaw, then pitch, then roll), in radians;
* an accelerometer measures specific force, about ``(0, 0, -g)`` when level and still.

The array functions broadcast over leading dimensions so tests and benches can work on whole
recordings at once. The filters' hot paths use the ``*_f`` scalar variants on Python floats,
because for 3- and 4-element vectors numpy's per-call overhead dominates the arithmetic.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.core.mathutil import wrap_pi

FloatArray = NDArray[np.float64]

GRAVITY_M_S2 = 9.80665
"""Standard gravity; the navigation frame's gravity vector is ``(0, 0, +GRAVITY_M_S2)``."""


def quat_multiply(p: ArrayLike, q: ArrayLike) -> FloatArray:
    """Hamilton product ``p * q`` (apply ``q`` first, then ``p``), broadcasting over ``(..., 4)``."""
    a = np.asarray(p, dtype=float)
    b = np.asarray(q, dtype=float)
    pw, px, py, pz = np.moveaxis(a, -1, 0)
    qw, qx, qy, qz = np.moveaxis(b, -1, 0)
    return np.stack(
        (
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ),
        axis=-1,
    )


def quat_conjugate(q: ArrayLike) -> FloatArray:
    """Inverse rotation of a unit quaternion."""
    c = np.array(q, dtype=float)
    c[..., 1:] *= -1.0
    return c


def quat_normalise(q: ArrayLike) -> FloatArray:
    """Unit quaternion with a non-negative scalar part (one canonical sign per rotation)."""
    a = np.asarray(q, dtype=float)
    n = np.linalg.norm(a, axis=-1, keepdims=True)
    out = a / n
    return np.where(out[..., :1] < 0.0, -out, out)


def quat_from_rotvec(rotvec: ArrayLike) -> FloatArray:
    """Exponential map: rotation vector (axis * angle, rad) to unit quaternion, exact at any angle."""
    r = np.asarray(rotvec, dtype=float)
    angle = np.linalg.norm(r, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(x)/x written as sinc keeps the small-angle limit exact without a branch.
    scale = 0.5 * np.sinc(half / np.pi)
    return np.concatenate((np.cos(half), r * scale), axis=-1)


def quat_to_rotvec(q: ArrayLike) -> FloatArray:
    """Logarithm map: unit quaternion to rotation vector (rad), angle in ``[0, pi]``."""
    a = quat_normalise(q)
    w = np.clip(a[..., :1], -1.0, 1.0)
    v = a[..., 1:]
    sin_half = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, w)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(sin_half > 1e-12, angle / np.where(sin_half > 0, sin_half, 1.0), 2.0)
    return v * scale


def quat_to_rotmat(q: ArrayLike) -> FloatArray:
    """Rotation matrix ``R`` with ``v_ned = R @ v_body``; shape ``(..., 3, 3)``."""
    a = np.asarray(q, dtype=float)
    w, x, y, z = np.moveaxis(a, -1, 0)
    return np.stack(
        (
            np.stack((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)), -1),
            np.stack((2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)), -1),
            np.stack((2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)), -1),
        ),
        axis=-2,
    )


def quat_rotate(q: ArrayLike, v: ArrayLike) -> FloatArray:
    """Rotate body-frame vectors into the navigation frame."""
    r = quat_to_rotmat(q)
    return np.einsum("...ij,...j->...i", r, np.asarray(v, dtype=float))


def quat_from_euler(roll_rad: ArrayLike, pitch_rad: ArrayLike, yaw_rad: ArrayLike) -> FloatArray:
    """Quaternion of the Z-Y-X Euler angles (yaw about down, pitch about right, roll about fwd)."""
    hr = 0.5 * np.asarray(roll_rad, dtype=float)
    hp = 0.5 * np.asarray(pitch_rad, dtype=float)
    hy = 0.5 * np.asarray(yaw_rad, dtype=float)
    cr, sr = np.cos(hr), np.sin(hr)
    cp, sp = np.cos(hp), np.sin(hp)
    cy, sy = np.cos(hy), np.sin(hy)
    return np.stack(
        (
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ),
        axis=-1,
    )


def quat_to_euler(q: ArrayLike) -> FloatArray:
    """Z-Y-X Euler angles ``(..., 3)`` as (roll, pitch, yaw) in rad; pitch clipped at +-pi/2."""
    a = np.asarray(q, dtype=float)
    w, x, y, z = np.moveaxis(a, -1, 0)
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.stack((roll, pitch, yaw), axis=-1)


def roll_pitch_from_accel(accel_m_s2: ArrayLike) -> tuple[float, float]:
    """Roll and pitch (rad) that make a still accelerometer read ``accel_m_s2``."""
    ax, ay, az = (float(c) for c in np.asarray(accel_m_s2, dtype=float).reshape(3))
    roll = math.atan2(-ay, -az)
    pitch = math.atan2(ax, math.hypot(ay, az))
    return roll, pitch


def quat_from_accel(accel_m_s2: ArrayLike, yaw_rad: float = 0.0) -> FloatArray:
    """Attitude that levels a still accelerometer, with the given heading."""
    roll, pitch = roll_pitch_from_accel(accel_m_s2)
    return quat_from_euler(roll, pitch, yaw_rad)


def skew(v: ArrayLike) -> FloatArray:
    """Cross-product matrix: ``skew(a) @ b == cross(a, b)``."""
    x, y, z = (float(c) for c in np.asarray(v, dtype=float).reshape(3))
    return np.array(((0.0, -z, y), (z, 0.0, -x), (-y, x, 0.0)))


def inclination_error_rad(q_est: ArrayLike, q_true: ArrayLike) -> FloatArray:
    """Tilt error: angle between the true and estimated vertical, seen from the body.

    Heading does not enter, so 6-D filters with an arbitrary heading are compared fairly.
    """
    down_est = quat_to_rotmat(q_est)[..., 2, :]
    down_true = quat_to_rotmat(q_true)[..., 2, :]
    cos_angle = np.sum(down_est * down_true, axis=-1)
    sin_angle = np.linalg.norm(np.cross(down_est, down_true), axis=-1)
    return np.arctan2(sin_angle, cos_angle)


def heading_error_rad(q_est: ArrayLike, q_true: ArrayLike) -> FloatArray:
    """Rotation about the NED vertical that separates the estimate from the truth, in ``[-pi, pi)``.

    Computed from the relative rotation ``q_est * q_true^-1`` expressed in the navigation frame,
    which stays meaningful when the vehicle is banked (unlike a difference of Euler yaws).
    """
    rel = quat_multiply(q_est, quat_conjugate(q_true))
    return wrap_pi(2.0 * np.arctan2(rel[..., 3], rel[..., 0]))


# --- scalar variants for per-sample filter loops -------------------------------------------


def quat_multiply_f(
    pw: float, px: float, py: float, pz: float, qw: float, qx: float, qy: float, qz: float
) -> tuple[float, float, float, float]:
    """Hamilton product on Python floats (the per-sample path)."""
    return (
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    )


def quat_from_rotvec_f(rx: float, ry: float, rz: float) -> tuple[float, float, float, float]:
    """Exponential map on floats; Taylor series below 1e-4 rad keeps it exact to rounding."""
    angle_sq = rx * rx + ry * ry + rz * rz
    if angle_sq < 1e-8:
        s = 0.5 - angle_sq / 48.0
        c = 1.0 - angle_sq / 8.0
    else:
        angle = math.sqrt(angle_sq)
        s = math.sin(0.5 * angle) / angle
        c = math.cos(0.5 * angle)
    return c, rx * s, ry * s, rz * s


def quat_normalise_f(
    w: float, x: float, y: float, z: float
) -> tuple[float, float, float, float]:
    """Normalise on floats with a non-negative scalar part."""
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if w < 0.0:
        n = -n
    return w / n, x / n, y / n, z / n


def rotmat_flat_f(w: float, x: float, y: float, z: float) -> tuple[float, ...]:
    """:func:`rotmat_f`'s nine elements, row-major, as floats: for callers that write them
    into a larger matrix or multiply them out themselves, without an array per call."""
    return (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


def rotmat_f(w: float, x: float, y: float, z: float) -> FloatArray:
    """Rotation matrix (body to NED) of a unit quaternion given as floats."""
    return np.array(rotmat_flat_f(w, x, y, z)).reshape(3, 3)


def quat_to_euler_f(w: float, x: float, y: float, z: float) -> tuple[float, float, float]:
    """Scalar :func:`quat_to_euler` for one quaternion: the per-sample path must not pay numpy's
    array overhead (about 30 us) for three angles."""
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw
