"""The ESKF's measurement updates: GPS (with its delay), horizon attitude, heading.

GPS latency is a state because no datasheet gives it and it changes with the receiver's
settings: a fix is the receiver's solution for an instant some 50-300 ms before its first byte,
and a filter told the wrong delay turns every turn into a velocity error (0.1 s of error at
5 m/s^2 of centripetal acceleration is 0.5 m/s). The fix is compared with the state history at
``now - (measured transfer + estimated delay)``; the innovation's sensitivity to the delay is
the velocity (position rows) and the acceleration (velocity rows) at that instant, so the delay
becomes observable whenever the aircraft accelerates, and stays put (with its uncertainty) in
straight flight, where it does not matter.

Every update uses the Joseph form and is chi-square gated; the first GPS course over
``yaw_align_min_speed_m_s`` aligns the heading. Separate from the time update: each aiding
sensor's model is read here alone.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from companion.core.mathutil import clamp
from companion.estimation.eskf_calibration import GyroCalibrationStates
from companion.estimation.eskf_state import (
    IDX_ACCEL_BIAS,
    IDX_ATT,
    IDX_GPS_LAG,
    IDX_GYRO_TEMP,
    IDX_POS,
    IDX_VEL,
    IDX_YAW,
    MAX_GYRO_TEMP_RAD_S_PER_C,
    N_STATES,
    UpdateResult,
    std3,
    vec3,
)
from companion.estimation.quat import (
    FloatArray,
    quat_from_rotvec_f,
    quat_multiply_f,
    quat_to_euler_f,
    rotmat_f,
    rotmat_flat_f,
    wrap_pi,
)

log = logging.getLogger(__name__)

_H_GPS = np.zeros((6, N_STATES))
_H_GPS[0:3, 0:3] = np.eye(3)
_H_GPS[3:6, 3:6] = np.eye(3)
_H_GPS.flags.writeable = False
"""The GPS measurement matrix's constant part (position and velocity observed directly)."""
_H_INDEX = np.array(
    [r * N_STATES + c for r, c in ((0, 3), (1, 4), (2, 5))]
    + [r * N_STATES + c for r in range(3, 6) for c in range(6, 9)]
    + [r * N_STATES + c for r in range(3, 6) for c in range(12, 15)]
    + [r * N_STATES + IDX_GPS_LAG for r in range(6)])
"""Flat positions of the GPS measurement matrix's entries that change with each fix, in the
order `Eskf.update_gps` computes them (the delay column last)."""
_H_INDEX_NO_LAG = _H_INDEX[:21].copy()
_H_GPS_NO_LATENCY = (0.0,) * 18
"""The attitude and accelerometer-bias entries when the fix has no latency."""




