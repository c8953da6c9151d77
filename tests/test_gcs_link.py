"""Links: several ground stations, ground stations that come back, TCP, serial, garbage, tlog.

Every test runs the MAVLink bridge on a `support.synthetic_vehicle.SyntheticVehicle`: synthetic
vehicle state (an aircraft in a steady banked circle) under a real ThreadManager, in this
process. No drivers, estimator, control law or simulator run, and the parameters are only
the manager's, the synthetic threads' and the bridge's (not the runtime's set) plus the
test's.
"""

from __future__ import annotations

import os
import random
import select
import socket
import struct
import time
from pathlib import Path

from conftest import free_tcp_port, free_udp_port, wait_for
from pymavlink import mavutil
from support.synthetic_vehicle import MiniGcs, SyntheticVehicle

from gcs_bridge.dialect import mavlink
from gcs_bridge.params import codec as param_codec

GCS_HB = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                           0, 0, 0, 3)


def test_two_ground_stations_on_one_udpin_link_and_one_coming_back() -> None:
    port = free_udp_port()
    with SyntheticVehicle([f"udpin:127.0.0.1:{port}"]) as v:
        a = MiniGcs(connect=("127.0.0.1", port), sysid=255)
        b = MiniGcs(connect=("127.0.0.1", port), sysid=254)
        try:
            a.send(GCS_HB)
            b.send(GCS_HB)
            assert a.recv(3.0, "HEARTBEAT") is not None
            assert b.recv(3.0, "HEARTBEAT") is not None
            a.send(mavlink.MAVLink_param_request_read_message(1, 1, b"MGR_STATUS_MS", -1))
            assert a.recv(2.0, "PARAM_VALUE") is not None
            assert wait_for(lambda: {p for p in v.bridge.stats()[0]["peers"]} == {(255, 190), (254, 190)}, 2.0)
            a.close()
            # the same ground station restarted: new socket, new source port
            c = MiniGcs(connect=("127.0.0.1", port), sysid=255)
            try:
                c.send(GCS_HB)
                assert c.recv(3.0, "HEARTBEAT") is not None
                c.send(mavlink.MAVLink_param_request_read_message(1, 1, b"MGR_STATUS_MS", -1))
                assert c.recv(2.0, "PARAM_VALUE") is not None
                assert b.recv(2.0, "HEARTBEAT") is not None  # the other one is still served
            finally:
                c.close()
        finally:
            a.close()
            b.close()


def test_udpout_ground_station_that_restarts_is_served_again() -> None:
    port = free_udp_port()
    with SyntheticVehicle([f"udpout:127.0.0.1:{port}", f"udpout:127.0.0.1:{free_udp_port()}"]) as v:
        gcs = MiniGcs(listen_port=port)
        assert gcs.recv(3.0, "HEARTBEAT") is not None
        gcs.close()
        # the ground station is away while the aircraft keeps sending into the void
        sent = v.bridge.stats()[0]["tx_frames"]
        assert wait_for(lambda: v.bridge.stats()[0]["tx_frames"] > sent + 5, 5.0)
        gcs = MiniGcs(listen_port=port)
        try:
            assert gcs.recv(3.0, "HEARTBEAT") is not None
            gcs.send(mavlink.MAVLink_param_request_read_message(1, 1, b"MGR_STATUS_MS", -1))
            assert gcs.recv(2.0, "PARAM_VALUE") is not None
        finally:
            gcs.close()


def _tcp_heartbeat(port: int) -> mavlink.MAVLink_message | None:
    parser = mavlink.MAVLink(None, 0, 0)
    with socket.create_connection(("127.0.0.1", port), timeout=3.0) as s:
        s.sendall(GCS_HB.pack(mavlink.MAVLink(None, 255, 190)))
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            data = s.recv(4096)
            if not data:
                return None
            for m in parser.parse_buffer(data) or []:
                if m.get_type() == "HEARTBEAT":
                    return m
    return None


def test_tcp_server_link_serves_clients_that_leave_and_come_back() -> None:
    port = free_tcp_port()
    with SyntheticVehicle([f"tcpin:127.0.0.1:{port}"]) as v:
        for _ in range(3):
            hb = _tcp_heartbeat(port)
            assert hb is not None and hb.get_srcComponent() == 1
        assert wait_for(lambda: v.bridge.links[0].transport.peer_count == 0, 2.0)
        assert v.bridge.links[0].transport.counters.peers_seen == 3


def test_serial_link_over_a_pseudo_terminal() -> None:
    master, slave = os.openpty()
    path = os.ttyname(slave)
    os.close(slave)
    try:
        with SyntheticVehicle([f"{path},57600"]) as v:
            parser = mavlink.MAVLink(None, 0, 0)
            os.write(master, mavlink.MAVLink_param_request_read_message(
                1, 1, b"MGR_STATUS_MS", -1).pack(mavlink.MAVLink(None, 255, 190)))
            got: set[str] = set()
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline and not {"HEARTBEAT", "PARAM_VALUE"} <= got:
                if select.select([master], [], [], 0.2)[0]:
                    for m in parser.parse_buffer(os.read(master, 4096)) or []:
                        got.add(m.get_type())
            assert {"HEARTBEAT", "PARAM_VALUE"} <= got
            assert v.bridge.links[0].transport.bytes_per_s == 5760.0
    finally:
        os.close(master)


