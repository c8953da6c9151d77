"""The replay's log readers on real logs of every kind, cut, damaged and malformed.

Real files (tests/data/replay/, provenance in tests/data/README.md): an ArduPlane 3.8 DataFlash
log from pymavlink's tests (ends inside its last message, as the issue's logs did), PX4 ULogs
of v1.11 (a CubeOrange) and v1.15-dev (SITL) from pyulog's tests, and an ArduPlane telemetry
log (the project's recorded SITL link, stamped as a ground station does). Each reading is checked against what pymavlink
or pyulog read from the same bytes, so the readers are checked against another reading, not
against themselves. The older DataFlash generation (ArduCopter 3.1: TimeMS, IMU/IMU2 types,
GPS dated by GPS week and boot time T) is written here from its documented layout.
"""

from __future__ import annotations

import io
import struct
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from companion.estimation.replay.dfwalk import walk_dataflash
from companion.estimation.replay.sources import LogReadError, close_dfreader, read_flight_log
from companion.estimation.replay.tlog import walk_tlog
from companion.estimation.replay.ulog import walk_ulog
from tests.conftest import data_file
from tests.support.replay_logs import dataflash_head, repeat_dataflash, stamp_capture_as_tlog

REPO = Path(__file__).resolve().parents[1]
DF_REAL = ("replay", "arduplane-pymavlink-test.bin")
ULOG_115 = ("replay", "px4-v1.15dev-sitl.ulg")
ULOG_111 = ("replay", "px4-v1.11-cubeorange.ulg")
TLOG = ("replay", "arduplane-sitl.tlog")
ALL_REAL = [DF_REAL, ULOG_115, ULOG_111, TLOG, ("px4-ulog", "sample.ulg")]


def _copy(tmp_path: Path, parts: tuple[str, ...], data: bytes | None = None) -> Path:
    src = data_file(*parts)
    out = tmp_path / src.name
    out.write_bytes(src.read_bytes() if data is None else data)
    return out


# ------------------------------------------------------------------ real logs, whole
def test_real_dataflash_matches_pymavlink() -> None:
    from pymavlink import DFReader

    path = data_file(*DF_REAL)
    fl = read_flight_log(path)
    reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
    rows: dict[str, list[tuple[float, ...]]] = {"IMU": [], "GPS": [], "NKF1": []}
    while (m := reader.recv_match(type=list(rows))) is not None:
        t = float(m.TimeUS)
        if m.get_type() == "IMU":
            rows["IMU"].append((t, m.GyrX, m.GyrY, m.GyrZ, m.AccX, m.AccY, m.AccZ))
        elif m.get_type() == "GPS":
            rows["GPS"].append((t, m.Lat, m.Lng, m.Alt))
        else:
            rows["NKF1"].append((t, m.Roll, m.Pitch, m.Yaw))
    close_dfreader(reader)
    imu = np.array(rows["IMU"])
    assert fl.kind == "ardupilot-dataflash" and fl.imu.source == "IMU[0]"
    assert np.array_equal(fl.imu.t_us, imu[:, 0].astype(np.int64))
    assert np.allclose(fl.imu.gyro_rad_s, imu[:, 1:4]) and np.allclose(fl.imu.accel_m_s2,
                                                                        imu[:, 4:7])
    gps = np.array(rows["GPS"])
    assert fl.gps is not None and np.allclose(fl.gps.lat_deg, gps[:, 1])
    assert np.allclose(fl.gps.alt_m, gps[:, 3]) and fl.gps.valid.all()
    nkf1 = next(r for r in fl.references if r.name == "NKF1")
    assert np.allclose(np.degrees(nkf1.yaw_rad), np.array(rows["NKF1"])[:, 3])
    assert fl.available_references == ["ATT", "AHR2", "NKF1"]
    # the file ends inside an AHR2 message: a note with its offset, not damage
    assert fl.damage is None and len(fl.skipped) == 1 and fl.skipped[0].tail
    assert fl.skipped[0].offset == 65512 and "AHR2" in fl.notes[0]
    assert any("IMU instances logged (samples): 0: 45, 1: 45; instance 0 used" in n
               for n in fl.notes)
    assert fl.temperature is not None


