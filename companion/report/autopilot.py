"""The autopilot's own estimate beside ours: the numbers the report compares them with.

Beside a flight controller (docs/autopilot.md) the link writes ``autopilot.bin``: the
autopilot's own attitude estimate (format 2), the map of its clock onto ours (format 1) and the
attitude targets the companion sent it in GUIDED (format 5). This module reads those formats and
computes what the report shows of them; the figures are drawn in `autopilot_figures` and the
summary table prints `AutopilotSummary`. A flight without ``autopilot.bin`` gets none of it, so
its report is the one it always was. Apart from `analysis` because it is one subject, a flight
controller's, that most flights do not have.

Angles are compared on our estimate's times, once our filter is aligned and within the span of
the autopilot's records: the autopilot's angles and the truth are interpolated there (through
their unwrapped form), so the difference, our error and the autopilot's error are taken over
the same instants.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.core.mathutil import wrap_pi
from companion.report.analysis import interp_angle_at
from companion.report.flight import FlightData
from gcs_bridge.autopilot.link import FMT_COMMAND, FMT_ESTIMATE, FMT_TSYNC

__all__ = [
    "AUTOPILOT_LOG",
    "ATTITUDE",
    "AXES",
    "AttitudeComparison",
    "AutopilotSummary",
    "ClockSyncRecords",
    "NotLogged",
    "TargetRecords",
    "attitude_comparison",
    "clock_sync",
    "has_autopilot_log",
    "rms",
    "summarise_autopilot",
    "targets",
]

AUTOPILOT_LOG = "autopilot"
ATTITUDE = ("roll_rad", "pitch_rad", "yaw_rad")
AXES = ("roll", "pitch", "yaw")
SYNC_COLUMNS = ("offset_ms", "drift_ppm", "latency_ms", "rtt_ms", "synced", "resets")
TARGET_COLUMNS = ("roll_sp_rad", "pitch_sp_rad", "yaw_sp_rad", "thrust")

Angles = tuple[float, float, float]


class NotLogged(LookupError):
    """What a comparison needs is not in the flight; the message names the file and format."""


def has_autopilot_log(fd: FlightData) -> bool:
    """The flight has an ``autopilot.bin`` (readable or not: a damaged one is reported)."""
    st = fd.status(AUTOPILOT_LOG)
    return st is not None and st.present


def rms(values: np.ndarray) -> float:
    """Root mean square of the finite values; NaN when there are none."""
    v = np.asarray(values, dtype=np.float64)
    ok = np.isfinite(v)
    return math.sqrt(float(np.mean(v[ok] ** 2))) if ok.any() else math.nan


def _rms_deg(err_rad: np.ndarray) -> Angles:
    deg = np.degrees(err_rad)
    return rms(deg[:, 0]), rms(deg[:, 1]), rms(deg[:, 2])


def _need(fd: FlightData, name: str, index: int, columns: tuple[str, ...]) -> np.ndarray:
    data = fd.block(name, index, columns)
    if data is None:
        raise NotLogged(fd.why_missing(name, index, columns))
    return data


def _angles_at(fd: FlightData, data: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw of `data` (a block with those columns) at flight times `t_s`, (n, 3)."""
    t_src = fd.rel_s(data["time_s"])
    out = np.full((t_s.size, 3), np.nan)
    for k, col in enumerate(ATTITUDE):
        a = np.asarray(data[col], dtype=np.float64)
        ok = np.isfinite(a)  # a NaN would spread through the unwrapping to every later angle
        if np.count_nonzero(ok) >= 2:
            out[:, k] = interp_angle_at(t_src[ok], a[ok], t_s)
    return out


def _aligned_estimate(fd: FlightData) -> np.ndarray:
    """Our attitude estimate's rows once the filter says it is aligned (all rows when the log
    has no ``aligned`` column)."""
    est = _need(fd, "estimator", 1, ATTITUDE)
    if "aligned" in (est.dtype.names or ()):
        est = est[np.asarray(est["aligned"]) > 0]
        if est.size == 0:
            raise NotLogged("estimator.bin: the filter never reported itself aligned")
    return est


@dataclass(frozen=True)
class _Series:
    """Rows at flight times `t_s` (seconds since the start of the flight), at least one."""

    t_s: np.ndarray

    @property
    def n(self) -> int:
        return int(self.t_s.size)

    @property
    def span_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])


@dataclass(frozen=True)
class AttitudeComparison(_Series):
    """Our attitude and the autopilot's (and the truth's) on our estimate's times, radians."""

    ours_rad: np.ndarray  # (n, 3) roll, pitch, yaw
    autopilot_rad: np.ndarray  # (n, 3), interpolated at t_s
    truth_rad: np.ndarray | None  # (n, 3), interpolated at t_s; None without truth.bin

    @property
    def diff_rad(self) -> np.ndarray:
        """Ours minus the autopilot's, wrapped to [-pi, pi)."""
        return np.asarray(wrap_pi(self.ours_rad - self.autopilot_rad))

    @property
    def rms_diff_deg(self) -> Angles:
        return _rms_deg(self.diff_rad)

    @property
    def ours_rmse_deg(self) -> Angles | None:
        if self.truth_rad is None:
            return None
        return _rms_deg(np.asarray(wrap_pi(self.ours_rad - self.truth_rad)))

    @property
    def autopilot_rmse_deg(self) -> Angles | None:
        if self.truth_rad is None:
            return None
        return _rms_deg(np.asarray(wrap_pi(self.autopilot_rad - self.truth_rad)))


