"""Hostile and vanishing ground stations against log download (LOG_*) and MAVLink FTP.

The fault campaign's promises for the bridge's transfer services: nothing a ground station
sends crashes or stalls the aircraft, the bulk sender never exceeds MAV_BULK_KB_S, memory stays
bounded (at most one log transfer and `bulk.MAX_PENDING` FTP transfers per link, at most the
FtpServer's four sessions), and a well-behaved ground station keeps working: it reads a
parameter within a bounded time during every attack, and downloads at the full budget once a
vanished client's transfers have been abandoned (`link.PEER_SILENCE_S`).

Everything runs over real UDP sockets on loopback against a `SyntheticVehicle` on a `udpin:`
link, so the attackers (several source ports and system ids) and the well-behaved client are
peers of one link, as on a shared network; every wait is bounded.
"""

from __future__ import annotations

import random
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from conftest import free_udp_port, wait_for
from support.synthetic_vehicle import SyntheticVehicle

from companion.logs.archive import FlightArchive
from gcs_bridge import bulk
from gcs_bridge.dialect import Message, mavlink
from gcs_bridge.link import PEER_SILENCE_S, Link
from gcs_bridge.services import ftp_wire
from gcs_bridge.services.link_services import UNKNOWN_LOG_REPORT_S
from gcs_bridge.services.log_download import ALL_BYTES, LOG_DATA_LEN

OLD = "20261123T100000Z"
CUR = "20261124T120000Z"
BULK_TYPES = frozenset({"LOG_DATA", "LOG_ENTRY", "FILE_TRANSFER_PROTOCOL"})
BUDGET_KB_S = 40  # low enough that a loaded machine keeps up with it, so it is what is measured
GOOD_SYSID = 250
PARAM_READ_S = 2.0  # the longest a well-behaved client may wait for a parameter under attack


# ============================================================================ clients
@dataclass
class Rx:
    t_s: float  # host monotonic time of arrival
    msg: Any
    nbytes: int


class Client:
    """A well-behaved pymavlink ground station on its own socket. A reader thread stamps
    everything that arrives, so bursts are measured where they arrive rather than when a test
    gets round to reading them."""

    def __init__(self, port: int, sysid: int = GOOD_SYSID, compid: int = 190) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.dest = ("127.0.0.1", port)
        self.sysid, self.compid = sysid, compid
        self._tx = mavlink.MAVLink(None, sysid, compid)
        self._tx_lock = threading.Lock()
        self._lock = threading.Lock()
        self.rx: list[Rx] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name=f"gcs-{sysid}", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        parser = mavlink.MAVLink(None, 0, 0)
        parser.robust_parsing = True
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65535)
            except TimeoutError:
                continue
            except OSError:
                return
            now = time.monotonic()
            got = [Rx(now, m, len(m.get_msgbuf())) for m in parser.parse_buffer(data) or []
                   if m.get_type() != "BAD_DATA"]
            with self._lock:
                self.rx.extend(got)

    def send(self, msg: Message) -> None:
        with self._tx_lock:
            frame = msg.pack(self._tx)
        try:
            self.sock.sendto(frame, self.dest)
        except OSError:
            pass

    def heartbeat(self) -> None:
        self.send(mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0,
            mavlink.MAV_STATE_ACTIVE))

    def since(self, t_s: float) -> list[Rx]:
        with self._lock:
            return [r for r in self.rx if r.t_s >= t_s]

    def wait(self, pred: Callable[[Any], bool], timeout_s: float, since_s: float) -> Rx | None:
        deadline = time.monotonic() + timeout_s
        while True:
            for r in self.since(since_s):
                if pred(r.msg):
                    return r
            if time.monotonic() > deadline:
                return None
            time.sleep(0.005)

    def param_read_s(self, timeout_s: float = PARAM_READ_S) -> float | None:
        """Seconds until PARAM_REQUEST_READ is answered (re-asked every 0.5 s), else None."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:
            asked = time.monotonic()
            self.send(mavlink.MAVLink_param_request_read_message(1, 1, b"MAV_BULK_KB_S", -1))
            got = self.wait(lambda m: m.get_type() == "PARAM_VALUE"
                            and m.param_id == "MAV_BULK_KB_S", 0.5, asked)
            if got is not None:
                return got.t_s - t0
        return None

    def close(self) -> None:
        self._stop.set()
        self.sock.close()
        self._thread.join(2.0)


class Attackers:
    """Fake ground stations: one socket and one system id each, sending raw requests."""

    def __init__(self, port: int, count: int = 4, first_sysid: int = 101) -> None:
        self.dest = ("127.0.0.1", port)
        self.socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(count)]
        for s in self.socks:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 64 << 10)  # never read: small
        self.mavs = [mavlink.MAVLink(None, first_sysid + i, 190) for i in range(count)]
        self.sent = 0

    def send(self, msg: Message, who: int | None = None) -> None:
        i = self.sent % len(self.socks) if who is None else who
        try:
            self.socks[i].sendto(msg.pack(self.mavs[i]), self.dest)
        except OSError:
            pass
        self.sent += 1

    def storm(self, make: Callable[[int], Message], seconds: float, *, rate_per_s: float = 3000.0,
              every: Callable[[], None] | None = None) -> int:
        """Send make(n) at about `rate_per_s` for `seconds`, calling `every` each 50 ms."""
        t0 = time.monotonic()
        n = 0
        next_tick = t0
        while (now := time.monotonic()) - t0 < seconds:
            due = int((now - t0) * rate_per_s)
            while n < due:
                self.send(make(n))
                n += 1
            if every is not None and now >= next_tick:
                every()
                next_tick = now + 0.05
            time.sleep(0.002)
        return n

    def close(self) -> None:
        for s in self.socks:
            s.close()


def ftp_msg(opcode: int, *, seq: int = 0, session: int = 0, offset: int = 0,
            data: bytes = b"", size: int | None = None) -> Message:
    payload = ftp_wire.HEADER.pack(seq & 0xFFFF, session & 0xFF, opcode,
                              len(data) if size is None else size, 0, 0, 0,
                              offset & 0xFFFFFFFF) + data
    return mavlink.MAVLink_file_transfer_protocol_message(
        0, 1, 1, list(payload[:ftp_wire.PAYLOAD_LEN].ljust(ftp_wire.PAYLOAD_LEN, b"\0")))


def ftp_head(m: Any) -> tuple[int, ...]:
    return tuple(ftp_wire.HEADER.unpack_from(bytes(m.payload)))


# ============================================================================ the vehicle
@dataclass
class Setup:
    v: SyntheticVehicle
    link: Link
    port: int
    root: Path
    good: Client
    attackers: Attackers


@contextmanager
def vehicle(tmp_path: Path, *, imu_bytes: int = 300_000, sparse_bytes: int = 0,
            budget_kb_s: int = BUDGET_KB_S) -> Iterator[Setup]:
    """A vehicle on udpin with two flights (an older one with `imu_bytes` of random data and,
    with `sparse_bytes`, a large sparse file), a good client that has been heard, attackers."""
    root = tmp_path / "flights"
    old = root / OLD
    old.mkdir(parents=True)
    (old / "imu.bin").write_bytes(random.Random(7).randbytes(imu_bytes))
    if sparse_bytes:
        with open(old / "big.bin", "wb") as f:
            f.truncate(sparse_bytes)
    cur = root / CUR
    cur.mkdir()
    (cur / "imu.bin").write_bytes(bytes(range(256)) * 4)
    port = free_udp_port()
    with SyntheticVehicle([f"udpin:127.0.0.1:{port}"], flight_dir=cur) as v:
        v.params.set("MAV_BULK_KB_S", budget_kb_s)
        good = Client(port)
        attackers = Attackers(port)
        try:
            t0 = time.monotonic()
            good.heartbeat()
            assert good.wait(lambda m: m.get_type() == "HEARTBEAT", 10.0, t0) is not None
            yield Setup(v, v.bridge.links[0], port, root, good, attackers)
            # whatever happened, no thread of the aircraft was restarted or given up
            for st in v.manager.thread_status():
                assert st.restarts == 0 and not st.failed, st
        finally:
            attackers.close()
            good.close()


def bulk_bytes_per_window(rx: list[Rx], window_s: float = 1.0,
                          extra: Callable[[Any], bool] = lambda m: False) -> int:
    """The most bytes of bulk messages (and of `extra` ones) that arrived within any window."""
    stamps = [(r.t_s, r.nbytes) for r in rx if r.msg.get_type() in BULK_TYPES or extra(r.msg)]
    best = total = 0
    lo = 0
    for hi, (t, n) in enumerate(stamps):
        total += n
        while stamps[lo][0] < t - window_s:
            total -= stamps[lo][1]
            lo += 1
        best = max(best, total)
        del hi
    return best


def budget_limit_bytes(budget_kb_s: int = BUDGET_KB_S) -> float:
    """What one second may carry: the budget, the token bucket's burst, one frame, and 25 %
    for the reader's jitter on a loaded machine (the flaw this guards against was 5x)."""
    rate = budget_kb_s * 1000.0
    return rate * 1.25 + rate * bulk.BURST_S + 300


