"""Streaming estimates to the aircraft: the legacy datagram and MAVLink, over real UDP."""

from __future__ import annotations

import json
import math
import socket
import struct
import threading
import time

import numpy as np
import pytest
from conftest import data_file, free_udp_port, wait_for

from horizon.estimate import HorizonEstimate
from horizon.geometry import OrientedLine
from horizon.robust import RobustDetector
from horizon.sources import Frame
from horizon.stream import (
    HORIZON_ATTITUDE_SIZE,
    LegacyHorizonSender,
    MavlinkHorizonSender,
    pack_horizon_attitude,
    run_stream,
)
from horizon.synth import SceneSpec, render_scene

# the contract's HORIZON_ATTITUDE test vector (vehicle 7, seq 1132)
VECTOR_HEX = "840724006c04000000f1536515cd5b0721b0323e4df30ebd6666663f00f153650065cd1d"


def _estimate(roll: float = 10.0, pitch: float | None = -2.0, quality: float = 0.9) -> HorizonEstimate:
    est = HorizonEstimate.from_line(OrientedLine.from_roll_offset(roll, 0.05, 320, 240), quality, "robust")
    return HorizonEstimate(**{**est.__dict__, "pitch_deg": pitch})


def test_pack_matches_the_contract_vector() -> None:
    data = pack_horizon_attitude(1132, 7, 1_700_000_000_123_456_789, 0.1745, -0.0349, 0.9,
                                 1_700_000_000_500_000_000)
    assert len(data) == HORIZON_ATTITUDE_SIZE
    assert data.hex() == VECTOR_HEX


def test_pack_matches_the_shared_vector_file() -> None:
    vec = next(v for v in json.loads(data_file("vectors", "legacy-udp.json").read_text()) if v["type"] == 0x84)
    roll, pitch, quality, sec, nsec = vec["fields_in_table_order"]
    hdr = vec["header"]
    data = pack_horizon_attitude(hdr["seq"], hdr["vehicle"], hdr["tv_sec"] * 10**9 + hdr["tv_nsec"],
                                 roll, pitch, quality, sec * 10**9 + nsec)
    assert data.hex() == vec["hex"]


def test_pack_refuses_what_the_aircraft_would_reject() -> None:
    with pytest.raises(ValueError, match="pitch must be finite"):
        pack_horizon_attitude(1, 1, 0, 0.0, math.nan, 0.5, 0)
    with pytest.raises(ValueError, match="vehicle id"):
        pack_horizon_attitude(1, 0, 0, 0.0, 0.0, 0.5, 0)


def test_legacy_sender_over_udp_and_acks() -> None:
    port = free_udp_port()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", port))
        rx.settimeout(5.0)
        with LegacyHorizonSender("127.0.0.1", port, vehicle_id=3, clock_ns=lambda: 5 * 10**9) as tx:
            tx(_estimate(10.0, -2.0, 0.75), 1_234_567_890_123_456_789)
            tx(HorizonEstimate.none("robust", 320, 240), 0)  # nothing to send
            tx(_estimate(pitch=None), 0)  # no pitch without intrinsics: not sent
            data, addr = rx.recvfrom(2048)
            typ, vehicle, size, seq, s_sec, s_nsec = struct.unpack_from("<BBHIiI", data)
            roll, pitch, quality, f_sec, f_nsec = struct.unpack_from("<fffiI", data, 16)
            assert (typ, vehicle, size, seq, s_sec, s_nsec) == (0x84, 3, 36, 1, 5, 0)
            assert len(data) == 36
            assert roll == pytest.approx(math.radians(10.0), abs=1e-6)
            assert pitch == pytest.approx(math.radians(-2.0), abs=1e-6)
            assert quality == pytest.approx(0.75)
            assert (f_sec, f_nsec) == (1_234_567_890, 123_456_789)
            assert tx.sent == 1 and tx.skipped == 2
            # the aircraft answers with a COMMAND_ACK (type 0x03, 24 bytes)
            ack = struct.pack("<BBHIiIBBHI", 0x03, 3, 24, 1, 0, 0, 0x84, 0, 0, seq)
            rx.sendto(ack, addr)
            assert wait_for(lambda: tx.poll_acks() >= 1, 5.0)
            rx.settimeout(0.05)
            with pytest.raises(TimeoutError):
                rx.recvfrom(2048)


def test_mavlink_sender_attitude_and_quality() -> None:
    from pymavlink import mavutil

    port = free_udp_port()
    rx = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}")
    try:
        with MavlinkHorizonSender(f"udpout:127.0.0.1:{port}", system_id=5) as tx:
            frame_ns = time.time_ns()
            tx(_estimate(-15.0, 3.0, 0.6), frame_ns)
            hb = rx.recv_match(type="HEARTBEAT", blocking=True, timeout=5)
            att = rx.recv_match(type="ATTITUDE", blocking=True, timeout=5)
            q = rx.recv_match(type="NAMED_VALUE_FLOAT", blocking=True, timeout=5)
            assert hb is not None and att is not None and q is not None
            assert hb.get_srcSystem() == 5 and hb.get_srcComponent() == 100
            assert hb.type == mavutil.mavlink.MAV_TYPE_CAMERA
            assert att.get_srcComponent() == 100
            assert att.roll == pytest.approx(math.radians(-15.0), abs=1e-6)
            assert att.pitch == pytest.approx(math.radians(3.0), abs=1e-6)
            assert math.isnan(att.yaw) and math.isnan(att.rollspeed)
            assert q.name == "HZN_QUAL" and q.value == pytest.approx(0.6)
            assert q.time_boot_ms == att.time_boot_ms
            tx(HorizonEstimate.none("robust", 320, 240), frame_ns)
            assert tx.sent == 1 and tx.skipped == 1
    finally:
        rx.close()


def _frames(n: int) -> list[Frame]:
    out = []
    for i in range(n):
        img, _ = render_scene(SceneSpec(160, 120, 5.0 * i, 0.0), np.random.default_rng(i))
        out.append(Frame(str(i), i, img, 1000 + i, "test"))
    return out


def test_run_stream_feeds_every_sender_and_survives_a_failing_one() -> None:
    got: list[tuple[float | None, int]] = []

    def collect(est: HorizonEstimate, t_ns: int) -> None:
        got.append((est.roll_deg, t_ns))

    def broken(est: HorizonEstimate, t_ns: int) -> None:
        raise OSError("network is unreachable")

    seen: list[str] = []
    stats = run_stream(_frames(4), RobustDetector().detect, [broken, collect],
                       on_estimate=lambda f, e: seen.append(f.label))
    assert stats.frames == 4 and stats.found == 4 and stats.send_errors == 4
    assert [t for _, t in got] == [1000, 1001, 1002, 1003]
    assert [round(r or 0) for r, _ in got] == [0, 5, 10, 15]
    assert seen == ["0", "1", "2", "3"]


def test_run_stream_paces_and_stops() -> None:
    frames = _frames(6)
    stop = threading.Event()
    count = 0

    def stop_after_three(est: HorizonEstimate, t_ns: int) -> None:
        nonlocal count
        count += 1
        if count == 3:
            stop.set()

    t0 = time.monotonic()
    stats = run_stream(frames, RobustDetector().detect, [stop_after_three], stop=stop, pace_hz=20.0)
    elapsed = time.monotonic() - t0
    assert stats.frames == 3
    assert elapsed >= 2 * 0.05 * 0.9  # three frames on 50 ms deadlines: at least two waits
