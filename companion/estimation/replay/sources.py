"""Readers for flight-controller logs: PX4 ULog (pyulog) and ArduPilot DataFlash (pymavlink).

Both formats come out as one `FlightLog`: IMU samples, GPS fixes and the flight controller's own
attitude estimates, as arrays with their log times in microseconds (the flight controller's
boot clock, raw: cleaning the timelines is the runner's job). Body axes are FRD and the earth
frame NED in both autopilots, as in this project, so no axis is converted.

Before a library parses a file, its record chain is walked here (a few bytes per record), so a
cut-short or damaged file is reported with its byte offset: the libraries themselves stop or
resynchronise silently. Anything unreadable is a `LogReadError` naming the file.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

ULOG_MAGIC = b"ULog\x01\x12\x35"
ULOG_HEADER_SIZE = 16
ULOG_TYPES = frozenset(b"BFIMPQARDLCSO")
DF_HEAD = b"\xa3\x95"
DF_FMT_TYPE = 0x80
DF_FMT_LEN = 89


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


def empty_imu(source: str) -> ImuSeries:
    """No IMU samples: the runner then replays what it can (nothing estimated)."""
    return ImuSeries(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), source)


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


TEMPERATURE_RANGE_C = (-60.0, 130.0)
"""Readings outside this are a sensor's "not available" code or garbage, never a part's
temperature (the MEMS parts' operating range is -40..85 C)."""


def _temperature(t_us: npt.ArrayLike, temp_c: npt.ArrayLike, source: str
                 ) -> TemperatureSeries | None:
    t = np.asarray(t_us, dtype=np.int64)
    c = np.asarray(temp_c, dtype=float)
    lo, hi = TEMPERATURE_RANGE_C
    ok = np.isfinite(c) & (c >= lo) & (c <= hi)
    if not ok.any():
        return None
    return TemperatureSeries(t[ok], c[ok], source)


@dataclass
class FlightLog:
    """What a replay needs from a log, whatever its format."""

    path: Path
    kind: str  # "px4-ulog" or "ardupilot-dataflash"
    imu: ImuSeries
    gps: GpsSeries | None
    references: list[AttitudeSeries]
    notes: list[str] = field(default_factory=list)
    damage: str | None = None  # what was skipped when reading with salvage
    info: dict[str, Any] = field(default_factory=dict)
    temperature: TemperatureSeries | None = None  # None: the log has none


def read_flight_log(path: Path | str, *, salvage: bool = False,
                    imu_instance: int | None = None) -> FlightLog:
    """Read a PX4 ULog or an ArduPilot DataFlash log, recognised by its first bytes.

    A cut-short or damaged file raises `LogReadError` unless `salvage`, in which case what reads
    is returned with the problem in `FlightLog.damage`. `imu_instance` picks an ArduPilot IMU
    (default: the first one logged); PX4's `sensor_combined` has one.
    """
    p = Path(path)
    try:
        with p.open("rb") as fh:
            head = fh.read(ULOG_HEADER_SIZE)
    except OSError as exc:
        raise LogReadError(p, f"cannot read: {exc.strerror or exc}") from None
    if not head:
        raise LogReadError(p, "empty file")
    if head.startswith(ULOG_MAGIC):
        return read_ulog(p, salvage=salvage)
    if head.startswith(DF_HEAD):
        return read_dataflash(p, salvage=salvage, imu_instance=imu_instance)
    raise LogReadError(p, "not a PX4 ULog (no 'ULog' magic) nor an ArduPilot DataFlash log "
                          "(no 0xA3 0x95 header)", 0)


# ------------------------------------------------------------------------------------- ULog
def check_ulog_chain(data: bytes) -> tuple[int | None, str]:
    """Walk the ULog message chain; (offset of the first problem, what) or (None, "")."""
    n = len(data)
    if n < ULOG_HEADER_SIZE or not data.startswith(ULOG_MAGIC):
        return 0, "not a ULog header"
    off = ULOG_HEADER_SIZE
    unpack = struct.Struct("<HB").unpack_from
    types = ULOG_TYPES
    while off < n:
        if n - off < 3:
            return off, "file cut short inside a message header"
        size, typ = unpack(data, off)
        if typ not in types:
            return off, f"damaged message (unknown type 0x{typ:02X})"
        if off + 3 + size > n:
            return off, f"file cut short inside a '{chr(typ)}' message of {size} bytes"
        off += 3 + size
    return None, ""


def _ulog_field(d: dict[str, Any], *names: str) -> Any:
    for name in names:
        if name in d:
            return d[name]
    return None


def _nan(n: int) -> FloatArray:
    return np.full(n, np.nan)


def _fix_code(fix_type: npt.ArrayLike) -> IntArray:
    """PX4 fix_type / ArduPilot GPS Status (3 3-D, 4 DGPS, 5 RTK float, 6 RTK fixed) ->
    this project's fix code."""
    f = np.asarray(fix_type, dtype=np.int64)
    return np.select([f >= 5, f == 4, f == 3], [3, 2, 1], 0).astype(np.int64)


def _chain_damage(path: Path, chain: tuple[int | None, str], fmt: str, salvage: bool,
                  recovery: str) -> tuple[int | None, str | None]:
    """A format's own framing check (`check_*_chain`) before its library reads the file: the
    first bad byte offset and, when salvaging, what `FlightLog.damage` says of it; a file
    damaged from its first byte, or any damage without `salvage`, is a `LogReadError`."""
    bad_at, what = chain
    if bad_at is None:
        return None, None
    if bad_at == 0 or not salvage:
        raise LogReadError(path, f"{fmt}: {what}", bad_at)
    return bad_at, f"{what} at byte offset {bad_at} ({recovery})"


def read_ulog(path: Path, *, salvage: bool = False) -> FlightLog:
    """PX4: `sensor_combined` (IMU), `vehicle_gps_position` or `sensor_gps` (GPS),
    `vehicle_attitude` and, in simulation, `vehicle_attitude_groundtruth` (references)."""
    from pyulog import ULog
    from pyulog.core import ULogException

    bad_at, damage = _chain_damage(path, check_ulog_chain(path.read_bytes()), "PX4 ULog",
                                   salvage, "the rest skipped or resynchronised")
    wanted = ["sensor_combined", "vehicle_gps_position", "sensor_gps", "vehicle_attitude",
              "vehicle_attitude_groundtruth", "vehicle_imu_status", "sensor_gyro"]
    quiet = io.StringIO()
    try:
        with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet):
            ulog = ULog(str(path), message_name_filter_list=wanted)
    except ULogException as exc:
        raise LogReadError(path, f"PX4 ULog: {exc}", bad_at) from None
    except Exception as exc:  # noqa: BLE001 - pyulog has no error type for damaged data
        raise LogReadError(path, f"PX4 ULog: pyulog cannot parse it ({type(exc).__name__}: "
                                 f"{exc})", bad_at) from None
    if ulog.file_corruption and damage is None:
        if not salvage:
            raise LogReadError(path, "PX4 ULog: damaged data (pyulog reports corruption)")
        damage = "damaged data (pyulog reports corruption; resynchronised)"
    sets = {(d.name, d.multi_id): d.data for d in ulog.data_list}
    sc = sets.get(("sensor_combined", 0))
    notes: list[str] = []
    if sc is None:
        # a partial replay (its GPS and references listed), not a refusal
        notes.append("PX4 ULog: no sensor_combined messages (the IMU)")
        imu = empty_imu("none")
    else:
        t_us = np.asarray(sc["timestamp"], dtype=np.int64)
        gyro = np.column_stack([np.asarray(
            _ulog_field(sc, f"gyro_rad[{i}]", f"gyro_rad_s[{i}]"), dtype=float)
            for i in range(3)])
        accel = np.column_stack([np.asarray(sc[f"accelerometer_m_s2[{i}]"], dtype=float)
                                 for i in range(3)])
        imu = ImuSeries(t_us, gyro, accel, "sensor_combined")
    instances = sorted(m for (name, m) in sets if name == "sensor_combined")
    if len(instances) > 1:
        notes.append(f"sensor_combined has instances {instances}: instance 0 used")
    gps = None
    for name in ("vehicle_gps_position", "sensor_gps"):
        g = sets.get((name, 0))
        if g is not None:
            gps = _px4_gps(g, name)
            break
    refs = []
    for name in ("vehicle_attitude", "vehicle_attitude_groundtruth"):
        a = sets.get((name, 0))
        if a is not None:
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
            "ver_hw": ulog.msg_info_dict.get("ver_hw"),
            "logger_dropouts": len(dropouts)}
    temperature = None
    for name, column in (("vehicle_imu_status", "temperature_gyro"),
                         ("sensor_gyro", "temperature")):
        d = sets.get((name, 0))
        if d is not None and column in d:
            temperature = _temperature(d["timestamp"], d[column], f"{name}.{column}")
            if temperature is not None:
                break
    return FlightLog(path, "px4-ulog", imu, gps, refs, notes, damage, info, temperature)