class Sampler:
    """Samples the bridge's transfer state from a thread while an attack runs."""

    def __init__(self, link: Link) -> None:
        self.link = link
        self.max_log = self.max_ftp = self.max_all = self.max_sessions = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            b = self.link.bulk
            self.max_log = max(self.max_log, b.pending("log"))
            self.max_ftp = max(self.max_ftp, b.pending("ftp"))
            self.max_all = max(self.max_all, b.pending())
            self.max_sessions = max(self.max_sessions, len(self.link.services.ftp._sessions))
            time.sleep(0.002)

    def stop(self) -> Sampler:
        self._stop.set()
        self._thread.join(2.0)
        return self


# ============================================================================ the tests
def storm_while_reading(s: Setup, request: Callable[[int], Message]
                        ) -> tuple[int, list[float | None], Sampler]:
    """2.5 s of `request` storm from the attackers while the good client reads two parameters
    and the sampler watches the link's queues: (requests sent, read times, sampler)."""
    reads: list[float | None] = []
    sampler = Sampler(s.link)
    reader = threading.Thread(target=lambda: reads.extend(
        [s.good.param_read_s(), s.good.param_read_s()]))
    reader.start()
    sent = s.attackers.storm(request, 2.5, every=s.good.heartbeat)
    reader.join(2 * PARAM_READ_S + 1)
    sampler.stop()
    return sent, reads, sampler


def test_bulk_channel_holds_at_most_max_pending_transfers() -> None:
    """Unit: a queue flood drops the oldest waiting transfer, never the one under way."""
    sender = bulk.BulkSender(lambda: 1e9, max_pending=4)
    out: list[Message] = []

    def replies(tag: int, n: int = 3) -> Iterator[Message | None]:
        for i in range(n):
            yield mavlink.MAVLink_log_data_message(tag, i * 90, 90, [tag & 0xFF] * 90)

    for tag in range(1000):
        sender.queue("ftp", replies(tag), preempt=False)
        assert sender.pending("ftp") <= 4
    assert sender.stats.dropped == 996
    sender.step(1, out.extend)
    assert sorted({m.id for m in out}) == [996, 997, 998, 999]  # the newest requests answered


def test_the_budget_counts_the_frames_really_sent_signature_included() -> None:
    """Unit: on a signed link a frame is 13 bytes longer than the estimate; the budget is
    charged with what was packed, so the bytes on the wire stay within it."""
    packer = mavlink.MAVLink(None, 1, 1)
    packer.signing.secret_key = bytes(range(32))
    packer.signing.sign_outgoing = True
    wire = [0]

    def emit(msgs: list[Message]) -> None:
        for m in msgs:
            wire[0] += len(m.pack(packer))

    def data() -> Iterator[Message | None]:
        rng = random.Random(3)
        for i in range(100_000):
            yield mavlink.MAVLink_log_data_message(0, i * 90, 90, list(rng.randbytes(90)))

    rate = 10_000.0
    sender = bulk.BulkSender(lambda: rate)
    sender.replace("log", data())
    t_ns = 1
    while t_ns <= 2_000_000_000:
        sender.step(t_ns, emit)
        t_ns += 1_000_000
    assert wire[0] == sender.stats.bytes
    assert wire[0] <= rate * 2 + rate * bulk.BURST_S + 122, wire[0]


