"""The two estimators a replay runs: the flight's GPS/INS filter, or an IMU-only filter.

The GPS/INS filter is `EstimatorCore` through its public cycle, one cycle per output period, as
the estimator thread drains its IMU queue, with the newest GPS fix of the cycle and the IMU's
temperature at most once a second; how it is started on a log is `start`'s. The IMU-only filter
is one of `companion.estimation.imu_filters` by name (VQF unless told), on the cleaned samples
at their median period: a gap is bridged as one period (its rotation is unknown either way).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from companion.estimation.replay.start import (
    StartReport,
    first_fed_index,
    refused_accel_norm,
)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

RESTART_GAP_US = 5_000_000
"""An IMU gap longer than this restarts the ESKF after it instead of coasting through: in
seconds without samples a vehicle can turn any way (a crashed copter righted by hand, 22 s
in one real log), and a filter that coasts keeps its old attitude, which the GPS corrects only
through its faults. A shorter gap is coasted as in flight: restarting in a turn levels the
new start by the bank angle (a 2 s gap in a 30 deg SITL turn came back worse restarted)."""


@dataclass
class Estimate:
    """Our estimate at each output instant (log time, corrected)."""

    t_us: IntArray
    quat_wxyz: FloatArray
    euler_rad: FloatArray
    pos_ned_m: FloatArray
    vel_ned_m_s: FloatArray
    aligned: npt.NDArray[np.bool_]
    faults: IntArray

    @classmethod
    def empty(cls) -> Estimate:
        return Recorder().done()


class Recorder:
    """Collects the estimate row by row."""

    def __init__(self) -> None:
        self.t: list[int] = []
        self.q: list[tuple[float, ...]] = []
        self.pos: list[tuple[float, ...]] = []
        self.vel: list[tuple[float, ...]] = []
        self.aligned: list[bool] = []
        self.faults: list[int] = []

    def done(self) -> Estimate:
        from companion.estimation.quat import quat_to_euler

        q = np.asarray(self.q, dtype=float).reshape(-1, 4)
        return Estimate(np.asarray(self.t, dtype=np.int64), q, quat_to_euler(q),
                        np.asarray(self.pos, dtype=float).reshape(-1, 3),
                        np.asarray(self.vel, dtype=float).reshape(-1, 3),
                        np.asarray(self.aligned, dtype=bool),
                        np.asarray(self.faults, dtype=np.int64))


def run_eskf(t_us: IntArray, gyro: FloatArray, accel: FloatArray, fixes: list[Any],
             params: dict[str, float], period_us: int, report: StartReport, t0_us: int,
             temps: list[tuple[int, float]] | None = None,
             initial_yaw: Callable[[int], float | None] | None = None,
             ) -> tuple[Estimate, dict[str, Any]]:
    """`EstimatorCore` through its public cycle, one cycle per output period, fed from
    `INIT_S` before the first fix; a refused start begins again with a new core on the next
    samples (each refusal is in `report`).

    ``temps`` (time us on the IMU's timeline, C) reach the filter at most once a simulated
    second, as the flight thread gets them from the IMU's 1 Hz slow block: the default
    temperature coefficients were chosen with that rate.
    """
    from companion.core.state import ImuSample
    from companion.estimation.fusion import EstimatorCore

    def new_core() -> EstimatorCore:
        c = EstimatorCore(params, None, dt_source="time")
        c.initial_yaw = initial_yaw
        return c

    core = new_core()
    rec = Recorder()
    g_list, a_list, t_list = gyro.tolist(), accel.tolist(), t_us.tolist()
    n = len(t_list)
    k0 = first_fed_index(t_us, fixes[0].t_ns // 1000, params["INIT_S"]) if fixes else 0
    report.fed_from_s = (t_list[k0] - t0_us) / 1e6 if k0 < n else None
    gi = 0
    while gi < len(fixes) and fixes[gi].t_ns // 1000 < (t_list[k0] if k0 < n else 0):
        gi += 1
    batch: list[ImuSample] = []
    batch_t0 = t_list[k0] if k0 < n else 0
    started_at: int | None = None
    temps = temps or []
    ti = 0
    next_temp_us = -(1 << 62)
    for k in range(k0, n):
        tk = t_list[k]
        if k > k0 and tk - t_list[k - 1] > RESTART_GAP_US and core.filter is not None:
            # the attitude after a long gap is unknown (a crashed copter righted by hand):
            # start again from the samples after it, as on a log that begins there
            report.restarts.append(((t_list[k - 1] - t0_us) / 1e6, (tk - t_list[k - 1]) / 1e6))
            core = new_core()
            batch, batch_t0 = [], tk
        batch.append(ImuSample(tk * 1000, k & 0xFFFF, tuple(g_list[k]),  # type: ignore[arg-type]
                               tuple(a_list[k])))  # type: ignore[arg-type]
        if tk - batch_t0 < period_us and k < n - 1:
            continue
        fix = None
        while gi < len(fixes) and fixes[gi].t_ns <= tk * 1000:
            fix = fixes[gi]
            gi += 1
        # the temperatures logged up to now, at most once a second: consumed only once the
        # filter runs (a cycle before its start leaves them for the first one after)
        temp_c = None
        tj = ti
        if ti < len(temps) and tk >= next_temp_us:
            while tj < len(temps) and temps[tj][0] <= tk:
                temp_c = temps[tj][1]
                tj += 1
        running = core.cycle(batch, fix, temperature_c=temp_c)
        batch = []
        batch_t0 = tk
        if core.filter is not None:
            ti = tj
            if temp_c is not None:
                next_temp_us = tk + 1_000_000
        if not running or core.filter is None:
            if core.init_failed:
                report.refusals.append(((tk - t0_us) / 1e6, refused_accel_norm(
                    accel, t_us, tk, params["INIT_S"])))
                core = new_core()
            continue
        if started_at is None:
            started_at = tk
            report.started_at_s = (tk - t0_us) / 1e6
            yaw0 = initial_yaw(tk * 1000) if initial_yaw is not None else None
            report.heading_start_deg = None if yaw0 is None else math.degrees(yaw0)
        st = core.filter.state()
        rec.t.append(tk)
        rec.q.append(tuple(st.quaternion.tolist()))
        rec.pos.append(tuple(st.pos_ned_m.tolist()))
        rec.vel.append(tuple(st.vel_ned_m_s.tolist()))
        rec.aligned.append(bool(st.initialised and st.yaw_aligned))
        rec.faults.append(int(st.faults))
    est = rec.done()
    if started_at is None and not report.reason:
        report.reason = _never_started(report, fixes, t_us, t0_us)
    stats: dict[str, Any] = {
        "started": started_at is not None, "init_refused": len(report.refusals),
        "moving_start": core.moving_start, "gps_fixes_offered": len(fixes),
        "gps_accepted": core.gps_accepted, "gps_rejected": core.gps_rejected,
        "temperature_readings": core.temperature_readings,
        "faults": int(est.faults[-1]) if len(est.faults) else 0,
        "heading_aligned_fraction": float(est.aligned.mean()) if len(est.aligned) else 0.0}
    if core.filter is not None:
        st = core.filter.state()
        stats["last_fault_reason"] = st.last_fault_reason or None
        stats["gyro_bias_rad_s"] = [round(float(x), 6) for x in st.gyro_bias_rad_s]
        stats["accel_bias_m_s2"] = [round(float(x), 5) for x in st.accel_bias_m_s2]
    return est, stats


def _never_started(report: StartReport, fixes: list[Any], t_us: IntArray, t0_us: int) -> str:
    """The one-line reason a run without a start gives (times from the first IMU sample)."""
    if report.refusals:
        first, last = report.refusals[0], report.refusals[-1]
        return (f"every start was refused ({len(report.refusals)} tries from {first[0]:.1f} s "
                f"to {last[0]:.1f} s): the accelerometer's mean was not about 1 g "
                f"(|a| {first[1]:.2f} m/s^2 at the first, {last[1]:.2f} at the last)")
    if not len(t_us):
        return "no IMU samples"
    last_fix = (fixes[-1].t_ns // 1000 - t0_us) / 1e6 if fixes else math.nan
    return (f"not enough IMU samples with the GPS fixes (the last fix at {last_fix:.1f} s, "
            f"the IMU ends at {(int(t_us[-1]) - t0_us) / 1e6:.1f} s)")


def run_imu_only(name: str, t_us: IntArray, gyro: FloatArray, accel: FloatArray,
                 nominal_s: float, period_us: int, gap_us: float
                 ) -> tuple[Estimate, dict[str, Any]]:
    """The IMU-only filter ``name`` of the registry on every sample, kept once per output
    period; its attitudes turned body-to-NED (heading arbitrary).

    Ours runs on the samples' own periods (``ours_timed``: a log's samples have time stamps),
    every step longer than ``gap_us`` shortened to one nominal period; a fixed-rate filter
    (VQF) takes every sample as one period, which bridges a gap the same way.
    """
    from companion.estimation.imu_filters import ImuSeries, resolve, run_filter, to_ned

    real = resolve(name)
    if real == "ours":
        real = "ours_timed"
    if not len(t_us):
        return Estimate.empty(), {"started": False, "imu_filter": real}
    steps = np.diff(t_us).astype(float)
    bridged = int((steps > gap_us).sum())
    steps[steps > gap_us] = nominal_s * 1e6
    t_s = np.concatenate(([0.0], np.cumsum(steps) / 1e6))
    q, frame = run_filter(real, ImuSeries(np.ascontiguousarray(gyro, dtype=float),
                                          np.ascontiguousarray(accel, dtype=float),
                                          nominal_s, t_s=t_s))
    q = to_ned(q, frame)
    keep: list[int] = []
    last_out: int | None = None
    t_list = t_us.tolist()
    for k, tk in enumerate(t_list):
        if last_out is None or tk - last_out >= period_us or k == len(t_list) - 1:
            last_out = tk
            keep.append(k)
    rec = Recorder()
    nan3 = (math.nan, math.nan, math.nan)
    for k in keep:
        rec.t.append(t_list[k])
        rec.q.append(tuple(q[k].tolist()))
        rec.pos.append(nan3)
        rec.vel.append(nan3)
        rec.aligned.append(False)
        rec.faults.append(0)
    return rec.done(), {"started": bool(rec.t), "imu_filter": real, "gaps_bridged": bridged}
