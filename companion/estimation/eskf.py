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

GPS latency is a state because no datasheet gives it and it changes with the receiver's
settings: a fix is the receiver's solution for an instant some 50-300 ms before its first byte,
and a filter told the wrong delay turns every turn into a velocity error (0.1 s of error at
5 m/s^2 of centripetal acceleration is 0.5 m/s). The fix is compared with the state history at
``now - (measured transfer + estimated delay)``; the innovation's sensitivity to the delay is
the velocity (position rows) and the acceleration (velocity rows) at that instant, so the delay
becomes observable whenever the aircraft accelerates, and stays put (with its uncertainty) in
straight flight, where it does not matter.

Gyro matrix: a consumer gyro's sensitivity is good to a few per cent per axis and each axis
sees a per cent or two of the others. In a banked turn that is a rate error which comes and
goes with the turn, too quick for the bias states and, over a 20 s turn, a degree of tilt. Each
sample is corrected with the estimated ``(I + M)^-1``; the states learn through the attitude
errors the GPS sees, so only in turns and rolls (``gyro_matrix_std`` 0 leaves them out).

Temperature: the biases of a MEMS part follow its temperature by an unknown coefficient, and
the part warms by some 20 C after switch-on; ``set_temperature`` lets the bias covariance grow
with each measured temperature change (a random walk in temperature, not in time), so the
estimate keeps up with a warm-up and stays tight once the part is warm.

Rate independence: the nominal state is integrated sample by sample, at whatever rate the IMU
runs (50 Hz to 1 kHz), composing each sample's rotation exactly (the coning motion between
samples is captured by the composition) and rotating each sample's velocity increment with
the mid-sample attitude (sculling to second order). The covariance, the expensive part, is
propagated once per ``cov_period_s`` from the increments accumulated over that period, so its
cost does not grow with the IMU rate; it is brought up to date before every measurement.

