"""Estimator thread: the GPS/INS filter (`Eskf`) as a managed thread.

Initial phase (the aperiodic prologue, as in the thesis): average the IMU for EST_INIT_S to
level the attitude and take the gyro bias, and wait for a GPS fix. Periodic section, paced by
the IMU: every sample is integrated (all of them, from the IMU stream queue, not only the newest),
then the newest GPS fix and horizon attitude, if any, are fused with their latencies. The result
goes to the estimator slot (control reads it), the log and the bridges.

A filter divergence is repaired inside the filter and counted as an estimator fault
(`faults`); it never raises, so it never costs a thread restart.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

import numpy as np

from companion.estimation.eskf import IDX_ATT, IDX_POS, IDX_VEL, Eskf
from companion.geo import NedFrame
from companion.params import ParamSpec, float_param, int_param
from companion.state import EstimatorState, GpsFix, ImuSample
from companion.watchdog.thread import ManagedThread

log = logging.getLogger(__name__)

FMT_STATE = 1
FMT_GPS = 2
STATE_COLUMNS = ["roll_rad", "pitch_rad", "yaw_rad", "north_m", "east_m", "down_m",
                 "vn_m_s", "ve_m_s", "vd_m_s", "gbx_rad_s", "gby_rad_s", "gbz_rad_s",
                 "bax_m_s2", "bay_m_s2", "baz_m_s2", "std_n_m", "std_e_m", "std_d_m",
                 "std_vn_m_s", "std_ve_m_s", "std_vd_m_s", "std_roll_rad", "std_pitch_rad",
                 "std_yaw_rad", "faults", "aligned"]
GPS_COLUMNS = ["in_n_m", "in_e_m", "in_d_m", "in_vn_m_s", "in_ve_m_s", "in_vd_m_s", "nis",
               "accepted", "latency_s"]
IMU_PERIOD_S = 0.01
UNKNOWN_STD = 1e3  # 1-sigma given to a component the receiver did not measure
COUNTER_WRAP = 100


class EstimatorThread(ManagedThread):
    def __init__(self, *, name: str = "estimator", thread_id: int = 4) -> None:
        super().__init__(name, thread_id=thread_id, watchdog_ms=1000, message_ms=1000,
                         budget_ms=3.0, param_prefix="EST")
        self.filter: Eskf | None = None
        self.frame: NedFrame | None = None
        self._last_counter: int | None = None
        self._gps_seen = 0
        self._hzn_seen = 0
        self._last_imu: ImuSample | None = None
        self.faults_reported = 0
        self.gps_accepted = 0
        self.gps_rejected = 0
        self.horizon_used = 0

    def declare_params(self) -> list[ParamSpec]:
        p = self.param_prefix
        return [
            float_param(f"{p}_INIT_S", 1.0, 0.1, 60.0, "s",
                        "Initial phase: IMU averaging time that levels the attitude and takes "
                        "the gyro bias before the filter starts."),
            float_param(f"{p}_GYR_NSD", 0.003, 1e-5, 1.0, "rad/s/rtHz",
                        "Gyro white-noise density (angle random walk)."),
            float_param(f"{p}_ACC_NSD", 0.05, 1e-4, 5.0, "m/s^2/rtHz",
                        "Accelerometer white-noise density."),
            float_param(f"{p}_GB_RW", 5e-5, 1e-8, 0.01, "rad/s/rts", "Gyro bias random walk."),
            float_param(f"{p}_AB_RW", 1e-3, 1e-7, 0.1, "m/s^2/rts",
                        "Accelerometer bias random walk."),
            float_param(f"{p}_GPS_HSTD", 1.0, 0.05, 100.0, "m",
                        "GPS horizontal position 1-sigma per unit HDOP."),
            float_param(f"{p}_GPS_VSTD", 2.0, 0.05, 100.0, "m",
                        "GPS vertical position 1-sigma (GST altitude std used when larger)."),
            float_param(f"{p}_GPS_VEL", 0.15, 0.01, 10.0, "m/s", "GPS velocity 1-sigma."),
            float_param(f"{p}_GPS_LAG", 0.05, 0.0, 0.5, "s",
                        "Receiver output delay beyond the latency the driver measures."),
            int_param(f"{p}_HZN_USE", 1, 0, 1, "",
                      "1 fuses horizon attitude (HORIZON_ATTITUDE / MAVLink) weighted by quality."),
            float_param(f"{p}_HZN_STD", 0.05, 0.001, 1.0, "rad",
                        "Horizon roll/pitch 1-sigma at quality 1."),
        ]

    def define_logs(self, tlog: Any) -> None:
        tlog.define(FMT_STATE, ",".join(["%.6f"] * 3 + ["%.3f"] * 6 + ["%.6f"] * 6
                                        + ["%.4f"] * 9) + ",%u,%hhu", STATE_COLUMNS)
        tlog.define(FMT_GPS, ",".join(["%.3f"] * 6) + ",%.3f,%hhu,%.3f", GPS_COLUMNS)

    def _new_filter(self, *, moving: bool = False) -> Eskf:
        g = self.param
        extra: dict[str, Any] = (
            {"init_tilt_std_rad": 0.6, "init_gyro_bias_std_rad_s": 0.02} if moving else {})
        return Eskf(gyro_noise_rad_s_rt_hz=g("GYR_NSD"), accel_noise_m_s2_rt_hz=g("ACC_NSD"),
                    gyro_bias_rw_rad_s_rt_s=g("GB_RW"), accel_bias_rw_m_s2_rt_s=g("AB_RW"),
                    horizon_std_rad=g("HZN_STD"), **extra)

    def on_params_changed(self) -> None:
        f = self.filter
        if f is None:
            return
        # noise densities apply from the next prediction (the process-noise cache is rebuilt)
        g = self.param
        f.gyro_noise_rad_s_rt_hz = g("GYR_NSD")
        f.accel_noise_m_s2_rt_hz = g("ACC_NSD")
        f.gyro_bias_rw_rad_s_rt_s = g("GB_RW")
        f.accel_bias_rw_m_s2_rt_s = g("AB_RW")
        f.horizon_std_rad = g("HZN_STD")
        f._q_cache.clear()

    def recover(self) -> None:
        self.filter = None
        self._last_counter = None

    # ------------------------------------------------------------------ initial phase
    def prologue(self) -> bool:
        state = self.ctx.state
        clock = self.ctx.clock
        init_s = float(self.param("INIT_S"))
        gyro: list[tuple[float, float, float]] = []
        accel: list[tuple[float, float, float]] = []
        state.imu_stream.drain()
        need = max(1, int(init_s / IMU_PERIOD_S))
        fix: GpsFix | None = None
        while not self.stop_requested and (len(gyro) < need or fix is None):
            sample = state.imu_stream.get(clock.to_host_s(0.05))
            if sample is not None and len(gyro) < need:
                gyro.append(sample.rates_rad_s)
                accel.append(sample.accel_m_s2)
                self._last_counter = sample.counter
                self._last_imu = sample
            candidate = state.gps.read()
            if candidate is not None and candidate.fix > 0 and candidate.lat_deg is not None:
                fix = candidate
        if self.stop_requested or fix is None:
            return False
        home = self.ctx.home_lla
        if home is None:
            home = (float(fix.lat_deg or 0.0), float(fix.lon_deg or 0.0), float(fix.alt_m or 0.0))
        self.frame = NedFrame(*home)
        pos, vel = self._gps_ned(fix)
        gyro_arr, accel_arr = np.asarray(gyro), np.asarray(accel)
        gyro_mean = gyro_arr.mean(axis=0)
        # The initial phase assumes the aircraft is still (on the ground, or straight and level).
        # If the gyro says it is turning, its mean is not the bias and the accelerometer does not
        # point down: start with zero bias and a wide tilt uncertainty instead of a wrong certainty.
        moving = bool(np.abs(gyro_mean).max() > 0.02 or gyro_arr.std(axis=0).max() > 0.02
                      or abs(np.linalg.norm(accel_arr.mean(axis=0)) - 9.80665) > 0.5)
        self.filter = self._new_filter(moving=moving)
        ok = self.filter.initialise(accel_arr.mean(axis=0),
                                    np.zeros(3) if moving else gyro_mean, pos, vel)
        self._gps_seen = state.gps.version
        if not ok:
            self.last_error = "initialisation refused (IMU mean is not ~1 g)"
            return False
        log.info("estimator initialised at %s after %d IMU samples", home, len(gyro))
        return True

    def _gps_ned(self, fix: GpsFix) -> tuple[np.ndarray, np.ndarray]:
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

    # ------------------------------------------------------------------ periodic section
    def step(self) -> int:
        f = self.filter
        if f is None:
            return 0
        stream = self.ctx.state.imu_stream
        first = stream.get(self.ctx.clock.to_host_s(0.05))
        if first is None:
            return 0
        self.work_t0_ns = time.perf_counter_ns()  # step time excludes the wait
        samples = [first, *stream.drain()]
        for s in samples:
            dt = IMU_PERIOD_S
            if self._last_counter is not None:
                dt = ((s.counter - self._last_counter) % COUNTER_WRAP) * IMU_PERIOD_S
            self._last_counter = s.counter
            if dt <= 0.0:
                continue  # a repeated frame
            f.predict(s.rates_rad_s, s.accel_m_s2, dt)
            self._last_imu = s
        self._fuse_gps(f)
        self._fuse_horizon(f)
        self._publish(f)
        return len(samples)

    def _fuse_gps(self, f: Eskf) -> None:
        fix, version, _ = self.ctx.state.gps.read_versioned()
        if fix is None or version == self._gps_seen or self._last_imu is None:
            return
        self._gps_seen = version
        if fix.fix <= 0 or fix.lat_deg is None or fix.lon_deg is None or fix.alt_m is None:
            return
        pos, vel = self._gps_ned(fix)
        hstd = float(self.param("GPS_HSTD")) * (fix.hdop or 1.5)
        if fix.h_std_m is not None and math.isfinite(fix.h_std_m):
            hstd = max(hstd, fix.h_std_m / math.sqrt(2))
        vstd = float(self.param("GPS_VSTD"))
        if fix.alt_std_m is not None and math.isfinite(fix.alt_std_m):
            vstd = max(vstd, fix.alt_std_m)
        vel_std_h = float(self.param("GPS_VEL"))
        # NMEA without $PASHR,POS carries no vertical velocity: leave it unconstrained rather
        # than claim the aircraft is level (0 m/s) while it climbs
        vel_std = (vel_std_h, vel_std_h, vel_std_h if fix.vd_m_s is not None else UNKNOWN_STD)
        # age of the fix relative to the newest IMU sample: the receiver's own delay, the
        # transfer measured by the driver, and the time since hand-off
        device_s = fix.latency_s or 0.0
        since_handoff_s = (self._last_imu.t_ns - fix.t_ns) / 1e9
        latency = max(0.0, float(self.param("GPS_LAG")) + device_s + since_handoff_s)
        res = f.update_gps(pos, vel, (hstd, hstd, vstd), vel_std, latency)
        if res.accepted:
            self.gps_accepted += 1
        else:
            self.gps_rejected += 1
        if self.tlog is not None and res.innovation.size == 6:
            self.tlog.log(FMT_GPS, *res.innovation, res.nis if math.isfinite(res.nis) else -1.0,
                          int(res.accepted), latency)

    def _fuse_horizon(self, f: Eskf) -> None:
        if not self.param("HZN_USE"):
            return
        h, version, _ = self.ctx.state.horizon.read_versioned()
        if h is None or version == self._hzn_seen or self._last_imu is None:
            return
        self._hzn_seen = version
        latency = max(0.0, (self._last_imu.t_ns - h.t_ns) / 1e9)
        if h.quality > 0 and f.update_attitude(h.roll_rad, h.pitch_rad, h.quality, latency).accepted:
            self.horizon_used += 1

    def _publish(self, f: Eskf) -> None:
        st = f.state()
        if st.faults != self.faults_reported:
            log.warning("estimator fault %d: %s (filter reset)", st.faults, st.last_fault_reason)
            self.faults_reported = st.faults
        imu = self._last_imu
        t_ns = imu.t_ns if imu is not None else self.ctx.clock.realtime_ns()
        rates = imu.rates_rad_s if imu is not None else (0.0, 0.0, 0.0)
        bias = st.gyro_bias_rad_s
        home = self.frame
        out = EstimatorState(
            t_ns=t_ns,
            quat_wxyz=tuple(float(c) for c in st.quaternion),  # type: ignore[arg-type]
            roll_rad=st.roll_rad, pitch_rad=st.pitch_rad, yaw_rad=st.yaw_rad,
            pos_ned_m=(float(st.pos_ned_m[0]), float(st.pos_ned_m[1]), float(st.pos_ned_m[2])),
            vel_ned_m_s=(float(st.vel_ned_m_s[0]), float(st.vel_ned_m_s[1]),
                         float(st.vel_ned_m_s[2])),
            gyro_bias_rad_s=(float(bias[0]), float(bias[1]), float(bias[2])),
            accel_bias_m_s2=tuple(float(c) for c in st.accel_bias_m_s2),  # type: ignore[arg-type]
            origin_lat_deg=home.lat0_deg if home else None,
            origin_lon_deg=home.lon0_deg if home else None,
            origin_alt_m=home.alt0_m if home else None,
            cov_diag=tuple(float(c) for c in st.cov_diag),
            innovations=tuple(float(c) for c in st.last_gps_innovation),
            rates_rad_s=(rates[0] - bias[0], rates[1] - bias[1], rates[2] - bias[2]),
            aligned=st.initialised and st.yaw_aligned,
            faults=st.faults,
        )
        self.ctx.state.estimator.write(out)
        if self.tlog is not None:
            std = np.sqrt(np.maximum(st.cov_diag, 0.0))
            self.tlog.log(FMT_STATE, st.roll_rad, st.pitch_rad, st.yaw_rad, *out.pos_ned_m,
                          *out.vel_ned_m_s, *out.gyro_bias_rad_s, *out.accel_bias_m_s2,
                          *std[IDX_POS], *std[IDX_VEL], *std[IDX_ATT], st.faults,
                          int(out.aligned), t_ns=t_ns)