def _px4_gps(g: dict[str, Any], name: str) -> GpsSeries:
    n = len(g["timestamp"])

    def arr(*names: str, scale: float = 1.0) -> FloatArray:
        v = _ulog_field(g, *names)
        return _nan(n) if v is None else np.asarray(v, dtype=float) * scale

    lat = arr("latitude_deg")
    if "latitude_deg" not in g:
        lat = arr("lat", scale=1e-7)
    lon = arr("longitude_deg") if "longitude_deg" in g else arr("lon", scale=1e-7)
    alt = arr("altitude_msl_m") if "altitude_msl_m" in g else arr("alt", scale=1e-3)
    vn, ve, vd = arr("vel_n_m_s"), arr("vel_e_m_s"), arr("vel_d_m_s")
    if "vel_ned_valid" in g:
        bad = np.asarray(g["vel_ned_valid"]) == 0
        vn[bad] = ve[bad] = vd[bad] = np.nan
    return GpsSeries(
        t_us=np.asarray(g["timestamp"], dtype=np.int64),
        lat_deg=lat, lon_deg=lon, alt_m=alt,
        fix=_fix_code(np.asarray(g["fix_type"]) if "fix_type" in g else np.zeros(n)),
        sats=arr("satellites_used"), hdop=arr("hdop"), h_std_m=arr("eph"), v_std_m=arr("epv"),
        vn_m_s=vn, ve_m_s=ve, vd_m_s=vd, speed_m_s=arr("vel_m_s"),
        course_deg=np.degrees(arr("cog_rad")), source=name)


# -------------------------------------------------------------------------------- DataFlash
def check_dataflash_chain(data: bytes) -> tuple[int | None, str]:
    """Walk the DataFlash message chain by its FMT lengths; (first problem offset, what)."""
    n = len(data)
    lengths = {DF_FMT_TYPE: DF_FMT_LEN}
    off = 0
    while off < n:
        if n - off < 3:
            return off, "file cut short inside a message header"
        if data[off] != 0xA3 or data[off + 1] != 0x95:
            return off, "damaged message (no 0xA3 0x95 header)"
        typ = data[off + 2]
        length = lengths.get(typ)
        if length is None:
            return off, f"message type {typ} used before its FMT"
        if off + length > n:
            return off, f"file cut short inside a message of type {typ}"
        if typ == DF_FMT_TYPE:
            defined, defined_len = data[off + 3], data[off + 4]
            if defined_len < 3:
                return off, f"FMT of type {defined} with impossible length {defined_len}"
            lengths[defined] = defined_len
        off += length
    return None, ""


def _df_time_us(m: Any) -> int | None:
    t = getattr(m, "TimeUS", None)
    if t is None:
        ms = getattr(m, "TimeMS", None)
        return None if ms is None else int(ms) * 1000
    return int(t)


def _df_gps_time_us(m: Any, t_us: int) -> int:
    """A GPS message's boot time. Before TimeUS (ArduPilot 3.2 and older) a GPS message's
    TimeMS is the receiver's GPS time of week and its boot time is the field ``T`` (ms): read
    as boot time, every fix would lie days after the IMU samples and never be fused."""
    if getattr(m, "TimeUS", None) is None:
        boot_ms = getattr(m, "T", None)
        if boot_ms is not None:
            return int(boot_ms) * 1000
    return t_us


def close_dfreader(reader: Any) -> None:
    """Release a DFReader's file: it keeps an mmap and the file open until collected."""
    for name in ("data_map", "filehandle"):
        handle = getattr(reader, name, None)
        if handle is not None:
            with contextlib.suppress(Exception):
                handle.close()


def _best_gps_instance(rows: list[tuple[Any, ...]]) -> tuple[list[int], int, str]:
    """The instances logged, the one to use and why: the one with the most 3-D fixes (what
    ArduPilot's GPS auto-switch favours; the log does not say which one the EKF fused), the
    lowest on a tie (the primary)."""
    inst = sorted({int(r[0]) for r in rows})
    good = {i: sum(1 for r in rows if r[0] == i and (r[2] or 0) >= 3) for i in inst}
    use = max(inst, key=lambda i: (good[i], -i))
    why = ", ".join(f"{good[i]} 3-D fixes on {i}" for i in inst)
    return inst, use, f"most 3-D fixes: {why}"


def read_dataflash(path: Path, *, salvage: bool = False,
                   imu_instance: int | None = None) -> FlightLog:
    """ArduPilot: `IMU` (first instance unless told), `GPS` (first instance), and the
    references `ATT`, `AHR2`, `XKF1` (EKF3) and `NKF1` (EKF2, older logs), core 0, when
    logged."""
    from pymavlink import DFReader

    bad_at, damage = _chain_damage(path, check_dataflash_chain(path.read_bytes()),
                                   "ArduPilot DataFlash", salvage, "pymavlink resynchronised")
    types = ["IMU", "IMU2", "IMU3", "GPS", "ATT", "AHR2", "XKF1", "NKF1"]
    rows: dict[str, list[tuple[Any, ...]]] = {t: [] for t in types}
    quiet = io.StringIO()
    reader: Any = None
    try:
        with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet):
            reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
            while True:
                m = reader.recv_match(type=types)
                if m is None:
                    break
                name = m.get_type()
                t = _df_time_us(m)
                if t is None:
                    continue
                if name.startswith("IMU"):
                    inst = int(getattr(m, "I", 0) or 0) if name == "IMU" else int(name[3]) - 1
                    rows["IMU"].append((inst, t, m.GyrX, m.GyrY, m.GyrZ, m.AccX, m.AccY,
                                        m.AccZ, getattr(m, "T", math.nan)))
                elif name == "GPS":
                    t = _df_gps_time_us(m, t)
                    rows[name].append((int(getattr(m, "I", 0) or 0), t,
                                       *(getattr(m, f, math.nan) for f in
                                         ("Status", "NSats", "HDop", "Lat", "Lng", "Alt", "Spd",
                                          "GCrs", "VZ"))))
                elif name in ("XKF1", "NKF1"):
                    rows[name].append((int(getattr(m, "C", 0) or 0), t, m.Roll, m.Pitch, m.Yaw))
                else:
                    rows[name].append((0, t, m.Roll, m.Pitch, m.Yaw))
    except Exception as exc:  # noqa: BLE001 - pymavlink raises bare Exceptions on bad data
        raise LogReadError(path, f"ArduPilot DataFlash: pymavlink cannot parse it ({exc})",
                           bad_at) from None
    finally:
        close_dfreader(reader)
    notes: list[str] = []
    imu_rows = rows["IMU"]
    instances = sorted({r[0] for r in imu_rows})
    temperature = None
    if not imu_rows:
        # a partial replay (its GPS and references listed), not a refusal
        notes.append("ArduPilot DataFlash: no IMU messages")
        imu = empty_imu("none")
    else:
        use = instances[0] if imu_instance is None else imu_instance
        if use not in instances:
            raise LogReadError(path, f"ArduPilot DataFlash: no IMU instance {use} "
                                     f"(instances: {instances})")
        if len(instances) > 1:
            notes.append(f"IMU instances {instances} logged: instance {use} used (the first: "
                         "the autopilot's primary IMU unless its parameters chose another)")
        a = np.array([r[1:] for r in imu_rows if r[0] == use], dtype=float)
        imu = ImuSeries(a[:, 0].astype(np.int64), a[:, 1:4].copy(), a[:, 4:7].copy(),
                        f"IMU[{use}]")
        temperature = _temperature(a[:, 0], a[:, 7], f"IMU[{use}].T")
    gps = None
    if rows["GPS"]:
        g_inst, g_use, why = _best_gps_instance(rows["GPS"])
        if len(g_inst) > 1:
            notes.append(f"GPS instances {g_inst} logged: instance {g_use} used ({why})")
        g = np.array([r[1:] for r in rows["GPS"] if r[0] == g_use], dtype=float)
        n = len(g)
        gps = GpsSeries(
            t_us=g[:, 0].astype(np.int64), fix=_fix_code(g[:, 1]), sats=g[:, 2],
            hdop=g[:, 3], lat_deg=g[:, 4], lon_deg=g[:, 5], alt_m=g[:, 6],
            h_std_m=_nan(n), v_std_m=_nan(n), vn_m_s=_nan(n), ve_m_s=_nan(n),
            vd_m_s=g[:, 9], speed_m_s=g[:, 7], course_deg=g[:, 8], source=f"GPS[{g_use}]")
    refs = []
    for name in ("ATT", "AHR2", "XKF1", "NKF1"):
        r = rows[name]
        if not r:
            continue
        cores = sorted({x[0] for x in r})
        if len(cores) > 1:
            notes.append(f"{name} cores {cores} logged: core {cores[0]} used")
        a = np.array([x[1:] for x in r if x[0] == cores[0]], dtype=float)
        refs.append(AttitudeSeries(name, a[:, 0].astype(np.int64), np.radians(a[:, 1]),
                                   np.radians(a[:, 2]), np.radians(a[:, 3])))
    return FlightLog(path, "ardupilot-dataflash", imu, gps, refs, notes, damage,
                     {"imu_instances": instances}, temperature)
