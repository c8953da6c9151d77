"""Log server: flights as MAVLink log entries, checked against how QGroundControl, MAVSDK and
MAVProxy list, download (chunks, gaps, completion) and erase logs."""

from __future__ import annotations

import json
import logging
import os
import random
from collections.abc import Iterable
from datetime import UTC, datetime
from pathlib import Path

import pytest

from companion.logs.archive import FlightArchive
from gcs_bridge.dialect import Identity, mavlink
from gcs_bridge.services.log_download import ALL_BYTES, PIECE_MESSAGES, LogServer, first_log_id

T0 = 1_714_558_953  # 2024-05-01T10:22:33Z
STAMPS = ["20240501T102233Z", "20240502T080000Z", "20240503T120000Z-1"]
LEN = 90


def stamp_s(name: str) -> int:
    return int(datetime.strptime(name[:16], "%Y%m%dT%H%M%SZ").replace(tzinfo=UTC).timestamp())


def make_flight(root: Path, name: str, files: dict[str, bytes], mtime_s: int = T0) -> Path:
    d = root / name
    for rel, data in files.items():
        p = d / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
        os.utime(p, (mtime_s, mtime_s))
    return d


def three_flights(root: Path) -> list[Path]:
    rng = random.Random(3)
    return [make_flight(root, name, {"imu.bin": rng.randbytes(700 + 9000 * k),
                                     "run.json": b"{}"})
            for k, name in enumerate(STAMPS)]


def entries(server: LogServer, start: int = 0, end: int = 0xFFFF) -> list[tuple[int, ...]]:
    return [(e.id, e.num_logs, e.last_log_num, e.time_utc, e.size)
            for e in server.request_list(start, end)]


def data_messages(server: LogServer, log_id: int, offset: int, count: int
                  ) -> list[mavlink.MAVLink_log_data_message]:
    return [m for m in server.request_data(log_id, offset, count) if m is not None]


