"""Estimator thread: the GPS/INS filter (`Eskf`) as a managed thread.

Initial phase (the aperiodic prologue, as in the thesis): average the IMU for EST_INIT_S to
level the attitude and take the gyro bias, and wait for a GPS fix. Periodic section, paced by
the IMU: every sample is integrated (all of them, from the IMU stream queue, not only the newest),
then the newest GPS fix and horizon attitude, if any, are fused with their latencies. The result
goes to the estimator slot (control reads it), the log and the bridges.

A filter divergence is repaired inside the filter and counted as an estimator fault
(`faults`); it never raises, so it never costs a thread restart.

Level calibration (the manager command ``calibrate_level``, from MAV_CMD_PREFLIGHT_CALIBRATION
with param5 = 2, MAVProxy's ``ahrstrim``): the next `LEVEL_CAL_S` of IMU samples,
in either phase, become `EST_TRIM_ROLL/PITCH` (companion.estimation.level), or a refusal that
says why (moving, not 1 g, no samples).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.core.params import ParamError, ParamSpec, float_param, int_param
from companion.core.state import EstimatorState, ImuSample
from companion.watchdog.thread import ManagedThread, Task

if TYPE_CHECKING:
    # the filter loads when the thread starts, not when its
    # parameters are listed (`companion params`, the docs)
    from companion.estimation.eskf import Eskf
    from companion.estimation.fusion import EstimatorCore

log = logging.getLogger(__name__)

LEVEL_CAL_S = 2.0
"""IMU time a level calibration averages."""
LEVEL_CAL_TIMEOUT_S = 5.0
"""A level calibration that has not collected its samples by then is refused."""


@dataclass
class _LevelRequest:
    reply: Callable[[bool, str], None]
    started_s: float
    first_t_ns: int | None = None
    last_t_ns: int = 0
    rates: list[tuple[float, float, float]] = field(default_factory=list)
    accel: list[tuple[float, float, float]] = field(default_factory=list)

FMT_STATE = 1
FMT_GPS = 2
FMT_CAL = 3
CAL_EVERY = 10
"""GPS fusions between two calibration records (once a second with a 10 Hz receiver)."""
STATE_COLUMNS = ["roll_rad", "pitch_rad", "yaw_rad", "north_m", "east_m", "down_m",
                 "vn_m_s", "ve_m_s", "vd_m_s", "gbx_rad_s", "gby_rad_s", "gbz_rad_s",
                 "bax_m_s2", "bay_m_s2", "baz_m_s2", "std_n_m", "std_e_m", "std_d_m",
                 "std_vn_m_s", "std_ve_m_s", "std_vd_m_s", "std_roll_rad", "std_pitch_rad",
                 "std_yaw_rad", "faults", "aligned"]
GPS_COLUMNS = ["in_n_m", "in_e_m", "in_d_m", "in_vn_m_s", "in_ve_m_s", "in_vd_m_s", "nis",
               "accepted", "latency_s", "gps_lag_s", "gps_lag_std_s", "gyro_scale_x",
               "gyro_scale_y", "gyro_scale_z", "gyro_temp_x", "gyro_temp_y", "gyro_temp_z"]
"""Per fused fix: innovations, NIS, verdict, the whole latency applied, and the receiver delay
the filter estimates within it (with its 1-sigma), the gyro scale-factor errors it estimates
(the diagonal of ``EST_GS_STD``'s matrix; fractions, 0 when not estimated) and the gyro
bias's temperature coefficient it estimates (rad/s per degree C, 0 without ``EST_GB_TEMP``)."""
CAL_COLUMNS = ([f"gm_{r}{c}" for r in "xyz" for c in "xyz"]
               + [f"gm_std_{r}{c}" for r in "xyz" for c in "xyz"]
               + ["gt_x", "gt_y", "gt_z", "gt_std_x", "gt_std_y", "gt_std_z"])
"""What the filter has learnt of the gyro (`Eskf.gyro_calibration`): its matrix error and
temperature coefficient with their 1-sigma, so ``companion estimation calibration`` can hand
them to the next flight (companion.estimation.calibration)."""


def estimator_param_defaults(prefix: str = "EST") -> dict[str, float]:
    """The estimator thread's parameter defaults, by suffix (``GPS_LAG``, ``GYR_NSD``...).

    Read from the class's metadata (no thread is built), so evaluations and tools follow the
    thread's defaults instead of copying them.
    """
    return {spec.name.removeprefix(prefix + "_"): float(spec.default)
            for spec in EstimatorThread.declare_params(prefix)}


class EstimatorThread(ManagedThread):
    def __init__(self, *, task: Task) -> None:
        super().__init__(task)
        self.core: EstimatorCore | None = None
        self._std_index: list[int] = list(range(9))
        self._gps_seen = 0
        self._hzn_seen = 0
        self._temp_seen = 0
        self._fused = 0
        self.faults_reported = 0
        self._level_lock = threading.Lock()
        self._level: _LevelRequest | None = None

    @classmethod
    def declare_params(cls, p: str) -> list[ParamSpec]:
        return [
            float_param(f"{p}_INIT_S", 1.0, 0.1, 60.0, "s",
                        "Initial phase: IMU averaging time that levels the attitude and takes "
                        "the gyro bias before the filter starts."),
            float_param(f"{p}_GYR_NSD", 0.001, 1e-5, 1.0, "rad/s/rtHz",
                        "Gyro white-noise density (angle random walk), widened beyond a "
                        "datasheet's to cover vibration and g-sensitivity the filter does not "
                        "model."),
            float_param(f"{p}_ACC_NSD", 0.05, 1e-4, 5.0, "m/s^2/rtHz",
                        "Accelerometer white-noise density."),
            float_param(f"{p}_GB_RW", 2e-4, 1e-8, 0.01, "rad/s/rts",
                        "Gyro bias random walk (wide enough to follow a consumer part warming "
                        "up: about 1 deg/s over its first minutes)."),
            float_param(f"{p}_AB_RW", 1e-3, 1e-7, 0.1, "m/s^2/rts",
                        "Accelerometer bias random walk."),
            float_param(f"{p}_GS_STD", 0.015, 0.0, 0.1, "",
                        "1-sigma of each element of the gyro's scale-factor and cross-axis "
                        "error before the flight (fraction; a consumer part's +-3 % "
                        "tolerance is about 0.01 at 1 sigma, and the prior is kept wider "
                        "than that): the filter estimates the 3x3 error in turns. 0 takes "
                        "the gyro's scale as exact."),
            float_param(f"{p}_GB_TEMP", 1.5e-3, 0.0, 0.01, "rad/s/degC",
                        "Gyro bias change per degree of IMU temperature, 1-sigma: the prior "
                        "of the coefficient the filter estimates per axis while the part "
                        "warms up (a consumer MEMS part's datasheet allows about 0.05 deg/s/C "
                        "at 1 sigma; the prior is kept wider, 0.086 deg/s/C). 0 ignores the "
                        "temperature."),
            *[float_param(f"{p}_GM_{r}{c}", 0.0, -0.1, 0.1, "",
                          f"Gyro matrix error, row {r.lower()}, column {c.lower()} (the part "
                          "reads (I + M) w + bias): where the filter's estimate starts, from "
                          "what a previous flight of this part learnt (`companion estimation "
                          "calibration`); EST_GS_STD is its 1-sigma. 0 with no such flight.")
              for r in "XYZ" for c in "XYZ"],
            *[float_param(f"{p}_GT_{a}", 0.0, -0.01, 0.01, "rad/s/degC",
                          f"Gyro {a.lower()} bias temperature coefficient where the filter's "
                          "estimate starts, from a previous flight of this part (`companion "
                          "estimation calibration`); EST_GB_TEMP is its 1-sigma.")
              for a in "XYZ"],
            float_param(f"{p}_AB_TEMP", 1.5e-3, 0.0, 0.1, "m/s^2/degC",
                        "Accelerometer bias change per degree of IMU temperature, 1-sigma "
                        "(0.15 mg/C). 0 ignores the temperature."),
            float_param(f"{p}_GPS_HSTD", 1.0, 0.05, 100.0, "m",
                        "GPS horizontal position 1-sigma per unit HDOP."),
            float_param(f"{p}_GPS_VSTD", 2.0, 0.05, 100.0, "m",
                        "GPS vertical position 1-sigma (GST altitude std used when larger)."),
            float_param(f"{p}_TRIM_ROLL", 0.0, -0.5, 0.5, "rad",
                        "IMU board roll against the airframe (level calibration): samples are "
                        "turned into airframe axes before the filter."),
            float_param(f"{p}_TRIM_PITCH", 0.0, -0.5, 0.5, "rad",
                        "IMU board pitch against the airframe (level calibration)."),
            float_param(f"{p}_TRIM_YAW", 0.0, -0.5, 0.5, "rad",
                        "IMU board yaw against the airframe (a level calibration cannot see it; "
                        "measure it on the ground)."),
            int_param(f"{p}_TRIM_BIAS", 1, 0, 1, "",
                      "1: TRIM_ROLL/PITCH come from a level calibration, which read that "
                      "moment's accelerometer bias as a board tilt; the filter gives that tilt "
                      "back as it learns the bias in flight. 0 for trims measured otherwise "
                      "(no effect while both are 0)."),
            float_param(f"{p}_GPS_VEL", 0.25, 0.01, 10.0, "m/s",
                        "GPS velocity 1-sigma (a receiver's own figure is about 0.05 m/s; "
                        "the rest covers its latency jitter in turns)."),
            float_param(f"{p}_GPS_LAG", 0.05, 0.0, 0.5, "s",
                        "Receiver output delay beyond the latency the driver measures: the "
                        "starting guess, refined online unless GPS_LAGSD is 0."),
            float_param(f"{p}_GPS_LAGSD", 0.1, 0.0, 0.5, "s",
                        "1-sigma of the GPS_LAG guess; the filter estimates the delay from "
                        "turns and accelerations. 0 trusts GPS_LAG as exact."),
            int_param(f"{p}_HZN_USE", 1, 0, 1, "",
                      "1 fuses horizon attitude (HORIZON_ATTITUDE / MAVLink) weighted by quality."),
            float_param(f"{p}_HZN_STD", 0.05, 0.001, 1.0, "rad",
                        "Horizon roll/pitch 1-sigma at quality 1."),
            int_param(f"{p}_HDG_USE", 1, 0, 1, "",
                      "1 fuses a dual-antenna receiver's heading (NMEA HDT, GPS_HDT) with its "
                      "fix. Only an unbiased heading helps: in a turn a heading error becomes "
                      "a tilt error, so measure HDG_OFS on the ground."),
            float_param(f"{p}_HDG_STD", 0.01, 0.0001, 1.0, "rad",
                        "1-sigma of the receiver's heading (about the relative position's "
                        "error over the antenna baseline: 0.01 rad for 5 mm over 0.5 m)."),
            float_param(f"{p}_HDG_OFS", 0.0, -math.pi, math.pi, "rad",
                        "Yaw of the antenna baseline (first to second antenna) against the "
                        "airframe's forward axis, clockwise: 0 with the second antenna straight "
                        "ahead of the first, pi/2 with the first on the left wing and the "
                        "second on the right."),
        ]

    def define_logs(self, tlog: Any) -> None:
        tlog.define(FMT_STATE, ",".join(["%.6f"] * 3 + ["%.3f"] * 6 + ["%.6f"] * 6
                                        + ["%.4f"] * 9) + ",%u,%hhu", STATE_COLUMNS)
        tlog.define(FMT_GPS, ",".join(["%.3f"] * 6) + ",%.3f,%hhu,%.3f,%.4f,%.4f,%.5f,%.5f,%.5f"
                    + ",%.7f,%.7f,%.7f", GPS_COLUMNS)
        tlog.define(FMT_CAL, ",".join(["%.6f"] * 18 + ["%.8f"] * 6), CAL_COLUMNS)

    def _params(self) -> dict[str, float]:
        prefix = self.param_prefix + "_"
        return {spec.name.removeprefix(prefix): float(self.ctx.params.get(spec.name))
                for spec in self.declare_params(self.param_prefix)}

    def on_params_changed(self) -> None:
        if self.core is not None:
            self.core.update_params(self._params())

    # ------------------------------------------------------------------ commands
    COMMANDS = frozenset({"calibrate_level"})

    def post_command(self, kind: str, reply: Callable[[bool, str], None]) -> str | None:
        if kind not in self.COMMANDS:
            return super().post_command(kind, reply)
        if not self.running:
            return "level calibration: the estimator is not running"
        with self._level_lock:
            if self._level is not None:
                return "level calibration: one is already in progress"
            self._level = _LevelRequest(reply, self.ctx.clock.monotonic())
        log.info("level calibration: keep the aircraft level and still for %.0f s", LEVEL_CAL_S)
        return None

    def _collect_level(self, samples: Sequence[ImuSample]) -> None:
        """Worker: feed a pending level calibration; finish it once it has its samples."""
        with self._level_lock:
            req = self._level
        if req is None:
            return
        for s in samples:
            if req.first_t_ns is None:
                req.first_t_ns = s.t_ns
            req.last_t_ns = s.t_ns
            req.rates.append(s.rates_rad_s)
            req.accel.append(s.accel_m_s2)
        span_s = (req.last_t_ns - req.first_t_ns) / 1e9 if req.first_t_ns is not None else 0.0
        if span_s < LEVEL_CAL_S:
            if self.ctx.clock.monotonic() - req.started_s > LEVEL_CAL_TIMEOUT_S:
                self._finish_level(req, False, (
                    f"level calibration: {len(req.accel)} IMU samples over {span_s:.1f} s in "
                    f"{LEVEL_CAL_TIMEOUT_S:.0f} s, {LEVEL_CAL_S:.0f} s needed"))
            return
        from companion.estimation.level import LevelCalibrationError, level_trim

        try:
            trim = level_trim(req.accel, req.rates)
        except LevelCalibrationError as exc:
            self._finish_level(req, False, str(exc))
            return
        try:
            self.ctx.params.set_many(trim.params(self.param_prefix))
        except ParamError as exc:
            self._finish_level(req, False, f"level calibration: {exc}")
            return
        if self.core is not None:  # at once, also in the initial phase (no cycle boundary)
            self.core.update_params(self._params())
        # one STATUSTEXT's 50 characters
        self._finish_level(req, True, (
            f"level calibration done: roll {math.degrees(trim.roll_rad):+.2f} pitch "
            f"{math.degrees(trim.pitch_rad):+.2f} deg"))

    def _finish_level(self, req: _LevelRequest, ok: bool, message: str) -> None:
        with self._level_lock:
            self._level = None
        (log.info if ok else log.warning)("%s", message)
        try:
            req.reply(ok, message)
        except Exception:  # the requester's hook must not cost the estimator a cycle
            log.exception("level calibration reply failed")

    def _abandon_level(self, why: str) -> None:
        with self._level_lock:
            req = self._level
        if req is not None:
            self._finish_level(req, False, f"level calibration: {why}")

    def recover(self) -> None:
        self.core = None
        self._abandon_level("the estimator restarted")

    # ------------------------------------------------------------------ initial phase
    def prologue(self) -> bool:
        state = self.ctx.state
        clock = self.ctx.clock
        from companion.estimation.eskf import IDX_ATT, IDX_POS, IDX_VEL
        from companion.estimation.fusion import EstimatorCore

        # the logged standard deviations
        self._std_index = [int(i) for i in np.r_[IDX_POS, IDX_VEL, IDX_ATT]]
        core = EstimatorCore(self._params(), self.ctx.home_lla)
        state.imu_stream.drain()
        self.core = core  # a level calibration in this phase updates its trims at once
        while not self.stop_requested:
            sample = state.imu_stream.get(0.05, clock)
            self._collect_level([sample] if sample is not None else [])
            if core.initial_phase([sample] if sample is not None else [], state.gps.read()):
                break
            if core.init_failed:
                self.last_error = "initialisation refused (IMU mean is not ~1 g)"
                self.core = None
                return False
        if self.stop_requested or core.filter is None:
            self.core = None
            return False
        self._gps_seen = state.gps.version
        self._temp_seen = -1  # the last slow block's temperature counts as new
        log.info("estimator initialised (moving start: %s)", core.moving_start)
        return True

    # ------------------------------------------------------------------ periodic section
    def step(self) -> int:
        core = self.core
        if core is None or core.filter is None:
            return 0
        stream = self.ctx.state.imu_stream
        first = stream.get(0.05, self.ctx.clock)
        if first is None:
            if self._level is not None:  # a calibration without samples still times out
                self._collect_level([])
            return 0
        self.work_t0_ns = time.perf_counter_ns()  # step time excludes the wait
        samples = [first, *stream.drain()]
        if self._level is not None:
            self._collect_level(samples)
        core.predict(samples)
        fix, version, _ = self.ctx.state.gps.read_versioned()
        if fix is not None and version != self._gps_seen:
            self._gps_seen = version
            fused = core.fuse_gps(fix)
            if fused is not None and self.tlog is not None:
                res, latency = fused
                f = core.filter
                if res.innovation.size == 6 and f is not None:
                    self.tlog.log(FMT_GPS, *res.innovation.tolist(),
                                  res.nis if math.isfinite(res.nis) else -1.0,
                                  int(res.accepted), latency, f.gps_lag_estimate_s,
                                  f.gps_lag_estimate_std_s, *f.gyro_matrix_diagonal(),
                                  *f.gyro_temp_estimate_rad_s_per_c)
                    self._fused += 1
                    if self._fused % CAL_EVERY == 1:
                        m, m_std, k, k_std = f.gyro_calibration()
                        self.tlog.log(FMT_CAL, *m, *m_std, *k, *k_std)
        slow, slow_version, _ = self.ctx.state.imu_slow.read_versioned()
        if slow is not None and slow_version != self._temp_seen:
            self._temp_seen = slow_version
            core.set_temperature(slow.temperature_c)
        h, h_version, _ = self.ctx.state.horizon.read_versioned()
        if h is not None and h_version != self._hzn_seen:
            self._hzn_seen = h_version
            core.fuse_horizon(h)
        self._publish(core.filter)
        return len(samples)

    def counters(self) -> dict[str, int]:
        """What the filter did with its aiding, for the flight summary: whether a camera's
        horizon fixes or the GPS were used at all is the first question after a flight. Counts
        since the filter's last (re)start."""
        out = super().counters()
        core = self.core
        if core is not None:
            out.update(gps_accepted=core.gps_accepted, gps_rejected=core.gps_rejected,
                       horizon_used=core.horizon_used, heading_used=core.heading_used,
                       heading_rejected=core.heading_rejected,
                       temperature_readings=core.temperature_readings)
        return out

    @property
    def gps_accepted(self) -> int:
        return self.core.gps_accepted if self.core is not None else 0

    @property
    def horizon_used(self) -> int:
        return self.core.horizon_used if self.core is not None else 0

    def _publish(self, f: Eskf) -> None:
        v = f.flight_view()
        if v.faults != self.faults_reported:
            log.warning("estimator fault %d: %s (filter reset)", v.faults, v.last_fault_reason)
            self.faults_reported = v.faults
        assert self.core is not None
        imu = self.core.last_imu
        t_ns = imu.t_ns if imu is not None else self.ctx.clock.realtime_ns()
        rates = self.core.last_rates_rad_s
        bias = v.gyro_bias_rad_s
        home = self.core.frame
        out = EstimatorState(
            t_ns=t_ns,
            quat_wxyz=v.quaternion,
            roll_rad=v.roll_rad, pitch_rad=v.pitch_rad, yaw_rad=v.yaw_rad,
            pos_ned_m=v.pos_ned_m,  # type: ignore[arg-type]
            vel_ned_m_s=v.vel_ned_m_s,  # type: ignore[arg-type]
            gyro_bias_rad_s=bias,
            accel_bias_m_s2=v.accel_bias_m_s2,
            origin_lat_deg=home.lat0_deg if home else None,
            origin_lon_deg=home.lon0_deg if home else None,
            origin_alt_m=home.alt0_m if home else None,
            cov_diag=v.cov_diag,
            innovations=v.last_gps_innovation,
            rates_rad_s=(rates[0] - bias[0], rates[1] - bias[1], rates[2] - bias[2]),
            aligned=v.aligned,
            faults=v.faults,
        )
        self.ctx.state.estimator.write(out)
        if self.tlog is not None:
            diag = v.cov_diag
            sqrt = math.sqrt
            self.tlog.log(FMT_STATE, v.roll_rad, v.pitch_rad, v.yaw_rad, *out.pos_ned_m,
                          *out.vel_ned_m_s, *bias, *v.accel_bias_m_s2,
                          *[sqrt(diag[i]) if diag[i] > 0.0 else 0.0 for i in self._std_index],
                          v.faults, int(v.aligned), t_ns=t_ns)
