"""Hostile and vanishing ground stations against log download and MAVLink FTP, for the fault
campaign: floods a runtime's `udpin:` MAVLink port with LOG_* and FTP requests, or starts
transfers and vanishes.

`transfer_flood` sends, from several fake ground stations (one socket and system id each),
LOG_REQUEST_DATA for huge ranges and unknown ids, LOG_REQUEST_LIST, and FTP opens of huge,
absent and climbing paths, reads and burst reads beyond the end and with oversized sizes,
sessions never closed, directory listings and CRCs; it never reads what comes back.
`vanishing_download` starts a log download and an FTP burst read, drops its socket after the
first data, and measures what a second, well-behaved ground station gets meanwhile. Run alone
against `companion sim --fast --mavlink udpin:127.0.0.1:PORT`:

    python bench/transfer_flood.py 127.0.0.1 14550 --seconds 10
    python bench/transfer_flood.py 127.0.0.1 14550 --vanish
"""

from __future__ import annotations

import argparse
import random
import socket
import struct
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

FTP_HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst, pad, ofs
FTP_PAYLOAD_LEN = 251
FTP_ACK = 128
FTP_OPEN_RO = 4
FTP_READ = 5
FTP_LIST = 3
FTP_RESET = 2
FTP_CRC = 14
FTP_BURST = 15
ALL_BYTES = 0xFFFFFFFF
META_FILE = "/@meta/parameters.json"  # always there: the bridge's parameter metadata
LOG_KINDS = ("log_data_huge", "log_data_unknown_id", "log_data_every_id", "log_list")
FTP_KINDS = ("ftp_open_huge", "ftp_open_absent", "ftp_open_climbing", "ftp_open_unclosed",
             "ftp_read_past_end", "ftp_read_oversized", "ftp_burst", "ftp_burst_past_end",
             "ftp_list", "ftp_crc")


def ftp_message(target_system: int, opcode: int, *, seq: int = 0, session: int = 0,
                offset: int = 0, data: bytes = b"", size: int | None = None
                ) -> mavlink.MAVLink_file_transfer_protocol_message:
    """A FILE_TRANSFER_PROTOCOL request with the header fields as given (sizes not checked:
    an attacker's sizes are the point)."""
    payload = FTP_HEADER.pack(seq & 0xFFFF, session & 0xFF, opcode,
                              (len(data) if size is None else size) & 0xFF, 0, 0, 0,
                              offset & 0xFFFFFFFF) + data
    return mavlink.MAVLink_file_transfer_protocol_message(
        0, target_system, 1, list(payload[:FTP_PAYLOAD_LEN].ljust(FTP_PAYLOAD_LEN, b"\0")))


class TransferFlood:
    """Makes hostile LOG_* and FTP requests; deterministic for a seed."""

    def __init__(self, seed: int = 0, *, target_system: int = 1) -> None:
        self.rng = random.Random(seed)
        self.target = target_system
        self.sent: Counter[str] = Counter()
        self.n = 0

    def request(self) -> tuple[str, Any]:
        rng, t = self.rng, self.target
        self.n += 1
        n = self.n
        kind = rng.choice(LOG_KINDS + FTP_KINDS)
        self.sent[kind] += 1
        if kind == "log_data_huge":
            msg: Any = mavlink.MAVLink_log_request_data_message(
                t, 1, rng.randrange(4), rng.choice([0, 2**32 - 1, 2**32 - 90, 2**31]),
                rng.choice([ALL_BYTES, 2**31, 0]))
        elif kind == "log_data_unknown_id":
            msg = mavlink.MAVLink_log_request_data_message(t, 1, rng.randrange(100, 65536), 0,
                                                           ALL_BYTES)
        elif kind == "log_data_every_id":
            msg = mavlink.MAVLink_log_request_data_message(t, 1, n % 8, 0, ALL_BYTES)
        elif kind == "log_list":
            msg = mavlink.MAVLink_log_request_list_message(t, 1, 0, 0xFFFF)
        elif kind == "ftp_open_huge":
            msg = ftp_message(t, FTP_OPEN_RO, seq=n, session=n, data=b"/" + b"a" * 238)
        elif kind == "ftp_open_absent":
            msg = ftp_message(t, FTP_OPEN_RO, seq=n, session=n, data=b"/no/such/file.bin")
        elif kind == "ftp_open_climbing":
            msg = ftp_message(t, FTP_OPEN_RO, seq=n, session=n, data=b"/../../../etc/passwd")
        elif kind == "ftp_open_unclosed":
            msg = ftp_message(t, FTP_OPEN_RO, seq=n, session=rng.randrange(256),
                              data=META_FILE.encode())
        elif kind == "ftp_read_past_end":
            msg = ftp_message(t, FTP_READ, seq=n, session=rng.randrange(256),
                              offset=rng.choice([2**32 - 1, 10**9]), size=239)
        elif kind == "ftp_read_oversized":
            msg = ftp_message(t, FTP_READ, seq=n, session=rng.randrange(256),
                              size=rng.randrange(240, 256))
        elif kind == "ftp_burst":
            msg = ftp_message(t, FTP_BURST, seq=n, session=rng.randrange(256), size=239)
        elif kind == "ftp_burst_past_end":
            msg = ftp_message(t, FTP_BURST, seq=n, session=rng.randrange(256), offset=2**32 - 1,
                              size=255)
        elif kind == "ftp_list":
            msg = ftp_message(t, FTP_LIST, seq=n, data=b"/", offset=rng.choice([0, 2**32 - 1]))
        else:
            msg = ftp_message(t, FTP_CRC, seq=n, data=META_FILE.encode())
        return kind, msg