def on_the_wire(msgs: Iterable[mavlink.MAVLink_message]) -> list[mavlink.MAVLink_message]:
    """Each message packed and parsed again, as a client receives it."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    return [mav.decode(bytearray(m.pack(mav))) for m in msgs]


# ----------------------------------------------------------------------------- listing
def test_no_flight_is_one_entry_with_id_0_and_num_logs_0(tmp_path: Path) -> None:
    assert entries(LogServer(tmp_path / "missing", lambda: None)) == [(0, 0, 0, 0, 0)]
    (tmp_path / "dry-run").mkdir()  # directories without a log file are not flights
    make_flight(tmp_path, "20240101T000000Z", {"report/report.html": b"<html>"})
    (tmp_path / "notes.bin").write_bytes(b"a log file, but not in a flight directory")
    for first in (0, 1):
        server = LogServer(tmp_path, lambda: None, first_id=first)
        assert entries(server) == [(0, 0, 0, 0, 0)]
        assert entries(server, 5, 9) == [(0, 0, 0, 0, 0)]
        assert list(server.request_data(0, 0, ALL_BYTES)) == []


def test_one_flight(tmp_path: Path) -> None:
    d = make_flight(tmp_path, STAMPS[0], {"imu.bin": b"\x01" * 1000, "run.json": b"{}"})
    size = FlightArchive.snapshot(d).size
    assert entries(LogServer(tmp_path, lambda: None)) == [(0, 1, 0, T0, size)]
    assert entries(LogServer(tmp_path, lambda: None, first_id=1)) == [(1, 1, 1, T0, size)]
    (wire,) = on_the_wire(LogServer(tmp_path, lambda: None).request_list(0, 0xFFFF))
    assert (wire.get_type(), wire.id, wire.size, wire.time_utc) == ("LOG_ENTRY", 0, size, T0)


def test_three_flights_sorted_by_name_with_ranges(tmp_path: Path) -> None:
    dirs = three_flights(tmp_path)
    sizes = [FlightArchive.snapshot(d).size for d in dirs]
    times = [stamp_s(n) for n in STAMPS]
    assert times[0] == T0
    server = LogServer(tmp_path, lambda: None)
    assert entries(server) == [(k, 3, 2, times[k], sizes[k]) for k in range(3)]
    assert [e[0] for e in entries(server, 1, 1)] == [1]
    assert [e[0] for e in entries(server, 1, 0xFFFF)] == [1, 2]
    assert entries(server, 2, 1) == [] and entries(server, 3, 9) == []
    apm = LogServer(tmp_path, lambda: None, first_id=1)  # QGC counts from 1 for ArduPilot only
    assert [(e[0], e[2]) for e in entries(apm)] == [(1, 3), (2, 3), (3, 3)]
    assert first_log_id(Identity.ARDUPILOT) == 1
    assert first_log_id(Identity.GENERIC) == first_log_id(Identity.PX4) == 0
    with pytest.raises(ValueError):
        LogServer(tmp_path, lambda: None, first_id=2)


def test_time_utc_from_the_name_then_run_json_then_the_files(tmp_path: Path) -> None:
    make_flight(tmp_path, "a-named-by-hand", {"x.tlog": b"t", "run.json": json.dumps(
        {"started_utc": "2024-05-02T00:00:00.5+00:00"}).encode()})
    make_flight(tmp_path, "b-no-run-json", {"x.csv": b"1,2\n", "y.bin": b"1"}, mtime_s=T0 + 9)
    os.utime(tmp_path / "b-no-run-json" / "x.csv", (T0 + 5, T0 + 5))
    make_flight(tmp_path, "c-bad-run-json", {"x.uavlog": b"1", "run.json": b"{not json"},
                mtime_s=T0 + 1)
    times = [e[3] for e in entries(LogServer(tmp_path, lambda: None))]
    assert times == [1_714_608_000, T0 + 5, T0 + 1]


def test_a_narrow_list_request_reuses_the_snapshot(tmp_path: Path) -> None:
    dirs = three_flights(tmp_path)
    server = LogServer(tmp_path, lambda: dirs[-1])
    first = entries(server)
    with open(dirs[-1] / "imu.bin", "ab") as f:  # the flight being recorded grows
        f.write(bytes(5000))
    # a client re-asking for a missed entry gets the size it was told before...
    assert entries(server, 2, 2) == [first[2]]
    assert entries(server, 1, 2) == first[1:]
    archive = server.archive(2)
    assert archive is not None and archive.size == first[2][4]
    # ...and a new listing of every id sees the growth
    assert entries(server)[2][4] > first[2][4]


# ----------------------------------------------------------------------------- data
def assemble(msgs: Iterable[mavlink.MAVLink_log_data_message], into: bytearray) -> None:
    for m in msgs:
        into[m.ofs:m.ofs + m.count] = bytes(m.data[:m.count])


def test_whole_download_with_one_request_reassembles_the_archive(tmp_path: Path) -> None:
    three_flights(tmp_path)
    server = LogServer(tmp_path, lambda: None)
    for e in entries(server):
        log_id, size = e[0], e[4]
        archive = server.archive(log_id)
        assert archive is not None
        raw = list(server.request_data(log_id, 0, ALL_BYTES))
        # read in pieces: the caller can pace a slow link between them
        assert (None in raw) == (size > PIECE_MESSAGES * LEN)
        msgs = on_the_wire(m for m in raw if m is not None)
        assert all(m.get_type() == "LOG_DATA" and m.id == log_id for m in msgs)
        assert [m.ofs for m in msgs] == list(range(0, size, LEN))
        assert all(m.count == LEN for m in msgs[:-1]) and 0 < msgs[-1].count <= LEN
        got = bytearray(size)
        assemble(msgs, got)
        assert bytes(got) == archive.read(0, archive.size)


def mavproxy_like(server: LogServer, log_id: int) -> tuple[bytes, int]:
    """MAVProxy's way, as its log module behaves: all bytes from 0, done at a count-0 LOG_DATA
    or at a short one once every earlier 90-byte slot came; after a silence, ask again for
    everything from the slot after the highest received. Returns the file and the requests."""
    got = bytearray()
    slots: set[int] = set()
    requests = 0
    offset = 0
    while requests < 5:
        requests += 1
        for m in data_messages(server, log_id, offset, ALL_BYTES):
            if m.count:
                got[m.ofs:m.ofs + m.count] = bytes(m.data[:m.count])
                slots.add(m.ofs // LEN)
            if m.count == 0 or (m.count < LEN and len(slots) == 1 + m.ofs // LEN):
                return bytes(got), requests
        offset = (max(slots) + 1) * LEN  # the silence: nothing said the download ended
    raise AssertionError("MAVProxy would never finish")


def test_mavproxy_finishes_whatever_the_size(tmp_path: Path) -> None:
    # 41 blocks of data + the two headers + the end marker: 45 * 512 = 256 * 90 bytes
    on_boundary = make_flight(tmp_path, STAMPS[0], {"imu.bin": bytes(range(256)) * 82})
    make_flight(tmp_path, STAMPS[1], {"imu.bin": b"\x07" * 1000})
    server = LogServer(tmp_path, lambda: None)
    sizes = [e[4] for e in entries(server)]
    assert sizes[0] == FlightArchive.snapshot(on_boundary).size == 256 * LEN
    assert sizes[1] % LEN != 0
    for log_id in (0, 1):
        archive = server.archive(log_id)
        assert archive is not None
        data, requests = mavproxy_like(server, log_id)
        assert data == archive.read(0, archive.size) and requests == 1
    last = data_messages(server, 0, 0, ALL_BYTES)[-2:]  # a full one, then the count-0 end
    assert [(m.ofs, m.count) for m in last] == [(sizes[0] - LEN, LEN), (sizes[0], 0)]


def chunked(server: LogServer, log_id: int, size: int, chunk_bins: int, *, exact: bool,
            drop: float = 0.0, seed: int = 0) -> bytes:
    """QGroundControl's (whole 90-byte bins per chunk) and MAVSDK's (exact byte counts) way:
    one chunk at a time, LOG_DATA checked like they do, lost pieces asked again by range."""
    rng = random.Random(seed)
    got = bytearray(size)
    chunk = chunk_bins * LEN
    for start in range(0, size, chunk):
        length = min(chunk, size - start)
        bins = -(-length // LEN)
        have = [False] * bins
        asks = [(start, length if exact else bins * LEN)]
        rounds = 0
        while asks:
            rounds += 1
            assert rounds < 50
            for ofs, count in asks:
                for m in on_the_wire(data_messages(server, log_id, ofs, count)):
                    assert m.ofs % LEN == 0 and m.ofs <= size and 0 < m.count <= LEN
                    assert m.ofs // chunk == start // chunk  # never spills into the next chunk
                    if rng.random() < drop:
                        continue
                    got[m.ofs:m.ofs + m.count] = bytes(m.data[:m.count])
                    have[(m.ofs - start) // LEN] = True
            asks = []
            k = 0
            while k < bins:  # each run of missing bins, as one request
                if have[k]:
                    k += 1
                    continue
                j = k
                while j < bins and not have[j]:
                    j += 1
                asks.append((start + k * LEN, (j - k) * LEN))
                k = j
    return bytes(got)


@pytest.mark.parametrize(("client", "chunk_bins", "exact"), [
    ("qgc", 512, False), ("qgc-newer", 2048, False), ("mavsdk", 128, True)])
def test_chunked_downloads_with_losses_reassemble_the_archive(
        tmp_path: Path, client: str, chunk_bins: int, exact: bool) -> None:
    rng = random.Random(5)
    make_flight(tmp_path, STAMPS[0], {"imu.bin": rng.randbytes(150_000),
                                      "gps.bin": rng.randbytes(33_333),
                                      "sub/dir/servo.bin": rng.randbytes(7)})
    make_flight(tmp_path, STAMPS[1], {"imu.bin": bytes(range(256)) * 82})  # ends on a 90 bin
    server = LogServer(tmp_path, lambda: None)
    for log_id, *_, size in entries(server):
        archive = server.archive(log_id)
        assert archive is not None
        expected = archive.read(0, archive.size)
        assert chunked(server, log_id, size, chunk_bins, exact=exact) == expected
        assert chunked(server, log_id, size, chunk_bins, exact=exact, drop=0.2, seed=1) == expected


def test_requests_at_and_past_the_end(tmp_path: Path) -> None:
    make_flight(tmp_path, STAMPS[0], {"imu.bin": b"\x05" * 1000})
    server = LogServer(tmp_path, lambda: None)
    ((_, _, _, _, size),) = entries(server)
    assert size % LEN != 0
    tail = size - size % LEN

    def sent(offset: int, count: int) -> list[tuple[int, int]]:
        return [(m.ofs, m.count) for m in data_messages(server, 0, offset, count)]

    assert sent(size, ALL_BYTES) == [(size, 0)]  # MAVProxy's re-ask from the end
    assert sent(size + 5000, 90) == [(size, 0)]
    assert sent(tail, ALL_BYTES) == [(tail, size % LEN)]  # short: the end is plain
    assert sent(tail - LEN, 2 * LEN) == [(tail - LEN, LEN), (tail, size % LEN)]
    assert sent(tail - LEN, LEN) == [(tail - LEN, LEN)]  # inside: no end marker
    assert sent(tail - LEN, 0) == [] and sent(size, 0) == []
    assert sent(45, 100) == [(45, 90), (135, 10)]  # any offset is served as asked
    assert data_messages(server, 7, 0, ALL_BYTES) == []  # unknown id: nothing
    data = data_messages(server, 0, 0, 2 * LEN)
    assert [bytes(m.data) for m in data] == [data[0].data, data[1].data]
    assert all(len(m.data) == LEN for m in data_messages(server, 0, 0, ALL_BYTES))


def test_data_before_any_list_takes_a_snapshot(tmp_path: Path) -> None:
    (d,) = three_flights(tmp_path)[:1]
    server = LogServer(tmp_path, lambda: None)
    msgs = data_messages(server, 0, 0, ALL_BYTES)
    got = bytearray(FlightArchive.snapshot(d).size)
    assemble(msgs, got)
    assert bytes(got) == FlightArchive.snapshot(d).read(0, len(got))


def test_a_flight_gone_during_a_download_ends_the_data_with_a_logged_error(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    dirs = three_flights(tmp_path)
    server = LogServer(tmp_path, lambda: None)
    entries(server)
    (dirs[2] / "imu.bin").unlink()
    with caplog.at_level(logging.ERROR, logger="gcs_bridge.services.log_download"):
        msgs = data_messages(server, 2, 0, ALL_BYTES)
    assert msgs == [] or msgs[-1].ofs < 512 * 2  # only the headers before the vanished file
    assert any("imu.bin: vanished" in r.getMessage() for r in caplog.records)


# ----------------------------------------------------------------------------- erase
def test_erase_keeps_the_flight_being_recorded(tmp_path: Path,
                                               caplog: pytest.LogCaptureFixture) -> None:
    root = tmp_path / "logs"
    dirs = three_flights(root)
    (root / "dry-run").mkdir()
    (root / "params.parm").write_text("keep me")
    outside = make_flight(tmp_path, "20200101T000000Z", {"imu.bin": b"outside"})
    (root / "20230101T000000Z").symlink_to(outside)
    server = LogServer(root, lambda: dirs[1])
    assert len(entries(server)) == 3
    with caplog.at_level(logging.INFO, logger="gcs_bridge.services.log_download"):
        erased, text = server.erase()
    assert erased == 2 and text == "Erased 2 flights, current flight kept" and len(text) <= 50
    assert sorted(p.name for p in root.iterdir()) == sorted(
        ["dry-run", "params.parm", "20230101T000000Z", dirs[1].name])
    assert (outside / "imu.bin").read_bytes() == b"outside"  # a link is never followed
    assert sum("erased flight" in r.getMessage() for r in caplog.records) == 2
    assert entries(server) == [(0, 1, 0, stamp_s(STAMPS[1]),
                                FlightArchive.snapshot(dirs[1]).size)]
    assert data_messages(server, 2, 0, ALL_BYTES) == []  # ids of the erased flights are gone

    assert LogServer(root, lambda: None).erase() == (1, "Erased 1 flight")
    assert entries(server) == [(0, 0, 0, 0, 0)]
    assert server.erase() == (0, "Erased 0 flights")


# ----------------------------------------------------------------------------- MAVProxy itself
class _MavproxyLink:
    """What MAVProxy's log module sends, queued and answered by the log server in turn (its
    handlers send while handling: answering at once would nest)."""

    def __init__(self, server: LogServer) -> None:
        self.server = server
        self.queue: list[mavlink.MAVLink_message] = []
        self.ends = 0
        self.erased: tuple[int, str] | None = None

    def log_request_list_send(self, _sys: int, _comp: int, start: int, end: int) -> None:
        self.queue += on_the_wire(self.server.request_list(start, end))

    def log_request_data_send(self, _sys: int, _comp: int, log_id: int, ofs: int,
                              count: int) -> None:
        self.queue += on_the_wire(m for m in self.server.request_data(log_id, ofs, count)
                                  if m is not None)

    def log_request_end_send(self, _sys: int, _comp: int) -> None:
        self.ends += 1

    def log_erase_send(self, _sys: int, _comp: int) -> None:
        self.erased = self.server.erase()


def _mavproxy_log_module(server: LogServer):  # type: ignore[no-untyped-def]
    from types import SimpleNamespace

    from MAVProxy.modules import mavproxy_log

    link = _MavproxyLink(server)
    master = SimpleNamespace(mav=link)
    state = SimpleNamespace(
        multi_instance={}, instance_count={}, public_modules={}, command_map={},
        completions={}, settings=SimpleNamespace(target_system=1, target_component=1),
        console=SimpleNamespace(set_status=lambda *a, **k: None), master=lambda: master)
    module = mavproxy_log.init(state)

    def command(*args: str) -> None:
        module.cmd_log(list(args))
        while link.queue:
            module.mavlink_packet(link.queue.pop(0))

    return module, link, command


def test_mavproxy_log_module_lists_downloads_and_erases(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = tmp_path / "logs"
    make_flight(root, STAMPS[0], {"imu.bin": bytes(range(256)) * 82})  # ends on a 90-byte bin
    make_flight(root, STAMPS[1], {"imu.bin": b"\x07" * 1000, "run.json": b"{}"})
    server = LogServer(root, lambda: root / STAMPS[1])
    module, link, command = _mavproxy_log_module(server)
    command("list")
    assert sorted(module.entries) == [0, 1]
    for log_id in (0, 1):
        target = tmp_path / f"log{log_id}.bin"
        command("download", str(log_id), str(target))
        assert "Finished downloading" in capsys.readouterr().out  # no retry timer needed
        archive = server.archive(log_id)
        assert archive is not None and target.read_bytes() == archive.read(0, archive.size)
    assert link.ends == 2  # MAVProxy closed each download itself
    command("erase")
    assert link.erased == (1, "Erased 1 flight, current flight kept")
    command("list")
    assert sorted(module.entries) == [0, 1]  # MAVProxy keeps old entries; the server has one
    assert len(entries(server)) == 1
    LogServer(root, lambda: None).erase()
    capsys.readouterr()
    command("list")
    assert "No logs" in capsys.readouterr().out
