"""Estimator thread: the GPS/INS filter (`Eskf`) as a managed thread.

Initial phase (the aperiodic prologue, as in the thesis): average the IMU for EST_INIT_S to
level the attitude and take the gyro bias, and wait for a GPS fix. Periodic section, paced by
the IMU: one `EstimatorCore.cycle` integrates every sample (all of them, from the IMU stream
queue, not only the newest), then fuses the newest GPS fix, IMU temperature and horizon
attitude, if any, with their latencies. The result goes to the estimator slot (control reads
it), the log (companion.estimation.logformats) and the bridges.

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

from companion.core.params import ParamError, ParamSpec
from companion.core.state import EstimatorState, ImuSample
from companion.estimation.logformats import (
    CAL_EVERY,
    FMT_CAL,
    FMT_GPS,
    FMT_STATE,
    define_estimator_logs,
)
from companion.estimation.params import estimator_param_specs
from companion.watchdog.thread import ManagedThread, Task

if TYPE_CHECKING:
    # the filter loads when the thread starts, not when its
    # parameters are listed (`companion params`, the docs)
    from companion.estimation.eskf import Eskf
    from companion.estimation.eskf_state import UpdateResult
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
        return estimator_param_specs(p)

    def define_logs(self, tlog: Any) -> None:
        define_estimator_logs(tlog)

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
        from companion.estimation.eskf_state import IDX_ATT, IDX_POS, IDX_VEL
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
        fix, version, _ = self.ctx.state.gps.read_versioned()
        if fix is not None and version != self._gps_seen:
            self._gps_seen = version
        else:
            fix = None
        temperature_c = None
        slow, slow_version, _ = self.ctx.state.imu_slow.read_versioned()
        if slow is not None and slow_version != self._temp_seen:
            self._temp_seen = slow_version
            temperature_c = slow.temperature_c
        h, h_version, _ = self.ctx.state.horizon.read_versioned()
        if h is not None and h_version != self._hzn_seen:
            self._hzn_seen = h_version
        else:
            h = None
        core.cycle(samples, fix, h, temperature_c=temperature_c, on_gps=self._log_gps)
        self._publish(core.filter)
        return len(samples)

    def _log_gps(self, res: UpdateResult, latency_s: float) -> None:
        """A fused fix's record, taken as the cycle fuses it (before the temperature and the
        horizon move the filter), and every `CAL_EVERY` fixes what the filter learnt of the
        gyro."""
        f = self.core.filter if self.core is not None else None
        if self.tlog is None or res.innovation.size != 6 or f is None:
            return
        self.tlog.log(FMT_GPS, *res.innovation.tolist(),
                      res.nis if math.isfinite(res.nis) else -1.0,
                      int(res.accepted), latency_s, f.gps_lag_estimate_s,
                      f.gps_lag_estimate_std_s, *f.gyro_matrix_diagonal(),
                      *f.gyro_temp_estimate_rad_s_per_c)
        self._fused += 1
        if self._fused % CAL_EVERY == 1:
            m, m_std, k, k_std = f.gyro_calibration()
            self.tlog.log(FMT_CAL, *m, *m_std, *k, *k_std)

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
