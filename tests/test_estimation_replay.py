"""`companion estimation replay`: PX4 and ArduPilot logs through the flight's estimator.

The DataFlash tests here write logs from a simulated flight (`record_flight`), to have truth:
`write_dataflash` follows the documented format (FMT records, then IMU/GPS/ATT messages,
little-endian, 0xA3 0x95 headers) and every file it writes is read back with pymavlink's
`DFReader` first. The PX4 tests use the real `tests/data/px4-ulog/sample.ulg` (no GPS: the
IMU-only path). Real logs of every kind are read in tests/test_estimation_replay_sources.py.
"""

from __future__ import annotations

import json
import math
import struct
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from companion.estimation.replay.output import summary_dict, write_estimate_log
from companion.estimation.replay.runner import ReplayOptions, clean_timeline, replay
from companion.estimation.replay.sources import LogReadError, close_dfreader, read_flight_log
from companion.evaluation.sitl import FlightSpec, SitlRecording, record_flight
from companion.evaluation.sitl_estimator import run_eskf
from companion.logs import read_log

REPO = Path(__file__).resolve().parents[1]
SAMPLE_ULG = REPO / "tests" / "data" / "px4-ulog" / "sample.ulg"

# ------------------------------------------------------------------ a small DataFlash writer
DF_STRUCT = {"B": "B", "b": "b", "H": "H", "h": "h", "I": "I", "i": "i", "f": "f", "d": "d",
             "Q": "Q", "q": "q", "c": "h", "C": "H", "e": "i", "E": "I", "L": "i", "n": "4s",
             "N": "16s", "Z": "64s"}
DF_SCALE = {"c": 100.0, "C": 100.0, "e": 100.0, "E": 100.0, "L": 1e7}
DF_MESSAGES = {  # name: (type id, format, columns), as ArduPilot 4.x logs them
    "FMT": (128, "BBnNZ", "Type,Length,Name,Format,Columns"),
    "IMU": (1, "QBffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ"),
    "GPS": (2, "QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,"
                                 "Yaw,U"),
    "ATT": (3, "QccccCCffB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF"),
}


IMU_WITH_T = (1, "QBffffffIIf", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T")
"""ArduPilot 4.x's IMU message as far as its temperature (error counts, then T in C)."""


def _df_struct(fmt: str) -> struct.Struct:
    return struct.Struct("<" + "".join(DF_STRUCT[c] for c in fmt))


def df_fmt(name: str, spec: tuple[int, str, str] | None = None) -> bytes:
    type_id, fmt, columns = spec or DF_MESSAGES[name]
    length = 3 + _df_struct(fmt).size
    return b"\xa3\x95\x80" + _df_struct("BBnNZ").pack(type_id, length, name.encode(),
                                                      fmt.encode(), columns.encode())


def df_msg(name: str, *values: float, spec: tuple[int, str, str] | None = None) -> bytes:
    type_id, fmt, _ = spec or DF_MESSAGES[name]
    packed = []
    for c, v in zip(fmt, values, strict=True):
        if c in DF_SCALE:
            v = int(round(v * DF_SCALE[c]))
        elif c in "BbHhIiQq":
            v = int(v)
        packed.append(v)
    return b"\xa3\x95" + bytes([type_id]) + _df_struct(fmt).pack(*packed)


Row = tuple[int, tuple[float, ...]]


@dataclass
class Rows:
    """A simulated flight as log rows (times in us), to be edited and written."""

    imu: list[Row]
    gps: list[Row]
    att: list[Row]


def flight_rows(rec: SitlRecording, imu_rate_hz: float = 100.0, gps: bool = True) -> Rows:
    """IMU (resampled to `imu_rate_hz` by linear interpolation), GPS and ATT (= truth) rows."""
    t_s = rec.t_s
    gyro, accel = rec.imu_arrays()
    t_new = np.arange(t_s[0], t_s[-1] + 1e-9, 1.0 / imu_rate_hz)
    g = np.column_stack([np.interp(t_new, t_s, gyro[:, i]) for i in range(3)])
    a = np.column_stack([np.interp(t_new, t_s, accel[:, i]) for i in range(3)])
    imu = [(int(round(t * 1e6)), (*g[k], *a[k])) for k, t in enumerate(t_new)]
    gps_rows = []
    if gps:
        for k, fix in sorted(rec.gps.items()):
            vd = float(rec.vel_true_m_s[max(0, k - 5), 2])  # at the fix's validity time
            gps_rows.append((fix.t_ns // 1000, (
                3, 0, 0, fix.sats or 9, fix.hdop or 1.0, fix.lat_deg, fix.lon_deg, fix.alt_m,
                fix.speed_m_s or 0.0, fix.course_deg or 0.0, vd, 0.0, 1)))
    att = [(int(round(t * 1e6)), tuple(math.degrees(x) for x in rec.euler_true_rad[k]))
           for k, t in enumerate(t_s)]
    return Rows(imu, gps_rows, att)


