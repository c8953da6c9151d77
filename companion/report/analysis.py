"""The numbers behind the figures: sample periods, local positions, errors, log statistics.

Kept apart from the plotting so the live view, the replay and the tests use the same numbers
the report draws.
"""

from __future__ import annotations

import logging
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.core.geo import NedFrame
from companion.estimation.quat import quat_from_euler, wrap_pi
from companion.logs import Stream
from companion.report.flight import FlightData, LogStatus

__all__ = [
    "PERIOD_SOURCES",
    "PeriodStats",
    "Track",
    "counter_gaps",
    "csv_size_bytes",
    "estimate_track",
    "gps_frame",
    "gps_track",
    "interp_at",
    "period_stats",
    "quat_xyzw",
    "truth_track",
    "wrap_pi",
]

log = logging.getLogger(__name__)

#: thread -> (log, format index, nominal period in ms) of the sample-period analysis
PERIOD_SOURCES: dict[str, tuple[str, int, float]] = {
    "imu": ("imu", 1, 10.0),
    "gps": ("gps", 1, 100.0),
    "servo": ("servo", 1, 20.0),
}


@dataclass(frozen=True)
class PeriodStats:
    """Intervals between consecutive records of one stream (milliseconds)."""

    t_s: np.ndarray  # time of the later record of each interval, since flight start
    period_ms: np.ndarray
    mean_ms: float
    p99_ms: float
    max_ms: float
    nominal_ms: float

    @property
    def n(self) -> int:
        return int(self.period_ms.size)


def period_stats(t_s: np.ndarray, nominal_ms: float = math.nan) -> PeriodStats | None:
    """Sample periods of a time series; None with fewer than two samples."""
    t = np.asarray(t_s, dtype=np.float64)
    if t.size < 2:
        return None
    period = np.diff(t) * 1e3
    return PeriodStats(
        t_s=t[1:],
        period_ms=period,
        mean_ms=float(period.mean()),
        p99_ms=float(np.percentile(period, 99)),
        max_ms=float(period.max()),
        nominal_ms=nominal_ms,
    )


def counter_gaps(counter: np.ndarray, modulo: int) -> int:
    """Frames missing from a wrapping counter (device or log losses): steps other than +1."""
    c = np.asarray(counter, dtype=np.int64)
    if c.size < 2:
        return 0
    step = np.mod(np.diff(c), modulo)
    return int(np.sum(np.where(step == 0, 0, step - 1)))


@dataclass(frozen=True)
class Track:
    """Positions in the flight's local NED frame (metres) with their times."""

    t_s: np.ndarray
    north_m: np.ndarray
    east_m: np.ndarray
    down_m: np.ndarray

    @property
    def n(self) -> int:
        return int(self.t_s.size)

    def ned(self) -> np.ndarray:
        return np.column_stack((self.north_m, self.east_m, self.down_m))


def _valid_geodetic(lat: np.ndarray, lon: np.ndarray, alt: np.ndarray) -> np.ndarray:
    return (np.isfinite(lat) & np.isfinite(lon) & np.isfinite(alt)
            & (np.abs(lat) <= 90.0) & (lon >= -180.0) & (lon <= 360.0)
            & (alt > -1.0e5) & (alt < 1.0e6) & ~((lat == 0.0) & (lon == 0.0)))


def gps_frame(fd: FlightData) -> NedFrame | None:
    """The flight's local frame: at the first valid GPS fix (as the thesis plotted it), else at
    the first truth point (a SITL flight whose GPS log is missing)."""
    gps = fd.block("gps", 1, ("lat_deg", "lon_deg", "alt_m", "fix"))
    if gps is not None:
        ok = (gps["fix"] > 0) & _valid_geodetic(gps["lat_deg"], gps["lon_deg"], gps["alt_m"])
        if ok.any():
            k = int(np.argmax(ok))
            return NedFrame(float(gps["lat_deg"][k]), float(gps["lon_deg"][k]), float(gps["alt_m"][k]))
    truth = fd.block("truth", 1, ("lat_deg", "lon_deg", "alt_m"))
    if truth is not None:
        ok = _valid_geodetic(truth["lat_deg"], truth["lon_deg"], truth["alt_m"])
        if ok.any():
            k = int(np.argmax(ok))
            return NedFrame(float(truth["lat_deg"][k]), float(truth["lon_deg"][k]),
                            float(truth["alt_m"][k]))
    return None