Why not filterpy's ``KalmanFilter``: its state is additive (``x + K y``) and its transition
acts on the state itself, while here the transition acts on an error state and the correction
is injected multiplicatively into a quaternion, then the error is reset to zero. The
position/velocity process noise block and the chi-square gates are closed forms
(:mod:`companion.estimation.noise`, checked against filterpy's ``Q_continuous_white_noise`` and
scipy's ``chi2``, which are not imported in flight: half a second of start-up); filterpy's NEES
helper is used in the tests.

Size: the filter's prediction, updates (GPS, horizon, heading, zero velocity), delayed-
measurement history and health checks are one piece of mathematics.
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

from companion.core.mathutil import clamp
from companion.estimation.noise import chi2_ppf_even, white_accel_q
from companion.estimation.quat import (
    GRAVITY_M_S2,
    FloatArray,
    quat_from_rotvec_f,
    quat_multiply_f,
    quat_to_euler_f,
    roll_pitch_from_accel,
    rotmat_f,
    rotmat_flat_f,
    wrap_pi,
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


class Eskf:
    """GPS/INS error-state Kalman filter; see the module docstring for the model.

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

    # -- set-up --------------------------------------------------------------------------------

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
            accel = _vec3(accel_mean)
            gyro = _vec3(gyro_mean)
            pos = _vec3(pos_ned)
            vel = _vec3(vel_ned)
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
        self._q = _quat_from_euler_f(roll, pitch, yaw)
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

    def set_temperature(self, temperature_c: float) -> None:
        """The IMU's temperature (its slow block, about once a second).

        A MEMS part's biases follow its temperature with a coefficient no datasheet pins
        down (the MPU-6000's zero-rate output may move 20 deg/s between -40 and 85 C), so
        while the part warms up after switch-on its gyro bias can move a degree per second
        within minutes, far faster than a random walk tuned for a warm part allows. Each
        change of ``TEMP_STEP_C`` or more (quantisation and sensor noise stay below it) adds
        ``(coefficient^2) * TEMP_SPAN_C * |change|`` to the bias variances: a random walk in
        temperature rather than in time, whose spread over a warm-up of ``TEMP_SPAN_C``
        equals the coefficient's (for the gyro, ``GYRO_TEMP_RESIDUAL`` of it: what a straight
        line leaves). The gyro's bias also moves by its estimated coefficient times the
        change, and the change couples the bias error to the coefficient's, so the drift seen
        early in a warm-up is predicted later. A part at a steady temperature adds nothing.
        """
        try:
            t = float(temperature_c)
        except (TypeError, ValueError):
            self.rejected_inputs += 1
            return
        if not math.isfinite(t) or abs(t) > 200.0:
            self.rejected_inputs += 1
            return
        if not math.isfinite(self._temp_ref_c):
            self._temp_ref_c = t
            return
        change = t - self._temp_ref_c
        if abs(change) >= TEMP_STEP_C:
            self._pend_temp_c += abs(change)
            self._temp_ref_c = t
            if self._initialised and self.gyro_bias_temp_rad_s_per_c > 0.0:
                self._follow_temperature(change)

    def _follow_temperature(self, change_c: float) -> None:
        """Move the gyro bias by the estimated coefficient over a temperature change, and its
        error by the coefficient's error: b' = b + k dT, so d(b') = d(b) + dT d(k)."""
        self._propagate_covariance()  # the samples so far saw the bias as it was
        lim = self.max_gyro_bias_rad_s
        self._set_biases(np.array([clamp(self._bg_f[i] + k * change_c, -lim, lim)
                                   for i, k in enumerate(self._gyro_temp)]), self._ba)
        p = self._p
        b, k = IDX_GYRO_BIAS, IDX_GYRO_TEMP
        # P' = T P T' with T = I + dT (rows of b, columns of k), written out on the blocks
        p[b, :] += change_c * p[k, :]
        p[:, b] += change_c * p[:, k]

    # -- prediction ----------------------------------------------------------------------------

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

    def _state_finite(self) -> bool:
        """The cheap part of the health check, for samples that did not move the covariance."""
        # finite attitude and acceleration keep position and velocity finite
        if math.isfinite(sum(self._q) + sum(self._f_nav_f)):
            return True
        self._fault("non-finite state")
        return False

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

    # -- measurement updates -------------------------------------------------------------------

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
            z_pos = _vec3(pos_ned_m)
            z_vel = _vec3(vel_ned_m_s)
            p_std = _std3(pos_std_m)
            v_std = _std3(vel_std_m_s)
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

    # -- heading alignment ---------------------------------------------------------------------

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

    # -- health --------------------------------------------------------------------------------

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
                q = _quat_from_euler_f(roll, pitch, 0.0)
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
    def gyro_matrix_estimate(self) -> FloatArray:
        """The estimated scale-factor and cross-axis error ``M`` (3x3, a copy; zeros when it is
        not estimated): the gyro reads ``(I + M) w + b``."""
        return self._gm.copy()

    @property
    def gyro_temp_estimate_rad_s_per_c(self) -> tuple[float, float, float]:
        """The gyro bias's estimated temperature coefficient per axis (rad/s per degree C),
        without :meth:`state`'s copies (the flight thread logs it at every fix)."""
        return self._gyro_temp

    def gyro_calibration(self) -> tuple[list[float], list[float], list[float], list[float]]:
        """What the filter has learnt of the part: ``M`` (9, row-major), its 1-sigma per
        element, the temperature coefficient (3, rad/s/C) and its 1-sigma; a 1-sigma reads 0
        for what is not estimated. The flight thread logs it, and the next flight can start
        from it (`set_gyro_calibration`, companion.estimation.calibration)."""
        d = np.sqrt(np.maximum(np.diagonal(self._p), 0.0))
        m_std = d[IDX_GYRO_MATRIX].tolist() if self._gm_on else [0.0] * 9
        t_std = (d[IDX_GYRO_TEMP].tolist() if self.gyro_bias_temp_rad_s_per_c > 0.0
                 else [0.0] * 3)
        return self._gm.reshape(-1).tolist(), m_std, list(self._gyro_temp), t_std

    def gyro_matrix_diagonal(self) -> list[float]:
        """The scale-factor errors alone (the diagonal of :attr:`gyro_matrix_estimate`)."""
        return self._gm.diagonal().tolist()  # type: ignore[no-any-return]

    def _remember_good(self) -> None:
        self._last_good = (self._q, self._pos, self._vel)

    def _state_at_f(self, t_s: float) -> tuple[Vec3f, Vec3f, tuple[float, ...]] | None:
        """Nominal position, velocity and attitude at ``t_s`` from the history (interpolated;
        the attitude is the nearer stored one), as floats; None before the history."""
        if t_s >= self._t - 1e-9 or not self._history:
            return self._pos_f, self._vel_f, self._q
        newer = None
        for entry in reversed(self._history):
            if entry[0] <= t_s:
                if newer is None:
                    return entry[1], entry[2], entry[3]
                t0, t1 = entry[0], newer[0]
                a = (t_s - t0) / (t1 - t0) if t1 > t0 else 0.0
                p0, v0, p1, v1 = entry[1], entry[2], newer[1], newer[2]
                pos = (p0[0] + a * (p1[0] - p0[0]), p0[1] + a * (p1[1] - p0[1]),
                       p0[2] + a * (p1[2] - p0[2]))
                vel = (v0[0] + a * (v1[0] - v0[0]), v0[1] + a * (v1[1] - v0[1]),
                       v0[2] + a * (v1[2] - v0[2]))
                return pos, vel, (newer[3] if a >= 0.5 else entry[3])
            newer = entry
        return None

    def _mean_accel_at(self, t_s: float, half_window_s: float = 0.05) -> Vec3f:
        """NED acceleration around ``t_s`` as a velocity difference over +-``half_window_s``.

        Not the sample's own acceleration: one sample carries the accelerometer's white noise
        (0.5 m/s^2 at 100 Hz for a consumer part), and as the delay's Jacobian that noise would
        make the delay look observable in straight flight, where it is not.
        """
        lo = self._state_at_f(t_s - half_window_s)
        hi = self._state_at_f(min(t_s + half_window_s, self._t))
        if lo is None or hi is None:
            return (0.0, 0.0, 0.0)
        span = min(t_s + half_window_s, self._t) - (t_s - half_window_s)
        if not span > 1e-6:
            return (0.0, 0.0, 0.0)
        v0, v1 = lo[1], hi[1]
        return ((v1[0] - v0[0]) / span, (v1[1] - v0[1]) / span, (v1[2] - v0[2]) / span)

    # -- outputs -------------------------------------------------------------------------------

    @property
    def initialised(self) -> bool:
        return self._initialised

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

    def set_gyro_matrix_std(self, std: float) -> bool:
        """Restart the gyro scale-factor and cross-axis estimate with a new prior (a parameter
        change): 0 stops estimating it and takes the gyro as exact again.

        False (and nothing changed) on a negative or non-finite value.
        """
        value = float(std)
        if not (math.isfinite(value) and value >= 0.0):
            self.rejected_inputs += 1
            return False
        self._propagate_covariance()
        self.gyro_matrix_std, self._gm_on = value, value > 0.0
        self._set_gm_apply()
        self._q_cache.clear()
        self._set_gyro_matrix(self._gm_prior.copy())
        self._pend_dth_f = (0.0, 0.0, 0.0)
        self._f[IDX_ATT, IDX_GYRO_MATRIX] = 0.0
        self._inflate(IDX_GYRO_MATRIX, self._gm_prior_var())
        return True

    def set_gyro_bias_temp(self, value: float) -> bool:
        """Change the gyro's temperature coefficient prior in flight (a parameter set): the
        coefficient restarts from zero with that 1-sigma (0: no coefficient, and the
        temperature no longer widens the gyro bias). False for a value that is not finite
        and >= 0."""
        if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0.0):
            self.rejected_inputs += 1
            return False
        self._propagate_covariance()
        self.gyro_bias_temp_rad_s_per_c = float(value)
        self._gyro_temp = self._gt_prior
        self._inflate(IDX_GYRO_TEMP, self._gt_prior_var())
        return True

    def set_gyro_calibration(self, matrix: ArrayLike, temp_rad_s_per_c: ArrayLike) -> bool:
        """Start the gyro's matrix error ``M`` and its bias's temperature coefficient from
        what a previous flight of this part learnt, instead of from zero.

        Both belong to the part and its mounting, not to one power-on, so what one flight
        learnt holds for the next. Without it every flight spends its first turns both ways
        relearning them, and a 20 s turn on a cross-axis error not yet seen is where the
        largest tilt errors fall: a rotation about the specific force is not observable in a
        steady turn, so the gyro's error about the body z axis goes straight into the tilt.
        ``gyro_matrix_std`` and ``gyro_bias_temp_rad_s_per_c`` stay the 1-sigma around these
        values; with ``gyro_matrix_std`` 0 the matrix is applied as exact. A running filter
        restarts both estimates from the new values.

        False (nothing changed) unless ``matrix`` is 3x3 (or 9 values, row-major) within
        ``max_gyro_matrix`` and ``temp_rad_s_per_c`` 3 values within
        ``MAX_GYRO_TEMP_RAD_S_PER_C``, all finite.
        """
        try:
            m = np.asarray(matrix, dtype=float).reshape(3, 3)
            k = np.asarray(temp_rad_s_per_c, dtype=float).reshape(3)
        except (TypeError, ValueError):
            self.rejected_inputs += 1
            return False
        if not (np.isfinite(m).all() and np.isfinite(k).all()
                and float(np.abs(m).max()) <= self.max_gyro_matrix * (1.0 + 1e-6)
                and float(np.abs(k).max()) <= MAX_GYRO_TEMP_RAD_S_PER_C * (1.0 + 1e-6)):
            # (the tolerance lets a float32 parameter at its range's end through)
            self.rejected_inputs += 1
            return False
        if self._initialised:
            self._propagate_covariance()
        self._gm_prior = m.copy()
        self._gt_prior = (float(k[0]), float(k[1]), float(k[2]))
        self._set_gm_apply()
        self._set_gyro_matrix(m.copy())
        self._gyro_temp = self._gt_prior
        self._pend_dth_f = (0.0, 0.0, 0.0)
        if self._initialised:
            self._inflate(IDX_GYRO_MATRIX, self._gm_prior_var())
            self._inflate(IDX_GYRO_TEMP, self._gt_prior_var())
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

    @property
    def fault_log(self) -> list[EstimatorFault]:
        """The most recent faults (up to 32), oldest first."""
        return list(self._fault_log)

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


def _floats3(value: object) -> tuple[float, float, float] | None:
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


def _vec3(value: ArrayLike) -> FloatArray:
    fast = _floats3(value)
    if fast is not None:
        return np.array(fast)
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape != (3,):
        raise ValueError(f"expected 3 values, got {arr.shape[0]}")
    if not np.isfinite(arr).all():
        raise ValueError(f"non-finite value in {arr.tolist()}")
    return arr.copy()


def _std3(value: float | Sequence[float] | FloatArray) -> FloatArray:
    """A standard deviation per axis from a scalar or 3 values; must be finite and > 0."""
    fast = _floats3(value)
    if fast is not None and min(fast) > 0.0:
        return np.array((max(fast[0], 1e-3), max(fast[1], 1e-3), max(fast[2], 1e-3)))
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape == (1,):
        arr = np.repeat(arr, 3)
    if arr.shape != (3,) or not np.isfinite(arr).all() or (arr <= 0.0).any():
        raise ValueError(f"standard deviation must be 1 or 3 finite values > 0, got {value!r}")
    return np.maximum(arr, 1e-3)


def _quat_from_euler_f(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )
