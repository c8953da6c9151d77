"""Log download (LOG_*) and MAVLink FTP end to end, over real UDP links to a SyntheticVehicle.

The flight root holds two flights: an older finished one (a ~300 kB random imu.bin and a small
text file) and the one being recorded (the vehicle's flight_dir, where the bridge's tlog grows).
MAVProxy 1.8.75 runs as a separate process (driver shared with test_gcs_mavproxy.py); the error
paths, the pacing and the abandonment of a download whose client vanished are checked with a
minimal pymavlink ground station (`support.synthetic_vehicle.MiniGcs`).
"""

from __future__ import annotations

import random
import re
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from conftest import free_udp_port, wait_for
from support.synthetic_vehicle import MiniGcs, SyntheticVehicle

# the MAVProxy driver (commands on stdin, output collected line by line) is shared
from test_gcs_mavproxy import MavProxy

from companion.logs.archive import FlightArchive
from gcs_bridge.dialect import mavlink
from gcs_bridge.link import PEER_SILENCE_S
from gcs_bridge.services import ftp_wire
from gcs_bridge.services.log_download import ALL_BYTES, LOG_DATA_LEN

OLD = "20261123T100000Z"  # the finished flight
CUR = "20261124T120000Z"  # the flight being recorded (the vehicle's flight_dir)
IMU_BYTES = 300_000


@dataclass
class Flights:
    root: Path
    old: Path
    cur: Path
    imu: bytes


def make_flights(tmp_path: Path, imu_bytes: int = IMU_BYTES) -> Flights:
    root = tmp_path / "flights"
    old = root / OLD
    old.mkdir(parents=True)
    imu = random.Random(20261123).randbytes(imu_bytes)
    (old / "imu.bin").write_bytes(imu)
    (old / "notes.txt").write_text("older flight: steady circle, no events\n")
    cur = root / CUR
    cur.mkdir()
    (cur / "imu.bin").write_bytes(bytes(range(256)) * 4)
    return Flights(root, old, cur, imu)


def old_archive_bytes(flights: Flights) -> bytes:
    archive = FlightArchive.snapshot(flights.old)
    return archive.read(0, archive.size)


# ============================================================================ MAVProxy
class MavProxyWithLog(MavProxy):
    """The shared driver with MAVProxy's `log` module loaded at start as well."""

    def __init__(self, port: int, cwd: Path) -> None:
        super().__init__(port, cwd, modules="param,ftp,cmdlong,signing,log")

    def since(self, mark: int) -> list[str]:
        with self._lock:
            return list(self.lines[mark:])


LOG_LINE = re.compile(r"Log (\d+)\s+numLogs (\d+) lastLog (\d+) size (\d+)")


def test_mavproxy_log_list_download_and_ftp(tmp_path: Path) -> None:
    flights = make_flights(tmp_path)
    work = tmp_path / "mavproxy"
    work.mkdir()
    port = free_udp_port()
    with SyntheticVehicle([f"udpout:127.0.0.1:{port}?identity=px4"], flight_dir=flights.cur):
        mp = MavProxyWithLog(port, work)
        try:
            assert mp.wait_line("Received", 25.0) is not None, "\n".join(mp.lines)

            # ---- log list: both flights, the finished one with its archive's exact size
            mark = mp.mark()
            mp.cmd("log list")
            listed: dict[int, tuple[int, ...]] = {}

            def both_listed() -> bool:
                for ln in mp.since(mark):
                    m = LOG_LINE.search(ln)
                    if m:
                        listed[int(m.group(1))] = tuple(int(g) for g in m.groups())
                return sorted(listed) == [0, 1]

            assert wait_for(both_listed, 10.0, 0.05), "\n".join(mp.since(mark))
            old_size = FlightArchive.snapshot(flights.old).size
            assert listed[0] == (0, 2, 1, old_size)  # ids from 0 on a PX4 link, sorted by name
            cur_size = listed[1][3]
            # the current flight grows (the bridge's tlog is in it): listed between the two
            assert 1024 < cur_size <= FlightArchive.snapshot(flights.cur).size

            # ---- log download: byte-exact archive of the finished flight
            target = work / "old-flight.tar"
            mark = mp.mark()
            mp.cmd(f"log download 0 {target}")
            assert wait_for(lambda: target.is_file() and target.stat().st_size == old_size, 30.0,
                            0.05), "\n".join(mp.since(mark))
            assert mp.wait_line("Finished downloading", 30.0, mark) is not None, \
                "\n".join(mp.since(mark))
            assert target.read_bytes() == old_archive_bytes(flights)

            # ---- ftp list /: the flight directories under the root
            mark = mp.mark()
            mp.cmd("ftp list /")
            assert mp.wait_line("Total size", 10.0, mark) is not None, "\n".join(mp.since(mark))
            shown = mp.since(mark)
            for name in (OLD, CUR):
                assert any(f"D {name}" in ln for ln in shown), "\n".join(shown)

            # ---- ftp get: byte-exact file from the finished flight
            local = work / "imu.bin"
            mark = mp.mark()
            mp.cmd(f"ftp get /{OLD}/imu.bin {local}")
            assert mp.wait_line(f"Wrote {IMU_BYTES} bytes", 30.0, mark) is not None, \
                "\n".join(mp.since(mark))
            assert local.read_bytes() == flights.imu
        finally:
            mp.close()


# ============================================================================ pymavlink
@dataclass
class Setup:
    v: SyntheticVehicle
    gcs: MiniGcs
    flights: Flights
    target: tuple[int, int]

    def heartbeat(self) -> None:
        self.gcs.send(mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0,
            mavlink.MAV_STATE_ACTIVE))


@contextmanager
def vehicle_and_gcs(tmp_path: Path, imu_bytes: int = IMU_BYTES) -> Iterator[Setup]:
    flights = make_flights(tmp_path, imu_bytes)
    with MiniGcs() as gcs, SyntheticVehicle([f"udpout:127.0.0.1:{gcs.port}"],
                                            flight_dir=flights.cur) as v:
        hb = gcs.recv(10.0, "HEARTBEAT")
        assert hb is not None, "no HEARTBEAT from the vehicle"
        s = Setup(v, gcs, flights, (hb.get_srcSystem(), hb.get_srcComponent()))
        s.heartbeat()
        yield s


def ftp_call(s: Setup, seq: int, opcode: int, *, session: int = 0, offset: int = 0,
             data: bytes = b"", size: int | None = None) -> tuple[tuple[int, ...], bytes]:
    """One FTP request over the link; the reply's header fields and data."""
    payload = ftp_wire.HEADER.pack(seq, session, opcode, len(data) if size is None else size, 0, 0, 0,
                              offset) + data
    s.gcs.send(mavlink.MAVLink_file_transfer_protocol_message(
        0, s.target[0], s.target[1], list(payload.ljust(ftp_wire.PAYLOAD_LEN, b"\0"))))

    def answers(m: Any) -> bool:
        return ftp_wire.HEADER.unpack_from(bytes(m.payload))[0] == (seq + 1) & 0xFFFF

    reply = s.gcs.recv(5.0, "FILE_TRANSFER_PROTOCOL", answers)
    assert reply is not None, f"no FTP reply to opcode {opcode} seq {seq}"
    assert (reply.target_system, reply.target_component) == (255, 190)
    raw = bytes(reply.payload)
    head = ftp_wire.HEADER.unpack_from(raw)
    return head, raw[ftp_wire.HEADER.size:ftp_wire.HEADER.size + head[3]]


def assert_nak(reply: tuple[tuple[int, ...], bytes], request_opcode: int, session: int,
               error: int) -> None:
    (_seq, r_session, opcode, _size, req_opcode, _burst, _pad, _ofs), data = reply
    assert opcode == ftp_wire.OP_NAK, reply
    assert req_opcode == request_opcode and r_session == session, reply
    assert data[:1] == bytes([error]), f"NAK error {data[:1]!r}, expected {error}"


