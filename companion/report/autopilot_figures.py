"""The report's figures of a flight beside a flight controller: its estimate against ours, the
link's clock sync, the attitude targets sent in GUIDED.

`AUTOPILOT_FIGURES` follows the shape of `figures.FIGURES` (a `FigureSpec` a figure, a builder
that raises `MissingData` with the reason) but is added to a report only when the flight has an
``autopilot.bin`` (`figures_for`): a flight without one has the figures and the "Missing" list
it always had. Apart from `figures` so that module keeps the figures every flight has; the
numbers come from `companion.report.autopilot`.
"""

from __future__ import annotations

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from companion.report.autopilot import (
    ATTITUDE,
    AUTOPILOT_LOG,
    AXES,
    AttitudeComparison,
    ClockSyncRecords,
    NotLogged,
    TargetRecords,
    attitude_comparison,
    clock_sync,
    has_autopilot_log,
    targets,
)
from companion.report.figures import FIGURES, FigureSpec, MissingData, Products, new_figure
from companion.report.flight import FlightData
from gcs_bridge.autopilot.link import FMT_ESTIMATE

__all__ = ["AUTOPILOT_FIGURES", "figures_for"]

GAP_S = 1.0
"""Targets further apart than this are drawn as separate stretches (GUIDED left and re-entered)."""


def _compared(p: Products) -> AttitudeComparison:
    try:
        return attitude_comparison(p.fd)
    except NotLogged as exc:
        raise MissingData(str(exc)) from None


def _deg(data: np.ndarray, col: str) -> np.ndarray:
    return np.degrees(np.asarray(data[col], dtype=np.float64))


def _rms_text(rms_deg: tuple[float, float, float] | None, k: int) -> str:
    return "-" if rms_deg is None else f"{rms_deg[k]:.2f}"


def fig_autopilot_attitude(p: Products) -> Figure:
    cmp = _compared(p)
    fd = p.fd
    ours = fd.block("estimator", 1, ATTITUDE)
    ap = fd.block(AUTOPILOT_LOG, FMT_ESTIMATE, ATTITUDE)
    truth = fd.block("truth", 1, ATTITUDE)
    assert ours is not None and ap is not None  # the comparison needed both
    fig, axes = new_figure(4, height_in=1.8, sharex=True)
    ours_rmse, ap_rmse = cmp.ours_rmse_deg, cmp.autopilot_rmse_deg
    for k, (ax, col, axis) in enumerate(zip(axes, ATTITUDE, AXES, strict=False)):
        ax.plot(fd.rel_s(ours["time_s"]), _deg(ours, col), color="tab:red", label="ours")
        ax.plot(fd.rel_s(ap["time_s"]), _deg(ap, col), color="tab:blue", label="autopilot")
        if truth is not None:
            ax.plot(fd.rel_s(truth["time_s"]), _deg(truth, col), color="black", linestyle="--",
                    label="truth")
            ax.set_title(f"{axis} RMSE against truth: ours {_rms_text(ours_rmse, k)} deg, "
                         f"autopilot {_rms_text(ap_rmse, k)} deg")
        ax.set_ylabel(f"{axis} (deg)")
        ax.legend(loc="upper right")
    if truth is None:
        axes[0].set_title("attitude: our estimate and the autopilot's (no ground truth in this "
                          "flight)")
    ax = axes[3]
    diff = np.degrees(cmp.diff_rad)
    for k, axis in enumerate(AXES):
        ax.plot(cmp.t_s, diff[:, k], label=f"{axis} (rms {cmp.rms_diff_deg[k]:.2f} deg)")
    ax.set_ylabel("ours - autopilot (deg)")
    ax.set_title(f"difference, on our {cmp.n} samples once our filter is aligned")
    ax.legend(loc="upper right")
    axes[-1].set_xlabel("time since start (s)")
    return fig