def test_real_tlog_matches_pymavlink() -> None:
    from pymavlink import mavutil

    path = data_file(*TLOG)
    fl = read_flight_log(path)
    conn = mavutil.mavlink_connection(str(path))
    raw, gps = [], []
    while (m := conn.recv_match(type=["RAW_IMU", "GPS_RAW_INT"])) is not None:
        if m.get_type() == "RAW_IMU":
            raw.append((m.time_usec, m.xgyro, m.zacc))
        else:
            gps.append((m.lat, m.alt))
    conn.close()
    r = np.array(raw, dtype=float)
    assert fl.kind == "mavlink-tlog" and fl.imu.source == "RAW_IMU[sys 1]"
    assert np.array_equal(fl.imu.t_us, r[:, 0].astype(np.int64))
    assert np.allclose(fl.imu.gyro_rad_s[:, 0], r[:, 1] / 1000.0)  # mrad/s
    assert np.allclose(fl.imu.accel_m_s2[:, 2], r[:, 2] * 9.80665e-3)  # mG
    assert abs(np.median(fl.imu.accel_m_s2[:, 2]) + 9.8) < 0.3  # on the ground: -1 g
    assert fl.gps is not None and len(fl.gps) == len(gps)
    assert np.allclose(fl.gps.alt_m, np.array(gps)[:, 1] / 1000.0)
    assert [r.name for r in fl.references] == ["ATTITUDE", "AHRS2"]
    assert fl.skipped == [] and fl.damage is None


@pytest.mark.parametrize("parts", [ULOG_115, ULOG_111])
def test_real_ulogs_of_two_px4_versions(parts: tuple[str, ...]) -> None:
    from pyulog import ULog

    fl = read_flight_log(data_file(*parts))
    ref = ULog(str(data_file(*parts)), message_name_filter_list=["sensor_combined"])
    sc = ref.get_dataset("sensor_combined").data
    assert np.array_equal(fl.imu.t_us, sc["timestamp"].astype(np.int64))
    assert fl.gps is not None and fl.gps.source == "vehicle_gps_position" and fl.gps.valid.any()
    assert fl.references[0].name == "vehicle_attitude" and fl.skipped == []


# ------------------------------------------------------------------ cut and damaged
@pytest.mark.parametrize("parts", ALL_REAL)
def test_a_cut_last_message_is_a_note_and_strict_refuses(tmp_path: Path,
                                                        parts: tuple[str, ...]) -> None:
    data = data_file(*parts).read_bytes()
    whole = read_flight_log(data_file(*parts))
    for keep in (len(data) - 5, int(len(data) * 0.8) + 3):
        cut = _copy(tmp_path, parts, data[:keep])
        fl = read_flight_log(cut)
        assert fl.damage is None and fl.skipped and fl.skipped[-1].tail
        assert fl.skipped[-1].offset + fl.skipped[-1].length == keep
        assert any("byte offset" in n for n in fl.notes)
        assert 0.5 * len(whole.imu.t_us) < len(fl.imu.t_us) <= len(whole.imu.t_us)
        with pytest.raises(LogReadError) as info:
            read_flight_log(cut, strict=True)
        assert info.value.offset == fl.skipped[-1].offset and cut.name in str(info.value)


@pytest.mark.parametrize("parts", ALL_REAL)
def test_damage_in_the_middle_is_skipped_and_reported(tmp_path: Path,
                                                      parts: tuple[str, ...]) -> None:
    data = data_file(*parts).read_bytes()
    whole = read_flight_log(data_file(*parts))
    at = len(data) // 2
    noise = bytes((i * 37 + 11) % 256 for i in range(300))
    bad = _copy(tmp_path, parts, data[:at] + noise + data[at:])
    fl = read_flight_log(bad)
    inner = [s for s in fl.skipped if not s.tail]
    assert inner and fl.damage is not None and "byte offset" in fl.damage
    # the noise starts inside a record, which is read with the noise's first bytes in it (its
    # length said so); the chain breaks at most one record later, and the skipped region ends
    # at the first whole record after the noise: only records the noise touched are lost
    assert at - 300 <= inner[0].offset <= at + 300
    assert inner[0].offset + inner[0].length >= at + 300
    assert len(whole.imu.t_us) - 5 <= len(fl.imu.t_us) <= len(whole.imu.t_us)
    with pytest.raises(LogReadError) as info:
        read_flight_log(bad, strict=True)
    assert info.value.offset == inner[0].offset


