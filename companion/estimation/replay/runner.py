"""Run a flight-controller log through this project's estimator and compare the result.

The estimator is the flight's: `EstimatorCore` (GPS/INS ESKF, the estimator thread's parameter
defaults, sample periods from the samples' time stamps) when the log has usable GPS fixes and
it starts (`start` says how, or why not), else an IMU-only filter of the registry
(`companion.estimation.imu_filters`, VQF unless told): `filters` runs both.

Logs are not clean, so every timeline is cleaned first and what was done is reported, never
raised: repeated time stamps (duplicated samples) and small steps back (out of order) are
dropped; a step back of `CLOCK_JUMP_S` or more is a clock jump, and the rest of that stream is
shifted to continue one sample period after the jump (the same shift for every stream, so they
stay aligned); long steps forward are gaps, which the ESKF coasts through as in flight and the
IMU-only filter bridges with one nominal period (a gap's rotation is unknown either way).

A log without IMU samples gives a partial replay (no estimate, its references and GPS listed),
never an exception: the notes say what was used.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from companion.estimation.imu_filters import DEFAULT_FILTER
from companion.estimation.replay.filters import Estimate, run_eskf, run_imu_only
from companion.estimation.replay.sources import AttitudeSeries, FlightLog, GpsSeries
from companion.estimation.replay.start import StartReport, heading_lookup, why_no_fix

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
    """`estimator`: "auto" (ESKF when the log has GPS fixes and it starts, else IMU-only),
    "eskf" or "attitude" (IMU-only). `imu_filter`: the IMU-only filter by registry name.
    `heading_from`: "auto" (the GPS course when the first fix is already fast enough to give
    one, else the log's first reference), "gps" (the flight's: the GPS course aligns the
    heading) or the name of one of the log's references (or "ref": the first) whose yaw
    starts the ESKF's heading.
    `skip_s`: seconds after our estimator starts that are not scored (it is still
    converging). `params`: estimator-thread parameters by suffix (``GPS_LAG``...)."""

    estimator: str = "auto"
    skip_s: float = 2.0
    output_period_s: float = 0.01
    params: dict[str, float] = field(default_factory=dict)
    imu_filter: str = DEFAULT_FILTER
    heading_from: str = "auto"


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
    estimator: str  # "eskf", "attitude" (IMU-only) or "none" (no IMU samples)
    estimator_reason: str
    estimate: Estimate
    t0_us: int
    timelines: dict[str, Timeline]
    comparisons: list[Comparison]
    notes: list[str]
    stats: dict[str, Any]
    run_time_s: float = 0.0
    start: StartReport = field(default_factory=StartReport)
    imu_filter: str = ""  # the IMU-only filter that ran ("" when the ESKF did)


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
            else round(math.degrees(offset), 3),
            # the time alignment: nearest reference sample, no shift (docs/estimation.md)
            "match_tolerance_ms": round(tol / 1e3, 1),
            "median_time_offset_ms": round(float(np.median(
                np.abs(ref_t_us[nearer] - est.t_us)[scored])) / 1e3, 1)
            if scored.any() else None}
    return Comparison(ref.name, est.t_us, err, metrics, ref_at)


def _check_options(opts: ReplayOptions, flight: FlightLog) -> None:
    """Bad options are the caller's mistake (ValueError), not the log's."""
    from companion.estimation.imu_filters import resolve

    if opts.estimator not in ("auto", "eskf", "attitude"):
        raise ValueError(f"estimator must be auto, eskf or attitude, got {opts.estimator!r}")
    resolve(opts.imu_filter)


HEADING_SPEED_M_S = 5.0
"""The ground speed from which the ESKF takes its heading from the GPS course (its
`yaw_align_min_speed_m_s`): "auto" asks the log's attitude below it."""


def _heading_reference(opts: ReplayOptions, flight: FlightLog, ref_tl: list[Any],
                       fixes: list[Any], notes: list[str]) -> tuple[str, Any]:
    """(what starts the heading, a lookup of its yaw by time or None).

    "auto" takes the log's attitude when the first fix is too slow for a GPS course (a vehicle
    on the ground or hovering at the start): on 38 real ArduPilot logs an unaligned heading
    cost the ESKF more inclination than the reference's heading (docs/estimation.md)."""
    want = opts.heading_from
    if want == "auto":
        first = fixes[0] if fixes else None
        speed = 0.0
        if first is not None:
            if first.vn_m_s is not None and first.ve_m_s is not None:
                speed = math.hypot(first.vn_m_s, first.ve_m_s)
            elif first.speed_m_s is not None:
                speed = first.speed_m_s
        if speed >= HEADING_SPEED_M_S or not ref_tl:
            return "gps", None
        want = "ref"
    if want == "gps":
        return "gps", None
    for ref, r_keep, r_t in ref_tl:
        if want in ("ref", ref.name):
            return ref.name, heading_lookup(r_t, ref.yaw_rad[r_keep])
    names = ", ".join(r.name for r in flight.references) or "none"
    notes.append(f"--heading-from {want}: the log has no such reference ({names}): the "
                 "heading waits for the GPS course")
    return "gps", None


