"""How the on-board estimator feeds the filter: one implementation for flight and for evaluation.

`EstimatorCore` holds everything between the decoded sensor data and `Eskf`: the initial phase
(average the IMU to level and take the gyro bias, wait for a GPS fix, and widen the initial
uncertainty when the aircraft is evidently not still), the IMU period from the frame counters,
the GPS measurement model (position in the shared NED frame, standard deviations from HDOP, GST
and the parameters, an unmeasured vertical velocity left unconstrained) and its latency, and the
horizon weighting, and the one estimator cycle (`EstimatorCore.cycle`). The estimator thread
wraps it with queues, slots and logs; the replay (`companion.estimation.replay`) and the SITL
evaluation (`companion.evaluation.sitl_estimator`) drive the same cycle, so what is replayed
and benchmarked is what flies.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.core.geo import NedFrame
from companion.core.state import GpsFix, HorizonMeasurement, ImuSample
from companion.estimation.calibration import GYRO_MATRIX_PARAMS, GYRO_TEMP_PARAMS
from companion.estimation.eskf import Eskf
from companion.estimation.eskf_state import UpdateResult
from companion.estimation.quat import quat_from_euler, quat_multiply_f

log = logging.getLogger(__name__)

IMU_PERIOD_S = 0.01
COUNTER_WRAP = 100
UNKNOWN_STD = 1e3  # 1-sigma given to a component the receiver did not measure
GRAVITY_M_S2 = 9.80665
STILL_GYRO_RAD_S = 0.02  # initial phase: above this mean or spread the aircraft is turning
COV_PERIOD_S = 0.04
"""The filter's covariance moves every 40 ms of IMU time whatever the IMU rate (and before
every measurement). In the realistic SITL turns (tuning seeds 101 and 102, both aircraft, still
air and 8 m/s wind, 150 s) 20, 40 and 50 ms gave the same inclination RMSE (0.374, 0.373,
0.373 deg); earlier, with the simple sensors, 10 and 20 ms had (0.180 deg). 40 ms pays for the
gyro scale-factor and cross-axis states at 100 Hz."""


def board_to_body(roll_rad: float, pitch_rad: float,
                  yaw_rad: float) -> tuple[tuple[float, float, float], ...]:
    """The rotation that turns IMU board axes into airframe axes for the trims
    (`TRIM_ROLL/PITCH/YAW`): the board is the airframe turned by yaw, pitch, roll."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return ((cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy),
            (cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy),
            (-sp, sr * cp, cr * cp))


def _turned(m: tuple[tuple[float, float, float], ...],
            v: tuple[float, float, float]) -> tuple[float, float, float]:
    """``m v`` on floats (the per-sample path: numpy's call costs more than the arithmetic)."""
    x, y, z = v
    return (m[0][0] * x + m[0][1] * y + m[0][2] * z,
            m[1][0] * x + m[1][1] * y + m[1][2] * z,
            m[2][0] * x + m[2][1] * y + m[2][2] * z)


@dataclass(frozen=True)
class HeadingFix:
    """A heading of the airframe from a sensor other than the GPS receiver (whose heading comes
    with its fix): a magnetometer, or an evaluation's stand-in for one."""

    yaw_rad: float
    std_rad: float
    latency_s: float = 0.0