@pytest.mark.parametrize("parts", [DF_REAL, ULOG_115, TLOG])
def test_megabytes_of_noise_are_skipped_exactly(tmp_path: Path, parts: tuple[str, ...]) -> None:
    """2 MiB of random bytes between two whole records: no false resynchronisation inside them
    (noise often looks like one record; the readers ask for several in a row, a known message
    with a good CRC, a time near the last one), so exactly the noise is skipped."""
    data = data_file(*parts).read_bytes()
    whole = read_flight_log(data_file(*parts))
    at = _boundary_before(parts, data, len(data) // 2)
    noise = np.random.default_rng(7).bytes(2 << 20)
    fl = read_flight_log(_copy(tmp_path, parts, data[:at] + noise + data[at:]))
    inner = [(s.offset, s.length) for s in fl.skipped if not s.tail]
    assert inner == [(at, len(noise))]
    assert len(fl.imu.t_us) == len(whole.imu.t_us)


def _boundary_before(parts: tuple[str, ...], data: bytes, limit: int) -> int:
    """The start of the last record before `limit`, by each format's own framing."""
    if parts == TLOG:
        off = 0
        while True:
            ln = data[off + 9]
            size = 8 + (8 + ln if data[off + 8] == 0xFE else 12 + ln + (13 if data[off + 10] & 1
                                                                        else 0))
            if off + size > limit:
                return off
            off += size
    if parts == DF_REAL:
        from companion.estimation.replay.dfwalk import parse_fmt

        lengths, off = {0x80: 89}, 0
        while True:
            ln = lengths[data[off + 2]]
            if data[off + 2] == 0x80:
                f = parse_fmt(data[off + 3:off + ln])
                lengths[f.type_id] = f.length
            if off + ln > limit:
                return off
            off += ln
    off = 16
    while True:
        size = 3 + (data[off] | data[off + 1] << 8)
        if off + size > limit:
            return off
        off += size


@pytest.mark.parametrize("chunk", [61, 977])
def test_small_chunks_read_the_same(chunk: int) -> None:
    """Records split across chunk boundaries: the walks carry the partial record over."""
    df = data_file(*DF_REAL).read_bytes()
    wanted = frozenset({"IMU", "GPS"})
    a, b = walk_dataflash(io.BytesIO(df), wanted), walk_dataflash(io.BytesIO(df), wanted, chunk)
    assert a.counts == b.counts and [bytes(r) for _, r in a.bodies] == [bytes(r) for _, r in
                                                                       b.bodies]
    assert [(s.offset, s.length) for s in a.skipped] == [(s.offset, s.length) for s in b.skipped]
    damaged = df[:30_000] + b"\xa3\x95" * 40 + df[30_000:]
    a, b = (walk_dataflash(io.BytesIO(damaged), wanted),
            walk_dataflash(io.BytesIO(damaged), wanted, chunk))
    assert a.counts == b.counts and a.skipped == b.skipped and len(a.skipped) == 2
    tl = data_file(*TLOG).read_bytes()[:200_000]
    ta, tb = walk_tlog(io.BytesIO(tl)), walk_tlog(io.BytesIO(tl), chunk)
    assert ta.frames == tb.frames and ta.skipped == tb.skipped
    assert {k: len(v) for k, v in ta.series.items()} == {k: len(v) for k, v in tb.series.items()}
    ul = data_file(*ULOG_115).read_bytes()
    ul = ul[:400_000] + b"\xee" * 50 + ul[400_000:]
    assert walk_ulog(io.BytesIO(ul)) == walk_ulog(io.BytesIO(ul), chunk)


# ------------------------------------------------------------------ an older generation
def _fmt(type_id: int, name: str, letters: str, columns: str) -> bytes:
    size = struct.calcsize("<" + letters.translate(str.maketrans("cCeEL", "hHiIi")))
    return b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", type_id, 3 + size, name.encode(),
                                          letters.encode(), columns.encode())


def _msg(type_id: int, letters: str, *values: float) -> bytes:
    st = "<" + letters.translate(str.maketrans("cCeEL", "hHiIi"))
    return b"\xa3\x95" + bytes([type_id]) + struct.pack(st, *values)


def copter31_log(seconds: float = 20.0, imu0_every: int = 1) -> bytes:
    """An ArduCopter 3.1-style log: IMU and IMU2 types with TimeMS (boot ms), GPS whose TimeMS
    is the GPS time of week (with Week) and whose boot time is `T`, ATT in hundredths of a
    degree. The layouts are ArduCopter 3.1's (LogStructure.h of that release)."""
    imu_l, gps_l, att_l = "Iffffff", "BIHBcLLeeeeeI", "IccccCC"
    out = [_fmt(129, "IMU", imu_l, "TimeMS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ"),
           _fmt(130, "IMU2", imu_l, "TimeMS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ"),
           _fmt(131, "GPS", gps_l, "Status,TimeMS,Week,NSats,HDop,Lat,Lng,RelAlt,Alt,Spd,GCrs,"
                                   "VZ,T"),
           _fmt(132, "ATT", att_l, "TimeMS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw")]
    boot_ms = 30_000
    for k in range(int(seconds * 50)):
        t = boot_ms + 20 * k
        if k % imu0_every == 0:
            out.append(_msg(129, imu_l, t, 0.01, 0.0, 0.0, 0.0, 0.0, -9.81))
        out.append(_msg(130, imu_l, t, 0.02, 0.0, 0.0, 0.0, 0.0, -9.80))
        if k % 10 == 0:
            out.append(_msg(131, gps_l, 3, 345_600_000 + t, 1800, 9, 150, 473977420, 85455940,
                            0, 48812, 0, 0, 0, t))
            out.append(_msg(132, att_l, t, 0, 512, 0, -250, 0, 9000))
    return b"".join(out)


def test_an_arducopter_31_log_reads_by_its_fmt_table(tmp_path: Path) -> None:
    path = tmp_path / "copter31.bin"
    path.write_bytes(copter31_log())
    from pymavlink import DFReader

    reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
    n_gps = sum(1 for _ in iter(lambda: reader.recv_match(type="GPS"), None))
    close_dfreader(reader)
    fl = read_flight_log(path)
    assert fl.imu.source == "IMU[0]" and fl.imu.t_us[0] == 30_000_000
    assert np.all(np.diff(fl.imu.t_us) == 20_000) and fl.imu.gyro_rad_s[0, 0] == pytest.approx(
        0.01)
    assert fl.gps is not None and len(fl.gps) == n_gps == 100
    assert fl.gps.t_us[0] == 30_000_000  # from T (boot ms), not the GPS time of week
    assert fl.gps.alt_m[0] == pytest.approx(488.12) and fl.gps.lat_deg[0] == pytest.approx(
        47.397742)
    att = fl.references[0]
    assert att.name == "ATT" and np.degrees(att.roll_rad[0]) == pytest.approx(5.12)
    assert np.degrees(att.yaw_rad[0]) == pytest.approx(90.0)
    assert any("0: 1000, 1: 1000; instance 0 used" in n for n in fl.notes)
    assert read_flight_log(path, imu_instance=1).imu.gyro_rad_s[0, 0] == pytest.approx(0.02)


def copter4x_log(seconds: float = 4.0) -> bytes:
    """An ArduPilot 4.x-style log: one IMU type with instance `I` and temperature `T`, GPS with
    `I` and GPS week, EKF3's XKF1 for two cores `C` (layouts of ArduPilot 4.1's LogStructure)."""
    imu_l, gps_l, xkf_l = "QBffffffIIfBBHH", "QBBIHBcLLeffffB", "QBccCfffffffccce"
    out = [_fmt(140, "IMU", imu_l, "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,"
                                   "AHz"),
           _fmt(141, "GPS", gps_l, "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,"
                                   "Yaw,U"),
           _fmt(142, "XKF1", xkf_l, "TimeUS,C,Roll,Pitch,Yaw,VN,VE,VD,dPD,PN,PE,PD,GX,GY,GZ,OH")]
    for k in range(int(seconds * 400)):
        t = 5_000_000 + 2500 * k
        for inst in (0, 1, 2):
            out.append(_msg(140, imu_l, t, inst, 0.001 * inst, 0, 0, 0, 0, -9.8, 0, 0,
                            41.5 + inst, 1, 1, 400, 400))
        if k % 80 == 0:
            out.append(_msg(141, gps_l, t, 0, 3, 12345, 2200, 14, 80, 473977420, 85455940,
                            48812, 0.1, 10.0, 0.02, 0.0, 1))  # hundredths and 1e-7 as logged
        if k % 40 == 0:
            for core in (0, 1):
                out.append(_msg(142, xkf_l, t, core, 150 + 100 * core, -200, 18100, 0, 0, 0, 0,
                                0, 0, 0, 0, 0, 0, 0))
    return b"".join(out)


