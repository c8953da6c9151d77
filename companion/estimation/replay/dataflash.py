"""ArduPilot DataFlash logs (`.bin`) of every generation into a `FlightLog`.

Nothing here knows a particular firmware: types and fields are found by name in the log's own
FMT table (`dfwalk`), so ArduCopter 3.1 (IMU/IMU2 with TimeMS, GPS dated by GPS week and
millisecond with the boot time in `T`) and ArduPilot 4.x (one IMU type with an instance field
`I`, TimeUS everywhere, EKF3's XKF1 with its core `C`) read the same way. What is read: the IMU
(instance chosen below), GPS, and the attitude estimates ATT, AHR2, XKF1 (EKF3), NKF1 (EKF2)
and EKF1 (the EKF of ArduPilot 3.2-3.4) as references.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from companion.estimation.replay.dfwalk import DfFormat, DfWalk, walk_dataflash_file
from companion.estimation.replay.series import (
    AttitudeSeries,
    FlightLog,
    GpsSeries,
    ImuSeries,
    LogReadError,
    damage_line,
    fix_code,
    nan_array,
    refuse_if_strict,
    region_notes,
    temperature_series,
)

log = logging.getLogger(__name__)

KIND = "ardupilot-dataflash"
FORMAT = "ArduPilot DataFlash"
IMU_TYPES = {"IMU": 0, "IMU2": 1, "IMU3": 2}  # name: instance when the type has no `I` field
GPS_TYPES = {"GPS": 0, "GPS2": 1}
REFERENCES = ("ATT", "AHR2", "XKF1", "NKF1", "EKF1")
WANTED = frozenset([*IMU_TYPES, *GPS_TYPES, *REFERENCES])
MINOR_SHARE = 0.5
"""An IMU instance with less than this share of the busiest one's samples is not the default:
it was logged at a lower rate or only for part of the flight."""

Block = tuple[DfFormat, np.ndarray]


def _times_us(fmt: DfFormat, data: np.ndarray) -> np.ndarray | None:
    """A message's boot time in us: TimeUS, else TimeMS; a GPS message whose TimeMS is the GPS
    time of week (it also has Week/GWk) is dated by its `T` (boot ms) instead."""
    t = fmt.column(data, "TimeUS")
    if t is not None:
        return t.astype(np.int64)
    gps_week = "Week" in fmt.columns or "GWk" in fmt.columns
    if gps_week:
        t = fmt.column(data, "T")
        return None if t is None else (t * 1000).astype(np.int64)
    t = fmt.column(data, "TimeMS")
    return None if t is None else (t * 1000).astype(np.int64)


def _instance(fmt: DfFormat, data: np.ndarray, default: int, field: str = "I") -> np.ndarray:
    v = fmt.column(data, field)
    return np.full(len(data), default, dtype=np.int64) if v is None else v.astype(np.int64)


def _col(fmt: DfFormat, data: np.ndarray, name: str) -> np.ndarray:
    v = fmt.column(data, name)
    return nan_array(len(data)) if v is None else v


def _imu(path: Path, w: DfWalk, imu_instance: int | None, notes: list[str]
         ) -> tuple[ImuSeries, np.ndarray, str, list[int]]:
    parts: dict[int, list[np.ndarray]] = {}
    untimed = []
    for name, default in IMU_TYPES.items():
        for fmt, data in w.data(name):
            t = _times_us(fmt, data)
            if t is None:
                untimed.append(name)
                continue
            inst = _instance(fmt, data, default)
            block = np.column_stack([t.astype(float)] + [_col(fmt, data, c) for c in (
                "GyrX", "GyrY", "GyrZ", "AccX", "AccY", "AccZ", "T")])
            for i in np.unique(inst).tolist():
                parts.setdefault(int(i), []).append(block[inst == i])
    if not parts:
        present = sorted(n for n in IMU_TYPES if w.counts.get(n))
        why = (f"its {', '.join(present)} messages have no time field (TimeUS or TimeMS)"
               if untimed else f"{', '.join(present)} logged but its FMT is unusable"
               if present else "no IMU messages")
        # a partial replay (its GPS and references listed), not a refusal
        notes.append(f"{FORMAT}: {why}")
        return (ImuSeries(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), "none"),
                np.zeros(0), "none", [])
    counts = {i: sum(len(b) for b in bl) for i, bl in sorted(parts.items())}
    instances = list(counts)
    if imu_instance is not None:
        if imu_instance not in counts:
            raise LogReadError(path, f"{FORMAT}: no IMU instance {imu_instance} "
                                     f"(instances: {instances})")
        use, why = imu_instance, "asked for"
    else:
        busiest = max(counts.values())
        use = next(i for i in instances if counts[i] >= MINOR_SHARE * busiest)
        why = ("the first, ArduPilot's primary unless configured otherwise" if use == instances[0]
               else f"instance {instances[0]} has only {counts[instances[0]]} samples")
    if len(instances) > 1 or imu_instance is not None:
        listing = ", ".join(f"{i}: {c}" for i, c in counts.items())
        notes.append(f"IMU instances logged (samples): {listing}; instance {use} used ({why})")
    a = np.concatenate(parts[use])
    bad = ~np.all(np.isfinite(a[:, 1:7]), axis=1)
    if bad.any():
        notes.append(f"IMU[{use}]: {int(bad.sum())} sample(s) with a non-finite value dropped")
        a = a[~bad]
    if not len(a):
        raise LogReadError(path, f"{FORMAT}: IMU instance {use} has no finite sample")
    imu = ImuSeries(a[:, 0].astype(np.int64), a[:, 1:4].copy(), a[:, 4:7].copy(), f"IMU[{use}]")
    return imu, a[:, 7], f"IMU[{use}].T", instances


def _gps(w: DfWalk, notes: list[str]) -> GpsSeries | None:
    cols = ("Status", "NSats", "HDop", "Lat", "Lng", "Alt", "Spd", "GCrs", "VZ")
    parts: dict[int, list[np.ndarray]] = {}
    for name, default in GPS_TYPES.items():
        for fmt, data in w.data(name):
            t = _times_us(fmt, data)
            if t is None:
                notes.append(f"{name}: no boot time field (TimeUS, TimeMS or T): not used")
                continue
            inst = _instance(fmt, data, default)
            block = np.column_stack([t.astype(float)] + [_col(fmt, data, c) for c in cols])
            for i in np.unique(inst).tolist():
                parts.setdefault(int(i), []).append(block[inst == i])
    if not parts:
        return None
    blocks = {i: np.concatenate(b) for i, b in sorted(parts.items())}
    good = {i: int(np.sum(b[:, 1] >= 3)) for i, b in blocks.items()}
    first = next(iter(blocks))
    use = first if good[first] or not any(good.values()) else max(good, key=lambda i: good[i])
    if len(blocks) > 1:
        why = "the first" if use == first else f"instance {first} has no 3-D fix"
        notes.append(f"GPS instances logged (3-D fixes): "
                     f"{', '.join(f'{i}: {c}' for i, c in good.items())}; instance {use} used "
                     f"({why})")
    g = blocks[use]
    n = len(g)
    return GpsSeries(
        t_us=g[:, 0].astype(np.int64), fix=fix_code(np.nan_to_num(g[:, 1])), sats=g[:, 2],
        hdop=g[:, 3], lat_deg=g[:, 4], lon_deg=g[:, 5], alt_m=g[:, 6], h_std_m=nan_array(n),
        v_std_m=nan_array(n), vn_m_s=nan_array(n), ve_m_s=nan_array(n), vd_m_s=g[:, 9],
        speed_m_s=g[:, 7], course_deg=g[:, 8], source=f"GPS[{use}]")


def _references(w: DfWalk, notes: list[str]) -> list[AttitudeSeries]:
    refs = []
    for name in REFERENCES:
        blocks = []
        for fmt, data in w.data(name):
            t = _times_us(fmt, data)
            if t is None or not all(c in fmt.columns for c in ("Roll", "Pitch", "Yaw")):
                notes.append(f"{name}: no time or no Roll/Pitch/Yaw fields: not compared")
                continue
            core = _instance(fmt, data, 0, "C")
            blocks.append(np.column_stack([t.astype(float), core.astype(float)]
                                          + [_col(fmt, data, c) for c in ("Roll", "Pitch",
                                                                         "Yaw")]))
        if not blocks:
            continue
        a = np.concatenate(blocks)
        cores = sorted({int(c) for c in a[:, 1]})
        if len(cores) > 1:
            notes.append(f"{name} cores {cores} logged: core {cores[0]} used")
        a = a[a[:, 1] == cores[0]]
        refs.append(AttitudeSeries(name, a[:, 0].astype(np.int64), np.radians(a[:, 2]),
                                   np.radians(a[:, 3]), np.radians(a[:, 4])))
    return refs


def read_dataflash(path: Path, *, strict: bool = False, imu_instance: int | None = None
                   ) -> FlightLog:
    """Read what is whole; damage is skipped by resynchronising and reported (refused when
    `strict`). A file damaged from its first byte, or with no usable IMU, is a `LogReadError`."""
    try:
        w = walk_dataflash_file(path, WANTED)
    except OSError as exc:
        raise LogReadError(path, f"{FORMAT}: cannot read: {exc.strerror or exc}") from None
    if w.skipped and w.skipped[0].offset == 0:
        raise LogReadError(path, f"{FORMAT}: {w.skipped[0].what}", 0)
    if strict and w.fmt_problems:
        raise LogReadError(path, f"{FORMAT}: {w.fmt_problems[0]} (strict reading)")
    refuse_if_strict(path, FORMAT, w.skipped, strict)
    notes = region_notes(w.skipped)
    if w.regions_dropped:
        notes.append(f"and {w.regions_dropped} further damaged region(s), {w.bytes_dropped} "
                     "byte(s)")
    notes.extend(w.fmt_problems)
    imu, temp_c, temp_source, instances = _imu(path, w, imu_instance, notes)
    gps = _gps(w, notes)
    if gps is None:
        notes.append("no GPS messages: IMU-only")
    refs = _references(w, notes)
    if not len(imu.t_us) and gps is None and not refs:
        raise LogReadError(path, f"{FORMAT}: no IMU, GPS or attitude messages: nothing to "
                                 "replay")
    available = [n for n in REFERENCES if w.counts.get(n)]
    info = {"imu_instances": instances, "messages": w.messages, "size_bytes": w.size,
            "types": len(w.formats)}
    return FlightLog(path, KIND, imu, gps, refs, notes, damage_line(w.skipped), info,
                     temperature_series(imu.t_us, temp_c, temp_source), list(w.skipped),
                     available)