def write_dataflash(path: Path, rows: Rows, *, imu_instances: int = 1,
                    imu_temperature_c: Callable[[float], float] | None = None) -> Path:
    """Write `rows` as a DataFlash log, in time order, and check that DFReader reads it.

    ``imu_temperature_c(t_s)``: log the IMU's temperature (field T), as ArduPilot 4.x does;
    None writes the older IMU message without it."""
    from pymavlink import DFReader

    imu_spec = IMU_WITH_T if imu_temperature_c is not None else None
    out = [df_fmt(n, imu_spec if n == "IMU" else None) for n in DF_MESSAGES]
    events: list[tuple[int, int, bytes]] = []
    for t, v in rows.imu:
        for inst in range(imu_instances):
            bias = 0.01 * inst  # a second IMU with a gyro bias, to be told apart
            values = [t, inst, v[0] + bias, v[1], v[2], *v[3:6]]
            if imu_temperature_c is not None:
                values += [0, 0, imu_temperature_c(t / 1e6)]
            events.append((t, 0, df_msg("IMU", *values, spec=imu_spec)))
    for t, v in rows.gps:
        events.append((t, 1, df_msg("GPS", t, 0, *v)))
    for t, (r, p, y) in rows.att:
        events.append((t, 2, df_msg("ATT", t, r, r, p, p, y % 360.0, y % 360.0, 0.0, 0.0, 3)))
    events.sort(key=lambda e: (e[0], e[1]))
    out.extend(e[2] for e in events)
    path.write_bytes(b"".join(out))
    reader = DFReader.DFReader_binary(str(path))
    counts: dict[str, int] = {}
    while (m := reader.recv_match(type=["IMU", "GPS", "ATT"])) is not None:
        counts[m.get_type()] = counts.get(m.get_type(), 0) + 1
    close_dfreader(reader)
    assert counts.get("IMU", 0) == len(rows.imu) * imu_instances
    assert counts.get("ATT", 0) == len(rows.att)
    assert counts.get("GPS", 0) == len(rows.gps)
    return path


# ------------------------------------------------------------------ a small ULog writer
ULOG_TOPICS = {  # topic: (field definitions, struct format), as PX4 logs them (packed)
    "sensor_combined": ("uint64_t timestamp;float[3] gyro_rad;int32_t "
                        "accelerometer_timestamp_relative;float[3] accelerometer_m_s2;",
                        "<Q3fi3f"),
    "vehicle_gps_position": ("uint64_t timestamp;int32_t lat;int32_t lon;int32_t alt;float eph;"
                             "float epv;float vel_m_s;float vel_n_m_s;float vel_e_m_s;"
                             "float vel_d_m_s;float cog_rad;uint8_t fix_type;bool vel_ned_valid;"
                             "uint8_t satellites_used;", "<Qiii7fBBB"),
    "vehicle_attitude": ("uint64_t timestamp;float[4] q;", "<Q4f"),
}