class MeasurementUpdates(GyroCalibrationStates):
    """GPS, horizon and heading fixes, each against the state of its own instant."""

    def update_gps(
        self,
        pos_ned_m: ArrayLike,
        vel_ned_m_s: ArrayLike,
        pos_std_m: float | Sequence[float] | FloatArray,
        vel_std_m_s: float | Sequence[float] | FloatArray,
        latency_s: float = 0.0,
    ) -> UpdateResult:
        """Fuse a GPS fix handed off ``latency_s`` before the latest IMU sample.

        ``latency_s`` is what the caller knows (transfer and hand-off times); the fix is valid
        that long plus the estimated receiver delay (``gps_lag_s``) before now. The fix is
        compared with the stored nominal state at its validity time (interpolated from the
        last ``history_s`` of predictions); the resulting error is mapped to now through the
        first-order transition over the latency (position error drifts with the velocity
        error, velocity error with the attitude and accel-bias errors), the delay error through
        the velocity and acceleration at that instant, and the correction is applied to the
        current state. A fix older than the history is refused.
        """
        if not self._initialised:
            return UpdateResult(False, "not_initialised")
        try:
            z_pos = vec3(pos_ned_m)
            z_vel = vec3(vel_ned_m_s)
            p_std = std3(pos_std_m)
            v_std = std3(vel_std_m_s)
            latency = float(latency_s)
            if not (math.isfinite(latency) and latency >= 0.0):
                raise ValueError(f"latency_s is {latency_s!r}")
        except (TypeError, ValueError) as exc:
            self.rejected_inputs += 1
            log.debug("GPS fix refused: %s", exc)
            return UpdateResult(False, "bad_input")
        self._propagate_covariance()
        latency += self._lag
        past = self._state_at_f(self._t - latency)
        if past is None:
            return UpdateResult(False, "latency_out_of_range")
        pos_then, vel_then, _ = past
        acc_then = self._mean_accel_at(self._t - latency) if self._lag_on else None
        self._last_gps = (self._t, z_pos + z_vel * latency, z_vel)

        speed = math.hypot(z_vel[0], z_vel[1])
        if not self._yaw_aligned and speed >= self.yaw_align_min_speed_m_s:
            self._align_yaw(math.atan2(z_vel[1], z_vel[0]), z_pos, z_vel, latency, p_std, v_std)
            return UpdateResult(True, "yaw_aligned")

        # y, H and R assembled from floats, H's varying entries written with one call: the
        # same values as the array forms, without a dozen small numpy calls per fix
        zp, zv = z_pos.tolist(), z_vel.tolist()
        innovation = (zp[0] - pos_then[0], zp[1] - pos_then[1], zp[2] - pos_then[2],
                      zv[0] - vel_then[0], zv[1] - vel_then[1], zv[2] - vel_then[2])
        y = np.array(innovation)
        h = _H_GPS.copy()
        m = -latency
        if latency > 0.0:
            fx, fy, fz = (c * latency for c in self._f_nav_f)
            values = [m, m, m, 0.0, -fz, fy, fz, 0.0, -fx, -fy, fx, 0.0,
                      *[c * latency for c in rotmat_flat_f(*self._q)]]
        else:
            values = [m, m, m, *_H_GPS_NO_LATENCY]
        if acc_then is not None:
            # z = x(t - lag): a longer delay reads an older position and velocity
            values += [-vel_then[0], -vel_then[1], -vel_then[2],
                       -acc_then[0], -acc_then[1], -acc_then[2]]
            h.put(_H_INDEX, values)
        else:
            h.put(_H_INDEX_NO_LAG, values)
        ps, vs = p_std.tolist(), v_std.tolist()
        r = np.diag([ps[0] * ps[0], ps[1] * ps[1], ps[2] * ps[2],
                     vs[0] * vs[0], vs[1] * vs[1], vs[2] * vs[2]])
        result = self._kalman_update(y, h, r, self.gps_gate)
        self._last_gps_innovation = innovation
        self._last_gps_nis = result.nis
        if result.accepted:
            self._gps_rejections = 0
            self._remember_good()
            return result
        self._gps_rejections += 1
        if self._gps_rejections >= self.max_gps_rejections:
            self._fault(
                f"GPS rejected {self._gps_rejections} times in a row (NIS {result.nis:.1f} > "
                f"{result.gate:.1f})",
                gps=(z_pos + z_vel * latency, z_vel),
            )
            return UpdateResult(False, "reset", y, result.nis, result.gate)
        return result

    def update_attitude(
        self, roll_rad: float, pitch_rad: float, quality: float, latency_s: float = 0.0
    ) -> UpdateResult:
        """Fuse a roll/pitch fix (horizon detection); ``quality`` in (0, 1] scales its trust.

        The measurement variance is ``(horizon_std_rad / quality)^2``. Fixes near vertical
        pitch (where roll is undefined) are refused.
        """
        if not self._initialised:
            return UpdateResult(False, "not_initialised")
        try:
            roll, pitch, qual, latency = (
                float(roll_rad), float(pitch_rad), float(quality), float(latency_s)
            )
        except (TypeError, ValueError):
            self.rejected_inputs += 1
            return UpdateResult(False, "bad_input")
        if not (
            all(math.isfinite(c) for c in (roll, pitch, qual, latency))
            and 0.0 < qual <= 1.0
            and latency >= 0.0
            and abs(pitch) <= math.pi / 2
        ):
            self.rejected_inputs += 1
            return UpdateResult(False, "bad_input")
        then = self._airframe_then(latency)
        if then is None:
            return UpdateResult(False, "latency_out_of_range")
        q_then, (est_roll, est_pitch, est_yaw) = then
        if abs(est_pitch) > math.radians(75.0) or abs(pitch) > math.radians(75.0):
            return UpdateResult(False, "attitude_out_of_range")
        y = np.array((float(wrap_pi(roll - est_roll)), pitch - est_pitch))
        cy, sy = math.cos(est_yaw), math.sin(est_yaw)
        cp = math.cos(est_pitch)
        h = np.zeros((2, N_STATES))
        # Euler-angle errors from the NED rotation-vector error (first two rows of M^-1)
        h[0, 6:9] = (cy / cp, sy / cp, 0.0)
        h[1, 6:9] = (-sy, cy, 0.0)
        self._airframe_fix_columns(h, q_then, latency)
        var = (self.horizon_std_rad / qual) ** 2
        result = self._kalman_update(y, h, np.eye(2) * var, self.attitude_gate)
        self._last_att_innovation = y
        self._last_att_nis = result.nis
        if result.accepted:
            self._att_rejections = 0
            return result
        self._att_rejections += 1
        if self._att_rejections >= self.max_attitude_rejections:
            self._att_rejections = 0
            self._record_fault(
                f"horizon fixes rejected {self.max_attitude_rejections} times in a row"
            )
            # reopen the attitude uncertainty so the next fixes (and GPS) can pull it back
            self._inflate(IDX_ATT, self.init_tilt_std_rad**2)
            return UpdateResult(False, "reset", y, result.nis, result.gate)
        return result

    def update_heading(
        self, yaw_rad: float, std_rad: float, latency_s: float = 0.0
    ) -> UpdateResult:
        """Fuse a heading fix of the airframe (a dual-antenna receiver's, a calibrated
        magnetometer's after declination), ``std_rad`` its 1-sigma.

        Why it matters: in a steady coordinated turn a heading error and a tilt about the turn's
        radius leave the same mark on the GPS velocity (the centripetal acceleration seen
        turned), so without a heading reference the filter splits that error between them and
        the inclination error in a 30 deg bank is about tan(30 deg) times the heading error.
        A fix before the heading is aligned (from the GPS course) is refused.
        """
        if not self._initialised:
            return UpdateResult(False, "not_initialised")
        try:
            yaw, std, latency = float(yaw_rad), float(std_rad), float(latency_s)
        except (TypeError, ValueError):
            self.rejected_inputs += 1
            return UpdateResult(False, "bad_input")
        if not (all(math.isfinite(c) for c in (yaw, std, latency)) and std > 0.0
                and latency >= 0.0):
            self.rejected_inputs += 1
            return UpdateResult(False, "bad_input")
        if not self._yaw_aligned:
            return UpdateResult(False, "not_aligned")
        then = self._airframe_then(latency)
        if then is None:
            return UpdateResult(False, "latency_out_of_range")
        q_then, (_roll, est_pitch, est_yaw) = then
        if abs(est_pitch) > math.radians(75.0):
            return UpdateResult(False, "attitude_out_of_range")
        y = np.array((float(wrap_pi(yaw - est_yaw)),))
        t = math.tan(est_pitch)
        h = np.zeros((1, N_STATES))
        # the Euler yaw's error from the NED rotation-vector error (third row of M^-1)
        h[0, 6:9] = (t * math.cos(est_yaw), t * math.sin(est_yaw), 1.0)
        self._airframe_fix_columns(h, q_then, latency)
        return self._kalman_update(y, h, np.eye(1) * (std * std), self.heading_gate)

    def _airframe_then(
        self, latency_s: float
    ) -> tuple[tuple[float, ...], tuple[float, float, float]] | None:
        """For an airframe attitude fix (horizon, heading) ``latency_s`` old: the covariance
        brought up to now, the filter's attitude then, and the Euler angles of that attitude as
        reported (the fix sees the airframe, trims and bias tilt included); None when the fix
        is older than the history."""
        self._propagate_covariance()
        past = self._state_at_f(self._t - latency_s)
        if past is None:
            return None
        q = past[2]
        return q, quat_to_euler_f(*(self._reported_q(q) if self.trim_bias_tilt else q))

    def _airframe_fix_columns(self, h: FloatArray, q_then: tuple[float, ...],
                              latency_s: float) -> None:
        """The columns an airframe attitude fix (horizon, heading) shares, from its Euler rows
        on the attitude error (``h[:, 6:9]``) and the filter's attitude then (``q_then``)."""
        if latency_s > 0.0:
            # the attitude error then differs from now's by the gyro-bias drift in between
            h[:, 9:12] = h[:, 6:9] @ rotmat_f(*self._q) * latency_s
        if self.trim_bias_tilt:
            # the reported attitude turns with the accelerometer bias: (-b_y, b_x, 0) / g in
            # body axes, so the fix also speaks of the bias
            g = self.gravity_m_s2
            h[:, IDX_ACCEL_BIAS] = h[:, 6:9] @ rotmat_f(*q_then) @ np.array(
                ((0.0, -1.0 / g, 0.0), (1.0 / g, 0.0, 0.0), (0.0, 0.0, 0.0)))

    def _kalman_update(
        self, y: FloatArray, h: FloatArray, r: FloatArray, gate: float
    ) -> UpdateResult:
        # no positive-definiteness test before the update: S's Cholesky below refuses a
        # covariance broken where ``h`` looks, and the full test after the update (the same
        # outcome, one factorisation instead of two) catches the rest
        p = self._p
        if not self._yaw_aligned:
            h = h.copy()
            h[:, IDX_YAW] = 0.0
        pht = p @ h.T
        s = h @ pht + r
        try:
            s_inv = np.linalg.inv(np.linalg.cholesky(s))
            s_inv = s_inv.T @ s_inv
        except np.linalg.LinAlgError:
            self._fault("innovation covariance not positive definite")
            return UpdateResult(False, "reset", y)
        nis = float(y @ s_inv @ y)
        if not math.isfinite(nis):
            self._fault("non-finite innovation")
            return UpdateResult(False, "reset", y)
        if nis > gate:
            return UpdateResult(False, "gated", y, nis, gate)
        k = pht @ s_inv
        if not self._yaw_aligned:
            k[IDX_YAW, :] = 0.0
        dx = k @ y
        ikh = self._eye - k @ h
        self._p = ikh @ p @ ikh.T + k @ r @ k.T
        self._inject(dx)
        if self._after_step(check_pd=True):
            return UpdateResult(True, "ok", y, nis, gate)
        return UpdateResult(False, "reset", y, nis, gate)

    def _inject(self, dx: FloatArray) -> None:
        """Fold the error estimate into the nominal state and reset the error to zero."""
        # scalar adds and clamps: the same values as the array forms (np.clip alone cost
        # more than the rest of the injection)
        d = dx.tolist()
        p0, p1, p2 = self._pos_f
        v0, v1, v2 = self._vel_f
        self._pos_f = (p0 + d[0], p1 + d[1], p2 + d[2])
        self._vel_f = (v0 + d[3], v1 + d[4], v2 + d[5])
        tx, ty, tz = d[6], d[7], d[8]
        w, x, y, z = quat_multiply_f(*quat_from_rotvec_f(tx, ty, tz), *self._q)
        n = math.sqrt(w * w + x * x + y * y + z * z)
        self._q = (w / n, x / n, y / n, z / n)
        gb, ab = self.max_gyro_bias_rad_s, self.max_accel_bias_m_s2
        bg, ba = self._bg_f, self._ba_f
        self._set_biases(
            np.array([clamp(bg[i] + d[9 + i], -gb, gb) for i in range(3)]),
            np.array([clamp(ba[i] + d[12 + i], -ab, ab) for i in range(3)]),
        )
        if self._lag_on:
            self._lag = clamp(self._lag + d[IDX_GPS_LAG], 0.0, self.max_gps_lag_s)
        if self.gyro_bias_temp_rad_s_per_c > 0.0:
            lim_t, k0 = MAX_GYRO_TEMP_RAD_S_PER_C, IDX_GYRO_TEMP.start
            k = self._gyro_temp
            self._gyro_temp = (clamp(k[0] + d[k0], -lim_t, lim_t),
                               clamp(k[1] + d[k0 + 1], -lim_t, lim_t),
                               clamp(k[2] + d[k0 + 2], -lim_t, lim_t))
        if self._gm_on:
            lim = self.max_gyro_matrix
            m = self._gm.reshape(-1).tolist()
            self._set_gyro_matrix(np.array(
                [clamp(m[i] + d[16 + i], -lim, lim) for i in range(9)]).reshape(3, 3))
        # error-reset Jacobian for a NED-frame attitude error: G = I + [dtheta/2]x
        if tx * tx + ty * ty + tz * tz > 1e-12:
            hx, hy, hz = 0.5 * tx, 0.5 * ty, 0.5 * tz
            g = np.array(((1.0, -hz, hy), (hz, 1.0, -hx), (-hy, hx, 1.0)))
            p = self._p
            p[IDX_ATT, :] = g @ p[IDX_ATT, :]
            p[:, IDX_ATT] = p[:, IDX_ATT] @ g.T

    def _align_yaw(
        self,
        course_rad: float,
        z_pos: FloatArray,
        z_vel: FloatArray,
        latency_s: float,
        p_std: FloatArray,
        v_std: FloatArray,
    ) -> None:
        """Turn the attitude about NED-down so the heading equals the GPS course."""
        self._propagate_covariance()
        roll, pitch, yaw = quat_to_euler_f(*self._q)
        delta = float(wrap_pi(course_rad - yaw))
        dq = quat_from_rotvec_f(0.0, 0.0, delta)
        self._q = quat_multiply_f(*dq, *self._q)
        # velocity and position integrated with the wrong heading are worthless: restart them
        self._vel = z_vel.copy()
        self._pos = z_pos + z_vel * latency_s
        self._history.clear()
        self._yaw_aligned = True
        p = self._p
        for idx in (IDX_POS, IDX_VEL):
            p[idx, :] = 0.0
            p[:, idx] = 0.0
        p[IDX_YAW, :] = 0.0
        p[:, IDX_YAW] = 0.0
        p[IDX_POS, IDX_POS] = np.diag(p_std**2 + (v_std * latency_s) ** 2)
        p[IDX_VEL, IDX_VEL] = np.diag(v_std**2)
        p[IDX_YAW, IDX_YAW] = self.yaw_align_std_rad**2
        log.info("heading aligned to GPS course %.1f deg", math.degrees(course_rad))
        self._after_step(check_pd=True)