def test_a_57600_baud_radio_gets_a_schedule_it_can_carry() -> None:
    """The default schedule on a serial link uses at most MAV_RADIO_PCT of baud / 10, measured
    as the bytes really written (a pseudo-terminal does not pace like a radio, so the bridge
    must not count on the line to slow it down), while attitude still moves the HUD."""
    master, slave = os.openpty()
    path = os.ttyname(slave)
    os.close(slave)
    try:
        with SyntheticVehicle([f"{path},57600"]):
            parser = mavlink.MAVLink(None, 0, 0)
            parser.robust_parsing = True
            counts: dict[str, int] = {}
            received = 0
            t_end = time.monotonic() + 1.0  # let the start-up burst (first of each) pass
            while time.monotonic() < t_end:
                if select.select([master], [], [], 0.2)[0]:
                    os.read(master, 65536)
            t0 = time.monotonic()
            while time.monotonic() - t0 < 4.0:
                if select.select([master], [], [], 0.2)[0]:
                    data = os.read(master, 65536)
                    received += len(data)
                    for m in parser.parse_buffer(data) or []:
                        counts[m.get_type()] = counts.get(m.get_type(), 0) + 1
            elapsed = time.monotonic() - t0
            share_bytes_s = 5760.0 * 0.50  # MAV_RADIO_PCT's default
            assert received / elapsed <= share_bytes_s * 1.1, (received / elapsed, counts)
            assert counts.get("ATTITUDE", 0) / elapsed >= 4.0, counts
            assert counts.get("GPS_RAW_INT", 0) / elapsed >= 1.5, counts  # slow streams kept
    finally:
        os.close(master)


def test_garbage_is_counted_and_never_stops_the_link() -> None:
    port = free_udp_port()
    with SyntheticVehicle([f"udpin:127.0.0.1:{port}"]) as v:
        gcs = MiniGcs(connect=("127.0.0.1", port))
        try:
            rng = random.Random(7)
            good = mavlink.MAVLink_ping_message(1, 1, 0, 0).pack(mavlink.MAVLink(None, 255, 190))
            junk = [bytes(rng.randrange(256) for _ in range(rng.randrange(1, 300))) for _ in range(200)]
            junk += [good[:7], good[:-1] + bytes([good[-1] ^ 0xFF]), b"\xfd" * 500,
                     b"\xfd\xff\x80\x00" + b"\x00" * 300, b"\xfe" + b"\x00" * 5000]
            for chunk in junk:
                gcs.send_raw(chunk)
            gcs.send(mavlink.MAVLink_ping_message(42, 3, 0, 0))
            pong = gcs.recv(3.0, "PING", lambda m: m.time_usec == 42)
            assert pong is not None
            assert v.bridge.stats()[0]["parse_errors"] > 0
            assert all(t.restarts == 0 for t in v.bridge.threads)
        finally:
            gcs.close()


def test_tlog_records_both_directions_and_reads_back(tmp_path: Path) -> None:
    gcs = MiniGcs(listen_port=free_udp_port())
    try:
        with SyntheticVehicle([f"udpout:127.0.0.1:{gcs.port}"], flight_dir=tmp_path) as v:
            assert gcs.recv(3.0, "HEARTBEAT") is not None
            gcs.send(mavlink.MAVLink_param_request_list_message(1, 1))
            n = len(v.params)
            assert gcs.seen(3.0, "PARAM_VALUE", lambda m: m.param_index == n - 1) is not None
    finally:
        gcs.close()
    path = tmp_path / "mavlink-0.tlog"
    log = mavutil.mavlink_connection(str(path), dialect="common")
    try:
        msgs = []
        while (m := log.recv_match()) is not None:
            msgs.append(m)
    finally:
        log.close()
    types = [m.get_type() for m in msgs]
    assert "PARAM_REQUEST_LIST" in types  # received
    assert types.count("PARAM_VALUE") >= n and "HEARTBEAT" in types  # sent
    stamps = [m._timestamp for m in msgs]
    assert stamps == sorted(stamps) and abs(stamps[-1] - time.time()) < 60
    assert {m.get_srcSystem() for m in msgs} == {1, 255}


def test_several_aircraft_with_their_own_ids_on_one_ground_station() -> None:
    gcs = MiniGcs(listen_port=free_udp_port())
    try:
        with SyntheticVehicle([f"udpout:127.0.0.1:{gcs.port}"], vehicle_id=11), \
                SyntheticVehicle([f"udpout:127.0.0.1:{gcs.port}"], vehicle_id=12) as v12:
            systems: set[int] = set()
            while systems != {11, 12}:
                hb = gcs.recv(3.0, "HEARTBEAT")
                assert hb is not None, systems
                systems.add(hb.get_srcSystem())
            # both requests go to both aircraft: each answers only the one addressed to it
            v12.params.set("MGR_STATUS_MS", 1234)
            for target in (11, 12):
                frame = mavlink.MAVLink_param_request_read_message(
                    target, 1, b"MGR_STATUS_MS", -1).pack(gcs.mav)
                for system in (11, 12):
                    gcs.sock.sendto(frame, gcs.address_of[system])
            answers = []
            deadline = time.monotonic() + 1.5
            while time.monotonic() < deadline:
                m = gcs.recv(0.2, "PARAM_VALUE", lambda p: p.param_id == "MGR_STATUS_MS")
                if m is not None:
                    raw = param_codec.raw_value_of(m)
                    answers.append((m.get_srcSystem(), struct.unpack("<i", raw)[0]))
            assert set(answers) == {(11, 1000), (12, 1234)}  # (12 also announced its change)
            assert answers.count((11, 1000)) == 1
    finally:
        gcs.close()