def _to_track(frame: NedFrame, t_s: np.ndarray, lat: np.ndarray, lon: np.ndarray,
              alt: np.ndarray) -> Track:
    ok = _valid_geodetic(lat, lon, alt)
    pts = [frame.to_ned(float(a), float(b), float(c))
           for a, b, c in zip(lat[ok], lon[ok], alt[ok], strict=True)]
    ned = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    return Track(np.asarray(t_s, dtype=np.float64)[ok], ned[:, 0], ned[:, 1], ned[:, 2])


def gps_track(fd: FlightData, frame: NedFrame, *, valid_only: bool = True) -> Track | None:
    """GPS positions (fixes only, by default) in the flight frame."""
    gps = fd.block("gps", 1, ("lat_deg", "lon_deg", "alt_m", "fix"))
    if gps is None:
        return None
    sel = gps["fix"] > 0 if valid_only else np.ones(gps.size, dtype=bool)
    g = gps[sel]
    return _to_track(frame, fd.rel_s(g["time_s"]), g["lat_deg"], g["lon_deg"], g["alt_m"])


def truth_track(fd: FlightData, frame: NedFrame) -> Track | None:
    """SITL truth through the same geodetic conversion as the GPS, so only errors remain."""
    truth = fd.block("truth", 1, ("lat_deg", "lon_deg", "alt_m"))
    if truth is None:
        return None
    return _to_track(frame, fd.rel_s(truth["time_s"]), truth["lat_deg"], truth["lon_deg"],
                     truth["alt_m"])


ESTIMATE_POSITION = ("north_m", "east_m", "down_m")
ESTIMATE_ATTITUDE = ("roll_rad", "pitch_rad", "yaw_rad")


def _home_from_run(fd: FlightData) -> tuple[float, float, float] | None:
    """`vehicle.home` of the configuration in run.json ("lat,lon,alt"), when one was set."""
    try:
        text = str(fd.run_info["config"]["vehicle"]["home"])  # type: ignore[index]
        lat, lon, alt = (float(v) for v in text.split(","))
    except (KeyError, TypeError, ValueError):
        return None
    ok = _valid_geodetic(np.array([lat]), np.array([lon]), np.array([alt]))[0]
    return (lat, lon, alt) if ok else None


def _fix_before(fd: FlightData, t_abs_s: float) -> tuple[float, float, float] | None:
    """The last valid GPS fix logged at or before `t_abs_s` (else the first valid one)."""
    gps = fd.block("gps", 1, ("lat_deg", "lon_deg", "alt_m", "fix"))
    if gps is None:
        return None
    ok = (gps["fix"] > 0) & _valid_geodetic(gps["lat_deg"], gps["lon_deg"], gps["alt_m"])
    if not ok.any():
        return None
    before = np.flatnonzero(ok & (gps["time_s"] <= t_abs_s))
    k = int(before[-1]) if before.size else int(np.flatnonzero(ok)[0])
    return float(gps["lat_deg"][k]), float(gps["lon_deg"][k]), float(gps["alt_m"][k])