def test_an_ardupilot_4x_log_with_instances_and_cores(tmp_path: Path) -> None:
    path = tmp_path / "ap4.bin"
    path.write_bytes(copter4x_log())
    fl = read_flight_log(path)
    assert fl.imu.source == "IMU[0]" and len(fl.imu.t_us) == 1600
    assert any("0: 1600, 1: 1600, 2: 1600; instance 0 used" in n for n in fl.notes)
    assert fl.temperature is not None and fl.temperature.temperature_c[0] == pytest.approx(41.5)
    assert fl.gps is not None and fl.gps.source == "GPS[0]" and fl.gps.t_us[0] == 5_000_000
    assert fl.gps.valid.all() and fl.gps.alt_m[0] == pytest.approx(488.12)
    (xkf1,) = fl.references
    assert xkf1.name == "XKF1" and len(xkf1.t_us) == 40
    assert np.degrees(xkf1.roll_rad[0]) == pytest.approx(1.5)  # core 0's
    assert np.degrees(xkf1.yaw_rad[0]) == pytest.approx(181.0)
    assert "XKF1 cores [0, 1] logged: core 0 used" in fl.notes
    assert read_flight_log(path, imu_instance=2).imu.gyro_rad_s[0, 0] == pytest.approx(0.002)


def test_an_imu_logged_at_a_lower_rate_is_passed_over(tmp_path: Path) -> None:
    path = tmp_path / "slow_imu0.bin"
    path.write_bytes(copter31_log(4.0, imu0_every=5))
    fl = read_flight_log(path)
    assert fl.imu.source == "IMU[1]" and len(fl.imu.t_us) == 200
    assert any("0: 40, 1: 200; instance 1 used (instance 0 has only 40 samples)" in n
               for n in fl.notes)
    assert read_flight_log(path, imu_instance=0).imu.source == "IMU[0]"


