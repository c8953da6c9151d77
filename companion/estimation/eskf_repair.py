"""The ESKF's health: checks after every step and the repair of a fault.

Anything that goes wrong (a non-finite value, a covariance that is not positive definite, GPS
rejected again and again) is an *estimator fault*: counted, logged with a reason, and repaired
by a reset to the last healthy state with a widened covariance. Separate from the mathematics
it guards, which calls it after each step.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from companion.estimation.eskf_history import StateHistory
from companion.estimation.eskf_state import (
    FIXED_LAG_VAR,
    IDX_GPS_LAG,
    IDX_YAW,
    N_STATES,
    EstimatorFault,
    quat_from_euler_f,
)
from companion.estimation.quat import (
    FloatArray,
    roll_pitch_from_accel,
)

log = logging.getLogger(__name__)

class FaultRepair(StateHistory):
    """Health checks after each step, and the reset that repairs a fault."""

    def _state_finite(self) -> bool:
        """The cheap part of the health check, for samples that did not move the covariance."""
        # finite attitude and acceleration keep position and velocity finite
        if math.isfinite(sum(self._q) + sum(self._f_nav_f)):
            return True
        self._fault("non-finite state")
        return False

    def _after_step(self, check_pd: bool) -> bool:
        """Keep P symmetric and unaligned heading out of it; detect divergence. True if healthy."""
        p = self._p
        p = 0.5 * (p + p.T)
        if not self._yaw_aligned:
            p[IDX_YAW, :] = 0.0
            p[:, IDX_YAW] = 0.0
        if not self._lag_on:
            p[IDX_GPS_LAG, :] = 0.0
            p[:, IDX_GPS_LAG] = 0.0
            p[IDX_GPS_LAG, IDX_GPS_LAG] = FIXED_LAG_VAR
        self._p = p
        # one sum per vector: NaN or infinity in any element makes it non-finite (this runs
        # at the IMU rate, where four isfinite().all() calls cost more than the check is worth)
        state_ok = (
            all(math.isfinite(c) for c in self._q)
            and math.isfinite(sum(self._pos_f) + sum(self._vel_f) + sum(self._bg_f)
                              + sum(self._ba_f))
        )
        if not state_ok:
            self._fault("non-finite state")
            return False
        d = np.diagonal(p).tolist()  # two reductions over a list beat two numpy calls here
        if not (math.isfinite(sum(d)) and min(d) >= 0.0):
            self._fault("covariance not finite or negative variance")
            return False
        if check_pd and not self._is_pd(p):
            self._fault("covariance not positive definite")
            return False
        return True

    def _is_pd(self, p: FloatArray) -> bool:
        """Cholesky test over the states in use (an unaligned heading has variance 0)."""
        if self._yaw_aligned:
            sub = p
        else:
            keep = [i for i in range(N_STATES) if i != IDX_YAW]
            sub = p[np.ix_(keep, keep)]
        try:
            np.linalg.cholesky(sub)
        except np.linalg.LinAlgError:
            return False
        return True

    def _record_fault(self, reason: str) -> None:
        self.faults += 1
        self.last_fault_reason = reason
        self._fault_log.append(EstimatorFault(self._t, reason))
        log.warning("estimator fault %d at t=%.2f s: %s", self.faults, self._t, reason)

    def _fault(self, reason: str, gps: tuple[FloatArray, FloatArray] | None = None) -> None:
        """Count and log a divergence, then reset to the best state still believable."""
        self._record_fault(reason)
        good = self._last_good
        q: tuple[float, ...] = self._q
        if not all(math.isfinite(c) for c in q):
            if good is not None:
                q = good[0]
            else:
                # nothing believable left: level on the low-passed accelerometer (wrong in a
                # sustained turn, which is why a finite attitude is always preferred)
                if not all(math.isfinite(c) for c in self._accel_lp_f):
                    self._accel_lp_f = (0.0, 0.0, -self.gravity_m_s2)
                roll, pitch = roll_pitch_from_accel(np.array(self._accel_lp_f))
                q = quat_from_euler_f(roll, pitch, 0.0)
        pos, vel = self._pos, self._vel
        if gps is None and self._last_gps is not None:
            # a recent fix, carried forward to now, beats a state that just diverged
            t_fix, fix_pos, fix_vel = self._last_gps
            age = self._t - t_fix
            if age < 2.0:
                gps = (fix_pos + fix_vel * age, fix_vel)
        if gps is not None:
            pos, vel = gps[0].copy(), gps[1].copy()
        if not (np.isfinite(pos).all() and np.isfinite(vel).all()):
            pos, vel = (good[1].copy(), good[2].copy()) if good is not None else (np.zeros(3), np.zeros(3))
        self._set_biases(self._bg if np.isfinite(self._bg).all() else np.zeros(3),
                         self._ba if np.isfinite(self._ba).all() else np.zeros(3))
        if not np.isfinite(self._gm).all():
            self._set_gyro_matrix(self._gm_prior.copy())
        if not all(math.isfinite(c) for c in self._gyro_temp):
            self._gyro_temp = self._gt_prior
        self._pend_dth_f = (0.0, 0.0, 0.0)
        self._q = (q[0], q[1], q[2], q[3])
        self._pos, self._vel = pos, vel
        self._p = self._initial_covariance()
        self._pend_dt = 0.0
        self._pend_dv_f = (0.0, 0.0, 0.0)
        self._history.clear()
        self._gps_rejections = 0
        self._att_rejections = 0

    def _inflate(self, idx: slice, var: float) -> None:
        p = self._p
        p[idx, :] = 0.0
        p[:, idx] = 0.0
        for i in range(idx.start, idx.stop):
            if i != IDX_YAW or self._yaw_aligned:
                p[i, i] = var

    @property
    def fault_log(self) -> list[EstimatorFault]:
        """The most recent faults (up to 32), oldest first."""
        return list(self._fault_log)
