"""Run a flight-controller log through this project's estimator and compare the result.

The estimator is the flight's: `EstimatorCore` (GPS/INS ESKF, the estimator thread's parameter
defaults, sample periods from the samples' time stamps) when the log has usable GPS fixes, else
the IMU-only `AttitudeFilter`. Samples are handed over in cycles of `output_period_s`, as the
thread drains its IMU queue, with the newest GPS fix of the cycle and the IMU temperature at
most once a second, through the thread's own `EstimatorCore.cycle`.

Logs are not clean, so every timeline is cleaned first and what was done is reported, never
raised: repeated time stamps (duplicated samples) and small steps back (out of order) are
dropped; a step back of `CLOCK_JUMP_S` or more is a clock jump, and the rest of that stream is
shifted to continue one sample period after the jump (the same shift for every stream, so they
stay aligned); long steps forward are gaps, which the ESKF coasts through as in flight and the
IMU-only filter bridges with one nominal period (a gap's rotation is unknown either way).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from companion.estimation.replay.sources import AttitudeSeries, FlightLog, GpsSeries

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

CLOCK_JUMP_S = 0.5  # a step back at least this long is a clock jump, shorter ones out of order
GAP_MIN_S = 0.05  # a step forward is a gap above this and above GAP_PERIODS sample periods
GAP_PERIODS = 10.0
RATE_RANGE_HZ = (50.0, 1000.0)  # IMU rates the replay was tested with
MAX_LISTED = 20  # gaps and jumps listed one by one in the summary


@dataclass
class Timeline:
    """How one stream's time stamps were cleaned."""

    name: str
    samples_in: int
    samples_used: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    clock_jumps: list[tuple[float, float]] = field(default_factory=list)  # (at s, step s)
    gaps: list[tuple[float, float]] = field(default_factory=list)  # (start s, length s)
    rate_hz: float = math.nan

    def as_dict(self) -> dict[str, Any]:
        return {
            "samples_in": self.samples_in, "samples_used": self.samples_used,
            "duplicates_dropped": self.duplicates, "out_of_order_dropped": self.out_of_order,
            "clock_jumps": len(self.clock_jumps),
            "clock_jump_list": [{"at_s": round(a, 6), "step_s": round(s, 6)}
                                for a, s in self.clock_jumps[:MAX_LISTED]],
            "gaps": len(self.gaps),
            "gap_total_s": round(sum(g for _, g in self.gaps), 6),
            "gap_list": [{"start_s": round(a, 6), "length_s": round(g, 6)}
                         for a, g in self.gaps[:MAX_LISTED]],
            "rate_hz": None if not math.isfinite(self.rate_hz) else round(self.rate_hz, 3),
        }


def clean_timeline(t_us: IntArray, name: str, t0_us: int,
                   shifts_us: list[int] | None = None) -> tuple[IntArray, IntArray, Timeline,
                                                                 list[int]]:
    """Indices to keep, their corrected times, the report, and the shift of each clock jump.

    `shifts_us`: the shifts found on the IMU, applied in order to this stream's clock jumps so
    that all streams stay on one timeline; None for the IMU itself. Times in the report are
    seconds from `t0_us`.
    """
    tl = Timeline(name, len(t_us))
    t = np.asarray(t_us, dtype=np.int64)
    if len(t) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), tl, []
    steps = np.diff(t)
    positive = steps[steps > 0]
    nominal_us = int(np.median(positive)) if len(positive) else 10_000
    jump_us = int(CLOCK_JUMP_S * 1e6)
    keep: list[int] = []
    out: list[int] = []
    found: list[int] = []
    offset = 0
    last: int | None = None
    for k, raw in enumerate(t.tolist()):
        tc = raw + offset
        if last is not None and tc <= last:
            if tc == last:
                tl.duplicates += 1
                continue
            if last - tc < jump_us:
                tl.out_of_order += 1
                continue
            j = len(found)
            shift = (shifts_us[j] if shifts_us is not None and j < len(shifts_us)
                     else last + nominal_us - tc)
            if tc + shift <= last:
                shift = last + nominal_us - tc
            found.append(shift)
            tl.clock_jumps.append(((last - t0_us) / 1e6, (tc - last) / 1e6))
            offset += shift
            tc += shift
        keep.append(k)
        out.append(tc)
        last = tc
    kept_t = np.asarray(out, dtype=np.int64)
    tl.samples_used = len(kept_t)
    d = np.diff(kept_t)
    if len(d):
        med = float(np.median(d))
        tl.rate_hz = 1e6 / med if med > 0 else math.nan
        gap_us = max(GAP_MIN_S * 1e6, GAP_PERIODS * med)
        for i in np.flatnonzero(d > gap_us).tolist():
            tl.gaps.append(((kept_t[i] - t0_us) / 1e6, d[i] / 1e6))
    return np.asarray(keep, dtype=np.int64), kept_t, tl, found