def transfer_flood(host: str, port: int, seconds: float, *, seed: int = 0,
                   target_system: int = 1, rate_per_s: float = 3000.0,
                   sources: int = 4) -> dict[str, int]:
    """Send hostile LOG_* and FTP requests to host:port for `seconds` at about `rate_per_s`,
    from `sources` fake ground stations (own socket, system id 101...). Returns the requests
    sent per kind, and `send_failed`."""
    flood = TransferFlood(seed, target_system=target_system)
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(sources)]
    mavs = [mavlink.MAVLink(None, 101 + i, 190) for i in range(sources)]
    for s in socks:
        s.setblocking(False)
    t0 = time.monotonic()
    n = 0
    try:
        while (now := time.monotonic()) - t0 < seconds:
            due = int((now - t0) * rate_per_s)
            while n < due:
                i = n % sources
                _kind, msg = flood.request()
                try:
                    socks[i].sendto(msg.pack(mavs[i]), (host, port))
                except OSError:
                    flood.sent["send_failed"] += 1
                n += 1
            time.sleep(0.002)
    finally:
        for s in socks:
            s.close()
    return dict(flood.sent)


class _Gcs:
    """A minimal ground station on its own socket (sends, and reads with a deadline)."""

    def __init__(self, host: str, port: int, sysid: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        self.sock.bind(("0.0.0.0", 0))
        self.dest = (host, port)
        self.sysid = sysid
        self.mav = mavlink.MAVLink(None, sysid, 190)
        self.mav.robust_parsing = True

    def send(self, msg: Any) -> None:
        self.sock.sendto(msg.pack(self.mav), self.dest)

    def heartbeat(self) -> None:
        self.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS,
                                                    mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0,
                                                    mavlink.MAV_STATE_ACTIVE))

    def recv_until(self, done: Callable[[Any], bool], timeout_s: float,
                   every: Callable[[], None] | None = None) -> Any:
        """Read until `done(msg)` is true (that message) or timeout_s (None); `every` each 0.5 s."""
        deadline = time.monotonic() + timeout_s
        next_tick = 0.0
        while (now := time.monotonic()) < deadline:
            if every is not None and now >= next_tick:
                every()
                next_tick = now + 0.5
            self.sock.settimeout(max(0.001, min(0.1, deadline - now)))
            try:
                data = self.sock.recv(65535)
            except (TimeoutError, OSError):
                continue
            for msg in self.mav.parse_buffer(data) or []:
                if msg.get_type() != "BAD_DATA" and done(msg):
                    return msg
        return None

    def close(self) -> None:
        self.sock.close()


def _ftp_seq(msg: Any) -> int:
    return int(FTP_HEADER.unpack_from(bytes(msg.payload))[0])


def _ftp_answer(seq: int) -> Callable[[Any], bool]:
    """Matches the FTP reply to request `seq` (replies carry seq + 1)."""
    return lambda m: m.get_type() == "FILE_TRANSFER_PROTOCOL" and _ftp_seq(m) == seq + 1