def test_log_request_data_storm_keeps_the_budget_and_one_transfer(tmp_path: Path) -> None:
    """Thousands of LOG_REQUEST_DATA per second from four sources: huge ranges (offsets near
    2**32, count 0xFFFFFFFF), ids that do not exist, every listed id in turn. No exception, at
    most one log transfer at a time, bulk bytes within the budget, at most one "no such log"
    STATUSTEXT per UNKNOWN_LOG_REPORT_S (each was reflected before: five times the budget),
    and the good client reads a parameter meanwhile."""
    with vehicle(tmp_path) as s:
        size = FlightArchive.snapshot(s.root / OLD).size
        offsets = [0, 2**32 - 1, 2**32 - LOG_DATA_LEN, size - 1, size, size + 1, 90 * 1000]
        counts = [ALL_BYTES, 0, 1, 2**31, LOG_DATA_LEN * 512]
        ids = [0, 1, 2, 3, 0xFFFF, 5000]

        def request(n: int) -> Message:
            return mavlink.MAVLink_log_request_data_message(
                1, 1, ids[n % len(ids)], offsets[n // 3 % len(offsets)],
                counts[n // 7 % len(counts)])

        t0 = time.monotonic()
        sent, reads, sampler = storm_while_reading(s, request)
        t1 = time.monotonic()
        time.sleep(0.3)
        rx = s.good.since(t0)
        assert sent >= 5000, f"only {sent} requests sent"
        assert s.link.bulk.stats.failed == 0
        assert sampler.max_log <= 1 and sampler.max_all <= 1, vars(sampler)
        assert s.link.counters.queue_dropped == 0

        def no_such_log(m: Any) -> bool:
            return m.get_type() == "STATUSTEXT" and "no such log" in m.text

        worst = bulk_bytes_per_window(rx, extra=no_such_log)
        assert worst <= budget_limit_bytes(), f"{worst} bytes in one second"
        reported = sum(no_such_log(r.msg) for r in rx)
        print(f"LOG storm: {sent} requests, worst second {worst} B (limit "
              f"{budget_limit_bytes():.0f}), {reported} STATUSTEXT, parameter reads {reads}")
        assert 1 <= reported <= (t1 - t0) / UNKNOWN_LOG_REPORT_S + 2, reported
        assert s.link.services.unknown_log_requests >= sent // len(ids) // 2
        assert len(reads) == 2 and all(r is not None for r in reads), reads
        # and the log service still answers properly afterwards
        t2 = time.monotonic()
        s.good.send(mavlink.MAVLink_log_request_data_message(1, 1, 0, 0, 3 * LOG_DATA_LEN))
        got = s.good.wait(lambda m: m.get_type() == "LOG_DATA" and m.ofs == 2 * LOG_DATA_LEN,
                          5.0, t2)
        assert got is not None and got.msg.id == 0


def test_ftp_floods_are_bounded_and_answered_within_the_budget(tmp_path: Path) -> None:
    """OpenFileRO of huge, absent and climbing paths, sessions opened and never closed (every
    session byte), ReadFile/BurstReadFile beyond the end and with sizes 240..255, ListDirectory:
    the FTP queue stays at MAX_PENDING (it grew by every request before: 20 000 waiting
    transfers after 3 s), at most four sessions, budget kept, nothing fails."""
    with vehicle(tmp_path) as s:
        path = f"/{OLD}/imu.bin".encode()
        requests: list[Callable[[int], Message]] = [
            lambda n: ftp_msg(ftp_wire.OP_OPEN_FILE_RO, seq=n, session=n, data=path),
            lambda n: ftp_msg(ftp_wire.OP_OPEN_FILE_RO, seq=n, session=n, data=b"/" + b"x" * 238),
            lambda n: ftp_msg(ftp_wire.OP_OPEN_FILE_RO, seq=n, session=n, data=b"/../../etc/passwd"),
            lambda n: ftp_msg(ftp_wire.OP_OPEN_FILE_RO, seq=n, session=n, data=b"/nope/none.bin"),
            lambda n: ftp_msg(ftp_wire.OP_READ_FILE, seq=n, session=n, offset=2**32 - 1, size=239),
            lambda n: ftp_msg(ftp_wire.OP_READ_FILE, seq=n, session=n, size=240 + n % 16),
            lambda n: ftp_msg(ftp_wire.OP_BURST_READ_FILE, seq=n, session=n, offset=10**9, size=239),
            lambda n: ftp_msg(ftp_wire.OP_BURST_READ_FILE, seq=n, session=n, size=255),
            lambda n: ftp_msg(ftp_wire.OP_BURST_READ_FILE, seq=n, session=n, size=239),
            lambda n: ftp_msg(ftp_wire.OP_LIST_DIRECTORY, seq=n, session=n, data=b"/"),
            lambda n: ftp_msg(ftp_wire.OP_LIST_DIRECTORY_WITH_TIME, seq=n, data=f"/{OLD}".encode()),
            lambda n: ftp_msg(ftp_wire.OP_LIST_DIRECTORY, seq=n, offset=2**32 - 1, data=b"/"),
        ]

        def request(n: int) -> Message:
            return requests[n % len(requests)](n)

        t0 = time.monotonic()
        sent, reads, sampler = storm_while_reading(s, request)
        rx = s.good.since(t0)
        assert sent >= 5000, f"only {sent} requests sent"
        assert sampler.max_ftp <= bulk.MAX_PENDING, vars(sampler)
        assert sampler.max_sessions <= 4, vars(sampler)
        assert s.link.bulk.stats.dropped > 0  # the flood really was more than the budget
        assert s.link.bulk.stats.failed == 0
        worst = bulk_bytes_per_window(rx)
        print(f"FTP flood: {sent} requests, worst second {worst} B, queue <= {sampler.max_ftp},"
              f" sessions <= {sampler.max_sessions}, dropped {s.link.bulk.stats.dropped}, "
              f"parameter reads {reads}")
        assert worst <= budget_limit_bytes(), f"{worst} bytes in one second"
        assert len(reads) == 2 and all(r is not None for r in reads), reads
        naks = [ftp_head(r.msg) for r in rx if r.msg.get_type() == "FILE_TRANSFER_PROTOCOL"
                and ftp_head(r.msg)[2] == ftp_wire.OP_NAK]
        assert naks, "no NAK at all: the flood was not answered"
        # the queue drains, and a client that reuses a session (MAVSDK: always 0) gets it back
        assert wait_for(lambda: not s.link.bulk.busy(), 5.0, 0.02)
        t2 = time.monotonic()
        s.good.send(ftp_msg(ftp_wire.OP_OPEN_FILE_RO, seq=40_000, session=0, data=path))
        got = s.good.wait(lambda m: m.get_type() == "FILE_TRANSFER_PROTOCOL"
                          and m.target_system == GOOD_SYSID and ftp_head(m)[0] == 40_001,
                          5.0, t2)
        assert got is not None and ftp_head(got.msg)[2] == ftp_wire.OP_ACK, \
            got and ftp_head(got.msg)


def test_a_crc_flood_does_not_stall_telemetry(tmp_path: Path) -> None:
    """CalcFileCRC32 of a 64 MB file, over and over from four sources: the CRC is cut into
    64 KiB pieces within the sender's 2 ms step, so ATTITUDE (20 Hz) keeps coming with no gap
    longer than a few periods, and a parameter read is answered meanwhile."""
    with vehicle(tmp_path, imu_bytes=10_000, sparse_bytes=64 << 20) as s:
        path = f"/{OLD}/big.bin".encode()

        def request(n: int) -> Message:
            return ftp_msg(ftp_wire.OP_CALC_FILE_CRC32, seq=n, session=n % 4, data=path)

        t0 = time.monotonic()
        reads: list[float | None] = []
        reader = threading.Thread(target=lambda: reads.append(s.good.param_read_s()))
        reader.start()
        sent = s.attackers.storm(request, 2.5, rate_per_s=1000.0, every=s.good.heartbeat)
        reader.join(PARAM_READ_S + 1)
        t1 = time.monotonic()
        rx = s.good.since(t0)
        att = [r.t_s for r in rx if r.msg.get_type() == "ATTITUDE" and r.t_s <= t1]
        gaps = [b - a for a, b in zip(att, att[1:], strict=False)]
        assert sent >= 2000
        assert len(att) >= 20, f"{len(att)} ATTITUDE in {t1 - t0:.1f} s"
        assert max(gaps) < 0.3, f"telemetry stalled {max(gaps):.3f} s during the CRC flood"
        assert reads and reads[0] is not None, reads
        print(f"CRC flood: {sent} requests, longest ATTITUDE gap {max(gaps) * 1000:.0f} ms, "
              f"parameter read {reads[0] * 1000:.0f} ms")
        # the flood over, one CRC of the whole file is answered, right, in bounded time
        assert wait_for(lambda: not s.link.bulk.busy(), 5.0, 0.02)
        t2 = time.monotonic()
        s.good.send(ftp_msg(ftp_wire.OP_CALC_FILE_CRC32, seq=50_000, session=9, data=path))
        got = s.good.wait(lambda m: m.get_type() == "FILE_TRANSFER_PROTOCOL"
                          and m.target_system == GOOD_SYSID and ftp_head(m)[0] == 50_001,
                          10.0, t2)
        assert got is not None, "no answer to a CRC request"
        assert ftp_head(got.msg)[2] == ftp_wire.OP_ACK, ftp_head(got.msg)
        expected = ftp_wire.mavlink_crc32(bytes(64 << 20))
        assert bytes(got.msg.payload)[12:16] == expected.to_bytes(4, "little")
        print(f"one CRC of 64 MB: {got.t_s - t2:.2f} s")


def test_a_vanishing_ground_station_is_dropped_and_another_downloads_at_full_budget(
        tmp_path: Path) -> None:
    """A client starts a log download and an FTP burst read, then its socket closes. Within
    PEER_SILENCE_S (plus slack) after its last message the bridge stops both transfers and
    counts them abandoned; a second client then lists the logs and downloads at the budget."""
    budget = 20
    with vehicle(tmp_path, imu_bytes=600_000, budget_kb_s=budget) as s:
        gone = Client(s.port, sysid=201)
        t0 = time.monotonic()
        gone.heartbeat()
        gone.send(mavlink.MAVLink_log_request_data_message(1, 1, 0, 0, ALL_BYTES))
        gone.send(ftp_msg(ftp_wire.OP_OPEN_FILE_RO, seq=10, session=2, data=f"/{OLD}/imu.bin".encode()))
        opened = gone.wait(lambda m: m.get_type() == "FILE_TRANSFER_PROTOCOL"
                           and ftp_head(m)[0] == 11, 5.0, t0)
        assert opened is not None and ftp_head(opened.msg)[2] == ftp_wire.OP_ACK
        gone.send(ftp_msg(ftp_wire.OP_BURST_READ_FILE, seq=12, session=2, size=239))
        last_heard = time.monotonic()
        assert gone.wait(lambda m: m.get_type() == "FILE_TRANSFER_PROTOCOL"
                         and ftp_head(m)[0] == 13, 5.0, t0) is not None
        assert gone.wait(lambda m: m.get_type() == "LOG_DATA", 5.0, t0) is not None
        gone.close()  # vanishes: nothing more sent or read
        abandoned0 = s.link.bulk.stats.abandoned

        # the other client only sends heartbeats and watches what goes out for the vanished one
        def for_gone(m: Any) -> bool:
            return (m.get_type() == "LOG_DATA" or m.get_type() == "FILE_TRANSFER_PROTOCOL"
                    and m.target_system == 201)

        deadline = last_heard + PEER_SILENCE_S + 4.0
        while time.monotonic() < deadline and s.link.bulk.busy():
            s.good.heartbeat()
            time.sleep(0.1)
        stopped = time.monotonic()
        assert not s.link.bulk.busy(), "still sending for a client silent for 9 s"
        time.sleep(0.3)
        last = [r.t_s for r in s.good.since(last_heard) if for_gone(r.msg)]
        assert last, "nothing was sent for the vanished client at all"
        silent_s = max(last) - last_heard
        assert PEER_SILENCE_S - 1.0 <= silent_s <= PEER_SILENCE_S + 1.5, silent_s
        assert stopped - last_heard >= PEER_SILENCE_S - 0.2
        assert s.link.bulk.stats.abandoned - abandoned0 >= 2  # the download and the burst
        assert not [r for r in s.good.since(stopped + 0.3) if for_gone(r.msg)]

        # the well-behaved client: list, then download at the full budget
        t2 = time.monotonic()
        s.good.send(mavlink.MAVLink_log_request_list_message(1, 1, 0, 0xFFFF))
        entry = s.good.wait(lambda m: m.get_type() == "LOG_ENTRY" and m.id == 0, 2.0, t2)
        assert entry is not None and entry.t_s - t2 < 1.0
        t3 = time.monotonic()
        s.good.send(mavlink.MAVLink_log_request_data_message(1, 1, 0, 0, ALL_BYTES))
        while time.monotonic() - t3 < 2.5:
            s.good.heartbeat()
            time.sleep(0.1)
        data = [r for r in s.good.since(t3) if r.msg.get_type() == "LOG_DATA"]
        assert data, "no LOG_DATA for the well-behaved client"
        span = data[-1].t_s - data[0].t_s
        rate = sum(r.nbytes for r in data[:-1]) / span
        print(f"vanished: last bulk for it {silent_s:.2f} s after its last message, "
              f"then {rate:.0f} B/s for the other client (budget {budget * 1000})")
        assert 0.75 * budget * 1000 <= rate <= 1.1 * budget * 1000, f"{rate:.0f} B/s"
        assert s.good.param_read_s() is not None
