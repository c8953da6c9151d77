"""6-D attitude (roll and pitch) from a gyroscope and an accelerometer, sample by sample.

The old on-board estimator integrated rates and corrected with gravity using fixed gains; it
drifted when the gyro bias changed and was pulled off by manoeuvre accelerations. This filter
is a small error-state Kalman filter instead:

* the nominal attitude is propagated with the exact exponential map of the bias-corrected rate
  (sample ``k`` is the mean rate over the preceding sample period);
* the error state is the tilt error about the NED north and east axes, the three gyro biases
  and the three accelerometer biases. The heading error is left out on purpose: nothing in a
  6-D IMU observes it, and with the error expressed in the navigation frame it never feeds back
  into the tilt, so dropping it is exact and keeps its unbounded variance out of the matrices;
* the accelerometer is rotated into NED with the current estimate and low-passed there (a
  continuous 2nd-order Butterworth stepped exactly over each sample's own period, so unevenly
  timed samples are weighted by the time they cover). In that frame gravity is constant while
  the accelerations of a moving sensor average out, so a sharp filter rejects them without
  delaying the gravity reference; the filter memory is rotated along with every correction so
  it stays in the corrected frame;
* the filtered specific force is compared with ``(0, 0, -g)``. Its trust adapts: the variance
  grows with ``(|a| - g)^2`` (turns, pull-ups, linear accelerations) and with the rotation rate,
  and an innovation that is still improbable is down-weighted Huber-style rather than swallowed;
* the accelerometer bias is part of the state: with the gyro linking readings taken in
  different orientations, and gravity's magnitude known, it becomes observable as soon as the
  sensor has been tilted a few times, which removes the tilt floor it otherwise sets;
* rest is detected from the spread of gyro and accelerometer around their low-passed values;
  at rest the raw rates are direct measurements of the gyro bias, which makes its vertical
  component observable too. In motion the gyro bias is learnt through the tilt corrections;
* for a vehicle that flies along its body x axis at a known speed (an aeroplane), the
  centripetal acceleration ``omega x (V, 0, 0)`` is removed before the comparison, so a steady
  coordinated turn does not pull the wings level.

Use :class:`AttitudeFilter` on board (one :meth:`~AttitudeFilter.update` per IMU sample, with
that sample's own period) and :func:`estimate_attitude` for recordings (a nominal rate, or the
samples' time stamps ``t_s``).
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import ArrayLike

from companion.estimation.quat import (
    GRAVITY_M_S2,
    FloatArray,
    quat_from_accel,
    quat_from_rotvec_f,
    quat_multiply_f,
    rotmat_f,
)

log = logging.getLogger(__name__)

_N = 8
"""Error state: tilt north, tilt east (rad), gyro bias xyz (rad/s), accel bias xyz (m/s^2)."""
_GB = slice(2, 5)

_AB = slice(5, 8)


class AttitudeFilter:
    """Error-state Kalman filter for roll, pitch and IMU biases; heading is carried but free.

    All tuning values are plain keyword arguments with SI units in their names; the defaults
    are one set for a MEMS IMU at 50-400 Hz and are not tuned per recording. They were chosen
    on synthetic recordings, then three were revised on the tuning half of real robot-arm
    recordings (``tests/data/imu-truth``, split in ``companion/evaluation/realdata.py``):
    ``gyro_scale_error`` 0.01 -> 0.05, ``gyro_bias_std0_rad_s`` 0.02 -> 0.01,
    ``accel_rate_gain_m_s`` 2 -> 1 (the synthetic figures improved slightly as well).

    Args:
        gyro_noise_rad_s_rt_hz: white rate noise driving the tilt uncertainty, rad/s/sqrt(Hz).
            Larger than a data-sheet value on purpose: it also covers vibration-induced errors.
        gyro_scale_error: fraction of the rate added to the rate noise, for scale-factor and
            cross-axis errors during fast rotations. 0.05 because uncalibrated MEMS gyros have
            them: data sheets allow +-3 % sensitivity and +-2 % cross-axis. On the real
            recordings 0.01 left the filter leaning on the gyro through fast turns it had
            integrated wrongly (with the old defaults 11 % behind VQF on the tuning
            recordings, 1 % ahead with these; on the faster held-out recordings 2.5 % ahead
            before, 1.5 % after: see docs/benchmarks.md).
        gyro_bias_rw_rad_s_rt_s: gyro bias random walk, rad/s/sqrt(s).
        gyro_bias_std0_rad_s: initial 1-sigma gyro bias uncertainty, rad/s (0.01: turn-on
            biases of factory-trimmed MEMS gyros; larger let manoeuvre errors into the bias).
        gyro_bias_clip_rad_s: gyro bias estimates are clipped to +- this, rad/s.
        accel_bias_std0_m_s2: initial 1-sigma accelerometer bias, m/s^2 (0 disables the
            estimation of the accelerometer bias).
        accel_bias_rw_m_s2_rt_s: accelerometer bias random walk, m/s^2/sqrt(s).
        accel_bias_clip_m_s2: accelerometer bias estimates are clipped to +- this, m/s^2.
        accel_noise_m_s2: 1-sigma error of the filtered specific force as a gravity reference
            when the sensor is steady, m/s^2.
        accel_lpf_tau_s: time constant of the NED-frame low-pass on the accelerometer, s.
        accel_norm_gain: extra 1-sigma per m/s^2 of ``| |a_filtered| - g |``.
        accel_raw_norm_gain: extra 1-sigma per m/s^2 of ``| |a_raw| - g |``.
        accel_rate_gain_m_s: extra 1-sigma per rad/s of rotation rate, m/s (1: with the larger
            scale-factor noise the tilt variance already grows with the rate).
        robust_nis: NIS (3 dof) above which an accelerometer innovation is down-weighted in
            proportion.
        forward_speed_m_s: speed along body x used to remove the centripetal acceleration
            (0 for a sensor that does not travel along a body axis).
        tilt_std0_rad: initial 1-sigma tilt uncertainty after levelling on the first sample.
        rest_gyro_th_rad_s: gyro spread around its low-pass value below which the IMU may rest.
        rest_accel_th_m_s2: accelerometer spread threshold for rest, m/s^2.
        rest_time_s: how long both spreads must stay low before rest is declared.
        rest_filter_tau_s: time constant of the low-pass filters used by the rest detector.
        rest_max_rate_rad_s: rest also needs the bias-corrected low-passed rate below this, so
            a steady slow turn is not taken for a bias.
        rest_bias_noise_rad_s: 1-sigma of one raw gyro sample as a bias measurement at rest.
        gravity_m_s2: local gravity.
    """

    def __init__(
        self,
        *,
        gyro_noise_rad_s_rt_hz: float = 0.005,
        gyro_scale_error: float = 0.05,
        gyro_bias_rw_rad_s_rt_s: float = 1e-5,
        gyro_bias_std0_rad_s: float = 0.01,
        gyro_bias_clip_rad_s: float = 0.15,
        accel_bias_std0_m_s2: float = 0.1,
        accel_bias_rw_m_s2_rt_s: float = 1e-4,
        accel_bias_clip_m_s2: float = 0.5,
        accel_noise_m_s2: float = 0.6,
        accel_lpf_tau_s: float = 1.5,
        accel_norm_gain: float = 2.0,
        accel_raw_norm_gain: float = 0.0,
        accel_rate_gain_m_s: float = 1.0,
        robust_nis: float = 11.3,
        forward_speed_m_s: float = 0.0,
        tilt_std0_rad: float = 0.1,
        rest_gyro_th_rad_s: float = math.radians(2.0),
        rest_accel_th_m_s2: float = 0.5,
        rest_time_s: float = 1.5,
        rest_filter_tau_s: float = 0.5,
        rest_max_rate_rad_s: float = math.radians(3.0),
        rest_bias_noise_rad_s: float = 0.01,
        gravity_m_s2: float = GRAVITY_M_S2,
    ) -> None:
        positives = {
            "gyro_noise_rad_s_rt_hz": gyro_noise_rad_s_rt_hz,
            "gyro_bias_std0_rad_s": gyro_bias_std0_rad_s,
            "accel_noise_m_s2": accel_noise_m_s2,
            "accel_lpf_tau_s": accel_lpf_tau_s,
            "robust_nis": robust_nis,
            "tilt_std0_rad": tilt_std0_rad,
            "rest_time_s": rest_time_s,
            "rest_filter_tau_s": rest_filter_tau_s,
            "rest_bias_noise_rad_s": rest_bias_noise_rad_s,
            "gravity_m_s2": gravity_m_s2,
        }
        non_negatives = {
            "gyro_scale_error": gyro_scale_error,
            "gyro_bias_rw_rad_s_rt_s": gyro_bias_rw_rad_s_rt_s,
            "gyro_bias_clip_rad_s": gyro_bias_clip_rad_s,
            "accel_bias_std0_m_s2": accel_bias_std0_m_s2,
            "accel_bias_rw_m_s2_rt_s": accel_bias_rw_m_s2_rt_s,
            "accel_bias_clip_m_s2": accel_bias_clip_m_s2,
            "accel_norm_gain": accel_norm_gain,
            "accel_raw_norm_gain": accel_raw_norm_gain,
            "accel_rate_gain_m_s": accel_rate_gain_m_s,
            "forward_speed_m_s": forward_speed_m_s,
            "rest_gyro_th_rad_s": rest_gyro_th_rad_s,
            "rest_accel_th_m_s2": rest_accel_th_m_s2,
            "rest_max_rate_rad_s": rest_max_rate_rad_s,
        }
        for name, value in positives.items():
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0.0):
                raise ValueError(f"AttitudeFilter: {name} must be a finite number > 0, got {value!r}")
        for name, value in non_negatives.items():
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0.0):
                raise ValueError(f"AttitudeFilter: {name} must be a finite number >= 0, got {value!r}")
        self.gyro_noise_rad_s_rt_hz = float(gyro_noise_rad_s_rt_hz)
        self.gyro_scale_error = float(gyro_scale_error)
        self.gyro_bias_rw_rad_s_rt_s = float(gyro_bias_rw_rad_s_rt_s)
        self.gyro_bias_std0_rad_s = float(gyro_bias_std0_rad_s)
        self.gyro_bias_clip_rad_s = float(gyro_bias_clip_rad_s)
        self.accel_bias_std0_m_s2 = float(accel_bias_std0_m_s2)
        self.accel_bias_rw_m_s2_rt_s = float(accel_bias_rw_m_s2_rt_s)
        self.accel_bias_clip_m_s2 = float(accel_bias_clip_m_s2)
        self.accel_noise_m_s2 = float(accel_noise_m_s2)
        self.accel_lpf_tau_s = float(accel_lpf_tau_s)
        self.accel_norm_gain = float(accel_norm_gain)
        self.accel_raw_norm_gain = float(accel_raw_norm_gain)
        self.accel_rate_gain_m_s = float(accel_rate_gain_m_s)
        self.robust_nis = float(robust_nis)
        self.forward_speed_m_s = float(forward_speed_m_s)
        self.tilt_std0_rad = float(tilt_std0_rad)
        self.rest_gyro_th_rad_s = float(rest_gyro_th_rad_s)
        self.rest_accel_th_m_s2 = float(rest_accel_th_m_s2)
        self.rest_time_s = float(rest_time_s)
        self.rest_filter_tau_s = float(rest_filter_tau_s)
        self.rest_max_rate_rad_s = float(rest_max_rate_rad_s)
        self.rest_bias_noise_rad_s = float(rest_bias_noise_rad_s)
        self.gravity_m_s2 = float(gravity_m_s2)
        self.reset()

    # -- state -------------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget everything; the next sample levels the filter again."""
        self._q = (1.0, 0.0, 0.0, 0.0)
        self._gyro_bias = np.zeros(3)
        self._accel_bias = np.zeros(3)
        self._p = self._initial_covariance()
        self._initialised = False
        self._gyro_lp = np.zeros(3)
        self._accel_lp = np.zeros(3)
        self._rest_s = 0.0
        self._gyro_dev_sq = 0.0
        self._accel_dev_sq = 0.0
        self._sample_dt = 0.0
        self._lpf_phi = (1.0, 0.0, 0.0, 1.0)
        self._lpf_phi_dt = -1.0
        self._lpf_s1 = np.zeros(3)
        self._lpf_s2 = np.zeros(3)
        self._rot_s1 = np.zeros((3, 3))
        self._rot_s2 = np.zeros((3, 3))
        self._warmup_n = 0
        self._warmup_s = 0.0
        self.at_rest = False
        """True while the rest detector holds (the gyro bias is then measured directly)."""
        self.rejected_samples = 0
        """Samples skipped because they were not finite (or dt was not positive)."""
        self.covariance_resets = 0
        """Times the covariance lost positivity and was re-initialised (should stay 0)."""

    def _initial_covariance(self) -> FloatArray:
        return np.diag(
            [self.tilt_std0_rad**2] * 2
            + [self.gyro_bias_std0_rad_s**2] * 3
            + [self.accel_bias_std0_m_s2**2] * 3
        )

    @property
    def quaternion(self) -> FloatArray:
        """Current attitude (w, x, y, z), body to NED; heading is arbitrary."""
        return np.array(self._q)

    @property
    def gyro_bias_rad_s(self) -> FloatArray:
        return self._gyro_bias.copy()

    @property
    def accel_bias_m_s2(self) -> FloatArray:
        return self._accel_bias.copy()

    @property
    def tilt_std_rad(self) -> float:
        """1-sigma tilt uncertainty (rad), from the covariance."""
        return math.sqrt(max(self._p[0, 0] + self._p[1, 1], 0.0))

    @property
    def covariance(self) -> FloatArray:
        """Error-state covariance (8x8): tilt N/E, gyro bias, accel bias."""
        return self._p.copy()

    # -- per-sample step ---------------------------------------------------------------------

    def update(
        self,
        gyro_rad_s: ArrayLike,
        accel_m_s2: ArrayLike,
        dt_s: float,
        forward_speed_m_s: float | None = None,
    ) -> FloatArray:
        """Consume one IMU sample taken ``dt_s`` after the previous one; return the attitude.

        ``forward_speed_m_s`` overrides the constructor's value for this sample (an aeroplane
        passes its airspeed or ground speed here).
        """
        gyro = np.asarray(gyro_rad_s, dtype=float).reshape(3)
        accel = np.asarray(accel_m_s2, dtype=float).reshape(3)
        speed = self.forward_speed_m_s if forward_speed_m_s is None else float(forward_speed_m_s)
        if not (
            np.isfinite(gyro).all()
            and np.isfinite(accel).all()
            and math.isfinite(dt_s)
            and math.isfinite(speed)
        ):
            self.rejected_samples += 1
            return self.quaternion
        if not self._initialised:
            self._initialise(gyro, accel)
            return self.quaternion
        if dt_s <= 0.0:
            self.rejected_samples += 1
            return self.quaternion
        self._lpf_coefficients(dt_s)
        self._propagate(gyro, dt_s)
        self._detect_rest(gyro, accel, dt_s)
        if self.at_rest:
            self._update_bias_at_rest(gyro)
        self._update_accel(gyro, accel, speed)
        return self.quaternion

    def _initialise(self, gyro: FloatArray, accel: FloatArray) -> None:
        if float(np.linalg.norm(accel)) < 0.1 * self.gravity_m_s2:
            self.rejected_samples += 1
            return
        q = quat_from_accel(accel)
        self._q = (float(q[0]), float(q[1]), float(q[2]), float(q[3]))
        self._gyro_lp = gyro.copy()
        self._accel_lp = accel.copy()
        rot = rotmat_f(*self._q)
        self._lpf_s1 = rot @ accel
        self._rot_s1 = rot
        self._warmup_n = 1
        self._warmup_s = 0.0
        self._initialised = True

    def _lpf_coefficients(self, dt_s: float) -> None:
        """Transition of the NED low-pass over a sample that covers ``dt_s``.

        The low-pass is the continuous 2nd-order Butterworth with cutoff
        ``1 / (2 pi accel_lpf_tau_s)`` (state: output and its rate), stepped with the exact
        transition for each sample's own period, the input held over the period. Samples that
        arrive unevenly (a host stamping them on arrival, a log with gaps) are then weighted by
        the time they cover, and the memory never falls out of step with the coefficients, as a
        discrete filter's does when its coefficients change from sample to sample.
        """
        self._sample_dt = dt_s
        if dt_s == self._lpf_phi_dt:
            return
        self._lpf_phi_dt = dt_s
        omega = 1.0 / self.accel_lpf_tau_s
        sigma = omega * math.sqrt(0.5)  # damping 1/sqrt(2)
        omega_d = omega * math.sqrt(0.5)
        decay = math.exp(-sigma * dt_s)
        c = math.cos(omega_d * dt_s)
        sn = math.sin(omega_d * dt_s)
        self._lpf_phi = (
            decay * (c + sigma / omega_d * sn),
            decay * sn / omega_d,
            -decay * omega * omega / omega_d * sn,
            decay * (c - sigma / omega_d * sn),
        )

    def _propagate(self, gyro: FloatArray, dt_s: float) -> None:
        rate = gyro - self._gyro_bias
        rx, ry, rz = (float(c) * dt_s for c in rate)
        dq = quat_from_rotvec_f(rx, ry, rz)
        w, x, y, z = quat_multiply_f(*self._q, *dq)
        n = math.sqrt(w * w + x * x + y * y + z * z)
        self._q = (w / n, x / n, y / n, z / n)
        rot = rotmat_f(*self._q)
        # the tilt error grows with the gyro bias error rotated into NED
        f = np.eye(_N)
        f[0:2, _GB] = -rot[0:2, :] * dt_s
        p = f @ self._p @ f.T
        rate_sq = float(rate @ rate)
        # A scale-factor error is systematic over a manoeuvre, not white: modelled as rate noise
        # of density scale * |rate| * sqrt(1 s), it grows the tilt variance at the pace the
        # error really accumulates, so the filter leans on the accelerometer (not on the
        # bias) while the sensor turns fast.
        q_tilt = (self.gyro_noise_rad_s_rt_hz**2 + self.gyro_scale_error**2 * rate_sq) * dt_s
        q_gb = self.gyro_bias_rw_rad_s_rt_s**2 * dt_s
        q_ab = self.accel_bias_rw_m_s2_rt_s**2 * dt_s
        p[0, 0] += q_tilt
        p[1, 1] += q_tilt
        for i in range(2, 5):
            p[i, i] += q_gb
        for i in range(5, 8):
            p[i, i] += q_ab
        self._p = p

    def _detect_rest(self, gyro: FloatArray, accel: FloatArray, dt_s: float) -> None:
        # Compare the mean-square spread around the low-passed signals (not single samples)
        # with the thresholds, so white noise at high sample rates does not break up rest.
        alpha = min(1.0, dt_s / self.rest_filter_tau_s)
        self._gyro_lp += alpha * (gyro - self._gyro_lp)
        self._accel_lp += alpha * (accel - self._accel_lp)
        dg = gyro - self._gyro_lp
        da = accel - self._accel_lp
        self._gyro_dev_sq += alpha * (float(dg @ dg) - self._gyro_dev_sq)
        self._accel_dev_sq += alpha * (float(da @ da) - self._accel_dev_sq)
        slow = float(np.linalg.norm(self._gyro_lp - self._gyro_bias)) < self.rest_max_rate_rad_s
        if (
            self._gyro_dev_sq < self.rest_gyro_th_rad_s**2
            and self._accel_dev_sq < self.rest_accel_th_m_s2**2
            and slow
        ):
            self._rest_s += dt_s
        else:
            self._rest_s = 0.0
        self.at_rest = self._rest_s >= self.rest_time_s

    def _update_bias_at_rest(self, gyro: FloatArray) -> None:
        # measurement: raw rate = gyro bias (+ white noise); H selects the gyro bias states
        p = self._p
        r = self.rest_bias_noise_rad_s**2
        s = p[_GB, _GB] + np.eye(3) * r
        k = p[:, _GB] @ np.linalg.inv(s)
        self._apply(k @ (gyro - self._gyro_bias))
        ikh = np.eye(_N)
        ikh[:, _GB] -= k
        self._p = ikh @ p @ ikh.T + r * (k @ k.T)
        self._check_covariance()

    def _filter(self, a_nav: FloatArray, rot: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Low-pass the NED specific force, and the rotation that maps the accel bias into it.

        ``_lpf_s1``/``_rot_s1`` hold the outputs, ``_lpf_s2``/``_rot_s2`` their rates.
        """
        if self._warmup_s < self.accel_lpf_tau_s:
            # until one time constant has passed, a running mean is both faster and less noisy
            # than a low-pass started from a single sample
            self._warmup_n += 1
            self._warmup_s += self._sample_dt
            self._lpf_s1 = self._lpf_s1 + (a_nav - self._lpf_s1) / self._warmup_n
            self._rot_s1 = self._rot_s1 + (rot - self._rot_s1) / self._warmup_n
            if self._warmup_s >= self.accel_lpf_tau_s:
                # hand over to the low-pass in its steady state for the current mean
                self._lpf_s2 = np.zeros(3)
                self._rot_s2 = np.zeros((3, 3))
            return self._lpf_s1.copy(), self._rot_s1.copy()
        p11, p12, p21, p22 = self._lpf_phi
        # exact step with the input held: x <- x_ss + phi (x - x_ss), x_ss = (input, 0)
        dy = self._lpf_s1 - a_nav
        self._lpf_s1 = a_nav + p11 * dy + p12 * self._lpf_s2
        self._lpf_s2 = p21 * dy + p22 * self._lpf_s2
        dr = self._rot_s1 - rot
        self._rot_s1 = rot + p11 * dr + p12 * self._rot_s2
        self._rot_s2 = p21 * dr + p22 * self._rot_s2
        return self._lpf_s1.copy(), self._rot_s1.copy()

    def _update_accel(self, gyro: FloatArray, accel: FloatArray, speed_m_s: float) -> None:
        rate = gyro - self._gyro_bias
        specific = accel - self._accel_bias
        if speed_m_s != 0.0:
            # centripetal part of a body moving along its x axis: omega x (V, 0, 0)
            specific = specific - np.array((0.0, rate[2] * speed_m_s, -rate[1] * speed_m_s))
        norm_raw = float(np.linalg.norm(specific))
        if norm_raw < 1e-6:
            return
        rot = rotmat_f(*self._q)
        out, rot_out = self._filter(rot @ specific, rot)
        g = self.gravity_m_s2
        innovation = out - np.array((0.0, 0.0, -g))
        norm = float(np.linalg.norm(out))
        sigma_sq = (
            self.accel_noise_m_s2**2
            + (self.accel_norm_gain * (norm - g)) ** 2
            + (self.accel_raw_norm_gain * (norm_raw - g)) ** 2
            + self.accel_rate_gain_m_s**2 * float(rate @ rate)
        )
        # filtered reading = (g * tilt_e, -g * tilt_n, -g) + filtered(R) @ accel_bias_error
        h = np.zeros((3, _N))
        h[0, 1] = g
        h[1, 0] = -g
        h[:, _AB] = rot_out
        p = self._p
        pht = p @ h.T
        s_base = h @ pht
        r = np.eye(3) * sigma_sq
        s_inv = np.linalg.inv(s_base + r)
        nis = float(innovation @ s_inv @ innovation)
        if nis > self.robust_nis:
            r *= nis / self.robust_nis
            s_inv = np.linalg.inv(s_base + r)
        k = pht @ s_inv
        self._apply(k @ innovation)
        ikh = np.eye(_N) - k @ h
        self._p = ikh @ p @ ikh.T + k @ r @ k.T
        self._check_covariance()

    def _apply(self, dx: FloatArray) -> None:
        tn, te = float(dx[0]), float(dx[1])
        dq = quat_from_rotvec_f(tn, te, 0.0)
        w, x, y, z = quat_multiply_f(*dq, *self._q)
        n = math.sqrt(w * w + x * x + y * y + z * z)
        self._q = (w / n, x / n, y / n, z / n)
        # keep the low-pass memory in the corrected navigation frame, and take the accel bias
        # correction out of the readings it has already absorbed
        turn = np.array(((1.0, 0.0, te), (0.0, 1.0, -tn), (-te, tn, 1.0)))
        old_ab = self._accel_bias.copy()
        self._gyro_bias += dx[_GB]
        self._accel_bias += dx[_AB]
        np.clip(self._gyro_bias, -self.gyro_bias_clip_rad_s, self.gyro_bias_clip_rad_s,
                out=self._gyro_bias)
        np.clip(self._accel_bias, -self.accel_bias_clip_m_s2, self.accel_bias_clip_m_s2,
                out=self._accel_bias)
        # The filters are linear and the rotation filter saw the same inputs, so its memory
        # times the bias change is exactly what the readings' memory must lose.
        shift = self._accel_bias - old_ab
        self._lpf_s1 = turn @ (self._lpf_s1 - self._rot_s1 @ shift)
        self._rot_s1 = turn @ self._rot_s1
        if self._warmup_s >= self.accel_lpf_tau_s:
            self._lpf_s2 = turn @ (self._lpf_s2 - self._rot_s2 @ shift)
            self._rot_s2 = turn @ self._rot_s2

    def _check_covariance(self) -> None:
        p = self._p
        p = 0.5 * (p + p.T)
        if not np.isfinite(p).all() or (np.diag(p) < 0.0).any():
            self.covariance_resets += 1
            log.warning("attitude filter covariance lost positivity; re-initialising it")
            p = self._initial_covariance()
        self._p = p


def estimate_attitude(
    gyro_rad_s: ArrayLike,
    accel_m_s2: ArrayLike,
    rate_hz: float,
    *,
    t_s: ArrayLike | None = None,
    **params: float,
) -> FloatArray:
    """Causal attitude of a whole recording: output ``k`` uses samples ``0..k`` only.

    Args:
        gyro_rad_s: (N, 3) body rates, rad/s; sample k is the mean over the preceding period.
        accel_m_s2: (N, 3) specific force, m/s^2, about (0, 0, -g) level and still.
        rate_hz: sample rate; with ``t_s`` only the first sample's period (``1 / rate_hz``).
        t_s: optional (N,) time stamps, s. Real IMUs read by a host are not sampled evenly
            (the robot-arm recordings in ``tests/data/imu-truth`` arrive 2-20 ms apart): with
            the time stamps each sample is integrated over its own period ``t[k] - t[k-1]``
            instead of a nominal one. A sample whose period is not positive is skipped (and
            counted in ``rejected_samples`` of the filter).
        **params: keyword arguments of :class:`AttitudeFilter`.

    Returns:
        (N, 4) quaternions (w, x, y, z), body to NED, heading arbitrary (starts at 0).
        Rows before the first usable sample hold the identity.
    """
    gyro = np.asarray(gyro_rad_s, dtype=float)
    accel = np.asarray(accel_m_s2, dtype=float)
    if gyro.ndim != 2 or gyro.shape[1] != 3:
        raise ValueError(f"estimate_attitude: gyro_rad_s must have shape (N, 3), got {gyro.shape}")
    if accel.shape != gyro.shape:
        raise ValueError(
            f"estimate_attitude: accel_m_s2 shape {accel.shape} differs from gyro shape {gyro.shape}"
        )
    if not (isinstance(rate_hz, int | float) and math.isfinite(rate_hz) and rate_hz > 0.0):
        raise ValueError(f"estimate_attitude: rate_hz must be a number > 0, got {rate_hz!r}")
    dt = np.full(len(gyro), 1.0 / float(rate_hz))
    if t_s is not None:
        t = np.asarray(t_s, dtype=float)
        if t.shape != (len(gyro),):
            raise ValueError(
                f"estimate_attitude: t_s must have shape ({len(gyro)},), got {t.shape}"
            )
        dt[1:] = np.diff(t)
    filt = AttitudeFilter(**params)
    out = np.empty((len(gyro), 4))
    for k in range(len(gyro)):
        out[k] = filt.update(gyro[k], accel[k], float(dt[k]))
    return out
