"""What every log reader hands the replay runner: IMU, GPS and reference series as arrays.

Kept apart from the readers so that each reader (`dataflash`, `ulog`, `tlog`) and the runner
depend on these types only, never on one another. Body axes are FRD and the earth frame NED in
every source (PX4, ArduPilot and MAVLink all use them), so nothing here converts axes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


class LogReadError(Exception):
    """A log that cannot be read (or only in part): names the file, and the byte offset if known."""

    def __init__(self, path: Path | str, message: str, offset: int | None = None) -> None:
        self.path = Path(path)
        self.message = message
        self.offset = offset
        where = f" at byte offset {offset}" if offset is not None else ""
        super().__init__(f"{self.path}: {message}{where}")


@dataclass
class ImuSeries:
    """IMU samples: body rates (rad/s) and specific force (m/s^2), FRD, log time in us."""

    t_us: IntArray
    gyro_rad_s: FloatArray
    accel_m_s2: FloatArray
    source: str


@dataclass
class GpsSeries:
    """GPS solutions; NaN where the receiver did not say. `fix` is this project's code
    (0 none, 1 GPS, 2 DGPS, 3 RTK): a 2-D fix or less is 0, since the filter needs an altitude."""

    t_us: IntArray
    lat_deg: FloatArray
    lon_deg: FloatArray
    alt_m: FloatArray
    fix: IntArray
    sats: FloatArray
    hdop: FloatArray
    h_std_m: FloatArray
    v_std_m: FloatArray
    vn_m_s: FloatArray
    ve_m_s: FloatArray
    vd_m_s: FloatArray
    speed_m_s: FloatArray
    course_deg: FloatArray
    source: str

    def __len__(self) -> int:
        return len(self.t_us)

    @property
    def valid(self) -> npt.NDArray[np.bool_]:
        """Fixes the estimator can use: 3-D or better, finite and not at (0, 0)."""
        return ((self.fix > 0) & np.isfinite(self.lat_deg) & np.isfinite(self.lon_deg)
                & np.isfinite(self.alt_m) & ((self.lat_deg != 0.0) | (self.lon_deg != 0.0)))


@dataclass
class AttitudeSeries:
    """One attitude estimate of the flight controller (Z-Y-X Euler angles, rad, NED)."""

    name: str
    t_us: IntArray
    roll_rad: FloatArray
    pitch_rad: FloatArray
    yaw_rad: FloatArray


@dataclass
class TemperatureSeries:
    """The IMU's temperature (C): the filter lets its biases move while the part warms
    (``Eskf.set_temperature``), as the flight thread does from the IMU's slow block."""

    t_us: IntArray
    temperature_c: FloatArray
    source: str


@dataclass
class SkippedRegion:
    """Bytes a reader could not use: where (offset, length) and what was there or why.

    A cut-short last message is one of these too (`tail` True): it is how logs end when the
    power goes, so it is reported but never refused unless the reading is strict."""

    offset: int
    length: int
    what: str
    tail: bool = False

    def describe(self) -> str:
        return f"{self.what} at byte offset {self.offset} ({self.length} byte(s) skipped)"


@dataclass
class FlightLog:
    """What a replay needs from a log, whatever its format.

    `notes` are the reading notes the summary shows (byte offsets of what was skipped, the IMU
    and GPS instances chosen and why); `damage` is one line on what was skipped in the middle
    of the file (None for a whole file or one that only ends inside its last message);
    `skipped` every region in detail; `available_references` what attitude estimates the log
    holds, by name, whether or not they could be read."""

    path: Path
    kind: str  # "px4-ulog", "ardupilot-dataflash" or "mavlink-tlog"
    imu: ImuSeries
    gps: GpsSeries | None
    references: list[AttitudeSeries]
    notes: list[str] = field(default_factory=list)
    damage: str | None = None
    info: dict[str, Any] = field(default_factory=dict)
    temperature: TemperatureSeries | None = None  # None: the log has none
    skipped: list[SkippedRegion] = field(default_factory=list)
    available_references: list[str] = field(default_factory=list)


TEMPERATURE_RANGE_C = (-60.0, 130.0)
"""Readings outside this are a sensor's "not available" code or garbage, never a part's
temperature (the MEMS parts' operating range is -40..85 C)."""


def temperature_series(t_us: npt.ArrayLike, temp_c: npt.ArrayLike, source: str
                       ) -> TemperatureSeries | None:
    """The plausible readings of a temperature column, or None when there are none."""
    t = np.asarray(t_us, dtype=np.int64)
    c = np.asarray(temp_c, dtype=float)
    lo, hi = TEMPERATURE_RANGE_C
    ok = np.isfinite(c) & (c >= lo) & (c <= hi)
    if not ok.any() or not np.any(c[ok] != 0.0):  # all zero: a field the sender never filled
        return None
    return TemperatureSeries(t[ok], c[ok], source)


def nan_array(n: int) -> FloatArray:
    return np.full(n, np.nan)


def fix_code(fix_type: npt.ArrayLike) -> IntArray:
    """PX4 fix_type / ArduPilot GPS Status / MAVLink GPS_FIX_TYPE (3 3-D, 4 DGPS, 5 RTK float,
    6 RTK fixed) -> this project's fix code."""
    f = np.asarray(fix_type, dtype=np.int64)
    return np.select([f >= 5, f == 4, f == 3], [3, 2, 1], 0).astype(np.int64)


def damage_line(skipped: list[SkippedRegion]) -> str | None:
    """One line on what was skipped before the end of the file, for `FlightLog.damage`."""
    inner = [s for s in skipped if not s.tail]
    if not inner:
        return None
    total = sum(s.length for s in inner)
    first = inner[0].describe()
    more = f"; {len(inner) - 1} more region(s)" if len(inner) > 1 else ""
    return f"{total} damaged byte(s) skipped by resynchronising: {first}{more}"


def refuse_if_strict(path: Path, fmt: str, skipped: list[SkippedRegion], strict: bool) -> None:
    """`--strict`: any skipped byte, even a cut-short last message, is a `LogReadError`."""
    if strict and skipped:
        s = skipped[0]
        raise LogReadError(path, f"{fmt}: {s.what} ({s.length} byte(s); strict reading refuses "
                                 "damage, drop --strict to read what is whole)", s.offset)


def region_notes(skipped: list[SkippedRegion], limit: int = 10) -> list[str]:
    """Reading notes for the summary: each skipped region with its offset, at most `limit`."""
    notes = [("log ends inside its last message: " if s.tail else "damaged data skipped: ")
             + s.describe() for s in skipped[:limit]]
    if len(skipped) > limit:
        rest = skipped[limit:]
        notes.append(f"{len(rest)} more damaged region(s), {sum(s.length for s in rest)} "
                     "byte(s) in all")
    return notes