@dataclass
class ReplayOptions:
    """`estimator`: "auto" (ESKF when the log has GPS fixes, else IMU-only), "eskf" or
    "attitude". `skip_s`: seconds after our estimator starts that are not scored (it is still
    converging). `params`: estimator-thread parameters by suffix (``GPS_LAG``...)."""

    estimator: str = "auto"
    skip_s: float = 2.0
    output_period_s: float = 0.01
    params: dict[str, float] = field(default_factory=dict)


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


@dataclass
class Comparison:
    """Our estimate against one of the flight controller's, at our output instants."""

    name: str
    t_us: IntArray  # the compared instants
    err_deg: FloatArray  # (N, 4): roll, pitch, yaw (NaN where not compared), inclination
    metrics: dict[str, Any]
    ref_euler_rad: FloatArray  # the reference at every estimate instant (NaN: none near)


@dataclass
class ReplayResult:
    flight: FlightLog
    estimator: str  # "eskf" or "attitude"
    estimator_reason: str
    estimate: Estimate
    t0_us: int
    timelines: dict[str, Timeline]
    comparisons: list[Comparison]
    notes: list[str]
    stats: dict[str, Any]
    run_time_s: float = 0.0


def replay_params(overrides: dict[str, float] | None = None) -> dict[str, float]:
    """The estimator's parameter defaults by suffix (a replay runs what flies) with
    `overrides` by suffix or by the vehicle's name (``EST_GPS_LAG``); unknown names are
    refused (ValueError)."""
    from companion.estimation.params import estimator_param_defaults
    from companion.vehicle import VEHICLE

    return estimator_param_defaults(VEHICLE["estimator"].task.param_prefix, overrides)


def _gps_fixes(gps: GpsSeries, keep: IntArray, t_us: IntArray) -> list[Any]:
    from companion.core.state import GpsFix

    def opt(a: FloatArray, i: int) -> float | None:
        v = float(a[i])
        return v if math.isfinite(v) else None

    valid = gps.valid
    fixes = []
    for i, tc in zip(keep.tolist(), t_us.tolist(), strict=True):
        if not valid[i]:
            continue
        sats = opt(gps.sats, i)
        fixes.append(GpsFix(
            t_ns=int(tc) * 1000, lat_deg=float(gps.lat_deg[i]), lon_deg=float(gps.lon_deg[i]),
            alt_m=float(gps.alt_m[i]), fix=int(gps.fix[i]),
            sats=None if sats is None else int(sats), hdop=opt(gps.hdop, i),
            speed_m_s=opt(gps.speed_m_s, i), course_deg=opt(gps.course_deg, i),
            vn_m_s=opt(gps.vn_m_s, i), ve_m_s=opt(gps.ve_m_s, i), vd_m_s=opt(gps.vd_m_s, i),
            alt_std_m=opt(gps.v_std_m, i), h_std_m=opt(gps.h_std_m, i)))
    return fixes


class _Recorder:
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