def test_ftp_error_paths_over_the_link(tmp_path: Path) -> None:
    with vehicle_and_gcs(tmp_path) as s:
        # a read on a session never opened
        assert_nak(ftp_call(s, 10, ftp_wire.OP_READ_FILE, session=7, size=ftp_wire.DATA_LEN),
                   ftp_wire.OP_READ_FILE, 7, ftp_wire.ERR_INVALIDSESSION)

        # open a real file, read it, then read past its end
        notes = (s.flights.old / "notes.txt").read_bytes()
        head, data = ftp_call(s, 20, ftp_wire.OP_OPEN_FILE_RO, session=3,
                              data=f"/{OLD}/notes.txt".encode())
        assert head[2] == ftp_wire.OP_ACK and data == len(notes).to_bytes(4, "little"), (head, data)
        head, data = ftp_call(s, 22, ftp_wire.OP_READ_FILE, session=3, size=ftp_wire.DATA_LEN)
        assert head[2] == ftp_wire.OP_ACK and data == notes
        assert_nak(ftp_call(s, 24, ftp_wire.OP_READ_FILE, session=3, offset=10_000,
                            size=ftp_wire.DATA_LEN), ftp_wire.OP_READ_FILE, 3, ftp_wire.ERR_EOF)
        head, _ = ftp_call(s, 26, ftp_wire.OP_TERMINATE_SESSION, session=3)
        assert head[2] == ftp_wire.OP_ACK

        # a file that does not exist, and a path climbing out of the flight root
        assert_nak(ftp_call(s, 30, ftp_wire.OP_OPEN_FILE_RO, session=4,
                            data=f"/{OLD}/missing.bin".encode()),
                   ftp_wire.OP_OPEN_FILE_RO, 4, ftp_wire.ERR_FILENOTFOUND)
        assert_nak(ftp_call(s, 32, ftp_wire.OP_OPEN_FILE_RO, session=5, data=b"/../etc/passwd"),
                   ftp_wire.OP_OPEN_FILE_RO, 5, ftp_wire.ERR_FILENOTFOUND)

        # a write on a link without a key
        assert_nak(ftp_call(s, 40, ftp_wire.OP_CREATE_FILE, session=6,
                            data=f"/{OLD}/new.txt".encode()),
                   ftp_wire.OP_CREATE_FILE, 6, ftp_wire.ERR_FILEPROTECTED)
        assert not (s.flights.old / "new.txt").exists()


def log_entries(s: Setup) -> dict[int, Any]:
    s.gcs.send(mavlink.MAVLink_log_request_list_message(s.target[0], s.target[1], 0, 0xFFFF))
    out: dict[int, Any] = {}
    first = s.gcs.recv(5.0, "LOG_ENTRY")
    assert first is not None, "no LOG_ENTRY"
    out[first.id] = first
    while first.num_logs and len(out) < first.num_logs:
        m = s.gcs.recv(5.0, "LOG_ENTRY")
        assert m is not None, f"only {len(out)} of {first.num_logs} LOG_ENTRY"
        out[m.id] = m
    return out


def test_log_data_past_the_end_then_erase(tmp_path: Path) -> None:
    with vehicle_and_gcs(tmp_path) as s:
        entries = log_entries(s)
        size = FlightArchive.snapshot(s.flights.old).size
        assert sorted(entries) == [0, 1]
        assert entries[0].size == size and entries[0].num_logs == 2

        # a range wholly past the end: one count-0 LOG_DATA at the end offset
        s.gcs.send(mavlink.MAVLink_log_request_data_message(
            s.target[0], s.target[1], 0, size + 5 * LOG_DATA_LEN, 10 * LOG_DATA_LEN))
        m = s.gcs.recv(5.0, "LOG_DATA")
        assert m is not None
        assert (m.id, m.ofs, m.count) == (0, size, 0)
        more = [x for x in s.gcs.collect(1.0) if x.get_type() == "LOG_DATA"]
        assert more == []

        # erase over the link: the finished flight goes, the one being recorded stays
        s.gcs.send(mavlink.MAVLink_log_erase_message(s.target[0], s.target[1]))
        text = s.gcs.recv(5.0, "STATUSTEXT", lambda t: "Erased" in t.text)
        assert text is not None and text.text == "Erased 1 flight, current flight kept"
        assert not s.flights.old.exists()
        assert s.flights.cur.is_dir() and (s.flights.cur / "imu.bin").is_file()
        after = log_entries(s)
        assert sorted(after) == [0] and after[0].num_logs == 1