def vanishing_download(host: str, port: int, timeout_s: float, *,
                       download_bytes: int = 200_000, target_system: int = 1) -> dict[str, str]:
    """A ground station (system id 201) lists the logs, starts a whole download of the first
    and an FTP burst read of the parameter metadata, and drops its socket after the first data.
    A second one (202) then lists the logs and downloads `download_bytes` of the first, while
    the bridge still serves the vanished one until it has been silent for 5 s; meanwhile it
    notes the last FTP reply addressed to the vanished one (udpin sends everything to every
    peer). Returns the figures as text: seconds to list, to download, the rate, and when the
    vanished client's transfers stopped ("never seen" / "still running" when they did not)."""
    out: dict[str, str] = {}
    gone = _Gcs(host, port, 201)
    t_start = time.monotonic()
    try:
        entry = None
        for _ in range(int(max(1.0, timeout_s))):
            gone.heartbeat()
            gone.send(mavlink.MAVLink_log_request_list_message(target_system, 1, 0, 0xFFFF))
            entry = gone.recv_until(lambda m: m.get_type() == "LOG_ENTRY", 1.0)
            if entry is not None:
                break
        if entry is None or entry.num_logs == 0:
            out["error"] = "no log to download" if entry is not None else "no LOG_ENTRY"
            return out
        log_id = int(entry.id)
        gone.send(mavlink.MAVLink_log_request_data_message(target_system, 1, log_id, 0,
                                                           ALL_BYTES))
        opened = None
        for seq in (10, 20):  # all sessions taken (a flood before): reset them, as QGC does
            gone.send(ftp_message(target_system, FTP_OPEN_RO, seq=seq, session=3,
                                  data=META_FILE.encode()))
            opened = gone.recv_until(_ftp_answer(seq), 5.0)
            if opened is not None and bytes(opened.payload)[3] == FTP_ACK:
                break
            gone.send(ftp_message(target_system, FTP_RESET, seq=seq + 5))
            time.sleep(0.2)
        if opened is not None:
            gone.send(ftp_message(target_system, FTP_BURST, seq=30, session=3, size=239))
        first = gone.recv_until(lambda m: m.get_type() == "FILE_TRANSFER_PROTOCOL"
                                and _ftp_seq(m) >= 31, 5.0)
        out["first_client_got"] = first.get_type() if first is not None else "nothing"
        out["ftp_open"] = "ack" if opened is not None and bytes(opened.payload)[3] == FTP_ACK \
            else "refused" if opened is not None else "no answer"
    finally:
        gone.close()
    t_vanish = time.monotonic()
    out["first_client_vanished_after_s"] = f"{t_vanish - t_start:.2f}"

    good = _Gcs(host, port, 202)
    last_for_gone = [0.0]

    def note(m: Any) -> bool:
        """Notes a reply for the vanished client; False: keep reading."""
        if m.get_type() == "FILE_TRANSFER_PROTOCOL" and m.target_system == 201:
            last_for_gone[0] = time.monotonic()
        return False

    try:
        t0 = time.monotonic()
        good.heartbeat()
        good.send(mavlink.MAVLink_log_request_list_message(target_system, 1, 0, 0xFFFF))

        def listed(m: Any) -> bool:
            note(m)
            return m.get_type() == "LOG_ENTRY" and int(m.id) == log_id

        got = good.recv_until(listed, timeout_s, good.heartbeat)
        out["list_s"] = f"{time.monotonic() - t0:.3f}" if got is not None else "timeout"
        size = int(got.size) if got is not None else download_bytes
        want = min(download_bytes, size)
        t1 = time.monotonic()
        good.send(mavlink.MAVLink_log_request_data_message(target_system, 1, log_id, 0, want))
        have = [0]

        def downloaded(m: Any) -> bool:
            note(m)
            if m.get_type() == "LOG_DATA" and int(m.id) == log_id:
                have[0] += int(m.count)
            return have[0] >= want

        done = good.recv_until(downloaded, timeout_s, good.heartbeat)
        dt = time.monotonic() - t1
        out["download_bytes"] = str(have[0])
        out["download_s"] = f"{dt:.3f}" if done is not None else "timeout"
        out["download_rate_B_s"] = f"{have[0] / dt:.0f}" if dt > 0 else "n/a"
        # watch until the bridge has been silent for the vanished client for a second
        deadline = t_vanish + min(timeout_s, 12.0)
        while time.monotonic() < deadline and time.monotonic() - max(last_for_gone[0],
                                                                     t_vanish) < 1.0:
            good.recv_until(note, 0.2, good.heartbeat)
        if last_for_gone[0] == 0.0:
            out["vanished_ftp_stopped_after_s"] = "never seen"
        elif time.monotonic() - last_for_gone[0] < 1.0:
            out["vanished_ftp_stopped_after_s"] = "still running"
        else:
            out["vanished_ftp_stopped_after_s"] = f"{last_for_gone[0] - t_vanish:.2f}"
    finally:
        good.close()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("host")
    ap.add_argument("port", type=int)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=3000.0, help="requests per second")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--target-system", type=int, default=1)
    ap.add_argument("--vanish", action="store_true",
                    help="run vanishing_download instead of the flood")
    ap.add_argument("--timeout", type=float, default=20.0, help="--vanish: longest wait, s")
    args = ap.parse_args()
    if args.vanish:
        for key, value in vanishing_download(args.host, args.port, args.timeout,
                                             target_system=args.target_system).items():
            print(f"{key:32s} {value}")
        return
    sent = transfer_flood(args.host, args.port, args.seconds, seed=args.seed,
                          target_system=args.target_system, rate_per_s=args.rate)
    for kind, n in sorted(sent.items()):
        print(f"{kind:22s} {n}")


if __name__ == "__main__":
    main()