class EstimatorCore:
    """`Eskf` driven by decoded IMU samples, GPS fixes and horizon measurements.

    `params` are the estimator's parameters by suffix (`INIT_S`, `GYR_NSD`, `GPS_HSTD`, ...:
    see `EstimatorThread.declare_params`); `home_lla` fixes the NED origin (None: the first GPS
    fix); `eskf_kwargs` are extra `Eskf` keyword arguments (tuning experiments).

    `dt_source` says where a sample's period comes from. ``"counter"`` (the flight): the IMU's
    own frame counter times `IMU_PERIOD_S`, immune to the host's reception jitter. ``"time"``
    (replayed logs of other IMUs, any rate): the difference of consecutive `ImuSample.t_ns`,
    which such logs stamp at the sensor.
    """

    def __init__(self, params: Mapping[str, float], home_lla: tuple[float, float, float] | None,
                 *, eskf_kwargs: Mapping[str, Any] | None = None,
                 dt_source: str = "counter") -> None:
        if dt_source not in ("counter", "time"):
            raise ValueError(f"EstimatorCore: dt_source must be 'counter' or 'time', got {dt_source!r}")
        self.dt_source = dt_source
        self.p: dict[str, float] = {k: float(v) for k, v in params.items()}
        self._board_to_body: tuple[tuple[float, float, float], ...] | None = None
        self._set_trim()
        self.eskf_kwargs = dict(eskf_kwargs or {})
        self.frame = NedFrame(*home_lla) if home_lla is not None else None
        self.filter: Eskf | None = None
        self.init_failed = False
        self.moving_start = False
        self.gps_accepted = 0
        self.gps_rejected = 0
        self.horizon_used = 0
        self.heading_used = 0
        self.heading_rejected = 0
        self.temperature_readings = 0
        self.last_imu: ImuSample | None = None
        """The newest sample taken in, for its time (its axes may be the board's: the rates
        in airframe axes are `last_rates_rad_s`)."""
        self.last_rates_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
        """Its rates in airframe axes (after the trims)."""
        self._last_counter: int | None = None
        self._last_t_ns: int | None = None
        self._first_t_ns: int | None = None
        self._gyro: list[tuple[float, float, float]] = []
        self._accel: list[tuple[float, float, float]] = []
        self._fix: GpsFix | None = None
        self.initial_yaw: Callable[[int], float | None] | None = None
        """A heading to start from, by the start's time (ns): a replay's reference attitude
        when the GPS course cannot align the heading (a hovering copter). None (the flight):
        the heading waits for the GPS course."""

    # ------------------------------------------------------------------ set-up
    def _set_trim(self) -> None:
        """The IMU board's rotation against the airframe (`TRIM_ROLL/PITCH/YAW`, from a level
        calibration): samples are turned into airframe axes before the filter sees them, so
        the attitude it reports is the aircraft's, not the board's."""
        roll, pitch, yaw = (self.p.get(k, 0.0) for k in ("TRIM_ROLL", "TRIM_PITCH", "TRIM_YAW"))
        if roll == pitch == yaw == 0.0:
            self._board_to_body = None
            return
        self._board_to_body = board_to_body(roll, pitch, yaw)

    def _trim_angles(self) -> tuple[float, float, float]:
        return (self.p.get("TRIM_ROLL", 0.0), self.p.get("TRIM_PITCH", 0.0),
                self.p.get("TRIM_YAW", 0.0))

    def _trim_changed(self, before: tuple[float, float, float]) -> None:
        """New trims (a level calibration): samples averaged under the old ones no longer
        level the filter, and a running filter's attitude and biases turn with the axes."""
        if self.filter is None:
            self._gyro.clear()
            self._accel.clear()
            self._first_t_ns = None
            return
        ow, ox, oy, oz = (float(v) for v in quat_from_euler(*before))
        nw, nx, ny, nz = (float(v) for v in quat_from_euler(*self._trim_angles()))
        dq = quat_multiply_f(nw, nx, ny, nz, ow, -ox, -oy, -oz)
        self.filter.turn_body_axes(dq)

    def _to_body(self, samples: Sequence[ImuSample]) -> Sequence[ImuSample]:
        m = self._board_to_body
        if m is None:
            return samples
        return [ImuSample(s.t_ns, s.counter, _turned(m, s.rates_rad_s), _turned(m, s.accel_m_s2),
                          s.gyro_ok, s.accel_ok, s.counter_period_s) for s in samples]

    def new_filter(self, moving: bool) -> Eskf:
        p = self.p
        kwargs: dict[str, Any] = {
            "gyro_noise_rad_s_rt_hz": p["GYR_NSD"], "accel_noise_m_s2_rt_hz": p["ACC_NSD"],
            "gyro_bias_rw_rad_s_rt_s": p["GB_RW"], "accel_bias_rw_m_s2_rt_s": p["AB_RW"],
            "horizon_std_rad": p["HZN_STD"],
            "gyro_bias_temp_rad_s_per_c": p.get("GB_TEMP", 0.0),
            "accel_bias_temp_m_s2_per_c": p.get("AB_TEMP", 0.0),
            "gyro_matrix_std": p.get("GS_STD", 0.0),
            "gps_lag_s": p["GPS_LAG"], "gps_lag_std_s": p.get("GPS_LAGSD", 0.0),
            "cov_period_s": COV_PERIOD_S}
        if moving:
            kwargs.update(init_tilt_std_rad=0.6, init_gyro_bias_std_rad_s=0.02)
        kwargs.update(self.eskf_kwargs)
        f = Eskf(**kwargs)
        f.trim_bias_tilt = self._trim_bias_tilt()
        self._apply_calibration(f)
        return f

    def _calibration(self) -> tuple[list[float], list[float]]:
        return ([self.p.get(name, 0.0) for name in GYRO_MATRIX_PARAMS],
                [self.p.get(name, 0.0) for name in GYRO_TEMP_PARAMS])

    def _apply_calibration(self, f: Eskf) -> None:
        """Start the filter's gyro matrix and temperature coefficient from `GM_*`/`GT_*`
        (what a previous flight learnt); out-of-range values are refused by the filter and
        logged, and it starts from zero as before."""
        matrix, temp = self._calibration()
        if not any(matrix) and not any(temp):
            return
        if not f.set_gyro_calibration(matrix, temp):
            log.warning("estimator: EST_GM_*/EST_GT_* refused (beyond the filter's limits); "
                        "the gyro calibration starts from zero")

    def _trim_bias_tilt(self) -> bool:
        """Whether the reported attitude gives back the bias a level calibration took for a
        tilt (`TRIM_BIAS` with a roll or pitch trim set; companion.estimation.level)."""
        return bool(self.p.get("TRIM_BIAS", 0.0)) and (
            self.p.get("TRIM_ROLL", 0.0) != 0.0 or self.p.get("TRIM_PITCH", 0.0) != 0.0)

    def update_params(self, params: Mapping[str, float]) -> None:
        """New parameter values; noise densities apply from the next prediction, a new GPS
        delay or delay uncertainty restarts the delay estimate from it."""
        lag_before = (self.p.get("GPS_LAG"), self.p.get("GPS_LAGSD"))
        cal_before = self._calibration()
        trim_before = self._trim_angles()
        self.p.update({k: float(v) for k, v in params.items()})
        self._set_trim()
        if self._trim_angles() != trim_before:
            self._trim_changed(trim_before)
        f = self.filter
        if f is not None and lag_before != (self.p.get("GPS_LAG"), self.p.get("GPS_LAGSD")):
            f.set_gps_lag(self.p["GPS_LAG"], self.p.get("GPS_LAGSD", 0.0))
        if f is not None:
            f.trim_bias_tilt = self._trim_bias_tilt()
            f.gyro_noise_rad_s_rt_hz = self.p["GYR_NSD"]
            f.accel_noise_m_s2_rt_hz = self.p["ACC_NSD"]
            f.gyro_bias_rw_rad_s_rt_s = self.p["GB_RW"]
            f.accel_bias_rw_m_s2_rt_s = self.p["AB_RW"]
            f.horizon_std_rad = self.p["HZN_STD"]
            if f.gyro_bias_temp_rad_s_per_c != self.p.get("GB_TEMP", 0.0):
                f.set_gyro_bias_temp(self.p.get("GB_TEMP", 0.0))
            f.accel_bias_temp_m_s2_per_c = self.p.get("AB_TEMP", 0.0)
            if f.gyro_matrix_std != self.p.get("GS_STD", 0.0):
                f.set_gyro_matrix_std(self.p.get("GS_STD", 0.0))
            if self._calibration() != cal_before:
                self._apply_calibration(f)
            f._q_cache.clear()

    def initial_phase(self, samples: Sequence[ImuSample], fix: GpsFix | None) -> bool:
        """Collect `INIT_S` of IMU and a GPS fix; start the filter when both are there.

        The phase assumes the aircraft is still (on the ground, or straight and level). If the
        gyro says it is turning, its mean is not the bias and the accelerometer does not point
        down: the filter then starts with zero bias and a wide tilt uncertainty instead of a
        wrong certainty. Returns True once the filter runs.
        """
        if self.filter is not None:
            return True
        if self.init_failed:
            return False
        need = max(1, int(self.p["INIT_S"] / IMU_PERIOD_S))
        for s in self._to_body(samples):
            if s.counter_period_s == 0.0:
                self.dt_source = "time"  # a source without a frame counter (an autopilot's IMU)
            if not self._enough_init(need):
                if self._first_t_ns is None:
                    self._first_t_ns = s.t_ns
                self._gyro.append(s.rates_rad_s)
                self._accel.append(s.accel_m_s2)
                self._last_counter = s.counter
                self._last_t_ns = s.t_ns
                self.last_imu = s
                self.last_rates_rad_s = s.rates_rad_s
        if fix is not None and fix.fix > 0 and fix.lat_deg is not None:
            self._fix = fix
        if not self._enough_init(need) or self._fix is None:
            return False
        first = self._fix
        if self.frame is None:
            self.frame = NedFrame(float(first.lat_deg or 0.0), float(first.lon_deg or 0.0),
                                  float(first.alt_m or 0.0))
        pos, vel = self.gps_ned(first)
        gyro, accel = np.asarray(self._gyro), np.asarray(self._accel)
        gyro_mean, accel_mean = gyro.mean(axis=0), accel.mean(axis=0)
        moving = bool(np.abs(gyro_mean).max() > STILL_GYRO_RAD_S
                      or gyro.std(axis=0).max() > STILL_GYRO_RAD_S
                      or abs(np.linalg.norm(accel_mean) - GRAVITY_M_S2) > 0.5)
        f = self.new_filter(moving)
        yaw = None
        if self.initial_yaw is not None and self._last_t_ns is not None:
            yaw = self.initial_yaw(self._last_t_ns)
        if not f.initialise(accel_mean, np.zeros(3) if moving else gyro_mean, pos, vel, yaw):
            self.init_failed = True
            log.warning("estimator initialisation refused (IMU mean is not ~1 g)")
            return False
        self.moving_start = moving
        self.filter = f
        return True

    def _enough_init(self, need: int) -> bool:
        """The initial phase has its `INIT_S`: in samples of the device, or in sample time."""
        if self.dt_source == "counter":
            return len(self._gyro) >= need
        if self._first_t_ns is None or self._last_t_ns is None:
            return False
        return (self._last_t_ns - self._first_t_ns) / 1e9 >= self.p["INIT_S"]

    # ------------------------------------------------------------------ one cycle
    def predict(self, samples: Sequence[ImuSample]) -> int:
        """Integrate every sample, with its period from the IMU's frame counter or its time."""
        f = self.filter
        if f is None:
            return 0
        used = 0
        by_time = self.dt_source == "time"
        m = self._board_to_body
        last: ImuSample | None = None
        rates = self.last_rates_rad_s
        for s in samples:
            if not by_time and s.counter_period_s == 0.0:
                self.dt_source = "time"
                by_time = True
                self._last_t_ns = last.t_ns if last is not None else self._last_t_ns
            if by_time:
                dt = IMU_PERIOD_S if self._last_t_ns is None else (s.t_ns - self._last_t_ns) / 1e9
                self._last_t_ns = s.t_ns
            else:
                dt = IMU_PERIOD_S
                if self._last_counter is not None:
                    dt = ((s.counter - self._last_counter) % COUNTER_WRAP) * IMU_PERIOD_S
            self._last_counter = s.counter
            if dt <= 0.0:
                continue  # a repeated frame
            # turned as `_to_body` does, without a sample object per sample
            rates = s.rates_rad_s if m is None else _turned(m, s.rates_rad_s)
            f.predict(rates, s.accel_m_s2 if m is None else _turned(m, s.accel_m_s2), dt)
            last = s
            used += 1
        if last is not None:
            self.last_imu = last
            self.last_rates_rad_s = rates
        return used

    def gps_ned(self, fix: GpsFix) -> tuple[np.ndarray, np.ndarray]:
        assert self.frame is not None
        pos = np.array(self.frame.to_ned(float(fix.lat_deg or 0.0), float(fix.lon_deg or 0.0),
                                         float(fix.alt_m or 0.0)))
        if fix.vn_m_s is not None and fix.ve_m_s is not None:
            vel = np.array([fix.vn_m_s, fix.ve_m_s, fix.vd_m_s or 0.0])
        elif fix.speed_m_s is not None and fix.course_deg is not None:
            c = math.radians(fix.course_deg)
            vel = np.array([fix.speed_m_s * math.cos(c), fix.speed_m_s * math.sin(c),
                            fix.vd_m_s or 0.0])
        else:
            vel = np.zeros(3)
        return pos, vel

    def fuse_gps(self, fix: GpsFix) -> tuple[UpdateResult, float] | None:
        """Fuse one fix; returns the filter's verdict and the whole latency applied (measured
        plus the estimated receiver delay), or None if unusable."""
        f = self.filter
        if f is None or self.last_imu is None:
            return None
        if fix.fix <= 0 or fix.lat_deg is None or fix.lon_deg is None or fix.alt_m is None:
            return None
        pos, vel = self.gps_ned(fix)
        hstd = self.p["GPS_HSTD"] * (fix.hdop or 1.5)
        if fix.h_std_m is not None and math.isfinite(fix.h_std_m):
            hstd = max(hstd, fix.h_std_m / math.sqrt(2))
        vstd = self.p["GPS_VSTD"]
        if fix.alt_std_m is not None and math.isfinite(fix.alt_std_m):
            vstd = max(vstd, fix.alt_std_m)
        vel_h = self.p["GPS_VEL"]
        # NMEA without $PASHR,POS carries no vertical velocity: leave it unconstrained rather
        # than claim the aircraft is level (0 m/s) while it climbs
        vel_std = (vel_h, vel_h, vel_h if fix.vd_m_s is not None else UNKNOWN_STD)
        # age of the fix relative to the newest IMU sample, as far as it is measured: the
        # transfer measured by the driver and the time since hand-off; the receiver's own
        # delay (GPS_LAG to start with) is the filter's to estimate
        device_s = fix.latency_s or 0.0
        since_handoff_s = (self.last_imu.t_ns - fix.t_ns) / 1e9
        latency = max(0.0, device_s + since_handoff_s)
        res = f.update_gps(pos, vel, (hstd, hstd, vstd), vel_std, latency)
        latency += f.gps_lag_estimate_s
        if res.accepted:
            self.gps_accepted += 1
        else:
            self.gps_rejected += 1
        if fix.heading_deg is not None and self.p.get("HDG_USE", 0.0):
            self.fuse_heading(fix.heading_deg, latency)
        return res, latency

    def fuse_heading(self, heading_deg: float, latency_s: float) -> bool:
        """A dual-antenna receiver's heading (HDT) of the same epoch as the fix, the baseline's
        yaw on the airframe (`HDG_OFS`) taken off; False when the filter refused it."""
        yaw = math.radians(heading_deg) - self.p.get("HDG_OFS", 0.0)
        return self.fuse_yaw(yaw, self.p.get("HDG_STD", 0.01), latency_s)

    def fuse_yaw(self, yaw_rad: float, std_rad: float, latency_s: float = 0.0) -> bool:
        """A heading of the airframe with its 1-sigma; False when the filter refused it."""
        f = self.filter
        if f is None or not math.isfinite(yaw_rad):
            return False
        if f.update_heading(yaw_rad, std_rad, latency_s).accepted:
            self.heading_used += 1
            return True
        self.heading_rejected += 1
        return False

    def set_temperature(self, temperature_c: float) -> None:
        """The IMU's temperature from its slow block: lets the biases follow a warm-up."""
        if self.filter is not None:
            self.filter.set_temperature(temperature_c)
            self.temperature_readings += 1

    def fuse_horizon(self, h: HorizonMeasurement) -> bool:
        """Roll and pitch from the horizon, weighted by its quality; False when not used."""
        f = self.filter
        if f is None or self.last_imu is None or not self.p["HZN_USE"] or h.quality <= 0:
            return False
        latency = max(0.0, (self.last_imu.t_ns - h.t_ns) / 1e9)
        if f.update_attitude(h.roll_rad, h.pitch_rad, h.quality, latency).accepted:
            self.horizon_used += 1
            return True
        return False

    def cycle(self, samples: Sequence[ImuSample], fix: GpsFix | None = None,
              horizon: HorizonMeasurement | None = None, *,
              temperature_c: float | None = None, heading: HeadingFix | None = None,
              on_gps: Callable[[UpdateResult, float], None] | None = None) -> bool:
        """One estimator cycle, the only one: the thread, the replay and the evaluations all run
        it. In this order: the IMU samples that arrived, the newest GPS fix (with its receiver's
        heading), the IMU's temperature, the horizon fix, then a heading fix from elsewhere.

        ``on_gps(result, latency_s)`` is called as the fix is fused, before the temperature and
        the horizon move the filter (the thread logs it then). Before the filter runs, the
        samples and the fix feed the initial phase; a filter that starts in this cycle takes
        the cycle's temperature and nothing else. Returns True once the filter runs.
        """
        if self.filter is None:
            if not self.initial_phase(samples, fix):
                return False
            if temperature_c is not None:
                self.set_temperature(temperature_c)
            return True
        self.predict(samples)
        if fix is not None:
            fused = self.fuse_gps(fix)
            if fused is not None and on_gps is not None:
                on_gps(*fused)
        if temperature_c is not None:
            self.set_temperature(temperature_c)
        if horizon is not None:
            self.fuse_horizon(horizon)
        if heading is not None:
            self.fuse_yaw(heading.yaw_rad, heading.std_rad, heading.latency_s)
        return True