def test_a_download_for_a_vanished_client_is_abandoned(tmp_path: Path) -> None:
    with vehicle_and_gcs(tmp_path) as s:
        link = s.v.bridge.links[0]
        s.v.params.set("MAV_BULK_KB_S", 20)  # ~370 kB on the wire: ~18 s, far beyond 5 s
        size = FlightArchive.snapshot(s.flights.old).size
        s.gcs.send(mavlink.MAVLink_log_request_data_message(s.target[0], s.target[1], 0, 0,
                                                            ALL_BYTES))
        last_heard = time.monotonic()
        assert s.gcs.recv(5.0, "LOG_DATA") is not None
        assert link.bulk.busy()
        # the client disappears: nothing sent, nothing read
        assert wait_for(lambda: not link.bulk.busy(), PEER_SILENCE_S + 5.0, 0.05), \
            "LOG_DATA still being sent to a client silent for 10 s"
        silent_s = time.monotonic() - last_heard
        assert silent_s >= PEER_SILENCE_S - 0.1, f"stopped after {silent_s:.2f} s already"
        assert link.bulk.stats.abandoned >= 1
        sent = link.bulk.stats.sent
        assert sent < size // LOG_DATA_LEN  # stopped, not finished
        s.gcs.collect(0.5)  # whatever was queued on the socket before the stop
        later = s.gcs.collect(2.5)
        assert [m for m in later if m.get_type() == "LOG_DATA"] == []
        assert sum(m.get_type() == "HEARTBEAT" for m in later) >= 2
        assert link.bulk.stats.sent == sent


def test_telemetry_keeps_its_rate_during_a_download(tmp_path: Path) -> None:
    # 1.5 MB at the default 400 kB/s budget: a download of about 4.5 s
    with vehicle_and_gcs(tmp_path, imu_bytes=1_500_000) as s:
        size = FlightArchive.snapshot(s.flights.old).size
        s.gcs.send(mavlink.MAVLink_log_request_data_message(s.target[0], s.target[1], 0, 0,
                                                            ALL_BYTES))
        stamped: list[tuple[float, Any]] = []
        deadline = time.monotonic() + 30.0
        next_hb = time.monotonic() + 1.0
        done = False
        while not done and time.monotonic() < deadline:
            now = time.monotonic()
            if now >= next_hb:
                s.heartbeat()
                next_hb = now + 1.0
            for m in s.gcs.collect(0.02):
                stamped.append((now, m))
                if m.get_type() == "LOG_DATA" and m.ofs + m.count >= size:
                    done = True
        data_t = [t for t, m in stamped if m.get_type() == "LOG_DATA"]
        assert done, f"download did not end: {len(data_t)} LOG_DATA of {size // 90 + 1}"
        t0, t1 = data_t[0], data_t[-1]
        assert t1 - t0 >= 2.0, f"download took only {t1 - t0:.2f} s: too short to judge"
        attitude = [m for t, m in stamped if m.get_type() == "ATTITUDE" and t0 <= t <= t1]
        rate = len(attitude) / (t1 - t0)
        print(f"download {size} B in {t1 - t0:.2f} s, ATTITUDE {rate:.1f} Hz, "
              f"{len(data_t)} LOG_DATA")
        assert rate >= 15.0, f"ATTITUDE at {rate:.1f} Hz during the download"
