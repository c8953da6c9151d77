"""The ESKF's state layout and its set-up: what every part of the filter shares.

The error state's indices (``IDX_*``), the result and snapshot types, the input checks, and
`EskfBase`: the settings, the nominal state and covariance at a (re)start and their setters.
The filter's jobs (history, repair, prediction, calibration states, updates) are classes on top
of it, one module each (companion.estimation.eskf assembles them), so each reads alone.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from statistics import NormalDist
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from companion.estimation.noise import chi2_ppf_even
from companion.estimation.quat import (
    GRAVITY_M_S2,
    FloatArray,
    quat_from_rotvec_f,
    quat_multiply_f,
)

log = logging.getLogger(__name__)

Vec3f = tuple[float, float, float]
N_STATES = 28
IDX_POS = slice(0, 3)
IDX_VEL = slice(3, 6)
IDX_ATT = slice(6, 9)
IDX_GYRO_BIAS = slice(9, 12)
IDX_ACCEL_BIAS = slice(12, 15)
IDX_YAW = 8
"""Heading error: the NED-down component of the attitude error."""
IDX_GPS_LAG = 15
"""The GPS receiver's unknown output delay, s (beyond the transfer time the driver measures)."""
IDX_GYRO_MATRIX = slice(16, 25)
"""The gyro's scale-factor and cross-axis error ``M`` (row-major, dimensionless): the part reads
``(I + M) w + b`` for a body rate ``w``."""
IDX_GYRO_TEMP = slice(25, 28)
"""The gyro bias's temperature coefficient per axis, rad/s per degree C: while the IMU warms up,
each counted temperature change moves the bias by this times the change."""
FIXED_LAG_VAR = 1e-12
"""Variance held by a delay that is not estimated: uncoupled from every other state, so the
covariance stays positive definite and nothing ever moves it."""
TEMP_STEP_C = 0.2
"""Smallest IMU temperature change that counts (`Eskf.set_temperature`): above the slow block's
0.01 C resolution and a sensor's noise, below what moves a bias noticeably."""
TEMP_SPAN_C = 20.0
"""Temperature span of a typical warm-up after switch-on (20 -> 40 C in an enclosure), over
which the temperature-driven bias walk spreads as much as the coefficient says."""
GYRO_TEMP_RESIDUAL = 0.2
"""The part of a gyro's temperature drift a straight line in temperature leaves (curvature,
hysteresis), as a fraction of the coefficient's 1-sigma: it stays a random walk in temperature
beside the estimated coefficient. Chosen on the tuning flights (0.1-0.3 score alike)."""
MAX_GYRO_TEMP_RAD_S_PER_C = 0.01
"""The estimated temperature coefficient is clipped to +-this (0.57 deg/s per C, far beyond any
MEMS part's)."""


@dataclass(frozen=True)
class UpdateResult:
    """Outcome of one measurement update; the filter never raises on a bad measurement."""

    accepted: bool
    reason: str
    """``ok``, ``yaw_aligned``, ``gated``, ``bad_input``, ``not_initialised``, ``not_aligned``
    (a heading fix before the heading is aligned), ``latency_out_of_range``,
    ``attitude_out_of_range`` or ``reset`` (a fault reset ran)."""
    innovation: FloatArray = field(default_factory=lambda: np.zeros(0))
    nis: float = math.nan
    """Normalised innovation squared, ``y' S^-1 y``; chi-square with ``len(innovation)`` dof."""
    gate: float = math.nan
    """The chi-square threshold the NIS was compared with."""


@dataclass(frozen=True)
class EstimatorFault:
    time_s: float
    reason: str


class FlightView(NamedTuple):
    """The published subset of the state as plain floats (see :meth:`Eskf.flight_view`)."""

    quaternion: tuple[float, float, float, float]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    pos_ned_m: tuple[float, ...]
    vel_ned_m_s: tuple[float, ...]
    gyro_bias_rad_s: tuple[float, float, float]
    accel_bias_m_s2: tuple[float, float, float]
    cov_diag: tuple[float, ...]
    last_gps_innovation: tuple[float, ...]
    aligned: bool
    faults: int
    last_fault_reason: str