def _run_eskf(t_us: IntArray, gyro: FloatArray, accel: FloatArray, fixes: list[Any],
              params: dict[str, float], period_us: int,
              temps: list[tuple[int, float]] | None = None) -> tuple[Estimate, dict[str, Any]]:
    """`EstimatorCore` through its public cycle, one cycle per output period.

    ``temps`` (time us on the IMU's timeline, C) reach the filter at most once a simulated
    second, as the flight thread gets them from the IMU's 1 Hz slow block: the default
    temperature coefficients were chosen with that rate.
    """
    from companion.core.state import ImuSample
    from companion.estimation.fusion import EstimatorCore

    core = EstimatorCore(params, None, dt_source="time")
    rec = _Recorder()
    g_list, a_list, t_list = gyro.tolist(), accel.tolist(), t_us.tolist()
    n = len(t_list)
    gi = 0
    batch: list[ImuSample] = []
    batch_t0 = t_list[0] if n else 0
    started_at: int | None = None
    temps = temps or []
    ti = 0
    next_temp_us = -(1 << 62)
    for k in range(n):
        tk = t_list[k]
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
                break
            continue
        if started_at is None:
            started_at = tk
        st = core.filter.state()
        rec.t.append(tk)
        rec.q.append(tuple(st.quaternion.tolist()))
        rec.pos.append(tuple(st.pos_ned_m.tolist()))
        rec.vel.append(tuple(st.vel_ned_m_s.tolist()))
        rec.aligned.append(bool(st.initialised and st.yaw_aligned))
        rec.faults.append(int(st.faults))
    est = rec.done()
    stats: dict[str, Any] = {
        "started": started_at is not None, "init_refused": core.init_failed,
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


def _run_attitude(t_us: IntArray, gyro: FloatArray, accel: FloatArray, gap_us: float,
                  nominal_s: float, period_us: int) -> tuple[Estimate, dict[str, Any]]:
    """The IMU-only filter through its public `update`; a gap is bridged with one period."""
    from companion.estimation.attitude import AttitudeFilter

    f = AttitudeFilter()
    rec = _Recorder()
    t_list = t_us.tolist()
    last_out: int | None = None
    bridged = 0
    nan3 = (math.nan, math.nan, math.nan)
    for k, tk in enumerate(t_list):
        if k == 0:
            dt = nominal_s
        else:
            step = tk - t_list[k - 1]
            if step > gap_us:
                dt = nominal_s
                bridged += 1
            else:
                dt = step / 1e6
        q = f.update(gyro[k], accel[k], dt)
        if last_out is None or tk - last_out >= period_us or k == len(t_list) - 1:
            last_out = tk
            rec.t.append(tk)
            rec.q.append(tuple(np.asarray(q, dtype=float).tolist()))
            rec.pos.append(nan3)
            rec.vel.append(nan3)
            rec.aligned.append(False)
            rec.faults.append(0)
    return rec.done(), {"started": bool(rec.t), "gaps_bridged": bridged}


def _stats(x: FloatArray) -> dict[str, float | None]:
    x = x[np.isfinite(x)]
    if not len(x):
        return {"rmse": None, "mean": None, "p95": None, "max": None}
    a = np.abs(x)
    return {"rmse": round(float(np.sqrt(np.mean(x * x))), 4), "mean": round(float(x.mean()), 4),
            "p95": round(float(np.percentile(a, 95)), 4), "max": round(float(a.max()), 4)}


def compare(est: Estimate, ref: AttitudeSeries, ref_t_us: IntArray, keep: IntArray, *,
            start_us: int, heading_free: bool) -> Comparison:
    """Errors (ours minus theirs, degrees) at our instants from `start_us`, against the nearest
    reference sample (within 1.5 of its periods, at least 50 ms).

    `heading_free` (the IMU-only filter, whose heading starts at 0): the yaw error is taken
    after removing its circular mean, so it shows drift, not the arbitrary offset.
    """
    from companion.estimation.quat import inclination_error_rad, quat_from_euler, wrap_pi

    n = len(est.t_us)
    ref_e = np.column_stack([ref.roll_rad[keep], ref.pitch_rad[keep], ref.yaw_rad[keep]])
    ref_at = np.full((n, 3), np.nan)
    err = np.full((n, 4), np.nan)
    metrics: dict[str, Any] = {"samples_compared": 0}
    if len(ref_t_us) and n:
        d = np.diff(ref_t_us)
        tol = max(50_000.0, 1.5 * float(np.median(d))) if len(d) else 50_000.0
        j = np.clip(np.searchsorted(ref_t_us, est.t_us), 1, max(1, len(ref_t_us) - 1))
        j0 = np.clip(j - 1, 0, len(ref_t_us) - 1)
        j1 = np.clip(j, 0, len(ref_t_us) - 1)
        nearer = np.where(np.abs(ref_t_us[j1] - est.t_us) < np.abs(ref_t_us[j0] - est.t_us),
                          j1, j0)
        ok = np.abs(ref_t_us[nearer] - est.t_us) <= tol
        ref_at[ok] = ref_e[nearer[ok]]
        ref_at[:, 2] = wrap_pi(ref_at[:, 2])  # ArduPilot logs yaw in 0..360 deg
        scored = ok & (est.t_us >= start_us)
        q_ref = quat_from_euler(ref_at[:, 0], ref_at[:, 1], ref_at[:, 2])
        diff = wrap_pi(est.euler_rad - ref_at)
        yaw_ok = scored if heading_free else scored & est.aligned
        offset = math.nan
        if heading_free and yaw_ok.any():
            offset = math.atan2(float(np.sin(diff[yaw_ok, 2]).mean()),
                                float(np.cos(diff[yaw_ok, 2]).mean()))
            diff[:, 2] = wrap_pi(diff[:, 2] - offset)
        err[scored, 0:2] = np.degrees(diff[scored, 0:2])
        err[yaw_ok, 2] = np.degrees(diff[yaw_ok, 2])
        err[scored, 3] = np.degrees(inclination_error_rad(est.quat_wxyz[scored], q_ref[scored]))
        metrics = {
            "samples_compared": int(scored.sum()),
            "yaw_samples_compared": int(yaw_ok.sum()),
            "roll_deg": _stats(err[:, 0]), "pitch_deg": _stats(err[:, 1]),
            "yaw_deg": _stats(err[:, 2]), "inclination_deg": _stats(err[:, 3]),
            "yaw_offset_removed_deg": None if not math.isfinite(offset)
            else round(math.degrees(offset), 3)}
    return Comparison(ref.name, est.t_us, err, metrics, ref_at)


def replay(flight: FlightLog, options: ReplayOptions | None = None) -> ReplayResult:
    """Clean the timelines, run the estimator, compare with every reference. Never raises on
    the data (bad parameters in `options` raise ValueError)."""
    opts = options or ReplayOptions()
    if opts.estimator not in ("auto", "eskf", "attitude"):
        raise ValueError(f"estimator must be auto, eskf or attitude, got {opts.estimator!r}")
    params = replay_params(opts.params)
    started = time.perf_counter()
    notes = list(flight.notes)
    imu = flight.imu
    t0_us = int(imu.t_us[0]) if len(imu.t_us) else 0
    keep, t_imu, tl_imu, shifts = clean_timeline(imu.t_us, "imu", t0_us)
    timelines = {"imu": tl_imu}
    gyro, accel = imu.gyro_rad_s[keep], imu.accel_m_s2[keep]
    finite = np.isfinite(gyro).all(axis=1) & np.isfinite(accel).all(axis=1)
    if not finite.all():
        notes.append(f"{int((~finite).sum())} IMU sample(s) with non-finite values dropped")
        keep, t_imu, gyro, accel = keep[finite], t_imu[finite], gyro[finite], accel[finite]
    rate = tl_imu.rate_hz
    lo, hi = RATE_RANGE_HZ
    if math.isfinite(rate) and not lo * 0.9 <= rate <= hi * 1.1:
        notes.append(f"IMU rate {rate:.1f} Hz is outside the {lo:.0f}..{hi:.0f} Hz the replay "
                     "was tested with")
    nominal_s = 1.0 / rate if math.isfinite(rate) and rate > 0 else 0.01
    gap_us = max(GAP_MIN_S * 1e6, GAP_PERIODS * nominal_s * 1e6)
    fixes: list[Any] = []
    if flight.gps is not None and len(flight.gps):
        g_keep, g_t, tl_gps, _ = clean_timeline(flight.gps.t_us, "gps", t0_us, shifts)
        timelines["gps"] = tl_gps
        fixes = _gps_fixes(flight.gps, g_keep, g_t)
        if not fixes:
            notes.append(f"{flight.gps.source}: {len(flight.gps)} GPS message(s), none with a "
                         "3-D fix")
    ref_tl = []
    for ref in flight.references:
        r_keep, r_t, tl_ref, _ = clean_timeline(ref.t_us, ref.name, t0_us, shifts)
        timelines[ref.name] = tl_ref
        ref_tl.append((ref, r_keep, r_t))

    choice = opts.estimator
    if choice == "auto":
        choice = "eskf" if fixes else "attitude"
        reason = f"{len(fixes)} GPS fixes" if fixes else "no GPS fix in the log"
    else:
        reason = "asked for"
    if choice == "eskf" and not fixes:
        notes.append("the ESKF was asked for but the log has no GPS fix: IMU-only instead")
        choice, reason = "attitude", "no GPS fix in the log"
    period_us = max(1, int(opts.output_period_s * 1e6))
    temps: list[tuple[int, float]] = []
    temp = flight.temperature
    if temp is not None:
        t_keep, t_t, tl_temp, _ = clean_timeline(temp.t_us, "temperature", t0_us, shifts)
        timelines["temperature"] = tl_temp
        temps = list(zip(t_t.tolist(), temp.temperature_c[t_keep].tolist(), strict=True))
    stats: dict[str, Any]
    if choice == "eskf":
        if temp is not None and temps:
            c = temp.temperature_c[t_keep]
            notes.append(f"IMU temperature from {temp.source}: {float(c.min()):.1f} to "
                         f"{float(c.max()):.1f} C, read once a second")
        else:
            notes.append("the log has no IMU temperature: the biases' temperature walk "
                         "(EST_GB_TEMP, EST_AB_TEMP) stays off")
        est, stats = _run_eskf(t_imu, gyro, accel, fixes, params, period_us, temps)
        if not stats["started"]:
            why = ("its initialisation was refused (IMU mean is not ~1 g)"
                   if stats["init_refused"] else "it never got its initial phase and a fix")
            notes.append(f"the ESKF did not start ({why}): IMU-only attitude instead")
            choice, reason = "attitude", f"ESKF did not start: {why}"
    if choice == "attitude":
        est, stats = _run_attitude(t_imu, gyro, accel, gap_us, nominal_s, period_us)
    if stats.get("faults"):
        notes.append(f"the ESKF reset {stats['faults']} time(s) (last: "
                     f"{stats.get('last_fault_reason')}); see the log's gaps")
    heading_free = choice == "attitude"
    start_us = (int(est.t_us[0]) if len(est.t_us) else t0_us) + int(opts.skip_s * 1e6)
    comparisons = [compare(est, ref, r_t, r_keep, start_us=start_us, heading_free=heading_free)
                   for ref, r_keep, r_t in ref_tl]
    if not flight.references:
        notes.append("the log has no attitude of the flight controller to compare with")
    if choice == "eskf" and len(est.aligned) and not est.aligned.any():
        notes.append("the ESKF's heading never aligned (ground speed stayed under "
                     "5 m/s): yaw is not compared")
    result = ReplayResult(flight, choice, reason, est, t0_us, timelines, comparisons, notes,
                          stats)
    result.run_time_s = time.perf_counter() - started
    return result
