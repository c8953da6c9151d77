"""The report's figures, one builder per figure, drawn with matplotlib's Agg canvas only.

Each builder takes the loaded flight and returns a `Figure`, or raises `MissingData` naming the
file (and format or column) it lacked; the report then lists that instead of the figure. Figures
are built on `matplotlib.figure.Figure` with an Agg canvas, never through pyplot, so nothing
here touches global GUI state and reports can be drawn from any thread. Nothing random and no
wall-clock text go into a figure: the same flight gives the same PNG bytes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from companion.core.geo import NedFrame
from companion.drivers.servo_protocol import CENTRE_US, HALF_TRAVEL_US
from companion.report.analysis import (
    PERIOD_SOURCES,
    Track,
    estimate_track,
    gps_frame,
    gps_track,
    interp_angle_at,
    interp_at,
    period_stats,
    truth_track,
)
from companion.report.flight import FlightData

__all__ = ["FIGURES", "FigureSpec", "MissingData", "Products", "STYLE", "new_figure"]

#: matplotlib settings every report figure is drawn with (rc_context), for reproducible output.
STYLE: dict[str, Any] = {
    "figure.dpi": 100,
    "savefig.dpi": 100,
    "font.size": 8,
    "axes.titlesize": 9,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "lines.linewidth": 0.9,
    "legend.fontsize": 7,
    "path.simplify": True,
    "agg.path.chunksize": 20000,
}

PULSE_CENTRE_US = float(CENTRE_US)
PULSE_HALF_RANGE_US = float(HALF_TRAVEL_US)


class MissingData(LookupError):
    """A figure cannot be drawn; the message says which file or column is missing."""


def new_figure(nrows: int, ncols: int = 1, *, height_in: float = 2.4, width_in: float = 9.0,
               sharex: bool = False) -> tuple[Figure, list[Axes]]:
    """A figure with an Agg canvas and its axes, flattened in row order."""
    fig = Figure(figsize=(width_in, height_in * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False, sharex=sharex)
    return fig, [ax for row in axes for ax in row]


@dataclass
class Products:
    """Numbers shared between figures, computed once per report."""

    fd: FlightData
    notes: dict[str, str] = field(default_factory=dict)

    @cached_property
    def frame(self) -> NedFrame | None:
        return gps_frame(self.fd)

    @cached_property
    def gps(self) -> Track | None:
        return gps_track(self.fd, self.frame) if self.frame is not None else None

    @cached_property
    def truth(self) -> Track | None:
        return truth_track(self.fd, self.frame) if self.frame is not None else None

    @cached_property
    def estimate(self) -> Track | None:
        if self.frame is None:
            return None
        found = estimate_track(self.fd, self.frame)
        if found is None:
            return None
        track, note = found
        self.notes["estimate"] = note
        return track


def _need(fd: FlightData, name: str, index: int, columns: tuple[str, ...]) -> np.ndarray:
    data = fd.block(name, index, columns)
    if data is None:
        raise MissingData(fd.why_missing(name, index, columns))
    return data


def _col(data: np.ndarray, name: str) -> np.ndarray | None:
    return np.asarray(data[name], dtype=np.float64) if name in (data.dtype.names or ()) else None


# ------------------------------------------------------------------------------- GPS (6-1..6-3)
def fig_gps_fix(p: Products) -> Figure:
    gps = _need(p.fd, "gps", 1, ("fix",))
    t = p.fd.rel_s(gps["time_s"])
    fig, (ax, ax2) = new_figure(2, height_in=1.9)
    fix = np.asarray(gps["fix"], dtype=np.float64)
    ax.step(t, fix, where="post", color="tab:blue", label="fix type")
    bad = fix <= 0
    if bad.any():
        ax.plot(t[bad], fix[bad], "x", color="tab:red", label=f"no fix ({int(bad.sum())} epochs)")
    ax.set_yticks([0, 1, 2, 3], ["none", "GPS", "DGPS", "RTK"])
    ax.set_ylim(-0.3, 3.3)
    ax.set_ylabel("fix")
    ax.set_title(f"GPS fix validity: {100.0 * (1 - bad.mean()):.1f} % of {fix.size} epochs valid")
    ax.legend(loc="lower right")
    sats = _col(gps, "sats")
    if sats is not None:
        ax2.step(t, sats, where="post", color="tab:green", label="satellites")
        ax2.legend(loc="lower right")
    ax2.set_ylabel("satellites")
    ax2.set_xlabel("time since start (s)")
    return fig


def fig_gps_track(p: Products) -> Figure:
    _need(p.fd, "gps", 1, ("lat_deg", "lon_deg", "alt_m", "fix"))
    if p.frame is None or p.gps is None or p.gps.n == 0:
        raise MissingData("gps.bin has no valid fix")
    g = p.gps
    fig = Figure(figsize=(9.0, 4.2), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2, 1)
    ax2 = fig.add_subplot(1, 2, 2)
    ax.plot(g.east_m, g.north_m, color="tab:blue", label="GPS")
    ax.plot(g.east_m[:1], g.north_m[:1], "o", color="tab:green", label="start")
    ax.plot(g.east_m[-1:], g.north_m[-1:], "s", color="tab:red", label="end")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(f"GPS track, origin at the first fix ({p.frame.lat0_deg:.6f}, "
                 f"{p.frame.lon0_deg:.6f})")
    ax.legend(loc="best")
    ax2.plot(g.t_s, -g.down_m, color="tab:blue", label="GPS")
    ax2.set_xlabel("time since start (s)")
    ax2.set_ylabel("height above the first fix (m)")
    ax2.set_title("GPS altitude")
    ax2.legend(loc="best")
    return fig


def fig_gps_quality(p: Products) -> Figure:
    gps = _need(p.fd, "gps", 1, ("fix",))
    t = p.fd.rel_s(gps["time_s"])
    fig, (ax, ax2, ax3) = new_figure(3, height_in=1.9, sharex=True)
    plotted = 0
    for name in ("hdop", "pdop", "vdop", "tdop"):
        v = _col(gps, name)
        if v is not None and np.isfinite(v).any():
            ax.plot(t, v, label=name.upper())
            plotted += 1
    if not plotted:
        raise MissingData("gps.bin format 1 has no DOP columns (hdop, pdop, vdop, tdop)")
    ax.set_ylabel("DOP")
    ax.set_title("GPS accuracy indicators")
    ax.legend(loc="upper right", ncols=4)
    lat = _col(gps, "latency_ms")
    if lat is not None:
        ax2.plot(t, lat, color="tab:purple", label="latency")
        ax2.set_title(f"receiver latency: mean {np.nanmean(lat):.1f} ms, max {np.nanmax(lat):.1f} ms")
        ax2.legend(loc="upper right")
    ax2.set_ylabel("latency (ms)")
    for name, label in (("alt_std_m", "altitude std"), ("h_std_m", "horizontal std")):
        v = _col(gps, name)
        if v is not None:
            ax3.plot(t, v, label=label)
    ax3.set_ylabel("std dev (m)")
    ax3.set_xlabel("time since start (s)")
    ax3.legend(loc="upper right")
    return fig


# ------------------------------------------------------------------------------- periods (6-4)
def fig_periods(p: Products) -> Figure:
    rows = []
    missing = []
    for thread, (name, index, nominal) in PERIOD_SOURCES.items():
        data = p.fd.block(name, index)
        stats = period_stats(p.fd.rel_s(data["time_s"]), nominal) if data is not None else None
        if stats is None:
            missing.append(f"{thread}: " + p.fd.why_missing(name, index))
        else:
            rows.append((thread, stats))
    if not rows:
        raise MissingData("no sample periods: " + "; ".join(missing))
    fig, axes = new_figure(len(rows), 2, height_in=2.0)
    for k, (thread, s) in enumerate(rows):
        ax, axh = axes[2 * k], axes[2 * k + 1]
        ax.plot(s.t_s, s.period_ms, color="tab:blue", label="period")
        ax.axhline(s.nominal_ms, color="tab:green", linestyle="--", label=f"nominal {s.nominal_ms:g} ms")
        ax.axhline(s.mean_ms, color="tab:orange", linestyle=":", label=f"mean {s.mean_ms:.1f} ms")
        ax.set_ylabel(f"{thread} period (ms)")
        ax.set_title(f"{thread}: mean {s.mean_ms:.2f} ms, p99 {s.p99_ms:.2f} ms, "
                     f"max {s.max_ms:.2f} ms ({s.n} intervals)")
        ax.legend(loc="upper right")
        hi = max(s.p99_ms * 1.5, s.nominal_ms * 2.0)
        bins = np.linspace(0.0, hi, 60).tolist()
        axh.hist(np.clip(s.period_ms, 0.0, hi), bins=bins, color="tab:blue")
        axh.set_yscale("log")
        axh.set_xlabel(f"{thread} period (ms, clipped at {hi:.0f})")
        axh.set_ylabel("count")
        axh.set_title(f"{thread} period histogram")
    axes[-2].set_xlabel("time since start (s)")
    if missing:
        fig.suptitle("not shown: " + "; ".join(missing), fontsize=7)
    return fig


# ------------------------------------------------------------------------------- IMU vs pilot (6-4)
def fig_roll_rate_aileron(p: Products) -> Figure:
    imu = _need(p.fd, "imu", 1, ("p_rad_s",))
    servo = _need(p.fd, "servo", 1, ("pilot1_us",))
    t_imu = p.fd.rel_s(imu["time_s"])
    t_srv = p.fd.rel_s(servo["time_s"])
    fig, (ax, ax2) = new_figure(2, height_in=2.3)
    rate_deg_s = np.degrees(np.asarray(imu["p_rad_s"], dtype=np.float64))
    ax.plot(t_imu, rate_deg_s, color="tab:blue", label="roll rate p")
    ax.set_ylabel("roll rate (deg/s)")
    ax.set_xlabel("time since start (s)")
    twin = ax.twinx()
    aileron = (np.asarray(servo["pilot1_us"], dtype=np.float64) - PULSE_CENTRE_US) / PULSE_HALF_RANGE_US
    twin.plot(t_srv, aileron, color="tab:red", label="pilot aileron")
    cmd = _col(servo, "cmd1_us")
    if cmd is not None and "auto_engaged" in (servo.dtype.names or ()):
        engaged = np.asarray(servo["auto_engaged"]) > 0
        if engaged.any():
            comp = np.where(engaged, (cmd - PULSE_CENTRE_US) / PULSE_HALF_RANGE_US, np.nan)
            twin.plot(t_srv, comp, color="tab:purple", linestyle="--", label="computer aileron")
    twin.set_ylabel("aileron command (-1..1)")
    twin.set_ylim(-1.1, 1.1)
    twin.grid(False)
    lines = ax.get_lines() + twin.get_lines()
    ax.legend(lines, [str(line.get_label()) for line in lines], loc="upper right")
    ax.set_title("roll rate against the pilot's aileron command")
    # Response at a glance: roll rate at each servo exchange against the command.
    p_at = interp_at(t_imu, rate_deg_s, t_srv)
    ok = np.isfinite(p_at)
    ax2.plot(aileron[ok], p_at[ok], ".", markersize=1.5, color="tab:blue")
    ax2.set_xlabel("pilot aileron command (-1..1)")
    ax2.set_ylabel("roll rate (deg/s)")
    ax2.set_title("roll rate against aileron (every servo exchange)")
    return fig


# ------------------------------------------------------------------------------- batteries (6-5)
def fig_batteries(p: Products) -> Figure:
    servo = _need(p.fd, "servo", 1, ("avionics_batt", "servo_batt"))
    t = p.fd.rel_s(servo["time_s"])
    fig, (ax, ax2) = new_figure(2, height_in=1.9, sharex=True)
    for a, col, label, colour in ((ax, "avionics_batt", "avionics battery", "tab:blue"),
                                  (ax2, "servo_batt", "servo battery", "tab:orange")):
        v = np.asarray(servo[col], dtype=np.float64)
        a.plot(t, v, color=colour, label=label)
        a.set_ylabel("level (raw, ~100 full)")
        a.set_title(f"{label}: start {v[0]:.0f}, end {v[-1]:.0f}, min {v.min():.0f}")
        a.legend(loc="lower left")
    ax2.set_xlabel("time since start (s)")
    return fig


# ------------------------------------------------------------------------------- position (6-6)
def fig_position_error(p: Products) -> Figure:
    gps, truth, est = p.gps, p.truth, p.estimate
    have = [name for name, tr in (("GPS", gps), ("truth", truth), ("estimate", est))
            if tr is not None and tr.n]
    if est is None and truth is None:
        raise MissingData("needs the estimator or SITL ground truth: "
                          + p.fd.why_missing("estimator", 1, ("north_m", "east_m", "down_m"))
                          + "; " + p.fd.why_missing("truth", 1, ("lat_deg", "lon_deg", "alt_m")))
    if len(have) < 2:
        raise MissingData(f"only {', '.join(have) or 'nothing'} to compare; "
                          + p.fd.why_missing("gps", 1, ("lat_deg", "lon_deg", "alt_m", "fix")))
    fig, (ax, ax2, ax3, ax4) = new_figure(4, height_in=2.0)
    styles = {"GPS": ("tab:blue", "-"), "truth": ("black", "--"), "estimate": ("tab:red", "-")}
    for name, tr in (("GPS", gps), ("truth", truth), ("estimate", est)):
        if tr is None or not tr.n:
            continue
        colour, ls = styles[name]
        ax.plot(tr.east_m, tr.north_m, color=colour, linestyle=ls, label=name)
        ax2.plot(tr.t_s, -tr.down_m, color=colour, linestyle=ls, label=name)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title("position: " + ", ".join(have) + (f" ({p.notes['estimate']})" if "estimate" in p.notes else ""))
    ax.legend(loc="best")
    ax2.set_ylabel("height (m)")
    ax2.set_xlabel("time since start (s)")
    ax2.legend(loc="best")
    pairs = []
    if truth is not None and truth.n:
        for name, tr in (("GPS", gps), ("estimate", est)):
            if tr is not None and tr.n:
                pairs.append((f"{name} - truth", tr, truth))
    if est is not None and est.n and gps is not None and gps.n:
        pairs.append(("estimate - GPS", est, gps))
    for label, a, ref in pairs:
        dn = a.north_m - interp_at(ref.t_s, ref.north_m, a.t_s)
        de = a.east_m - interp_at(ref.t_s, ref.east_m, a.t_s)
        dd = a.down_m - interp_at(ref.t_s, ref.down_m, a.t_s)
        horiz = np.hypot(dn, de)
        rms_h = math.sqrt(float(np.nanmean(horiz**2))) if np.isfinite(horiz).any() else math.nan
        rms_v = math.sqrt(float(np.nanmean(dd**2))) if np.isfinite(dd).any() else math.nan
        ax3.plot(a.t_s, horiz, label=f"{label} (rms {rms_h:.2f} m)")
        ax4.plot(a.t_s, -dd, label=f"{label} (rms {rms_v:.2f} m)")
    ax3.set_ylabel("horizontal error (m)")
    ax3.set_title("horizontal position error")
    ax3.legend(loc="upper right")
    ax4.set_ylabel("height error (m)")
    ax4.set_xlabel("time since start (s)")
    ax4.set_title("vertical position error")
    ax4.legend(loc="upper right")
    return fig


def fig_attitude(p: Products) -> Figure:
    est = _need(p.fd, "estimator", 1, ("roll_rad", "pitch_rad", "yaw_rad"))
    truth = p.fd.block("truth", 1, ("roll_rad", "pitch_rad", "yaw_rad"))
    t_est = p.fd.rel_s(est["time_s"])
    fig, axes = new_figure(4 if truth is not None else 3, height_in=1.8, sharex=True)
    for ax, col in zip(axes, ("roll_rad", "pitch_rad", "yaw_rad"), strict=False):
        ax.plot(t_est, np.degrees(np.asarray(est[col], dtype=np.float64)), color="tab:red",
                label="estimate")
        if truth is not None:
            ax.plot(p.fd.rel_s(truth["time_s"]), np.degrees(np.asarray(truth[col], dtype=np.float64)),
                    color="black", linestyle="--", label="truth")
        ax.set_ylabel(col.replace("_rad", " (deg)"))
        ax.legend(loc="upper right")
    axes[0].set_title("attitude estimate" + (" against SITL truth" if truth is not None else
                                             " (no ground truth in this flight)"))
    if truth is not None:
        ax = axes[3]
        t_tr = p.fd.rel_s(truth["time_s"])
        aligned = (np.asarray(est["aligned"]) > 0 if "aligned" in (est.dtype.names or ())
                   else np.ones(est.size, dtype=bool))
        for col in ("roll_rad", "pitch_rad", "yaw_rad"):
            ref = interp_angle_at(t_tr, np.asarray(truth[col], dtype=np.float64), t_est)
            err = np.degrees(np.asarray((np.asarray(est[col], dtype=np.float64) - ref + np.pi)
                                        % (2 * np.pi) - np.pi))
            err[~aligned] = np.nan
            rms = math.sqrt(float(np.nanmean(err**2))) if np.isfinite(err).any() else math.nan
            ax.plot(t_est, err, label=f"{col.replace('_rad', '')} (rms {rms:.2f} deg)")
        ax.set_ylabel("error (deg)")
        ax.set_title("estimate - truth" + ("" if aligned.all() else " (once the filter is aligned)"))
        ax.legend(loc="upper right")
    axes[-1].set_xlabel("time since start (s)")
    return fig


# ------------------------------------------------------------------------------- thread health
def _segments(t_s: np.ndarray) -> list[tuple[float, float]]:
    """Spans with records: a gap of five typical periods (at least 0.5 s) splits a span."""
    if t_s.size == 0:
        return []
    t = np.sort(t_s)
    if t.size == 1:
        return [(float(t[0]), 0.05)]
    dt = np.diff(t)
    gap = max(5.0 * float(np.median(dt)), 0.5)
    cuts = np.flatnonzero(dt > gap)
    starts = np.concatenate(([0], cuts + 1))
    ends = np.concatenate((cuts, [t.size - 1]))
    return [(float(t[a]), max(float(t[b] - t[a]), 0.05)) for a, b in zip(starts, ends, strict=True)]


def fig_thread_health(p: Products) -> Figure:
    present = [(name, st) for name, st in p.fd.logs.items() if st.present]
    if not present:
        raise MissingData(f"no log files in {p.fd.flight_dir}")
    threads = p.fd.run_summary.get("threads") if p.fd.run_summary else None
    n_axes = 3 if threads else 2
    fig, axes = new_figure(n_axes, height_in=2.2)
    ax = axes[0]
    labels = []
    for row, (name, st) in enumerate(present):
        labels.append(name)
        if st.log is not None:
            times = [s.time_ns for s in st.log.streams if s.n_records and s.kind == "block"]
            if not times:
                times = [s.time_ns for s in st.log.streams if s.n_records]
            if times:
                t = p.fd.rel_s(np.concatenate(times) / 1e9)
                ax.broken_barh(_segments(t), (row - 0.3, 0.6), color="tab:blue", alpha=0.6)
            begins = [p.fd.rel_s(np.array([m.time_ns / 1e9]))[0] for m in st.log.markers if m.kind == "begin"]
            ends = [p.fd.rel_s(np.array([m.time_ns / 1e9]))[0] for m in st.log.markers if m.kind == "end"]
            ax.plot(begins, [row] * len(begins), ">", color="tab:green", markersize=6)
            ax.plot(ends, [row] * len(ends), "s", color="tab:red", markersize=4)
    ax.set_yticks(range(len(labels)), [
        f"{name}\n({len(st.problems)} problem{'s' if len(st.problems) > 1 else ''})" if st.problems
        else name for name, st in present])
    for tick, (_, st) in zip(ax.get_yticklabels(), present, strict=True):
        if st.problems:
            tick.set_color("tab:red")
    ax.set_ylim(-0.7, len(labels) - 0.3)
    ax.set_xlabel("time since start (s)")
    ax.set_title("log activity: records (bars), Begin Data (>), End Data (squares)")
    ax2 = axes[1]
    restarts = [st.restarts for _, st in present]
    problems = [len(st.problems) for _, st in present]
    x = np.arange(len(present))
    ax2.bar(x - 0.2, restarts, width=0.4, label="restarts (extra Begin Data)", color="tab:orange")
    ax2.bar(x + 0.2, problems, width=0.4, label="log problems", color="tab:red")
    ax2.set_xticks(x, labels)
    ax2.set_ylabel("count")
    ax2.set_title("restarts and log problems per thread")
    ax2.legend(loc="upper right")
    if threads:
        ax3 = axes[2]
        names = [str(t.get("name", "?")) for t in threads]
        mean = [float(t.get("mean_step_us", 0.0) or 0.0) for t in threads]
        worst = [float(t.get("worst_step_us", math.nan) or math.nan) for t in threads]
        xs = np.arange(len(names))
        ax3.bar(xs - 0.2, mean, width=0.4, label="mean step", color="tab:blue")
        if np.isfinite(worst).any():
            ax3.bar(xs + 0.2, np.nan_to_num(worst), width=0.4, label="worst step", color="tab:purple")
        ax3.set_yscale("log")
        ax3.set_xticks(xs, names)
        ax3.set_ylabel("step time (us)")
        ax3.set_title("step-time statistics (summary.json)")
        ax3.legend(loc="upper right")
    return fig


@dataclass(frozen=True)
class FigureSpec:
    name: str  # file stem
    title: str
    thesis: str  # which thesis figure it redraws or extends
    build: Callable[[Products], Figure]


FIGURES: list[FigureSpec] = [
    FigureSpec("gps_fix", "GPS fix validity", "figure 6-1", fig_gps_fix),
    FigureSpec("gps_track", "GPS track and altitude", "figure 6-2", fig_gps_track),
    FigureSpec("gps_quality", "GPS DOPs, latency and standard deviations", "figure 6-3",
               fig_gps_quality),
    FigureSpec("periods", "Sample periods of the IMU, GPS and servo threads", "figures 6-3, 6-4",
               fig_periods),
    FigureSpec("roll_rate_aileron", "Roll rate against the pilot's aileron", "figure 6-4",
               fig_roll_rate_aileron),
    FigureSpec("batteries", "Battery levels", "figure 6-5", fig_batteries),
    FigureSpec("position_error", "Estimated, GPS and true position, and their errors", "figure 6-6",
               fig_position_error),
    FigureSpec("attitude", "Attitude estimate against truth", "new", fig_attitude),
    FigureSpec("thread_health", "Thread health: activity, restarts, log problems", "new",
               fig_thread_health),
]