@dataclass(frozen=True)
class EskfState:
    """A snapshot for the control thread, the logger and the ground station."""

    time_s: float
    initialised: bool
    yaw_aligned: bool
    quaternion: FloatArray
    """(w, x, y, z), body to NED."""
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    pos_ned_m: FloatArray
    vel_ned_m_s: FloatArray
    gyro_bias_rad_s: FloatArray
    accel_bias_m_s2: FloatArray
    cov_diag: FloatArray
    """Error-state variances in ``IDX_*`` order; the heading variance reads ``pi^2/3`` (a
    uniform heading) until the heading has been aligned."""
    last_gps_innovation: FloatArray
    last_gps_nis: float
    last_attitude_innovation: FloatArray
    last_attitude_nis: float
    faults: int
    last_fault_reason: str
    gps_rejections_in_row: int
    rejected_inputs: int
    gps_lag_s: float = 0.0
    """Estimated GPS output delay beyond the measured transfer time."""
    gps_lag_std_s: float = 0.0
    gyro_matrix: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))
    """Estimated gyro scale-factor and cross-axis error ``M`` (the part reads
    ``(I + M) w + b``); zeros when it is not estimated."""
    gyro_temp_rad_s_per_c: FloatArray = field(default_factory=lambda: np.zeros(3))
    """Estimated temperature coefficient of the gyro bias per axis; zeros when the filter
    has no coefficient (``gyro_bias_temp_rad_s_per_c`` 0)."""



