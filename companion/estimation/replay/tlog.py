"""MAVLink telemetry logs (`.tlog`, as Mission Planner, QGroundControl and MAVProxy record a
link) into a `FlightLog`.

A tlog is a sequence of (8-byte big-endian UNIX time in us of reception, MAVLink 1 or 2 frame).
The frames are walked here by their own lengths, in chunks, so damage is found by byte offset
and the file is never held whole; only the messages a replay needs are decoded, by pymavlink
(which checks each frame's CRC). The IMU is the vehicle's own time base: HIGHRES_IMU (SI units),
SCALED_IMU/2/3 (mG and mrad/s per the MAVLink spec) or ArduPilot's RAW_IMU (which ArduPilot
fills with the same mG and mrad/s; PX4's RAW_IMU is raw sensor counts and is not used). GPS
(GPS_RAW_INT) and the references (ATTITUDE, AHRS2) are dated by their own boot times when they
carry one, else by their reception time moved onto the vehicle's clock with the median offset
between the IMU messages' reception and boot times.
"""

from __future__ import annotations

import logging
import re
from array import array
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from companion.estimation.replay.series import (
    AttitudeSeries,
    FlightLog,
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

KIND = "mavlink-tlog"
FORMAT = "MAVLink telemetry log"
CHUNK_BYTES = 1 << 20
STAMP = 8
STAMP_WINDOW_US = 86_400 * 10**6
"""When resynchronising, a frame whose reception time is more than a day from the last good
one's is noise that happens to look like a frame."""
MAGIC = re.compile(b"[\xfe\xfd]")
G_M_S2 = 9.80665
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
BOOT_TIME_LIMIT_US = 10**14
"""A message time above this (about 3 years) is a UNIX time, not a time since boot."""

IMU_IDS = {105: "HIGHRES_IMU", 26: "SCALED_IMU", 27: "RAW_IMU", 116: "SCALED_IMU2",
           129: "SCALED_IMU3"}
IMU_PREFERENCE = ("HIGHRES_IMU", "SCALED_IMU", "RAW_IMU", "SCALED_IMU2", "SCALED_IMU3")
WANTED_IDS = frozenset([0, 24, 30, 178, *IMU_IDS])
UNKNOWN_U16 = 0xFFFF


@dataclass
class _Series:
    """Decoded rows of one message kind from one system: flat float columns."""

    width: int
    values: array = field(default_factory=lambda: array("d"))
    recv_us: array = field(default_factory=lambda: array("d"))

    def add(self, recv_us: float, row: tuple[float, ...]) -> None:
        self.values.extend(row)
        self.recv_us.append(recv_us)

    def matrix(self) -> np.ndarray:
        return np.frombuffer(self.values, dtype=float).reshape(-1, self.width)

    def __len__(self) -> int:
        return len(self.recv_us)


def _row(m: Any, msg_id: int) -> tuple[str, tuple[float, ...]] | None:
    """The numbers a replay takes from one decoded message, in fixed column order."""
    if msg_id in IMU_IDS:
        name = IMU_IDS[msg_id]
        if msg_id == 105:
            return name, (float(m.time_usec), m.xgyro, m.ygyro, m.zgyro, m.xacc, m.yacc, m.zacc,
                          float(m.temperature))
        t = float(m.time_usec) if msg_id == 27 else float(m.time_boot_ms) * 1000.0
        temp = float(getattr(m, "temperature", 0) or 0) / 100.0
        return name, (t, m.xgyro, m.ygyro, m.zgyro, m.xacc, m.yacc, m.zacc,
                      temp if temp else float("nan"))
    if msg_id == 24:
        return "GPS_RAW_INT", (float(m.time_usec), m.fix_type, m.lat, m.lon, m.alt, m.eph,
                               m.epv, m.vel, m.cog, m.satellites_visible,
                               float(getattr(m, "h_acc", 0) or 0),
                               float(getattr(m, "v_acc", 0) or 0))
    if msg_id == 30:
        return "ATTITUDE", (float(m.time_boot_ms) * 1000.0, m.roll, m.pitch, m.yaw)
    if msg_id == 178:
        return "AHRS2", (float("nan"), m.roll, m.pitch, m.yaw)
    if msg_id == 0:
        return "HEARTBEAT", (float(m.autopilot), float(m.type))
    return None


class _TlogWalk:
    def __init__(self) -> None:
        from pymavlink.dialects.v20 import ardupilotmega as dialect

        self.mav = dialect.MAVLink(None)
        self.unknown_type = dialect.MAVLink_unknown
        self.last_stamp = -1
        self.mav.robust_parsing = True
        self.series: dict[tuple[int, str], _Series] = {}
        self.skipped: list[SkippedRegion] = []
        self.bad_start: int | None = None
        self.frames = 0
        self.crc_errors = 0
        self.first_crc_error: int | None = None

    @staticmethod
    def frame_size(buf: bytes, p: int) -> int | None:
        """Size of the stamped frame at `p` (stamp included), 0 if `buf` is too short to say,
        None if no frame starts there."""
        n = len(buf)
        if p + STAMP + 3 > n:
            return 0
        magic = buf[p + STAMP]
        ln = buf[p + STAMP + 1]
        if magic == 0xFE:
            return STAMP + 8 + ln
        if magic == 0xFD:
            incompat = buf[p + STAMP + 2]
            if incompat & ~1:
                return None
            return STAMP + 12 + ln + (13 if incompat & 1 else 0)
        return None

    def _plausible(self, buf: bytes, p: int, final: bool) -> bool | None:
        size = self.frame_size(buf, p)
        if size is None:
            return False
        if size and self.last_stamp >= 0 and abs(
                int.from_bytes(buf[p:p + STAMP], "big") - self.last_stamp) > STAMP_WINDOW_US:
            return False
        if size == 0:
            return None if not final else False
        q = p + size
        nxt = self.frame_size(buf, q)
        if nxt == 0:
            return (q <= len(buf)) if final else None
        return nxt is not None and self._crc_ok(buf[p + STAMP:q])

    def _crc_ok(self, frame: bytes) -> bool:
        """A frame of a message the dialect knows, whose CRC checks (pymavlink skips the check
        for unknown ids, so those never count as found again)."""
        try:
            m = self.mav.decode(bytearray(frame))
        except Exception:  # noqa: BLE001 - pymavlink raises bare errors for bad frames
            return False
        return not isinstance(m, self.unknown_type)

    def _take(self, buf: bytes, off: int, size: int, base: int) -> None:
        stamp = int.from_bytes(buf[off:off + STAMP], "big")
        self.last_stamp = stamp
        frame = buf[off + STAMP:off + size]
        v2 = frame[0] == 0xFD
        msg_id = (frame[7] | frame[8] << 8 | frame[9] << 16) if v2 else frame[5]
        if msg_id not in WANTED_IDS:
            return
        sysid = frame[5] if v2 else frame[3]
        try:
            m = self.mav.decode(bytearray(frame))
        except Exception:  # noqa: BLE001 - CRC or length errors: the frame is dropped
            self.crc_errors += 1
            if self.first_crc_error is None:
                self.first_crc_error = base + off
            return
        got = _row(m, msg_id)
        if got is None:
            return
        name, row = got
        s = self.series.get((sysid, name))
        if s is None:
            s = self.series[(sysid, name)] = _Series(len(row))
        s.add(float(stamp), row)

    def walk(self, buf: bytes, base: int, final: bool) -> int:
        n = len(buf)
        off = 0
        while True:
            if self.bad_start is not None:
                while True:
                    m = MAGIC.search(buf, off + STAMP)
                    if m is None:
                        return max(off, n - STAMP - 1)
                    off = m.start() - STAMP
                    ok = self._plausible(buf, off, final)
                    if ok is None:
                        return off
                    if ok:
                        break
                    off += 1
                self.skipped.append(SkippedRegion(
                    self.bad_start, base + off - self.bad_start,
                    "unreadable bytes (no MAVLink frame where the previous one ended)"))
                self.bad_start = None
            size = self.frame_size(buf, off)
            if size == 0 or (size is not None and off + size > n):
                return off
            if size is None:
                self.bad_start = base + off
                off += 1
                continue
            self.frames += 1
            self._take(buf, off, size, base)
            off += size

    def finish(self, rest: bytes, base: int) -> None:
        if self.bad_start is not None:
            self.skipped.append(SkippedRegion(self.bad_start, base + len(rest) - self.bad_start,
                                              "unreadable bytes up to the end of the file",
                                              tail=True))
        elif rest:
            self.skipped.append(SkippedRegion(base, len(rest), "file cut short inside a "
                                              "MAVLink frame", tail=True))


def walk_tlog(fh: BinaryIO, chunk_bytes: int = CHUNK_BYTES) -> _TlogWalk:
    w = _TlogWalk()
    carry = b""
    base = 0
    while True:
        chunk = fh.read(chunk_bytes)
        buf = carry + chunk if carry else chunk
        used = w.walk(buf, base, final=not chunk)
        carry = buf[used:]
        base += used
        if not chunk:
            w.finish(carry, base)
            return w


def looks_like_tlog(head: bytes) -> bool:
    """A stamped MAVLink frame at the start: 8 bytes of time, then 0xFE or 0xFD."""
    return (len(head) > STAMP + 3 and head[STAMP] in (0xFE, 0xFD)
            and _TlogWalk.frame_size(head, 0) is not None)


def _autopilot(w: _TlogWalk, sysid: int) -> int | None:
    hb = w.series.get((sysid, "HEARTBEAT"))
    if hb is None or not len(hb):
        return None
    m = hb.matrix()
    vehicle = m[m[:, 1] != 6]  # MAV_TYPE_GCS is 6: a GCS's own heartbeats say nothing
    if not len(vehicle):
        return None
    values, counts = np.unique(vehicle[:, 0].astype(int), return_counts=True)
    return int(values[np.argmax(counts)])


def _choose_imu(w: _TlogWalk, notes: list[str]) -> tuple[int, str, int | None]:
    counts: dict[tuple[int, str], int] = {k: len(s) for k, s in w.series.items()
                                         if k[1] in IMU_PREFERENCE}
    usable = {}
    for (sysid, name), c in counts.items():
        ap = _autopilot(w, sysid)
        if name == "RAW_IMU" and ap == MAV_AUTOPILOT_PX4:
            notes.append(f"system {sysid}: RAW_IMU from PX4 is raw sensor counts: not used")
            continue
        usable[(sysid, name)] = c
    if not usable:
        return -1, "", None
    busiest = max(usable.values())
    best_sys = max({k[0] for k in usable}, key=lambda s: max(
        c for k, c in usable.items() if k[0] == s))
    for name in IMU_PREFERENCE:
        c = usable.get((best_sys, name), 0)
        if c and c >= 0.5 * busiest:
            ap = _autopilot(w, best_sys)
            listing = ", ".join(f"{k[1]}: {v}" for k, v in sorted(usable.items())
                                if k[0] == best_sys)
            notes.append(f"IMU messages from system {best_sys} ({listing}): {name} used "
                         "(the most precise kind logged at the full rate)")
            if name == "RAW_IMU" and ap != MAV_AUTOPILOT_ARDUPILOTMEGA:
                notes.append("RAW_IMU read with ArduPilot's scaling (mG, mrad/s): no heartbeat "
                             "says which autopilot sent it")
            return best_sys, name, ap
    return -1, "", None


def read_tlog(path: Path, *, strict: bool = False) -> FlightLog:
    """Read what is whole; damage is skipped by resynchronising on the next frame with a good
    CRC and reported (refused when `strict`)."""
    with path.open("rb") as fh:
        w = walk_tlog(fh)
    if w.skipped and w.skipped[0].offset == 0:
        raise LogReadError(path, f"{FORMAT}: {w.skipped[0].what}", 0)
    refuse_if_strict(path, FORMAT, w.skipped, strict)
    if strict and w.crc_errors:
        raise LogReadError(path, f"{FORMAT}: frame with a bad CRC (strict reading)",
                           w.first_crc_error)
    notes = region_notes(w.skipped)
    if w.crc_errors:
        notes.append(f"{w.crc_errors} frame(s) of the messages used had a bad CRC and were "
                     f"dropped, the first at byte offset {w.first_crc_error}")
    sysid, name, autopilot = _choose_imu(w, notes)
    if sysid < 0:
        raise LogReadError(path, f"{FORMAT}: no IMU messages (HIGHRES_IMU, SCALED_IMU, "
                                 f"RAW_IMU) in {w.frames} frames")
    s = w.series[(sysid, name)]
    m = s.matrix()
    recv = np.frombuffer(s.recv_us, dtype=float)
    if name == "HIGHRES_IMU":
        gyro, acc = m[:, 1:4].copy(), m[:, 4:7].copy()
    else:
        gyro, acc = m[:, 1:4] * 1e-3, m[:, 4:7] * (G_M_S2 * 1e-3)
    t_us = m[:, 0].astype(np.int64)
    imu = ImuSeries(t_us, gyro, acc, f"{name}[sys {sysid}]")
    offset_us = float(np.median(recv - m[:, 0])) if len(m) else 0.0
    temperature = temperature_series(t_us, m[:, 7], f"{name}.temperature")
    gps = _gps(w, sysid, offset_us)
    if gps is None:
        notes.append("no GPS_RAW_INT messages: IMU-only")
    refs = []
    for ref in ("ATTITUDE", "AHRS2"):
        r = w.series.get((sysid, ref))
        if r is None or not len(r):
            continue
        a = r.matrix()
        t = a[:, 0] if ref == "ATTITUDE" else np.frombuffer(r.recv_us, dtype=float) - offset_us
        refs.append(AttitudeSeries(ref, t.astype(np.int64), a[:, 1].copy(), a[:, 2].copy(),
                                   a[:, 3].copy()))
    info = {"frames": w.frames, "system": sysid, "autopilot": autopilot}
    return FlightLog(path, KIND, imu, gps, refs, notes, damage_line(w.skipped), info,
                     temperature, list(w.skipped), [r.name for r in refs])


def _gps(w: _TlogWalk, sysid: int, offset_us: float) -> GpsSeries | None:
    s = w.series.get((sysid, "GPS_RAW_INT"))
    if s is None or not len(s):
        return None
    g = s.matrix()
    recv = np.frombuffer(s.recv_us, dtype=float)
    own = g[:, 0]
    t = np.where((own > 0) & (own < BOOT_TIME_LIMIT_US), own, recv - offset_us)
    n = len(g)

    def known(col: np.ndarray, scale: float, missing: float = UNKNOWN_U16) -> np.ndarray:
        return np.where(col == missing, np.nan, col * scale)

    h_acc = np.where(g[:, 10] > 0, g[:, 10] * 1e-3, np.nan)
    v_acc = np.where(g[:, 11] > 0, g[:, 11] * 1e-3, np.nan)
    return GpsSeries(
        t_us=t.astype(np.int64), lat_deg=g[:, 2] * 1e-7, lon_deg=g[:, 3] * 1e-7,
        alt_m=g[:, 4] * 1e-3, fix=fix_code(g[:, 1]), sats=known(g[:, 9], 1.0, 255),
        hdop=known(g[:, 5], 0.01), h_std_m=h_acc, v_std_m=v_acc, vn_m_s=nan_array(n),
        ve_m_s=nan_array(n), vd_m_s=nan_array(n), speed_m_s=known(g[:, 7], 0.01),
        course_deg=known(g[:, 8], 0.01), source=f"GPS_RAW_INT[sys {sysid}]")