def estimate_track(fd: FlightData, frame: NedFrame) -> tuple[Track, str] | None:
    """Estimated positions moved into the flight frame, and a note on how.

    The estimator integrates from its own origin. In order of preference that origin is: the
    one it logs (origin_lat_deg, origin_lon_deg, origin_alt_m columns), the configured
    ``vehicle.home`` in run.json, or the GPS fix it started from, i.e. the last fix logged before
    its first state. Rows before the filter reports itself aligned (``aligned`` column) are left
    out: they are the start-up transient, not the estimate.
    """
    est = fd.block("estimator", 1, ESTIMATE_POSITION)
    if est is None:
        return None
    names = est.dtype.names or ()
    if "aligned" in names:
        est = est[np.asarray(est["aligned"]) > 0]
        if est.size == 0:
            return None
    n, e, d = (np.asarray(est[c], dtype=np.float64).copy() for c in ESTIMATE_POSITION)
    origin_cols = ("origin_lat_deg", "origin_lon_deg", "origin_alt_m")
    if all(c in names for c in origin_cols):
        lat, lon, alt = (np.asarray(est[c], dtype=np.float64) for c in origin_cols)
        # Origins may be re-anchored in flight: offset each sample by its own origin.
        off = np.full((est.size, 3), np.nan)
        uniq, inverse = np.unique(np.column_stack((lat, lon, alt)), axis=0, return_inverse=True)
        for k, (a, b, c) in enumerate(uniq):
            if _valid_geodetic(np.array([a]), np.array([b]), np.array([c]))[0]:
                off[inverse.reshape(-1) == k] = frame.to_ned(float(a), float(b), float(c))
        n, e, d = n + off[:, 0], e + off[:, 1], d + off[:, 2]
        note = "estimator origin from its log"
    else:
        home = _home_from_run(fd)
        note = "estimator origin: vehicle.home from run.json"
        if home is None:
            first = fd.block("estimator", 1, ESTIMATE_POSITION)
            home = _fix_before(fd, float(first["time_s"][0])) if first is not None else None
            note = "estimator origin: the GPS fix before its first state"
        if home is None:
            return None
        dn, de, dd = frame.to_ned(*home)
        n, e, d = n + dn, e + de, d + dd
    ok = np.isfinite(n) & np.isfinite(e) & np.isfinite(d)
    t = fd.rel_s(est["time_s"])
    return Track(t[ok], n[ok], e[ok], d[ok]), note


def interp_at(t_src: np.ndarray, values: np.ndarray, t_dst: np.ndarray) -> np.ndarray:
    """Linear interpolation of `values` at `t_dst`; NaN outside the source's time span."""
    t_src = np.asarray(t_src, dtype=np.float64)
    out = np.full(np.shape(t_dst), np.nan)
    if t_src.size < 2:
        return out
    order = np.argsort(t_src, kind="stable")
    ts, vs = t_src[order], np.asarray(values, dtype=np.float64)[order]
    inside = (t_dst >= ts[0]) & (t_dst <= ts[-1])
    out[inside] = np.interp(t_dst[inside], ts, vs)
    return out


def interp_angle_at(t_src: np.ndarray, angle_rad: np.ndarray, t_dst: np.ndarray) -> np.ndarray:
    """Interpolation of an angle through its unwrapped form, result wrapped to [-pi, pi)."""
    order = np.argsort(np.asarray(t_src, dtype=np.float64), kind="stable")
    unwrapped = np.unwrap(np.asarray(angle_rad, dtype=np.float64)[order])
    return np.asarray(wrap_pi(interp_at(np.asarray(t_src)[order], unwrapped, t_dst)))


def quat_xyzw(roll_rad: np.ndarray, pitch_rad: np.ndarray, yaw_rad: np.ndarray) -> np.ndarray:
    """Body-to-NED quaternions in rerun's (x, y, z, w) order."""
    q = quat_from_euler(roll_rad, pitch_rad, yaw_rad)
    return np.asarray(np.concatenate((q[..., 1:], q[..., :1]), axis=-1))


CSV_SAMPLE_RECORDS = 20_000


def _head(stream: Stream, k: int) -> Stream:
    """The first `k` records of a stream, as a stream."""
    return stream.head(k)


def csv_size_bytes(st: LogStatus, sample_records: int = CSV_SAMPLE_RECORDS) -> tuple[int, bool] | None:
    """Bytes the log takes as CSV and whether that is an estimate.

    Measured by converting into a scratch directory with the project's converter; a format with
    more than `sample_records` records is converted for its first `sample_records` only and
    scaled, which keeps a long flight's report fast (the CSV line length hardly varies).
    """
    if st.log is None:
        return None
    from companion.logs.convert import write_stream_csv

    total, estimated = 0, False
    try:
        with tempfile.TemporaryDirectory(prefix="companion-report-") as tmp:
            out = Path(tmp) / "stream.csv"
            for stream in st.log.streams:
                n = stream.n_records
                part = stream if n <= sample_records else _head(stream, sample_records)
                write_stream_csv(part, st.log.markers, out, source=st.path.name)
                size = out.stat().st_size
                if part is not stream:
                    size = round(size * n / sample_records)
                    estimated = True
                total += size
    except (OSError, ValueError) as exc:
        log.warning("%s: CSV size not measured: %s", st.path, exc)
        return None
    return total, estimated