class EskfBase:
    """The filter's settings and state, as `Eskf` builds them; see companion.estimation.eskf for the
    model.

    Every tuning value is a keyword argument with its unit in its name. Noise densities are
    continuous-time (per sqrt(Hz)); random walks per sqrt(s).

    Args:
        gyro_noise_rad_s_rt_hz: gyro white noise (angle random walk), rad/s/sqrt(Hz).
        accel_noise_m_s2_rt_hz: accelerometer white noise (velocity random walk), m/s^2/sqrt(Hz).
        gyro_bias_rw_rad_s_rt_s: gyro bias random walk, rad/s/sqrt(s).
        accel_bias_rw_m_s2_rt_s: accelerometer bias random walk, m/s^2/sqrt(s).
        init_tilt_std_rad: 1-sigma roll/pitch error after levelling on the mean accel.
        init_yaw_std_rad: 1-sigma heading error when ``initialise`` is given a heading.
        init_pos_std_m, init_vel_std_m_s: 1-sigma of the initial position and velocity.
        init_gyro_bias_std_rad_s: 1-sigma of the gyro bias after the at-rest mean.
        init_accel_bias_std_m_s2: 1-sigma of the initial accelerometer bias.
        max_gyro_bias_rad_s, max_accel_bias_m_s2: bias estimates are clipped to these.
        gps_gate_prob: chi-square probability of the GPS innovation gate (6 dof).
        max_gps_rejections: consecutive gated fixes that declare a divergence.
        attitude_gate_prob: chi-square probability of the horizon (roll/pitch) gate.
        max_attitude_rejections: consecutive gated horizon fixes that reset the attitude
            covariance (the horizon detector can be wrong for a while; GPS outranks it).
        horizon_std_rad: 1-sigma of a horizon roll/pitch fix of quality 1.
        yaw_align_min_speed_m_s: ground speed above which the GPS course aligns the heading.
        yaw_align_std_rad: 1-sigma heading error right after course alignment (sideslip and
            wind crab).
        gps_lag_s: the GPS receiver's output delay assumed at the start (beyond the transfer
            time the caller measures and passes to ``update_gps``).
        gps_lag_std_s: 1-sigma of that guess; the delay is then estimated online. 0 keeps it
            fixed (not estimated).
        gps_lag_rw_s_rt_s: random walk of the delay (receivers change it with their load).
        max_gps_lag_s: the estimate is clipped to 0..this.
        gyro_matrix_std: 1-sigma of each element of the gyro's scale-factor and cross-axis
            error ``M`` before the flight (0: not estimated, the gyro is taken as exact).
        gyro_matrix_rw_rt_s: random walk of ``M``'s elements, 1/sqrt(s) (scale factors move
            with temperature too).
        max_gyro_matrix: ``M``'s elements are clipped to +-this.
        gyro_bias_temp_rad_s_per_c, accel_bias_temp_m_s2_per_c: 1-sigma of the sensor's bias
            change per degree C (its temperature coefficient, unknown per part); with
            ``set_temperature`` the biases may then move that much faster while the part's
            temperature changes (0: no temperature term). The gyro's coefficient is also
            estimated (``IDX_GYRO_TEMP``, this its prior), so a warm-up's drift, once seen, is
            predicted instead of only allowed for.
        cov_period_s: the covariance is propagated once per this much IMU time (samples in
            between only accumulate); the nominal state follows every sample.
        history_s: how far back state history is kept to place late measurements.
        max_dt_s: longer prediction gaps are not integrated (the IMU data is missing); the
            covariance is grown for the gap instead and the gap counted.
        max_gyro_rad_s, max_accel_m_s2: readings beyond these are rejected as garbage.
        pd_check_every: full (Cholesky) positive-definiteness check every N predictions;
            every update is checked too.
        gravity_m_s2: local gravity.
    """

    def __init__(
        self,
        *,
        gyro_noise_rad_s_rt_hz: float = 0.003,
        accel_noise_m_s2_rt_hz: float = 0.05,
        gyro_bias_rw_rad_s_rt_s: float = 5e-5,
        accel_bias_rw_m_s2_rt_s: float = 1e-3,
        init_tilt_std_rad: float = 0.05,
        init_yaw_std_rad: float = 0.2,
        init_pos_std_m: float = 5.0,
        init_vel_std_m_s: float = 1.0,
        init_gyro_bias_std_rad_s: float = 0.01,
        init_accel_bias_std_m_s2: float = 0.2,
        max_gyro_bias_rad_s: float = 0.2,
        max_accel_bias_m_s2: float = 2.0,
        gps_gate_prob: float = 0.9999,
        max_gps_rejections: int = 10,
        attitude_gate_prob: float = 0.999,
        max_attitude_rejections: int = 50,
        horizon_std_rad: float = 0.05,
        yaw_align_min_speed_m_s: float = 5.0,
        yaw_align_std_rad: float = 0.3,
        gps_lag_s: float = 0.0,
        gps_lag_std_s: float = 0.0,
        gps_lag_rw_s_rt_s: float = 2e-4,
        max_gps_lag_s: float = 0.5,
        gyro_bias_temp_rad_s_per_c: float = 0.0,
        accel_bias_temp_m_s2_per_c: float = 0.0,
        gyro_matrix_std: float = 0.0,
        gyro_matrix_rw_rt_s: float = 1e-5,
        max_gyro_matrix: float = 0.1,
        cov_period_s: float = 0.01,
        history_s: float = 1.0,
        max_dt_s: float = 0.1,
        max_gyro_rad_s: float = 35.0,
        max_accel_m_s2: float = 200.0,
        pd_check_every: int = 100,
        gravity_m_s2: float = GRAVITY_M_S2,
    ) -> None:
        settings = dict(locals())
        settings.pop("self")
        may_be_zero = ("gps_lag_s", "gps_lag_std_s", "gyro_bias_temp_rad_s_per_c",
                       "accel_bias_temp_m_s2_per_c", "gyro_matrix_std", "gyro_matrix_rw_rt_s")
        for name, value in settings.items():
            if not (isinstance(value, int | float) and math.isfinite(value)
                    and (value > 0 or (value == 0 and name in may_be_zero))):
                raise ValueError(f"Eskf: {name} must be a finite number > 0, got {value!r}")
        if gps_lag_s > max_gps_lag_s:
            raise ValueError(f"Eskf: gps_lag_s {gps_lag_s!r} exceeds max_gps_lag_s {max_gps_lag_s!r}")
        for name in ("gps_gate_prob", "attitude_gate_prob"):
            if not settings[name] < 1.0:
                raise ValueError(f"Eskf: {name} must be < 1, got {settings[name]!r}")
        self.gyro_noise_rad_s_rt_hz = float(gyro_noise_rad_s_rt_hz)
        self.accel_noise_m_s2_rt_hz = float(accel_noise_m_s2_rt_hz)
        self.gyro_bias_rw_rad_s_rt_s = float(gyro_bias_rw_rad_s_rt_s)
        self.accel_bias_rw_m_s2_rt_s = float(accel_bias_rw_m_s2_rt_s)
        self.init_tilt_std_rad = float(init_tilt_std_rad)
        self.init_yaw_std_rad = float(init_yaw_std_rad)
        self.init_pos_std_m = float(init_pos_std_m)
        self.init_vel_std_m_s = float(init_vel_std_m_s)
        self.init_gyro_bias_std_rad_s = float(init_gyro_bias_std_rad_s)
        self.init_accel_bias_std_m_s2 = float(init_accel_bias_std_m_s2)
        self.max_gyro_bias_rad_s = float(max_gyro_bias_rad_s)
        self.max_accel_bias_m_s2 = float(max_accel_bias_m_s2)
        self.gps_gate = chi2_ppf_even(gps_gate_prob, 6)
        self.max_gps_rejections = int(max_gps_rejections)
        self.attitude_gate = chi2_ppf_even(attitude_gate_prob, 2)
        # one degree of freedom: the square of the two-sided normal quantile
        self.heading_gate = NormalDist().inv_cdf(0.5 + 0.5 * attitude_gate_prob) ** 2
        self.max_attitude_rejections = int(max_attitude_rejections)
        self.horizon_std_rad = float(horizon_std_rad)
        self.yaw_align_min_speed_m_s = float(yaw_align_min_speed_m_s)
        self.yaw_align_std_rad = float(yaw_align_std_rad)
        self.gps_lag_s = float(gps_lag_s)
        self.gps_lag_std_s = float(gps_lag_std_s)
        self.gps_lag_rw_s_rt_s = float(gps_lag_rw_s_rt_s)
        self.max_gps_lag_s = float(max_gps_lag_s)
        self.gyro_bias_temp_rad_s_per_c = float(gyro_bias_temp_rad_s_per_c)
        self.accel_bias_temp_m_s2_per_c = float(accel_bias_temp_m_s2_per_c)
        self.gyro_matrix_std = float(gyro_matrix_std)
        self.gyro_matrix_rw_rt_s = float(gyro_matrix_rw_rt_s)
        self.max_gyro_matrix = float(max_gyro_matrix)
        self._gm_on = self.gyro_matrix_std > 0.0
        self._gm_prior = np.zeros((3, 3))
        """The gyro matrix a previous flight learnt (`set_gyro_calibration`): the estimate
        starts from it, and with ``gyro_matrix_std`` 0 it is applied as exact."""
        self._set_gm_apply()
        self._gt_prior = (0.0, 0.0, 0.0)
        self._temp_ref_c = math.nan  # temperature at the last counted change
        self._gyro_temp = (0.0, 0.0, 0.0)  # estimated coefficient, rad/s/C (IDX_GYRO_TEMP)
        self._pend_temp_c = 0.0  # counted change not yet given to the covariance
        self.cov_period_s = float(cov_period_s)
        self._lag_on = self.gps_lag_std_s > 0.0
        self.history_s = float(history_s)
        self.max_dt_s = float(max_dt_s)
        self.max_gyro_rad_s = float(max_gyro_rad_s)
        self.max_accel_m_s2 = float(max_accel_m_s2)
        self.pd_check_every = int(pd_check_every)
        self.gravity_m_s2 = float(gravity_m_s2)
        self.trim_bias_tilt = False
        self._tilt_of_ba: tuple[tuple[float, ...] | None, tuple[float, float, float, float]] = (
            None, (1.0, 0.0, 0.0, 0.0))
        """Report the attitude turned by the tilt the accelerometer bias estimate amounts to
        (``b_a`` over g about x and y). Set when the samples come through a level calibration's
        trim (``EST_TRIM_BIAS``): that trim took the bias at calibration for a board tilt, so
        the filter's frame is the airframe turned by the bias's tilt, which the bias states
        learn in flight. Only what is reported turns; the filter's own state does not."""

        self._q_cache: dict[float, FloatArray] = {}
        self._f = np.eye(N_STATES)
        self._eye = np.eye(N_STATES)
        self._fault_log: deque[EstimatorFault] = deque(maxlen=32)
        self.faults = 0
        """Estimator faults so far (each one was repaired by a reset)."""
        self.last_fault_reason = ""
        self.rejected_inputs = 0
        """IMU samples and measurements refused as garbage (not faults: the state was safe)."""
        self._clear()

    def _clear(self) -> None:
        self._initialised = False
        self._yaw_aligned = False
        self._t = 0.0
        self._q = (1.0, 0.0, 0.0, 0.0)
        self._pos_f: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._vel_f: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._set_biases(np.zeros(3), np.zeros(3))
        self._set_gyro_matrix(self._gm_prior.copy())
        self._gyro_temp = self._gt_prior
        self._p = np.eye(N_STATES)
        self._lag = self.gps_lag_s
        self._f_nav_f = (0.0, 0.0, -self.gravity_m_s2)
        # increments since the covariance was last propagated (see cov_period_s)
        self._pend_dt = 0.0
        self._pend_dv_f = (0.0, 0.0, 0.0)
        self._pend_dth_f = (0.0, 0.0, 0.0)  # body-frame rotation (gyro-matrix Jacobian)
        self._pend_q: tuple[float, ...] = self._q
        # (time, position, velocity, attitude) after each sample
        self._history: deque[tuple[float, tuple[float, float, float], tuple[float, float, float],
                                   tuple[float, ...]]] = deque(
            maxlen=max(8, int(self.history_s * 1000))
        )
        self._predicts = 0
        self._gps_rejections = 0
        self._att_rejections = 0
        # a tuple, as flight_view publishes it at every sample; state() makes the array
        self._last_gps_innovation: tuple[float, ...] = (0.0,) * 6
        self._last_gps_nis = math.nan
        self._last_att_innovation = np.zeros(2)
        self._last_att_nis = math.nan
        self._accel_lp_f = (0.0, 0.0, -self.gravity_m_s2)
        self._last_imu = (0.0, 0.0, 0.0, 0.0, 0.0, -self.gravity_m_s2)
        self._last_good: tuple[tuple[float, ...], FloatArray, FloatArray] | None = None
        self._last_gps: tuple[float, FloatArray, FloatArray] | None = None

    def _initial_covariance(self) -> FloatArray:
        var = np.empty(N_STATES)
        var[IDX_POS] = self.init_pos_std_m**2
        var[IDX_VEL] = self.init_vel_std_m_s**2
        var[IDX_ATT] = self.init_tilt_std_rad**2
        var[IDX_YAW] = self.init_yaw_std_rad**2 if self._yaw_aligned else 0.0
        var[IDX_GYRO_BIAS] = self.init_gyro_bias_std_rad_s**2
        var[IDX_ACCEL_BIAS] = self.init_accel_bias_std_m_s2**2
        var[IDX_GPS_LAG] = self.gps_lag_std_s**2 if self._lag_on else FIXED_LAG_VAR
        var[IDX_GYRO_MATRIX] = self._gm_prior_var()
        var[IDX_GYRO_TEMP] = self._gt_prior_var()
        return np.diag(var)

    def _gm_prior_var(self) -> float:
        """Variance of each gyro-matrix state at a (re)start: its prior, or a fixed state's."""
        return self.gyro_matrix_std**2 if self._gm_on else FIXED_LAG_VAR

    def _gt_prior_var(self) -> float:
        """Variance of each temperature-coefficient state at a (re)start, likewise."""
        k = self.gyro_bias_temp_rad_s_per_c
        return k * k if k > 0.0 else FIXED_LAG_VAR

    def _set_gm_apply(self) -> None:
        """Whether samples are corrected by a matrix: one estimated, or one a previous flight
        learnt (applied as exact when not estimated). Kept as a flag for `predict`."""
        self._gm_apply = self._gm_on or bool(self._gm_prior.any())

    # Position and velocity live as float triples: the per-sample path updates them with
    # scalar arithmetic (numpy's per-call overhead exceeded the arithmetic at 100 Hz-1 kHz);
    # the measurement paths read and write them as arrays through these properties.
    @property
    def _pos(self) -> FloatArray:
        return np.array(self._pos_f)

    @_pos.setter
    def _pos(self, value: ArrayLike) -> None:
        v = np.asarray(value, dtype=float)
        self._pos_f = (float(v[0]), float(v[1]), float(v[2]))

    @property
    def _vel(self) -> FloatArray:
        return np.array(self._vel_f)

    @_vel.setter
    def _vel(self, value: ArrayLike) -> None:
        v = np.asarray(value, dtype=float)
        self._vel_f = (float(v[0]), float(v[1]), float(v[2]))

    def _set_biases(self, bg: FloatArray, ba: FloatArray) -> None:
        """Biases as arrays (updates, outputs) and as floats (the per-sample path)."""
        self._bg, self._ba = bg, ba
        self._bg_f = (float(bg[0]), float(bg[1]), float(bg[2]))
        self._ba_f = (float(ba[0]), float(ba[1]), float(ba[2]))

    def _set_gyro_matrix(self, m: FloatArray) -> None:
        """The gyro's estimated matrix error and the inverse of ``I + M`` the predictions apply."""
        self._gm = m
        # the 3x3 inverse in closed form (adjugate over determinant): np.linalg.inv's call
        # overhead was a third of a GPS update's state injection
        (a, b, c), (d, e, f), (g, h, i) = m.tolist()
        a, e, i = a + 1.0, e + 1.0, i + 1.0
        c0, c1, c2 = e * i - f * h, f * g - d * i, d * h - e * g
        det = a * c0 + b * c1 + c * c2
        if not (math.isfinite(det) and abs(det) > 1e-9):
            # only with max_gyro_matrix set near 1: a singular I + M is no estimate, drop it
            self._gm = np.zeros((3, 3))
            self._gm_inv_f = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
            return
        inv = (c0 / det, (c * h - b * i) / det, (b * f - c * e) / det,
               c1 / det, (a * i - c * g) / det, (c * d - a * f) / det,
               c2 / det, (b * g - a * h) / det, (a * e - b * d) / det)
        self._gm_inv_f = inv

    @property
    def initialised(self) -> bool:
        return self._initialised

    def _reported_q(self, q: tuple[float, ...] | None = None
                    ) -> tuple[float, float, float, float]:
        """The attitude as reported (`trim_bias_tilt`): the filter's quaternion (or ``q``)
        times the body-axes rotation (-b_y / g, b_x / g, 0)."""
        w, x, y, z = self._q if q is None else q
        if not self.trim_bias_tilt:
            return (w, x, y, z)
        ba = self._ba_f
        if ba is not self._tilt_of_ba[0]:  # the bias moves at the updates, not per sample
            g = self.gravity_m_s2
            self._tilt_of_ba = (ba, quat_from_rotvec_f(-ba[1] / g, ba[0] / g, 0.0))
        return quat_multiply_f(w, x, y, z, *self._tilt_of_ba[1])

    @property
    def covariance(self) -> FloatArray:
        """The full error-state covariance, ``N_STATES`` square (a copy)."""
        return self._p.copy()