def px4_tlog(seconds: float = 5.0) -> bytes:
    """A PX4-style telemetry log: HIGHRES_IMU (SI units) at 50 Hz, RAW_IMU in raw counts,
    GPS_RAW_INT dated in UNIX time (as some senders do), ATTITUDE; received 30 ms late."""
    from pymavlink.dialects.v20 import ardupilotmega as dialect

    mav = dialect.MAVLink(None, srcSystem=1, srcComponent=1)
    unix0_us, boot0_us = 1_700_000_000_000_000, 12_000_000
    out = []
    for k in range(int(seconds * 50)):
        boot = boot0_us + 20_000 * k
        stamp = struct.pack(">Q", unix0_us + boot + 30_000)
        msgs = [mav.highres_imu_encode(boot, 0.0, 0.0, -9.81, 0.02, 0.0, 0.0, 0, 0, 0, 0, 0, 0,
                                       35.5, 0),
                mav.raw_imu_encode(boot, 10, 20, 4000, 1, 2, 3, 0, 0, 0)]
        if k % 50 == 0:
            msgs.append(mav.heartbeat_encode(2, 12, 0, 0, 4))
        if k % 10 == 0:
            msgs.append(mav.gps_raw_int_encode(unix0_us + boot, 3, 473977420, 85455940, 488120,
                                               80, 120, 150, 9000, 12))
            msgs.append(mav.attitude_encode(boot // 1000, 0.1, -0.05, 1.0, 0, 0, 0))
        out += [stamp + m.pack(mav) for m in msgs]
    return b"".join(out)


def test_a_px4_tlog_uses_highres_imu_and_dates_unix_gps_by_reception(tmp_path: Path) -> None:
    path = tmp_path / "px4.tlog"
    path.write_bytes(px4_tlog())
    fl = read_flight_log(path)
    assert fl.kind == "mavlink-tlog" and fl.imu.source == "HIGHRES_IMU[sys 1]"
    assert fl.imu.accel_m_s2[0, 2] == pytest.approx(-9.81) and fl.imu.gyro_rad_s[0, 0] == (
        pytest.approx(0.02))
    assert any("RAW_IMU from PX4 is raw sensor counts: not used" in n for n in fl.notes)
    assert fl.gps is not None and len(fl.gps) == 25 and fl.gps.valid.all()
    assert np.array_equal(fl.gps.t_us, fl.imu.t_us[::10])  # UNIX time moved onto boot time
    assert fl.gps.hdop[0] == pytest.approx(0.8) and fl.gps.speed_m_s[0] == pytest.approx(1.5)
    assert fl.references[0].name == "ATTITUDE" and fl.references[0].t_us[1] == 12_200_000
    assert fl.temperature is not None and fl.temperature.temperature_c[0] == pytest.approx(35.5)


# ------------------------------------------------------------------ bad input
def _one_error(path: Path, *words: str) -> LogReadError:
    with pytest.raises(LogReadError) as info:
        read_flight_log(path)
    text = str(info.value)
    assert text.startswith(str(path)) and "\n" not in text
    for w in words:
        assert w in text, text
    return info.value


def test_bad_inputs_are_one_line_errors(tmp_path: Path) -> None:
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    _one_error(empty, "empty file")
    text = tmp_path / "notes.txt"
    text.write_text("this is not a log\n" * 20)
    assert _one_error(text, "not a PX4 ULog").offset == 0
    log31 = copter31_log(2.0)
    no_imu = tmp_path / "no_imu.bin"  # FMT of IMU/IMU2 and their messages removed
    no_imu.write_bytes(b"".join(m for m in _split(log31) if m[2] not in (129, 130)
                                and not (m[2] == 0x80 and m[3] in (129, 130))))
    # no IMU: a partial replay (GPS and references read, a note), not an error (issue #40)
    fl = read_flight_log(no_imu)
    assert len(fl.imu.t_us) == 0 and fl.gps is not None and fl.references
    assert any("no IMU messages" in n for n in fl.notes)
    bad_fmt = tmp_path / "bad_fmt.bin"  # the IMU's FMT has a letter no format has: IMU2 used
    bad_fmt.write_bytes(log31.replace(b"Iffffff\0", b"Iff?fff\0", 1))
    fl = read_flight_log(bad_fmt)
    assert fl.imu.source == "IMU[1]" and any("(IMU) unusable: unknown format letter" in n
                                             for n in fl.notes)
    bad_fmt.write_bytes(log31.replace(b"Iffffff\0", b"Iff?fff\0"))  # and IMU2's too
    fl = read_flight_log(bad_fmt)
    assert len(fl.imu.t_us) == 0
    assert any("IMU, IMU2 logged but its FMT is unusable" in n for n in fl.notes)
    head_only = tmp_path / "head.bin"
    head_only.write_bytes(b"\xa3\x95\x80" + b"\x00" * 10)
    assert _one_error(head_only, "cut short").offset == 0
    ulog_head = tmp_path / "head.ulg"
    ulog_head.write_bytes(data_file(*ULOG_115).read_bytes()[:2000])
    _one_error(ulog_head, "sensor_combined")
    from pymavlink.dialects.v20 import ardupilotmega as dialect

    mav = dialect.MAVLink(None, srcSystem=1)
    heartbeats = b"".join(struct.pack(">Q", 1_700_000_000_000_000 + k * 1_000_000)
                          + mav.heartbeat_encode(1, 3, 0, 0, 0).pack(mav) for k in range(5))
    hb_only = tmp_path / "heartbeats.tlog"
    hb_only.write_bytes(heartbeats)
    _one_error(hb_only, "MAVLink telemetry log", "no IMU messages", "in 5 frames")
    no_gps = tmp_path / "no_gps.bin"
    no_gps.write_bytes(b"".join(m for m in _split(log31) if m[2] != 131))
    fl = read_flight_log(no_gps)
    assert fl.gps is None and "no GPS messages: IMU-only" in fl.notes


def _split(data: bytes) -> list[bytes]:
    lengths = {0x80: 89}
    out, off = [], 0
    while off < len(data):
        ln = lengths[data[off + 2]]
        m = data[off:off + ln]
        if m[2] == 0x80:
            lengths[m[3]] = m[4]
        out.append(m)
        off += ln
    return out


def test_an_fmt_with_a_column_too_many_still_reads(tmp_path: Path) -> None:
    """ArduCopter 3.2 logged some FMTs whose names and letters disagree in number; the record
    still frames, so its names are taken for the first fields (as pymavlink does) with a note."""
    path = tmp_path / "extra_name.bin"
    cols = b"TimeMS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw"
    path.write_bytes(copter31_log(2.0).replace(cols + b"\0", cols + b",ErrRP", 1))
    fl = read_flight_log(path)
    (att,) = fl.references
    assert len(att.t_us) == 10 and np.degrees(att.roll_rad[0]) == pytest.approx(5.12)
    assert any("(ATT) irregular: 8 column names for 7 format letters" in n for n in fl.notes)


def test_a_corrupt_fmt_length_resynchronises(tmp_path: Path) -> None:
    """An FMT whose length byte is wrong: its type's records cannot be followed, the walk
    resynchronises after each and says so; the other types still read."""
    log31 = copter31_log(2.0)
    bad = tmp_path / "fmt_len.bin"
    parts = _split(log31)
    gps_fmt = next(i for i, m in enumerate(parts) if m[2] == 0x80 and m[3] == 131)
    parts[gps_fmt] = parts[gps_fmt][:4] + bytes([parts[gps_fmt][4] + 7]) + parts[gps_fmt][5:]
    bad.write_bytes(b"".join(parts))
    fl = read_flight_log(bad)
    assert len(fl.imu.t_us) >= 95 and fl.damage is not None
    assert any("GPS" in n and "length" in n for n in fl.notes)


def test_memory_stays_bounded_on_a_long_log(tmp_path: Path) -> None:
    """A log of 400 copies of the real one (26 MB): the reading holds the wanted types' bytes
    and a chunk or two (1 MiB each), not the file."""
    data = data_file(*DF_REAL).read_bytes()[:65512]
    big = tmp_path / "long.bin"
    big.write_bytes(data * 400)
    tracemalloc.start()
    try:
        fl = read_flight_log(big)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(fl.imu.t_us) == 45 * 400
    assert peak < 0.5 * big.stat().st_size, peak


def test_dataflash_head_cuts_at_a_record(tmp_path: Path) -> None:
    data = copter31_log(20.0)
    head = dataflash_head(data, 5.0)
    assert data.startswith(head) and len(head) < len(data)
    path = tmp_path / "head.bin"
    path.write_bytes(head)
    fl = read_flight_log(path)
    assert fl.skipped == [] and (fl.imu.t_us[-1] - fl.imu.t_us[0]) == 5_000_000


def test_repeated_dataflash_is_one_long_flight(tmp_path: Path) -> None:
    """The benchmark's 20-minute log: copies of the real one, times shifted, FMTs once."""
    path = tmp_path / "long.bin"
    path.write_bytes(repeat_dataflash(data_file(*DF_REAL).read_bytes(), 5, 1_000_000))
    fl = read_flight_log(path)
    assert len(fl.imu.t_us) == 5 * 45 and fl.skipped == []
    assert np.all(np.diff(fl.imu.t_us) > 0)
    assert fl.imu.t_us[-1] - fl.imu.t_us[0] > 4_800_000


def test_stamped_capture_is_a_tlog_pymavlink_reads(tmp_path: Path) -> None:
    from pymavlink import mavutil

    capture = data_file("autopilot", "arduplane-sitl-telem.bin").read_bytes()[:50_000]
    path = tmp_path / "c.tlog"
    path.write_bytes(stamp_capture_as_tlog(capture, 1_700_000_000_000_000))
    conn = mavutil.mavlink_connection(str(path))
    stamps = []
    while (m := conn.recv_match()) is not None:
        assert m.get_type() != "BAD_DATA"
        stamps.append(m._timestamp)
    conn.close()
    assert len(stamps) == walk_tlog(io.BytesIO(path.read_bytes())).frames > 300
    assert stamps[0] >= 1_700_000_000 and np.all(np.diff(stamps) >= 0)


# ------------------------------------------------------------------ the command
def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion", "estimation", "replay", *args],
                          capture_output=True, text=True, timeout=120, cwd=REPO)


def test_cli_reads_a_cut_log_and_strict_refuses(tmp_path: Path) -> None:
    src = data_file(*DF_REAL)  # ends inside its last message, as the logs did
    out = tmp_path / "out"
    proc = _cli(str(src), "-o", str(out), "--no-plot")
    assert proc.returncode == 0, proc.stderr
    assert "note: log ends inside its last message" in proc.stdout and "65512" in proc.stdout
    proc = _cli(str(src), "-o", str(out), "--strict")
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "byte offset 65512" in lines[0]
    assert "Traceback" not in proc.stderr
    proc = _cli(str(src), "-o", str(out), "--no-plot", "--salvage")
    assert proc.returncode == 0, proc.stderr


def test_cli_replays_a_tlog(tmp_path: Path) -> None:
    proc = _cli(str(data_file(*TLOG)), "-o", str(tmp_path / "t"), "--no-plot", "--json")
    assert proc.returncode == 0, proc.stderr
    assert '"mavlink-tlog"' in proc.stdout and "ATTITUDE" in proc.stdout
