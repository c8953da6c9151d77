"""A hostile MAVLink sender for the fault campaign: floods a UDP port on loopback.

Mixes, per datagram: valid frames of every message id with random payloads and valid CRCs
(MAVLink 1 and 2), garbage, truncated and oversized frames, wrong system ids, PARAM_SET and
COMMAND_LONG storms (random names and values, random commands), each kind chosen at random.
Used by `bench/faults_bench.py`; run alone for a manual check:

    python bench/mavflood.py 127.0.0.1 14550 --seconds 25
"""

from __future__ import annotations

import argparse
import random
import socket
import struct
import time
from collections import Counter
from collections.abc import Callable

from pymavlink.dialects.v20 import common as mavlink

KINDS = ("valid_random", "garbage", "truncated", "oversized", "v1_random", "param_set",
         "command_long", "wrong_sysid")


def _crc_extra(msg_id: int) -> int:
    return int(mavlink.mavlink_map[msg_id].crc_extra)


def _frame_v2(rng: random.Random, msg_id: int, payload: bytes, sysid: int, compid: int) -> bytes:
    header = struct.pack("<BBBBBBBHB", 0xFD, len(payload), 0, 0, rng.randrange(256), sysid,
                         compid, msg_id & 0xFFFF, msg_id >> 16)
    crc = mavlink.x25crc(header[1:] + payload)
    crc.accumulate(bytes([_crc_extra(msg_id)]))
    return header + payload + struct.pack("<H", crc.crc)


def _frame_v1(rng: random.Random, msg_id: int, payload: bytes, sysid: int, compid: int) -> bytes:
    header = struct.pack("<BBBBBB", 0xFE, len(payload), rng.randrange(256), sysid, compid, msg_id)
    crc = mavlink.x25crc(header[1:] + payload)
    crc.accumulate(bytes([_crc_extra(msg_id)]))
    return header + payload + struct.pack("<H", crc.crc)


class Flood:
    """Makes hostile datagrams; deterministic for a seed."""

    def __init__(self, seed: int = 0, *, target_system: int = 1) -> None:
        self.rng = random.Random(seed)
        self.target = target_system
        self.ids = sorted(mavlink.mavlink_map)
        self.ids_v1 = [i for i in self.ids if i < 256]
        self.mav = mavlink.MAVLink(None, 255, 190)
        self.sent: Counter[str] = Counter()

    def datagram(self) -> bytes:
        rng = self.rng
        kind = rng.choice(KINDS)
        self.sent[kind] += 1
        if kind == "garbage":
            return rng.randbytes(rng.randrange(1, 600))
        if kind == "truncated":
            full = _frame_v2(rng, rng.choice(self.ids), rng.randbytes(rng.randrange(1, 255)), 255, 190)
            return full[: rng.randrange(1, len(full))]
        if kind == "oversized":
            return _frame_v2(rng, rng.choice(self.ids), rng.randbytes(255), 255, 190) * 8
        if kind == "v1_random":
            return _frame_v1(rng, rng.choice(self.ids_v1), rng.randbytes(rng.randrange(1, 255)),
                             255, 190)
        if kind == "param_set":
            name = rng.choice([b"MGR_EXEC_TIME_S", b"MAV0RX_ENABLE", b"IMU_WDG_MS", b"CTL_MODE",
                               b"EST_GPS_LAG", rng.randbytes(16), b"MGR_WDG_GRAN_MS"])
            msg = self.mav.param_set_encode(self.target, 1, name, rng.uniform(-1e9, 1e9),
                                            rng.randrange(1, 11))
            return bytes(msg.pack(self.mav))
        if kind == "command_long":
            cmd = rng.choice([rng.randrange(65536), 246, 511, 512, 2600, 400, 176, 520])
            msg = self.mav.command_long_encode(self.target, 1, cmd, 0,
                                               *(rng.uniform(-1e6, 1e6) for _ in range(7)))
            return bytes(msg.pack(self.mav))
        sysid = rng.randrange(256) if kind == "wrong_sysid" else 255
        payload = rng.randbytes(rng.randrange(1, 255))
        return _frame_v2(rng, rng.choice(self.ids), payload, sysid, rng.randrange(256))


def flood(host: str, port: int, seconds: float, *, seed: int = 0,
          rate_per_s: float = 5000.0,
          datagram: Callable[[], bytes] | None = None) -> Counter[str]:
    """Send hostile datagrams to host:port for `seconds` at about `rate_per_s`: MAVLink ones
    (`Flood`), or whatever `datagram` makes (counted as "datagram")."""
    f = Flood(seed)
    make = f.datagram
    if datagram is not None:
        def make() -> bytes:
            f.sent["datagram"] += 1
            return datagram()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setblocking(False)
    t_end = time.monotonic() + seconds
    period = 1.0 / rate_per_s
    next_t = time.monotonic()
    try:
        while (now := time.monotonic()) < t_end:
            if now < next_t:
                time.sleep(min(next_t - now, 0.01))
                continue
            next_t += period
            try:
                sock.sendto(make(), (host, port))
            except (BlockingIOError, OSError):
                f.sent["send_failed"] += 1
    finally:
        sock.close()
    return f.sent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("host")
    ap.add_argument("port", type=int)
    ap.add_argument("--seconds", type=float, default=25.0)
    ap.add_argument("--rate", type=float, default=5000.0, help="datagrams per second")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    sent = flood(args.host, args.port, args.seconds, seed=args.seed, rate_per_s=args.rate)
    for kind, n in sorted(sent.items()):
        print(f"{kind:14s} {n}")


if __name__ == "__main__":
    main()