def floats3(value: object) -> tuple[float, float, float] | None:
    """Three finite floats from a flat 3-array or 3-sequence of numbers, else None (the callers
    then take the general path, which also names what was wrong). At 10 Hz per GPS fix the
    array checks cost more than the rest of the measurement's bookkeeping."""
    if isinstance(value, np.ndarray):
        if value.shape != (3,):
            return None
        value = value.tolist()
    if not isinstance(value, tuple | list) or len(value) != 3:
        return None
    items: list[object] = list(value)
    if not all(type(v) in (float, int) for v in items):
        return None
    x, y, z = (float(v) for v in items)  # type: ignore[arg-type]
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return None
    return x, y, z


def vec3(value: ArrayLike) -> FloatArray:
    fast = floats3(value)
    if fast is not None:
        return np.array(fast)
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape != (3,):
        raise ValueError(f"expected 3 values, got {arr.shape[0]}")
    if not np.isfinite(arr).all():
        raise ValueError(f"non-finite value in {arr.tolist()}")
    return arr.copy()


def std3(value: float | Sequence[float] | FloatArray) -> FloatArray:
    """A standard deviation per axis from a scalar or 3 values; must be finite and > 0."""
    fast = floats3(value)
    if fast is not None and min(fast) > 0.0:
        return np.array((max(fast[0], 1e-3), max(fast[1], 1e-3), max(fast[2], 1e-3)))
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape == (1,):
        arr = np.repeat(arr, 3)
    if arr.shape != (3,) or not np.isfinite(arr).all() or (arr <= 0.0).any():
        raise ValueError(f"standard deviation must be 1 or 3 finite values > 0, got {value!r}")
    return np.maximum(arr, 1e-3)


def quat_from_euler_f(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )
