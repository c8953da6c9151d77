"""PX4 ULog files (`.ulg`) into a `FlightLog`, with pyulog reading the messages.

PX4 moved topics between releases: the IMU is `sensor_combined` throughout (its gyro field was
`gyro_rad` or `gyro_rad_s`), the GPS `vehicle_gps_position` (lat/lon in 1e-7 deg and alt in mm)
or, from v1.14, `sensor_gps` (degrees and metres, `latitude_deg`...); fields are looked up by
name so either reads. Before pyulog parses the file its message chain is walked here in
chunks (three bytes a message), because pyulog resynchronises or stops in silence: the walk
says where the file was damaged or cut, by byte offset.
"""

from __future__ import annotations

import contextlib
import io
import logging
import re
import tempfile
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from companion.estimation.replay.series import (
    AttitudeSeries,
    FlightLog,
    FloatArray,
    GpsSeries,
    ImuSeries,
    LogReadError,
    SkippedRegion,
    damage_line,
    fix_code,
    nan_array,
    refuse_if_strict,
    region_notes,
    temperature_series,
)

log = logging.getLogger(__name__)

KIND = "px4-ulog"
FORMAT = "PX4 ULog"
ULOG_MAGIC = b"ULog\x01\x12\x35"
ULOG_HEADER_SIZE = 16
ULOG_TYPES = frozenset(b"BFIMPQARDLCSO")
CHUNK_BYTES = 1 << 20
RESYNC_CHAIN = 8
FIXED_SIZES = {ord("S"): 8, ord("O"): 2, ord("R"): 2}  # sync magic, dropout ms, msg id
MAX_RESYNC_SIZE = 8192
"""No uORB topic, subscription or log string comes near this; a size read from noise does. A
longer message (a big info message) is still read in the chain, only not resynchronised on."""
CANDIDATE = re.compile(b"..[" + bytes(sorted(ULOG_TYPES)) + b"]", re.DOTALL)
"""Where a message may start: its type byte is one of ULog's (searched in C, not byte by byte)."""
REFERENCES = ("vehicle_attitude", "vehicle_attitude_groundtruth")
GPS_TOPICS = ("vehicle_gps_position", "sensor_gps")


class _ChainWalk:
    """The ULog message chain (u16 size, u8 type, payload), walked chunk by chunk."""

    def __init__(self) -> None:
        self.skipped: list[SkippedRegion] = []
        self.bad_start: int | None = None

    @staticmethod
    def _plausible(buf: bytes, p: int, final: bool) -> bool | None:
        """Do RESYNC_CHAIN messages in a row start at `p` (or run to the end of the file)?
        ULog's type bytes are common letters, so one or two in a row happen in noise."""
        n = len(buf)
        for _ in range(RESYNC_CHAIN):
            if p + 3 > n:
                return (p == n) if final else None
            typ, size = buf[p + 2], buf[p] | buf[p + 1] << 8
            if typ not in ULOG_TYPES or FIXED_SIZES.get(typ, size) != size or (
                    size > MAX_RESYNC_SIZE):
                return False
            p += 3 + size
        return True

    def walk(self, buf: bytes, base: int, final: bool) -> int:
        n = len(buf)
        off = 0
        types = ULOG_TYPES
        while True:
            if self.bad_start is not None:
                while True:
                    m = CANDIDATE.search(buf, off)
                    if m is None:
                        return max(off, n - 2)
                    off = m.start()
                    ok = self._plausible(buf, off, final)
                    if ok is None:
                        return off
                    if ok:
                        break
                    off += 1
                self.skipped.append(SkippedRegion(self.bad_start, base + off - self.bad_start,
                                                  "unreadable bytes (no ULog message where the "
                                                  "previous one ended)"))
                self.bad_start = None
            if off + 3 > n:
                return off
            typ = buf[off + 2]
            if typ not in types:
                self.bad_start = base + off
                off += 1
                continue
            end = off + 3 + (buf[off] | buf[off + 1] << 8)
            if end > n:
                return off
            off = end

    def finish(self, rest: bytes, base: int) -> None:
        if self.bad_start is not None:
            self.skipped.append(SkippedRegion(self.bad_start, base + len(rest) - self.bad_start,
                                              "unreadable bytes up to the end of the file",
                                              tail=True))
        elif rest:
            what = ("file cut short inside a message header" if len(rest) < 3 else
                    f"file cut short inside a '{chr(rest[2])}' message of "
                    f"{rest[0] | rest[1] << 8} bytes")
            self.skipped.append(SkippedRegion(base, len(rest), what, tail=True))


def walk_ulog(fh: BinaryIO, chunk_bytes: int = CHUNK_BYTES) -> list[SkippedRegion]:
    """The regions of an open ULog file that are not a whole message (header checked first)."""
    head = fh.read(ULOG_HEADER_SIZE)
    if len(head) < ULOG_HEADER_SIZE or not head.startswith(ULOG_MAGIC):
        return [SkippedRegion(0, len(head), "not a ULog header")]
    w = _ChainWalk()
    carry = b""
    base = ULOG_HEADER_SIZE
    while True:
        chunk = fh.read(chunk_bytes)
        buf = carry + chunk if carry else chunk
        used = w.walk(buf, base, final=not chunk)
        carry = buf[used:]
        base += used
        if not chunk:
            w.finish(carry, base)
            return w.skipped


def check_ulog_chain(data: bytes) -> tuple[int | None, str]:
    """The first problem in a ULog held in memory: (byte offset, what), or (None, "")."""
    skipped = walk_ulog(io.BytesIO(data))
    return (skipped[0].offset, skipped[0].what) if skipped else (None, "")


def _field(d: dict[str, Any], *names: str) -> Any:
    for name in names:
        if name in d:
            return d[name]
    return None


def _px4_gps(g: dict[str, Any], name: str) -> GpsSeries:
    n = len(g["timestamp"])

    def arr(*names: str, scale: float = 1.0) -> FloatArray:
        v = _field(g, *names)
        return nan_array(n) if v is None else np.asarray(v, dtype=float) * scale

    lat = arr("latitude_deg") if "latitude_deg" in g else arr("lat", scale=1e-7)
    lon = arr("longitude_deg") if "longitude_deg" in g else arr("lon", scale=1e-7)
    alt = arr("altitude_msl_m") if "altitude_msl_m" in g else arr("alt", scale=1e-3)
    vn, ve, vd = arr("vel_n_m_s"), arr("vel_e_m_s"), arr("vel_d_m_s")
    if "vel_ned_valid" in g:
        bad = np.asarray(g["vel_ned_valid"]) == 0
        vn[bad] = ve[bad] = vd[bad] = np.nan
    return GpsSeries(
        t_us=np.asarray(g["timestamp"], dtype=np.int64),
        lat_deg=lat, lon_deg=lon, alt_m=alt,
        fix=fix_code(np.asarray(g["fix_type"]) if "fix_type" in g else np.zeros(n)),
        sats=arr("satellites_used"), hdop=arr("hdop"), h_std_m=arr("eph"), v_std_m=arr("epv"),
        vn_m_s=vn, ve_m_s=ve, vd_m_s=vd, speed_m_s=arr("vel_m_s"),
        course_deg=np.degrees(arr("cog_rad")), source=name)


def _spliced(path: Path, skipped: list[SkippedRegion]) -> BinaryIO:
    """The file without its damaged regions, in a temporary file: pyulog's own resynchronising
    loses whole seconds after a damaged message, so it is handed only whole messages. On disk,
    not in memory, since a log can be bigger than the memory a replay should take."""
    out = tempfile.TemporaryFile()
    with path.open("rb") as fh:
        pos = 0
        for s in [*skipped, SkippedRegion(path.stat().st_size, 0, "end")]:
            fh.seek(pos)
            left = s.offset - pos
            while left > 0:
                block = fh.read(min(left, CHUNK_BYTES))
                if not block:
                    break
                out.write(block)
                left -= len(block)
            pos = s.offset + s.length
    out.seek(0)
    return out


def _parse(path: Path, skipped: list[SkippedRegion]) -> Any:
    from pyulog import ULog
    from pyulog.core import ULogException

    wanted = ["sensor_combined", *GPS_TOPICS, *REFERENCES, "vehicle_imu_status", "sensor_gyro"]
    quiet = io.StringIO()
    inner = [s for s in skipped if not s.tail]
    try:
        with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet):
            if not inner:
                return ULog(str(path), message_name_filter_list=wanted)
            with _spliced(path, inner) as fh:
                return ULog(fh, message_name_filter_list=wanted)
    except ULogException as exc:
        raise LogReadError(path, f"{FORMAT}: {exc}") from None
    except Exception as exc:  # noqa: BLE001 - pyulog has no error type for damaged data
        raise LogReadError(path, f"{FORMAT}: pyulog cannot parse it ({type(exc).__name__}: "
                                 f"{exc})") from None


def read_ulog(path: Path, *, strict: bool = False) -> FlightLog:
    """PX4: `sensor_combined` (IMU), `vehicle_gps_position` or `sensor_gps` (GPS),
    `vehicle_attitude` and, in simulation, `vehicle_attitude_groundtruth` (references).
    What is whole is read; damage is reported (refused when `strict`)."""
    with path.open("rb") as fh:
        skipped = walk_ulog(fh)
    if skipped and skipped[0].offset == 0:
        raise LogReadError(path, f"{FORMAT}: {skipped[0].what}", 0)
    refuse_if_strict(path, FORMAT, skipped, strict)
    ulog = _parse(path, skipped)
    notes = region_notes(skipped)
    damage = damage_line(skipped)
    if ulog.file_corruption and not damage:
        if strict:
            raise LogReadError(path, f"{FORMAT}: damaged data (pyulog reports corruption)")
        if damage is None:
            damage = "damaged data (pyulog reports corruption; resynchronised)"
    sets = {(d.name, d.multi_id): d.data for d in ulog.data_list}
    sc = sets.get(("sensor_combined", 0))
    if sc is None or not len(sc["timestamp"]):
        # a partial replay (its GPS and references listed), not a refusal
        notes.append(f"{FORMAT}: no sensor_combined messages (the IMU)")
        imu = ImuSeries(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), "none")
    else:
        gyro_cols = [_field(sc, f"gyro_rad[{i}]", f"gyro_rad_s[{i}]") for i in range(3)]
        acc_cols = [_field(sc, f"accelerometer_m_s2[{i}]") for i in range(3)]
        if any(c is None for c in gyro_cols + acc_cols):
            raise LogReadError(path, f"{FORMAT}: sensor_combined has no gyro_rad/"
                                     "accelerometer_m_s2 fields")
        imu = ImuSeries(np.asarray(sc["timestamp"], dtype=np.int64),
                        np.column_stack([np.asarray(c, dtype=float) for c in gyro_cols]),
                        np.column_stack([np.asarray(c, dtype=float) for c in acc_cols]),
                        "sensor_combined")
    instances = sorted(m for (name, m) in sets if name == "sensor_combined")
    if len(instances) > 1:
        notes.append(f"sensor_combined has instances {instances}: instance 0 used")
    gps = None
    for name in GPS_TOPICS:
        g = sets.get((name, 0))
        if g is not None and len(g["timestamp"]):
            gps = _px4_gps(g, name)
            others = [o for o in GPS_TOPICS if o != name and (o, 0) in sets]
            if others:
                notes.append(f"GPS from {name} ({others[0]} also logged)")
            break
    if gps is None:
        notes.append("no vehicle_gps_position or sensor_gps messages: IMU-only")
    refs = []
    for name in REFERENCES:
        a = sets.get((name, 0))
        if a is not None and all(f"q[{i}]" in a for i in range(4)):
            from companion.estimation.quat import quat_to_euler

            q = np.column_stack([np.asarray(a[f"q[{i}]"], dtype=float) for i in range(4)])
            e = quat_to_euler(q)
            refs.append(AttitudeSeries(name, np.asarray(a["timestamp"], dtype=np.int64),
                                       e[:, 0], e[:, 1], e[:, 2]))
    dropouts = getattr(ulog, "dropouts", [])
    if dropouts:
        total_ms = sum(int(getattr(d, "duration", 0)) for d in dropouts)
        notes.append(f"the PX4 logger reports {len(dropouts)} dropout(s), {total_ms} ms in all")
    info = {"sys_name": ulog.msg_info_dict.get("sys_name"),
            "ver_sw": ulog.msg_info_dict.get("ver_sw"),
            "ver_sw_release": ulog.msg_info_dict.get("ver_sw_release"),
            "ver_hw": ulog.msg_info_dict.get("ver_hw"),
            "logger_dropouts": len(dropouts)}
    temperature = None
    for name, column in (("vehicle_imu_status", "temperature_gyro"),
                         ("sensor_gyro", "temperature")):
        d = sets.get((name, 0))
        if d is not None and column in d:
            temperature = temperature_series(d["timestamp"], d[column], f"{name}.{column}")
            if temperature is not None:
                break
    if not len(imu.t_us) and gps is None and not refs:
        raise LogReadError(path, f"{FORMAT}: no sensor_combined messages (the IMU), no GPS "
                                 "and no attitude: nothing to replay")
    available = [n for n in REFERENCES if (n, 0) in sets]
    return FlightLog(path, KIND, imu, gps, refs, notes, damage, info, temperature,
                     skipped, available)
