"""The ESKF's time update: the IMU samples integrated, the covariance propagated.

Rate independence: the nominal state is integrated sample by sample, at whatever rate the IMU
runs (50 Hz to 1 kHz), composing each sample's rotation exactly (the coning motion between
samples is captured by the composition) and rotating each sample's velocity increment with
the mid-sample attitude (sculling to second order). The covariance, the expensive part, is
propagated once per ``cov_period_s`` from the increments accumulated over that period, so its
cost does not grow with the IMU rate; it is brought up to date before every measurement.

Separate from the measurement updates: it runs at the IMU's rate, they at the aiding's.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import ArrayLike

from companion.estimation.eskf_repair import FaultRepair
from companion.estimation.eskf_state import (
    GYRO_TEMP_RESIDUAL,
    IDX_GPS_LAG,
    IDX_GYRO_MATRIX,
    N_STATES,
    TEMP_SPAN_C,
)
from companion.estimation.noise import white_accel_q
from companion.estimation.quat import (
    FloatArray,
    quat_from_rotvec_f,
    quat_multiply_f,
    rotmat_flat_f,
)

log = logging.getLogger(__name__)

_F_INDEX = np.array(
    [r * N_STATES + c for r, c in ((0, 3), (1, 4), (2, 5))]
    + [r * N_STATES + c for r in range(3, 6) for c in range(6, 9)]
    + [r * N_STATES + c for r in range(3, 6) for c in range(12, 15)]
    + [r * N_STATES + c for r in range(6, 9) for c in range(9, 12)]
    + [r * N_STATES + c for r in range(6, 9) for c in range(IDX_GYRO_MATRIX.start,
                                                            IDX_GYRO_MATRIX.stop)])
"""Flat positions of the transition matrix's entries that change every period, in the order
`Eskf._propagate_covariance` computes them (the gyro-matrix block last)."""
_F_INDEX_NO_GM = _F_INDEX[:30].copy()


class Propagation(FaultRepair):
    """The nominal state per IMU sample and the covariance per ``cov_period_s``."""

    def _process_noise(self, dt_s: float) -> FloatArray:
        key = round(dt_s, 5)
        q = self._q_cache.get(key)
        if q is None:
            q = np.zeros((N_STATES, N_STATES))
            # position/velocity driven by white accelerometer noise, exact discretisation
            q[0:6, 0:6] = white_accel_q(key, self.accel_noise_m_s2_rt_hz**2)
            for i in range(6, 9):
                q[i, i] = self.gyro_noise_rad_s_rt_hz**2 * key
            for i in range(9, 12):
                q[i, i] = self.gyro_bias_rw_rad_s_rt_s**2 * key
            for i in range(12, 15):
                q[i, i] = self.accel_bias_rw_m_s2_rt_s**2 * key
            if self._lag_on:
                q[IDX_GPS_LAG, IDX_GPS_LAG] = self.gps_lag_rw_s_rt_s**2 * key
            if self._gm_on:
                for i in range(IDX_GYRO_MATRIX.start, IDX_GYRO_MATRIX.stop):
                    q[i, i] = self.gyro_matrix_rw_rt_s**2 * key
            if len(self._q_cache) > 64:
                self._q_cache.clear()
            self._q_cache[key] = q
        return q

    def predict(self, gyro_rad_s: ArrayLike, accel_m_s2: ArrayLike, dt_s: float) -> bool:
        """Propagate with one IMU sample (mean rate and specific force over ``dt_s``).

        Returns False when the sample was refused or a fault was repaired. A garbage sample is
        replaced by the previous good one (zero-order hold); a gap longer than ``max_dt_s``
        coasts on the velocity; before ``initialise`` only time advances. Time always advances
        so late measurements stay aligned.
        """
        try:
            if type(gyro_rad_s) is tuple and type(accel_m_s2) is tuple:  # the flight path
                g0, g1, g2 = (float(c) for c in gyro_rad_s)
                a0, a1, a2 = (float(c) for c in accel_m_s2)
            else:
                g0, g1, g2 = (float(c) for c in np.asarray(gyro_rad_s, dtype=float).reshape(3))
                a0, a1, a2 = (float(c) for c in np.asarray(accel_m_s2, dtype=float).reshape(3))
            dt = float(dt_s)
        except (TypeError, ValueError):
            self.rejected_inputs += 1
            return False
        if not (math.isfinite(dt) and dt > 0.0):
            self.rejected_inputs += 1
            return False
        if not self._initialised:
            self._t += dt
            return False
        if dt > self.max_dt_s:
            # IMU data missing for a while: coast on the velocity and let the uncertainty grow
            self.rejected_inputs += 1
            self._coast(dt)
            return False
        finite = all(math.isfinite(c) for c in (g0, g1, g2, a0, a1, a2))
        if (
            not finite
            or g0 * g0 + g1 * g1 + g2 * g2 > self.max_gyro_rad_s**2
            or a0 * a0 + a1 * a1 + a2 * a2 > self.max_accel_m_s2**2
        ):
            # one garbage sample: hold the previous good one (zero-order hold)
            self.rejected_inputs += 1
            held = True
            g0, g1, g2, a0, a1, a2 = self._last_imu
        else:
            held = False
            self._last_imu = (g0, g1, g2, a0, a1, a2)

        # Scalar arithmetic on Python floats: at 100 Hz-1 kHz numpy's per-call overhead would
        # cost more than the arithmetic.
        bg0, bg1, bg2 = self._bg_f
        ba0, ba1, ba2 = self._ba_f
        if self._gm_apply:
            # the part reads (I + M) w + b: undo the estimated M (its inverse, kept as c)
            u0, u1, u2 = g0 - bg0, g1 - bg1, g2 - bg2
            c = self._gm_inv_f
            u0, u1, u2 = (c[0] * u0 + c[1] * u1 + c[2] * u2, c[3] * u0 + c[4] * u1 + c[5] * u2,
                          c[6] * u0 + c[7] * u1 + c[8] * u2)
            wx, wy, wz = u0 * dt, u1 * dt, u2 * dt
            if self._gm_on:
                th = self._pend_dth_f
                self._pend_dth_f = (th[0] + wx, th[1] + wy, th[2] + wz)
        else:
            wx, wy, wz = (g0 - bg0) * dt, (g1 - bg1) * dt, (g2 - bg2) * dt
        fb0, fb1, fb2 = a0 - ba0, a1 - ba1, a2 - ba2
        if self._pend_dt == 0.0:
            self._pend_q = self._q  # attitude at the start of the covariance period
        # attitude: exact exponential map; velocity uses the mid-sample attitude
        q = self._q
        w, x, y, z = quat_multiply_f(*q, *quat_from_rotvec_f(0.5 * wx, 0.5 * wy, 0.5 * wz))
        # f_nav = R(q_mid) f_body
        fx = ((1 - 2 * (y * y + z * z)) * fb0 + 2 * (x * y - w * z) * fb1
              + 2 * (x * z + w * y) * fb2)
        fy = (2 * (x * y + w * z) * fb0 + (1 - 2 * (x * x + z * z)) * fb1
              + 2 * (y * z - w * x) * fb2)
        fz = (2 * (x * z - w * y) * fb0 + 2 * (y * z + w * x) * fb1
              + (1 - 2 * (x * x + y * y)) * fb2)
        w, x, y, z = quat_multiply_f(*q, *quat_from_rotvec_f(wx, wy, wz))
        n = math.sqrt(w * w + x * x + y * y + z * z)
        self._q = (w / n, x / n, y / n, z / n)
        fz_g = fz + self.gravity_m_s2
        half_dt2 = 0.5 * dt * dt
        p0, p1, p2 = self._pos_f
        v0, v1, v2 = self._vel_f
        # the same operations, in the same order, as the array form this replaced
        self._pos_f = (p0 + (v0 * dt + half_dt2 * fx), p1 + (v1 * dt + half_dt2 * fy),
                       p2 + (v2 * dt + half_dt2 * fz_g))
        self._vel_f = (v0 + fx * dt, v1 + fy * dt, v2 + fz_g * dt)
        self._f_nav_f = (fx, fy, fz)
        self._t += dt
        lp = self._accel_lp_f
        self._accel_lp_f = (lp[0] + 0.02 * (a0 - lp[0]), lp[1] + 0.02 * (a1 - lp[1]),
                            lp[2] + 0.02 * (a2 - lp[2]))
        self._pend_dt += dt
        pd = self._pend_dv_f
        self._pend_dv_f = (pd[0] + fx * dt, pd[1] + fy * dt, pd[2] + fz * dt)
        self._history.append((self._t, self._pos_f, self._vel_f, self._q))
        self._predicts += 1
        if self._pend_dt >= self.cov_period_s - 1e-9:
            self._propagate_covariance()
            healthy = self._after_step(check_pd=self._predicts % self.pd_check_every == 0)
        else:
            healthy = self._state_finite()
        return healthy and not held

    def _propagate_covariance(self) -> None:
        """Move the covariance over the IMU time accumulated since it was last propagated.

        One transition for the whole period: the velocity error picks up the accumulated
        velocity increment's sensitivity to attitude, and the bias errors act through the
        attitude at the period's start (over 10-20 ms the difference is second order).
        """
        dt = self._pend_dt
        if dt <= 0.0:
            return
        f = self._f
        fx, fy, fz = self._pend_dv_f
        rot0 = rotmat_flat_f(*self._pend_q)
        m = -dt
        r_dt = [c * m for c in rot0]
        # the transition's varying entries, written in one call (each numpy call costs a few
        # microseconds on the flight path): position/velocity dt; d(dv)/d(dtheta) = -[dv_nav]x;
        # velocity/accelerometer bias and attitude/gyro bias -C dt
        values = [dt, dt, dt, 0.0, fz, -fy, -fz, 0.0, fx, fy, -fx, 0.0, *r_dt, *r_dt]
        if self._gm_on:
            # d(dtheta)/dM: the rate error -C dM w, over the period's body rotation
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = rot0
            c00, c01, c02, c10, c11, c12, c20, c21, c22 = self._gm_inv_f
            rc = (r00 * c00 + r01 * c10 + r02 * c20, r00 * c01 + r01 * c11 + r02 * c21,
                  r00 * c02 + r01 * c12 + r02 * c22,
                  r10 * c00 + r11 * c10 + r12 * c20, r10 * c01 + r11 * c11 + r12 * c21,
                  r10 * c02 + r11 * c12 + r12 * c22,
                  r20 * c00 + r21 * c10 + r22 * c20, r20 * c01 + r21 * c11 + r22 * c21,
                  r20 * c02 + r21 * c12 + r22 * c22)
            t0, t1, t2 = self._pend_dth_f
            n0, n1, n2 = -t0, -t1, -t2
            values += [v for c in rc for v in (c * n0, c * n1, c * n2)]
            self._pend_dth_f = (0.0, 0.0, 0.0)
            f.put(_F_INDEX, values)
        else:
            f.put(_F_INDEX_NO_GM, values)
        p = f @ self._p @ f.T
        p += self._process_noise(dt)
        if self._pend_temp_c > 0.0:
            scale = TEMP_SPAN_C * self._pend_temp_c
            gyro_var = (GYRO_TEMP_RESIDUAL * self.gyro_bias_temp_rad_s_per_c)**2 * scale
            accel_var = self.accel_bias_temp_m_s2_per_c**2 * scale
            for i in range(9, 12):
                p[i, i] += gyro_var
            for i in range(12, 15):
                p[i, i] += accel_var
            self._pend_temp_c = 0.0
        self._p = p
        self._pend_dt = 0.0
        self._pend_dv_f = (0.0, 0.0, 0.0)

    def _coast(self, dt_s: float) -> None:
        """Cover a gap in the IMU data: constant velocity, covariance grown for the gap."""
        self._propagate_covariance()
        self._pos += self._vel * dt_s
        self._t += dt_s
        steps = max(1, math.ceil(dt_s / self.max_dt_s))
        step = dt_s / steps
        f = self._eye.copy()
        f[0, 3] = f[1, 4] = f[2, 5] = step
        q = self._process_noise(step).copy()
        # unknown manoeuvres during the gap, about 1 m/s^2 1-sigma on each axis
        q[0:6, 0:6] += white_accel_q(step, 1.0)
        p = self._p
        for _ in range(min(steps, 1000)):
            p = f @ p @ f.T + q
        self._p = p
        self._history.clear()
        self._after_step(check_pd=True)