def fig_autopilot_clock(p: Products) -> Figure:
    try:
        s: ClockSyncRecords = clock_sync(p.fd)
    except NotLogged as exc:
        raise MissingData(str(exc)) from None
    fig, (ax, ax2, ax3) = new_figure(3, height_in=1.6, sharex=True)
    ax.plot(s.t_s, s.offset_change_ms, ".-", color="tab:blue", markersize=3,
            label="offset - first offset")
    unsynced = ~s.synced
    if unsynced.any():
        ax.plot(s.t_s[unsynced], s.offset_change_ms[unsynced], "x", color="tab:red",
                label="before the first round trip")
    for k, t in enumerate(s.reset_times_s):
        for a in (ax, ax2, ax3):
            a.axvline(float(t), color="tab:red", linestyle=":",
                      label="map restarted" if k == 0 and a is ax else None)
    ax.set_ylabel("offset change (ms)")
    ax.set_title(f"autopilot clock map: {s.n} round trips, {s.reset_count} restart"
                 f"{'' if s.reset_count == 1 else 's'}")
    ax.legend(loc="upper right")
    ax2.plot(s.t_s, s.drift_ppm, color="tab:purple", label="drift")
    ax2.set_ylabel("drift (ppm)")
    ax2.set_title(f"drift: last {s.drift_ppm[-1]:.2f} ppm")
    ax2.legend(loc="upper right")
    ax3.plot(s.t_s, s.latency_ms, color="tab:green", label="latency (one way)")
    ax3.plot(s.t_s, s.rtt_ms, color="tab:orange", linestyle="--", label="round trip")
    ax3.set_ylabel("ms")
    ax3.set_title(f"link latency: median {s.latency_median_ms:.2f} ms, round trip "
                  f"median {s.rtt_median_ms:.2f} ms")
    ax3.legend(loc="upper right")
    ax3.set_xlabel("time since start (s)")
    return fig


def _with_gaps(t_s: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A NaN between records further apart than GAP_S, so a line does not bridge them."""
    cut = np.flatnonzero(np.diff(t_s) > GAP_S) + 1
    return np.insert(t_s, cut, np.nan), np.insert(values, cut, np.nan)


def _plot(ax: Axes, t_s: np.ndarray, values: np.ndarray, colour: str, label: str) -> None:
    ax.plot(*_with_gaps(t_s, values), color=colour, label=label)


def fig_autopilot_targets(p: Products) -> Figure:
    try:
        s: TargetRecords = targets(p.fd)
    except NotLogged as exc:
        raise MissingData(str(exc)) from None
    fig, axes = new_figure(4, height_in=1.7, sharex=True)
    ours_rms = s.rms_from_target_deg(s.ours_rad)
    ap_rms = s.rms_from_target_deg(s.autopilot_rad)
    target_deg, ours_deg, ap_deg = (np.degrees(a) for a in (s.target_rad, s.ours_rad,
                                                             s.autopilot_rad))
    for k, (ax, axis) in enumerate(zip(axes, AXES, strict=False)):
        _plot(ax, s.t_s, target_deg[:, k], "tab:green", "target")
        _plot(ax, s.t_s, ours_deg[:, k], "tab:red", "ours")
        _plot(ax, s.t_s, ap_deg[:, k], "tab:blue", "autopilot")
        ax.set_ylabel(f"{axis} (deg)")
        ax.set_title(f"{axis}: estimate - target rms, ours {ours_rms[k]:.2f} deg, "
                     f"autopilot {ap_rms[k]:.2f} deg")
        ax.legend(loc="upper right")
    _plot(axes[3], s.t_s, s.thrust, "tab:gray", "thrust")
    axes[3].set_ylabel("thrust (0..1)")
    axes[3].set_title(f"{s.n} attitude targets sent in GUIDED over {s.span_s:.1f} s")
    axes[3].legend(loc="upper right")
    axes[-1].set_xlabel("time since start (s)")
    return fig


AUTOPILOT_FIGURES: list[FigureSpec] = [
    FigureSpec("autopilot_attitude", "Our attitude estimate against the autopilot's", "new",
               fig_autopilot_attitude),
    FigureSpec("autopilot_clock", "Autopilot link clock map: offset, drift, latency", "new",
               fig_autopilot_clock),
    FigureSpec("autopilot_targets", "Attitude targets sent in GUIDED against the estimates", "new",
               fig_autopilot_targets),
]


def figures_for(fd: FlightData) -> list[FigureSpec]:
    """Every figure of a report of `fd`: `FIGURES`, and `AUTOPILOT_FIGURES` when the flight has
    an ``autopilot.bin``."""
    return FIGURES + (AUTOPILOT_FIGURES if has_autopilot_log(fd) else [])