def _ulog_msg(kind: str, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def write_ulog(path: Path, rec: SitlRecording) -> Path:
    """A PX4 ULog (format 'F', subscription 'A', data 'D' messages) of a simulated flight."""
    from companion.estimation.quat import quat_from_euler

    out = [b"ULog\x01\x12\x35\x01" + struct.pack("<Q", 0)]
    for name, (fields, _) in ULOG_TOPICS.items():
        out.append(_ulog_msg("F", f"{name}:{fields}".encode()))
    for msg_id, name in enumerate(ULOG_TOPICS):
        out.append(_ulog_msg("A", struct.pack("<BH", 0, msg_id) + name.encode()))
    packers = [struct.Struct(fmt) for _, fmt in ULOG_TOPICS.values()]
    events: list[tuple[int, int, bytes]] = []
    gyro, accel = rec.imu_arrays()
    q = quat_from_euler(rec.euler_true_rad[:, 0], rec.euler_true_rad[:, 1],
                        rec.euler_true_rad[:, 2])
    for k, t in enumerate(rec.t_s):
        t_us = int(round(t * 1e6))
        events.append((t_us, 0, packers[0].pack(t_us, *gyro[k], 0, *accel[k])))
        events.append((t_us, 2, packers[2].pack(t_us, *q[k])))
    for k, fix in sorted(rec.gps.items()):
        # the receiver's horizontal velocity; the vertical one from the truth at the fix's
        # validity time (handed off 50 ms = 5 ticks later)
        vn, ve = fix.vn_m_s or 0.0, fix.ve_m_s or 0.0
        vd = float(rec.vel_true_m_s[max(0, k - 5), 2])
        events.append((fix.t_ns // 1000, 1, packers[1].pack(
            fix.t_ns // 1000, round(fix.lat_deg * 1e7), round(fix.lon_deg * 1e7),
            round(fix.alt_m * 1e3), 1.2, 1.8, fix.speed_m_s or 0.0, vn, ve, vd,
            math.radians(fix.course_deg or 0.0), 3, 1, 9)))
    events.sort(key=lambda e: (e[0], e[1]))
    out.extend(_ulog_msg("D", struct.pack("<H", i) + body) for _, i, body in events)
    path.write_bytes(b"".join(out))
    return path


@pytest.fixture(scope="module")
def flight() -> SitlRecording:
    # no level calibration: the logs written from it carry no trims the replay could apply, so
    # the thread-equivalent run it is held to must not have them either
    return record_flight(FlightSpec(duration_s=40, level_calibration=False))


@pytest.fixture(scope="module")
def thread_errors(flight: SitlRecording) -> dict[str, float]:
    """The same flight through the SITL evaluation's thread-equivalent run (`run_eskf`): what
    the replay is held to, so the bounds follow the simulator's sensor models."""
    return truth_errors_deg(None, flight, quat=run_eskf(flight).quat, t_s=flight.t_s)


def assert_close_to_thread(err: dict[str, float], ref: dict[str, float]) -> None:
    """Replayed from a log, the estimate is about as good as the thread's on the same flight
    (the log carries less: no measured GPS latency, its own GPS accuracy fields)."""
    assert err["incl"] < 1.5 * ref["incl"] + 0.5, (err, ref)
    assert err["heading"] < 1.5 * ref["heading"] + 1.0, (err, ref)


def truth_errors_deg(result: object, rec: SitlRecording, from_s: float = 10.0,
                     t0_s: float = 0.0, quat: np.ndarray | None = None,
                     t_s: np.ndarray | None = None) -> dict[str, float]:
    """An estimate against the simulator's truth from `from_s`: inclination and heading RMSE.
    `result` is a replay's (its log times less `t0_s`), or `quat` at times `t_s`."""
    from companion.estimation.quat import heading_error_rad, inclination_error_rad

    if quat is None:
        est = result.estimate  # type: ignore[attr-defined]
        quat, t_s = est.quat_wxyz, est.t_us / 1e6 - t0_s
    assert t_s is not None
    k = np.clip(np.round(t_s * 100).astype(int) - 1, 0, rec.ticks - 1)
    mask = (t_s >= from_s) & np.isfinite(quat).all(axis=1)
    incl = np.degrees(inclination_error_rad(quat[mask], rec.quat_true[k[mask]]))
    head = np.degrees(heading_error_rad(quat[mask], rec.quat_true[k[mask]]))
    return {"incl": float(np.sqrt(np.mean(incl ** 2))),
            "heading": float(np.sqrt(np.mean(head ** 2)))}


# ------------------------------------------------------------------ PX4 ULog (real)
def test_px4_sample_imu_only_matches_ekf2() -> None:
    fl = read_flight_log(SAMPLE_ULG)
    assert fl.kind == "px4-ulog" and fl.gps is None
    assert [r.name for r in fl.references] == ["vehicle_attitude"]
    res = replay(fl)
    assert res.estimator == "attitude"
    assert res.timelines["imu"].rate_hz == pytest.approx(250.0)
    m = res.comparisons[0].metrics
    assert m["samples_compared"] > 5000
    # a bench log, hand-tilted by +-20 deg: our IMU-only filter and EKF2 agree within tenths
    assert m["roll_deg"]["rmse"] < 0.5 and m["pitch_deg"]["rmse"] < 0.5
    assert m["inclination_deg"]["max"] < 3.0


def test_truncated_ulog_reads_what_is_whole_and_strict_refuses(tmp_path: Path) -> None:
    data = SAMPLE_ULG.read_bytes()
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(data[: len(data) // 2 + 7])
    with pytest.raises(LogReadError) as info:
        read_flight_log(cut, strict=True)
    assert info.value.offset is not None and 0 < info.value.offset <= len(data) // 2 + 7
    assert "cut.ulg" in str(info.value) and "cut short" in str(info.value)
    flight = read_flight_log(cut)  # the default: a cut last message is a note, not an error
    assert flight.damage is None and len(flight.imu.t_us) > 5000
    assert any("cut short" in n and "byte offset" in n for n in flight.notes)
    assert replay(flight).estimate.t_us.size > 0


@pytest.mark.parametrize("content", [b"", b"garbage" * 50, b"ULog\x01\x12\x35\x01" + b"\xff" * 9,
                                     b"\xa3\x95\x80" + b"\x00" * 10])
def test_garbage_is_one_error(tmp_path: Path, content: bytes) -> None:
    bad = tmp_path / "bad.bin"
    bad.write_bytes(content)
    with pytest.raises(LogReadError) as info:
        read_flight_log(bad)
    assert str(info.value).startswith(str(bad))


def test_px4_ulog_with_gps_runs_the_eskf(flight: SitlRecording, thread_errors: dict[str, float],
                                         tmp_path: Path) -> None:
    fl = read_flight_log(write_ulog(tmp_path / "sim.ulg", flight))
    assert fl.gps is not None and fl.gps.source == "vehicle_gps_position"
    assert fl.gps.valid.all() and abs(fl.gps.alt_m[0] - flight.gps[min(flight.gps)].alt_m) < 0.01
    res = replay(fl, ReplayOptions(skip_s=10.0))
    assert res.estimator == "eskf" and res.stats["faults"] == 0
    err = truth_errors_deg(res, flight)
    assert_close_to_thread(err, thread_errors)
    m = res.comparisons[0].metrics  # vehicle_attitude is the truth here
    assert m["inclination_deg"]["rmse"] < 1.5 * thread_errors["incl"] + 0.5
    forced = replay(fl, ReplayOptions(estimator="attitude", params={"EST_GPS_LAG": 0.1}))
    assert forced.estimator == "attitude"
    with pytest.raises(ValueError, match="unknown estimator parameter"):
        replay(fl, ReplayOptions(params={"NOPE": 1.0}))


# ------------------------------------------------------------------ DataFlash (simulated)
def test_dataflash_with_gps_runs_the_eskf_against_truth(
        flight: SitlRecording, thread_errors: dict[str, float], tmp_path: Path) -> None:
    path = write_dataflash(tmp_path / "sim.bin", flight_rows(flight), imu_instances=2)
    fl = read_flight_log(path)
    assert fl.kind == "ardupilot-dataflash" and fl.imu.source == "IMU[0]"
    assert any("IMU instances logged (samples): 0: " in n and "instance 0 used" in n
               for n in fl.notes)
    res = replay(fl)
    assert res.estimator == "eskf" and res.stats["started"]
    # the log starts in flight at 50 m/s (straight and level: no moving start needed)
    assert res.stats["faults"] == 0 and res.stats["gps_accepted"] > 300
    assert_close_to_thread(truth_errors_deg(res, flight), thread_errors)
    m = res.comparisons[0].metrics  # ATT is the truth here
    assert m["inclination_deg"]["rmse"] < 1.5 * thread_errors["incl"] + 0.5 and m["yaw_samples_compared"] > 1000
    # the binary log holds ours and theirs, read by the project's reader
    write_estimate_log(res, tmp_path)
    lg = read_log(tmp_path / "estimate.bin")
    assert len(lg.data(1)) == len(res.estimate.t_us) and "ATT_roll_rad" in lg.data(2).dtype.names
    json.dumps(summary_dict(res, {}), allow_nan=False)


def test_dataflash_imu_temperature_reaches_the_filter(flight: SitlRecording,
                                                      tmp_path: Path) -> None:
    t_start = flight.t_s[0]

    def warm(t_s: float) -> float:  # a part warming 20 -> 40 C over the flight
        return 20.0 + 20.0 * (1.0 - math.exp(-(t_s - t_start) / 60.0))

    path = write_dataflash(tmp_path / "warm.bin", flight_rows(flight), imu_temperature_c=warm)
    fl = read_flight_log(path)
    assert fl.temperature is not None and fl.temperature.source == "IMU[0].T"
    res = replay(fl)
    duration_s = flight.t_s[-1] - t_start
    # once a second, from the filter's start (after its initial phase)
    assert duration_s - 10 <= res.stats["temperature_readings"] <= duration_s + 1
    assert any("IMU temperature from IMU[0].T: 20.0 to" in n for n in res.notes)
    assert "temperature" in res.timelines
    # the older IMU message has no T: the replay says the walk stays off
    plain = replay(read_flight_log(write_dataflash(tmp_path / "plain.bin", flight_rows(flight))))
    assert plain.stats["temperature_readings"] == 0
    assert any("no IMU temperature" in n for n in plain.notes)
    # a sensor's "not available" code is not a temperature
    bad = write_dataflash(tmp_path / "bad.bin", flight_rows(flight),
                          imu_temperature_c=lambda t_s: -273.0)
    assert read_flight_log(bad).temperature is None


def test_dataflash_without_gps_is_imu_only(flight: SitlRecording, tmp_path: Path) -> None:
    path = write_dataflash(tmp_path / "nogps.bin", flight_rows(flight, gps=False))
    res = replay(read_flight_log(path))
    assert res.estimator == "attitude" and "no GPS" in res.estimator_reason
    assert res.comparisons[0].metrics["yaw_offset_removed_deg"] is not None


@pytest.mark.parametrize("rate_hz", [50.0, 500.0, 1000.0])
def test_other_imu_rates(flight: SitlRecording, thread_errors: dict[str, float], tmp_path: Path,
                        rate_hz: float) -> None:
    path = write_dataflash(tmp_path / "rate.bin", flight_rows(flight, imu_rate_hz=rate_hz))
    res = replay(read_flight_log(path))
    assert res.estimator == "eskf"
    assert res.timelines["imu"].rate_hz == pytest.approx(rate_hz, rel=0.01)
    assert res.stats["faults"] == 0
    assert_close_to_thread(truth_errors_deg(res, flight), thread_errors)


def test_imu_gap_duplicates_and_clock_jump(flight: SitlRecording, thread_errors: dict[str, float],
                                           tmp_path: Path) -> None:
    rows = flight_rows(flight)
    # a 2 s IMU gap from 15 s, five duplicated samples at 20 s, and at 25 s the clock of
    # every stream steps back by 100 s (the boot clock stood at 1000 s)
    rows.imu = [r for r in rows.imu if not 15e6 <= r[0] < 17e6]
    dup_at = next(i for i, r in enumerate(rows.imu) if r[0] >= 20e6)
    rows.imu[dup_at:dup_at] = rows.imu[dup_at:dup_at + 5]

    def part(rs: list[Row], late: bool) -> list[Row]:
        return [(t + 1_000_000_000 - (100_000_000 if late else 0), v) for t, v in rs
                if (t >= 25e6) == late]

    # written one part after the other, as the logger wrote them
    early = Rows(part(rows.imu, False), part(rows.gps, False), part(rows.att, False))
    late = Rows(part(rows.imu, True), part(rows.gps, True), part(rows.att, True))
    first = write_dataflash(tmp_path / "a.bin", early).read_bytes()
    second = write_dataflash(tmp_path / "b.bin", late).read_bytes()
    path = tmp_path / "messy.bin"
    path.write_bytes(first + second[len(DF_MESSAGES) * 89:])
    res = replay(read_flight_log(path))
    imu = res.timelines["imu"]
    assert imu.duplicates == 5
    assert len(imu.clock_jumps) == 1 and imu.clock_jumps[0][1] == pytest.approx(-100, abs=0.1)
    assert len(res.timelines["gps"].clock_jumps) == 1
    assert [round(g, 1) for _, g in imu.gaps] == [2.0]
    # 2 s without IMU in a 30 deg turn: the ESKF coasts, its position is then off by more
    # than its gate allows and it resets on the GPS (a fault, reported, as in flight)
    assert res.estimator == "eskf" and res.stats["faults"] <= 1
    assert res.stats["faults"] == 0 or any("reset" in n for n in res.notes)
    # our times are continuous again: the truth lines up after the corrected jump, and the
    # filter has recovered from the gap (it takes about 15 s to come back within 2 deg)
    err = truth_errors_deg(res, flight, from_s=33.0, t0_s=1000.0)
    assert_close_to_thread(err, thread_errors)
    assert res.comparisons[0].metrics["inclination_deg"]["max"] < 30.0


def test_clean_timeline_unit() -> None:
    t = np.array([0, 10, 10, 20, 15, 30, 1_000_000, 1_000_010, 10, 20], dtype=np.int64) * 1000
    keep, tc, tl, shifts = clean_timeline(t, "x", 0)
    assert tl.duplicates == 1 and tl.out_of_order == 1 and len(tl.clock_jumps) == 1
    assert np.all(np.diff(tc) > 0) and len(shifts) == 1
    assert [round(g, 2) for _, g in tl.gaps] == [999.97]


def test_truncated_dataflash(flight: SitlRecording, tmp_path: Path) -> None:
    data = write_dataflash(tmp_path / "ok.bin", flight_rows(flight)).read_bytes()
    cut = tmp_path / "cut.bin"
    cut.write_bytes(data[:-5])
    with pytest.raises(LogReadError) as info:
        read_flight_log(cut, strict=True)
    assert "cut short" in str(info.value) and info.value.offset is not None
    whole = read_flight_log(cut)
    assert whole.damage is None and any("cut short" in n for n in whole.notes)
    # 100 bytes of noise in the middle: skipped and reported by default, refused when strict
    middle = len(data) // 2
    damaged = tmp_path / "damaged.bin"
    damaged.write_bytes(data[:middle] + bytes(range(7, 107)) + data[middle:])
    with pytest.raises(LogReadError) as info:
        read_flight_log(damaged, strict=True)
    assert info.value.offset is not None and abs(info.value.offset - middle) <= 100
    salvaged = read_flight_log(damaged, salvage=True)  # --salvage: accepted, the default
    assert salvaged.damage is not None and len(salvaged.imu.t_us) > 3900
    assert replay(salvaged).estimator == "eskf"


# ------------------------------------------------------------------ the real command
def _cli(*args: str, timeout_s: float = 120.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion", "estimation", "replay", *args],
                          capture_output=True, text=True, timeout=timeout_s, cwd=REPO)


def test_cli_replays_the_px4_sample(tmp_path: Path) -> None:
    proc = _cli(str(SAMPLE_ULG), "-o", str(tmp_path))
    out = tmp_path / "sample-replay"
    assert proc.returncode == 0, proc.stderr
    assert "vehicle_attitude" in proc.stdout and "IMU-only" in proc.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["estimator"] == "attitude"
    assert summary["comparisons"]["vehicle_attitude"]["roll_deg"]["rmse"] < 0.5
    assert (out / "replay.png").stat().st_size > 10_000
    assert read_log(out / "estimate.bin").closed_cleanly


def test_cli_bad_files_exit_2(tmp_path: Path) -> None:
    garbage = tmp_path / "junk.bin"
    garbage.write_bytes(b"\x00\x01junk" * 100)
    empty = tmp_path / "empty.ulg"
    empty.write_bytes(b"")
    for path in (garbage, empty, tmp_path / "missing.ulg"):
        proc = _cli(str(path), "-o", str(tmp_path / "o"), timeout_s=60.0)
        assert proc.returncode == 2, proc.stderr
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and path.name in lines[0] and "Traceback" not in proc.stderr
    assert "byte offset" in _cli(str(garbage), timeout_s=60.0).stderr