def replay(flight: FlightLog, options: ReplayOptions | None = None) -> ReplayResult:
    """Clean the timelines, run the estimator, compare with every reference. Never raises on
    the data (bad parameters in `options` raise ValueError)."""
    opts = options or ReplayOptions()
    _check_options(opts, flight)
    params = replay_params(opts.params)
    started = time.perf_counter()
    notes = list(flight.notes)
    imu = flight.imu
    t0_us = int(imu.t_us[0]) if len(imu.t_us) else _first_time(flight)
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
    gps_t: IntArray | None = None
    if flight.gps is not None and len(flight.gps):
        g_keep, g_t, tl_gps, _ = clean_timeline(flight.gps.t_us, "gps", t0_us, shifts)
        timelines["gps"] = tl_gps
        gps_t = g_t
        fixes = _gps_fixes(flight.gps, g_keep, g_t)
        if not fixes:
            notes.append(f"{flight.gps.source}: {len(flight.gps)} GPS message(s), none with a "
                         "3-D fix")
    ref_tl = []
    for ref in flight.references:
        r_keep, r_t, tl_ref, _ = clean_timeline(ref.t_us, ref.name, t0_us, shifts)
        timelines[ref.name] = tl_ref
        ref_tl.append((ref, r_keep, r_t))
    report = StartReport()
    if len(t_imu):
        report.imu_span_s = (0.0, (int(t_imu[-1]) - t0_us) / 1e6)
    if gps_t is not None and len(gps_t):
        report.gps_span_s = ((int(gps_t[0]) - t0_us) / 1e6, (int(gps_t[-1]) - t0_us) / 1e6)
    fix_t = [f.t_ns // 1000 for f in fixes]
    if fix_t:
        report.first_fix_s = (fix_t[0] - t0_us) / 1e6
    no_fix = (why_no_fix(t_imu, gps_t, fix_t, len(fixes), t0_us) if len(t_imu)
              else "no IMU samples")

    choice = opts.estimator
    if not len(t_imu):
        choice, reason = "none", "the log has no usable IMU samples"
        notes.append("the log has no usable IMU samples: nothing estimated; its GPS and "
                     "references are listed only")
    elif choice == "auto":
        choice = "attitude" if no_fix else "eskf"
        reason = f"{len(fixes)} GPS fixes" if not no_fix else f"no GPS fix to start: {no_fix}"
    else:
        reason = "asked for"
    if choice == "eskf" and no_fix:
        notes.append(f"the ESKF was asked for but cannot start ({no_fix}): IMU-only instead")
        choice, reason = "attitude", f"no GPS fix to start: {no_fix}"
    if no_fix and choice != "none":
        report.reason = no_fix
    period_us = max(1, int(opts.output_period_s * 1e6))
    temps: list[tuple[int, float]] = []
    temp = flight.temperature
    if temp is not None:
        t_keep, t_t, tl_temp, _ = clean_timeline(temp.t_us, "temperature", t0_us, shifts)
        timelines["temperature"] = tl_temp
        temps = list(zip(t_t.tolist(), temp.temperature_c[t_keep].tolist(), strict=True))
    stats: dict[str, Any] = {"started": False}
    est = Estimate.empty()
    imu_filter = ""
    if choice == "eskf":
        report.heading_from, initial_yaw = _heading_reference(opts, flight, ref_tl, fixes,
                                                              notes)
        if temp is not None and temps:
            c = temp.temperature_c[t_keep]
            notes.append(f"IMU temperature from {temp.source}: {float(c.min()):.1f} to "
                         f"{float(c.max()):.1f} C, read once a second")
        else:
            notes.append("the log has no IMU temperature: the biases' temperature walk "
                         "(EST_GB_TEMP, EST_AB_TEMP) stays off")
        est, stats = run_eskf(t_imu, gyro, accel, fixes, params, period_us, report, t0_us,
                              temps, initial_yaw)
        if report.refusals:
            notes.append(f"the ESKF's start was refused {len(report.refusals)} time(s) (the "
                         "accelerometer's mean not about 1 g), first at "
                         f"{report.refusals[0][0]:.1f} s; started again on later samples")
        if report.restarts:
            notes.append(f"the ESKF started again after {len(report.restarts)} IMU gap(s) "
                         f"longer than 5 s (first at {report.restarts[0][0]:.1f} s, "
                         f"{report.restarts[0][1]:.1f} s long)")
        if not stats["started"]:
            notes.append(f"the ESKF did not start ({report.reason}): IMU-only attitude "
                         "instead")
            choice, reason = "attitude", f"ESKF did not start: {report.reason}"
    if choice == "attitude":
        est, stats_imu = run_imu_only(opts.imu_filter, t_imu, gyro, accel, nominal_s,
                                      period_us, gap_us)
        imu_filter = str(stats_imu["imu_filter"])
        stats = {**stats_imu, "eskf": stats} if stats.get("gps_fixes_offered") else stats_imu
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
                     "5 m/s): yaw is not compared (--heading-from ref starts it from the "
                     "log's own attitude)")
    if choice == "eskf" and report.heading_from not in ("gps", ""):
        notes.append(f"the ESKF's heading started from {report.heading_from}'s yaw "
                     f"({report.heading_start_deg:.1f} deg): its yaw difference shows how "
                     "the heading held, not an independent heading"
                     if report.heading_start_deg is not None else
                     f"no {report.heading_from} yaw near the start: the heading waited for "
                     "the GPS course")
    result = ReplayResult(flight, choice, reason, est, t0_us, timelines, comparisons, notes,
                          stats, start=report, imu_filter=imu_filter)
    result.run_time_s = time.perf_counter() - started
    return result


def _first_time(flight: FlightLog) -> int:
    """The log's first time stamp of any stream (the origin when there is no IMU)."""
    firsts = [int(s.t_us[0]) for s in (flight.gps, *flight.references)
              if s is not None and len(s.t_us)]
    return min(firsts) if firsts else 0
