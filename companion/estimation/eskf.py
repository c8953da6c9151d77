"""Error-state (multiplicative quaternion) GPS/INS Kalman filter for the on-board estimator.

The 2003 estimator restarted four times in one five-minute flight with numerical trouble. This
one is built so that cannot take the thread down:

* the nominal state (attitude quaternion, NED velocity and position, gyro and accel biases) is
  propagated exactly by the IMU; the Kalman filter only tracks a small error state
  whose linearisation stays valid, and the quaternion never has to be renormalised by the
  filter;
* every update uses the Joseph form, the covariance is symmetrised and checked (finite,
  positive diagonal, Cholesky), innovations are chi-square gated;
* anything that goes wrong (a non-finite value, a covariance that is not positive definite,
  GPS rejected again and again) is an *estimator fault*: it is counted, logged with a reason,
  and repaired by a reset. No method raises on bad data; bad inputs are rejected and counted.

Error state (25), in this order (see ``IDX_*``): position (m, NED), velocity (m/s, NED),
attitude error (rad, rotation vector in NED: ``q_true = exp(dtheta) * q``), gyro bias (rad/s),
accelerometer bias (m/s^2), the GPS receiver's unknown output delay (s), and the gyro's
scale-factor and cross-axis error ``M`` (nine elements, row-major; the part reads
``(I + M) w + b``). With the attitude
error in the navigation frame the gyro and accelerometer noises enter isotropically, so the
process noise does not depend on attitude and is computed once per propagation period.

Why not filterpy's ``KalmanFilter``: its state is additive (``x + K y``) and its transition
acts on the state itself, while here the transition acts on an error state and the correction
is injected multiplicatively into a quaternion, then the error is reset to zero. The
position/velocity process noise block and the chi-square gates are closed forms
(:mod:`companion.estimation.noise`, checked against filterpy's ``Q_continuous_white_noise`` and
scipy's ``chi2``, which are not imported in flight: half a second of start-up); filterpy's NEES
helper is used in the tests.

The filter is assembled from one class per job: the state and its set-up
(companion.estimation.eskf_state), the delayed-state history (eskf_history), health and repair
(eskf_repair), the time update (eskf_predict), the gyro calibration states (eskf_calibration)
and the measurement updates (eskf_updates).
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import ArrayLike

from companion.estimation.eskf_state import (
    FIXED_LAG_VAR,
    IDX_GPS_LAG,
    IDX_YAW,
    EskfState,
    FlightView,
    quat_from_euler_f,
    vec3,
)
from companion.estimation.eskf_updates import MeasurementUpdates
from companion.estimation.quat import (
    quat_multiply_f,
    quat_to_euler_f,
    roll_pitch_from_accel,
    rotmat_f,
)

log = logging.getLogger(__name__)

class Eskf(MeasurementUpdates):
    """GPS/INS error-state Kalman filter; see the module docstring for the model and
    `EskfBase` for the settings (keyword arguments, units in their names)."""

    def initialise(
        self,
        accel_mean: ArrayLike,
        gyro_mean: ArrayLike,
        pos_ned: ArrayLike,
        vel_ned: ArrayLike,
        yaw_rad: float | None = None,
    ) -> bool:
        """Start (or restart) the filter from means taken at rest; False on unusable input.

        ``accel_mean`` levels the attitude, ``gyro_mean`` is taken as the gyro bias (the thesis'
        initial bias phase), ``pos_ned``/``vel_ned`` start the navigation state. Without
        ``yaw_rad`` the heading comes from the GPS course as soon as the ground speed exceeds
        ``yaw_align_min_speed_m_s`` (now, if ``vel_ned`` already does); until then it is not
        estimated.
        """
        try:
            accel = vec3(accel_mean)
            gyro = vec3(gyro_mean)
            pos = vec3(pos_ned)
            vel = vec3(vel_ned)
        except ValueError as exc:
            log.warning("eskf initialise refused: %s", exc)
            self.rejected_inputs += 1
            return False
        if yaw_rad is not None and not math.isfinite(yaw_rad):
            log.warning("eskf initialise refused: yaw_rad is %r", yaw_rad)
            self.rejected_inputs += 1
            return False
        if not 0.5 * self.gravity_m_s2 < float(np.linalg.norm(accel)) < 1.5 * self.gravity_m_s2:
            log.warning("eskf initialise refused: |accel_mean| %.2f m/s^2 is not ~g", np.linalg.norm(accel))
            self.rejected_inputs += 1
            return False
        self._clear()
        roll, pitch = roll_pitch_from_accel(accel)
        course = math.atan2(vel[1], vel[0])
        speed = math.hypot(vel[0], vel[1])
        if yaw_rad is not None:
            yaw, self._yaw_aligned = float(yaw_rad), True
        elif speed >= self.yaw_align_min_speed_m_s:
            yaw, self._yaw_aligned = course, True
        else:
            yaw, self._yaw_aligned = 0.0, False
        self._q = quat_from_euler_f(roll, pitch, yaw)
        self._pos = pos
        self._vel = vel
        self._set_biases(np.clip(gyro, -self.max_gyro_bias_rad_s, self.max_gyro_bias_rad_s),
                         np.zeros(3))
        self._accel_lp_f = (float(accel[0]), float(accel[1]), float(accel[2]))
        g0, g1, g2 = (float(c) for c in gyro)
        a0, a1, a2 = (float(c) for c in accel)
        self._last_imu = (g0, g1, g2, a0, a1, a2)
        self._p = self._initial_covariance()
        if self._yaw_aligned and yaw_rad is None:
            self._p[IDX_YAW, IDX_YAW] = self.yaw_align_std_rad**2
        self._initialised = True
        self._remember_good()
        return True

    def set_gps_lag(self, lag_s: float, std_s: float) -> bool:
        """Restart the delay estimate from an operator's value (a parameter change).

        ``std_s`` 0 fixes the delay at ``lag_s``. False (and nothing changed) on a value out
        of ``0..max_gps_lag_s`` or a negative or non-finite ``std_s``.
        """
        lag, std = float(lag_s), float(std_s)
        if not (math.isfinite(lag) and 0.0 <= lag <= self.max_gps_lag_s
                and math.isfinite(std) and std >= 0.0):
            self.rejected_inputs += 1
            return False
        self._propagate_covariance()
        self.gps_lag_s, self.gps_lag_std_s = lag, std
        self._lag, self._lag_on = lag, std > 0.0
        self._q_cache.clear()
        p = self._p
        p[IDX_GPS_LAG, :] = 0.0
        p[:, IDX_GPS_LAG] = 0.0
        p[IDX_GPS_LAG, IDX_GPS_LAG] = std * std if self._lag_on else FIXED_LAG_VAR
        return True

    @property
    def gps_lag_estimate_s(self) -> float:
        """The receiver delay the filter currently applies on top of the measured latency."""
        return self._lag

    @property
    def gps_lag_estimate_std_s(self) -> float:
        """The 1-sigma uncertainty of :attr:`gps_lag_estimate_s` (s), :meth:`state`'s
        ``gps_lag_std_s``, without its array copies (the flight thread logs it at every fix)."""
        return math.sqrt(max(float(self._p[IDX_GPS_LAG, IDX_GPS_LAG]), 0.0))

    def state(self) -> EskfState:
        q_f = self._reported_q()
        q = np.array(q_f)
        roll, pitch, yaw = quat_to_euler_f(*q_f)
        diag = np.diagonal(self._p).copy()
        if not self._yaw_aligned:
            diag[IDX_YAW] = math.pi**2 / 3.0
        return EskfState(
            time_s=self._t,
            initialised=self._initialised,
            yaw_aligned=self._yaw_aligned,
            quaternion=q,
            roll_rad=roll,
            pitch_rad=pitch,
            yaw_rad=yaw,
            pos_ned_m=self._pos.copy(),
            vel_ned_m_s=self._vel.copy(),
            gyro_bias_rad_s=self._bg.copy(),
            accel_bias_m_s2=self._ba.copy(),
            cov_diag=diag,
            last_gps_innovation=np.array(self._last_gps_innovation),
            last_gps_nis=self._last_gps_nis,
            last_attitude_innovation=self._last_att_innovation.copy(),
            last_attitude_nis=self._last_att_nis,
            faults=self.faults,
            last_fault_reason=self.last_fault_reason,
            gps_rejections_in_row=self._gps_rejections,
            rejected_inputs=self.rejected_inputs,
            gps_lag_s=self._lag,
            gps_lag_std_s=self.gps_lag_estimate_std_s,
            gyro_matrix=self._gm.copy(),
            gyro_temp_rad_s_per_c=np.array(self._gyro_temp),
        )

    def flight_view(self) -> FlightView:
        """What the flight thread publishes at every IMU sample, as Python floats.

        :meth:`state` copies every array into a frozen snapshot (about 10 us); the thread turns
        those arrays straight back into tuples, at 100 Hz or more. This reads the same values
        without the copies; ``cov_diag`` follows :meth:`state`'s convention for the heading.
        """
        w, x, y, z = q = self._reported_q() if self.trim_bias_tilt else self._q
        roll, pitch, yaw = quat_to_euler_f(w, x, y, z)
        diag = self._p.diagonal().tolist()
        if not self._yaw_aligned:
            diag[IDX_YAW] = math.pi**2 / 3.0
        return FlightView(q, roll, pitch, yaw, self._pos_f, self._vel_f, self._bg_f, self._ba_f,
                          tuple(diag),
                          self._last_gps_innovation,
                          self._initialised and self._yaw_aligned, self.faults,
                          self.last_fault_reason)

    def turn_body_axes(self, dq: tuple[float, float, float, float]) -> None:
        """The samples' axes are turned by ``dq`` from now on (new axes = ``dq`` old axes: a
        new level trim): the attitude and both biases follow, so the estimate stays the same
        aircraft's. The gyro matrix and the covariance keep their axes (a trim moves by a
        fraction of a degree; a difference that large is second order)."""
        w, x, y, z = quat_multiply_f(*self._q, dq[0], -dq[1], -dq[2], -dq[3])
        n = math.sqrt(w * w + x * x + y * y + z * z)
        self._q = (w / n, x / n, y / n, z / n)
        r = rotmat_f(*dq)
        self._set_biases(r @ self._bg, r @ self._ba)