def attitude_comparison(fd: FlightData) -> AttitudeComparison:
    """Ours against the autopilot's attitude; raises NotLogged naming what is missing."""
    ours = _aligned_estimate(fd)
    ap = _need(fd, AUTOPILOT_LOG, FMT_ESTIMATE, ATTITUDE)
    t = fd.rel_s(ours["time_s"])
    ap_at = _angles_at(fd, ap, t)
    keep = np.isfinite(ap_at).all(axis=1)
    if not keep.any():
        raise NotLogged("our estimate and the autopilot's (autopilot.bin format 2) do not overlap "
                        "in time")
    ours_rad = np.column_stack([np.asarray(ours[c], dtype=np.float64) for c in ATTITUDE])
    truth = fd.block("truth", 1, ATTITUDE)
    truth_at = _angles_at(fd, truth, t[keep]) if truth is not None else None
    return AttitudeComparison(t[keep], ours_rad[keep], ap_at[keep], truth_at)


@dataclass(frozen=True)
class ClockSyncRecords(_Series):
    """The link's map of the autopilot's clock (autopilot.bin format 1), one row a round trip."""

    offset_ms: np.ndarray  # runtime minus autopilot clock
    drift_ppm: np.ndarray
    latency_ms: np.ndarray
    rtt_ms: np.ndarray
    synced: np.ndarray  # bool
    resets: np.ndarray  # the link's running count of restarts of the map

    @property
    def offset_change_ms(self) -> np.ndarray:
        """The offset relative to the first record's: what drift and resets move."""
        return self.offset_ms - self.offset_ms[0]

    @property
    def latency_median_ms(self) -> float:
        return float(np.nanmedian(self.latency_ms))

    @property
    def rtt_median_ms(self) -> float:
        return float(np.nanmedian(self.rtt_ms))

    @property
    def reset_count(self) -> int:
        """Restarts of the map during the flight (increases of the running count)."""
        return int(np.sum(np.clip(np.diff(self.resets), 0, None)))

    @property
    def reset_times_s(self) -> np.ndarray:
        return self.t_s[1:][np.diff(self.resets) > 0]


def clock_sync(fd: FlightData) -> ClockSyncRecords:
    data = _need(fd, AUTOPILOT_LOG, FMT_TSYNC, SYNC_COLUMNS)

    def col(name: str) -> np.ndarray:
        return np.asarray(data[name], dtype=np.float64)

    return ClockSyncRecords(fd.rel_s(data["time_s"]), col("offset_ms"), col("drift_ppm"),
                            col("latency_ms"), col("rtt_ms"), col("synced") > 0, col("resets"))


@dataclass(frozen=True)
class TargetRecords(_Series):
    """Attitude targets sent to the autopilot in GUIDED (autopilot.bin format 5), with both
    estimates at the time each was sent (NaN where an estimate has no value then)."""

    target_rad: np.ndarray  # (n, 3) roll, pitch, yaw set-points
    thrust: np.ndarray
    ours_rad: np.ndarray  # (n, 3)
    autopilot_rad: np.ndarray  # (n, 3)

    def rms_from_target_deg(self, attitude_rad: np.ndarray) -> Angles:
        """RMS of an estimate minus the target, per axis (degrees)."""
        return _rms_deg(np.asarray(wrap_pi(attitude_rad - self.target_rad)))


def targets(fd: FlightData) -> TargetRecords:
    data = fd.block(AUTOPILOT_LOG, FMT_COMMAND, TARGET_COLUMNS)
    if data is None:
        raise NotLogged(fd.why_missing(AUTOPILOT_LOG, FMT_COMMAND, TARGET_COLUMNS)
                        + " (no attitude target was sent: the autopilot was not in GUIDED with "
                        "the control law engaged)")
    t = fd.rel_s(data["time_s"])
    target = np.column_stack([np.asarray(data[c], dtype=np.float64) for c in TARGET_COLUMNS[:3]])
    try:
        ours = _angles_at(fd, _aligned_estimate(fd), t)
    except NotLogged:
        ours = np.full((t.size, 3), np.nan)
    ap = fd.block(AUTOPILOT_LOG, FMT_ESTIMATE, ATTITUDE)
    ap_at = _angles_at(fd, ap, t) if ap is not None else np.full((t.size, 3), np.nan)
    return TargetRecords(t, target, np.asarray(data["thrust"], dtype=np.float64), ours, ap_at)


@dataclass(frozen=True)
class AutopilotSummary:
    """What the summary table says of the autopilot; each part None with the reason when absent."""

    attitude: AttitudeComparison | None
    attitude_missing: str | None
    sync: ClockSyncRecords | None
    sync_missing: str | None
    targets: TargetRecords | None


def summarise_autopilot(fd: FlightData) -> AutopilotSummary | None:
    """None for a flight without ``autopilot.bin``."""
    if not has_autopilot_log(fd):
        return None
    att: AttitudeComparison | None = None
    sync: ClockSyncRecords | None = None
    sent: TargetRecords | None = None
    att_missing = sync_missing = None
    try:
        att = attitude_comparison(fd)
    except NotLogged as exc:
        att_missing = str(exc)
    try:
        sync = clock_sync(fd)
    except NotLogged as exc:
        sync_missing = str(exc)
    try:
        sent = targets(fd)
    except NotLogged:
        pass  # no GUIDED: nothing to say in the table
    return AutopilotSummary(att, att_missing, sync, sync_missing, sent)

