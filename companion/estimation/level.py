"""Level calibration: the IMU board's roll and pitch against the airframe, from the
accelerometer while the aircraft stands level and still.

Why it exists: the filter can only report the attitude of the frame its accelerometer defines.
A board taped into a fuselage sits a fraction of a degree off the airframe, and a consumer
accelerometer's cross-axis terms tilt its reading of gravity by as much again; in coordinated
flight the specific force stays along the body's z axis, so no estimator can tell either from
a tilt of the aircraft. Standing the aircraft level and reading the direction of gravity once
(MAV_CMD_PREFLIGHT_CALIBRATION with param5 = 2: MAVProxy's ``ahrstrim``) measures their sum; `EST_TRIM_ROLL` and
`EST_TRIM_PITCH` then turn every sample back into airframe axes (companion.estimation.fusion).

The reading also holds that moment's accelerometer bias, which is not a tilt: the filter
learns the bias in flight and gives that part of the trim back (`EST_TRIM_BIAS`,
companion.estimation.eskf). The same function calibrates the runtime (the estimator thread,
on MAV_CMD_PREFLIGHT_CALIBRATION) and the simulated installation of SITL.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from companion.estimation.quat import GRAVITY_M_S2

MIN_SAMPLES = 50
"""Half a second at 100 Hz: fewer is refused (noise would set the trim)."""
MAX_GYRO_RMS_RAD_S = 0.05
"""About 3 deg/s: above this the aircraft is being moved or the engine runs."""
MAX_ACCEL_STD_M_S2 = 0.5
"""Spread of the accelerometer per axis above which the aircraft is not still."""
MAX_G_ERROR_M_S2 = 1.0
"""The mean's magnitude must be within this of 1 g (an unscaled or failed accelerometer)."""
MAX_TRIM_RAD = 0.5
"""The trims' parameter range: a board further off is mounted wrongly, not trimmed."""


class LevelCalibrationError(ValueError):
    """The samples cannot give a trim; the message says which check failed, with the figure."""


@dataclass(frozen=True)
class LevelTrim:
    """The result of a level calibration (board axes -> airframe axes, the trims' convention)."""

    roll_rad: float
    pitch_rad: float
    samples: int
    gyro_rms_rad_s: float
    accel_mean_m_s2: tuple[float, float, float]

    def params(self, prefix: str = "EST") -> dict[str, float]:
        """The parameters a calibration sets (the board's yaw is not observable level)."""
        return {f"{prefix}_TRIM_ROLL": self.roll_rad, f"{prefix}_TRIM_PITCH": self.pitch_rad}


def level_trim(accel_m_s2: Sequence[Sequence[float]],
               rates_rad_s: Sequence[Sequence[float]]) -> LevelTrim:
    """Board roll and pitch from samples taken with the airframe level (board axes, raw).

    With the trim applied the mean specific force reads straight down the airframe's z axis:
    the trims' rotation (yaw, pitch, roll) has a third row that does not depend on yaw, so a
    board yaw trim set beforehand is kept. Raises :class:`LevelCalibrationError` when the
    samples are too few, the aircraft moves, or gravity does not read as 1 g.
    """
    n = len(accel_m_s2)
    if n < MIN_SAMPLES or len(rates_rad_s) != n:
        raise LevelCalibrationError(
            f"level calibration needs at least {MIN_SAMPLES} IMU samples with rates and "
            f"accelerations, got {n} and {len(rates_rad_s)}")
    sums = [0.0, 0.0, 0.0]
    squares = [0.0, 0.0, 0.0]
    gyro_sq = 0.0
    for a, w in zip(accel_m_s2, rates_rad_s, strict=True):
        for i in range(3):
            sums[i] += a[i]
            squares[i] += a[i] * a[i]
        gyro_sq += w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    mean = (sums[0] / n, sums[1] / n, sums[2] / n)
    if not all(math.isfinite(v) for v in (*mean, gyro_sq)):
        raise LevelCalibrationError("level calibration: a sample is not finite")
    gyro_rms = math.sqrt(gyro_sq / n)
    if gyro_rms > MAX_GYRO_RMS_RAD_S:
        raise LevelCalibrationError(
            f"level calibration: the aircraft is moving (gyro {math.degrees(gyro_rms):.1f} "
            f"deg/s RMS, at most {math.degrees(MAX_GYRO_RMS_RAD_S):.1f})")
    spread = max(math.sqrt(max(0.0, squares[i] / n - mean[i] ** 2)) for i in range(3))
    if spread > MAX_ACCEL_STD_M_S2:
        raise LevelCalibrationError(
            f"level calibration: the aircraft is not still (accelerometer spread {spread:.2f} "
            f"m/s^2, at most {MAX_ACCEL_STD_M_S2})")
    norm = math.sqrt(mean[0] ** 2 + mean[1] ** 2 + mean[2] ** 2)
    if abs(norm - GRAVITY_M_S2) > MAX_G_ERROR_M_S2:
        raise LevelCalibrationError(
            f"level calibration: gravity reads {norm:.2f} m/s^2, not 1 g "
            f"({GRAVITY_M_S2} +- {MAX_G_ERROR_M_S2})")
    ux, uy, uz = mean[0] / norm, mean[1] / norm, mean[2] / norm
    # board -> airframe B with B^T (0, 0, -1) = u: u = (sin p, -sin r cos p, -cos r cos p)
    pitch = math.asin(max(-1.0, min(1.0, ux)))
    roll = math.atan2(-uy, -uz)
    if abs(roll) > MAX_TRIM_RAD or abs(pitch) > MAX_TRIM_RAD:
        raise LevelCalibrationError(
            f"level calibration: the board reads {math.degrees(roll):.1f} deg roll, "
            f"{math.degrees(pitch):.1f} deg pitch with the aircraft level, beyond the trims' "
            f"+-{math.degrees(MAX_TRIM_RAD):.0f} deg: is the board mounted upright and the "
            "aircraft level?")
    return LevelTrim(roll, pitch, n, gyro_rms, mean)
