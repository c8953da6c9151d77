"""MAVLink 2 signing: writes must be signed, reads per link, refusals counted and never acted on.

Every test runs the MAVLink bridge on a `gcs_bridge.testing.SyntheticVehicle`: synthetic
vehicle state (an aircraft in a steady banked circle) under a real ThreadManager, in this
process. No drivers, estimator, control law or simulator run, and the parameters are only
the manager's, the synthetic threads' and the bridge's (not the runtime's set) plus the
test's.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from conftest import free_udp_port, wait_for
from pymavlink import mavutil

from companion.core.params import float_param
from gcs_bridge import param_codec
from gcs_bridge.dialect import mavlink
from gcs_bridge.signing import SignatureChecker, key_from_text, new_key_file, signing_timestamp
from gcs_bridge.testing import MiniGcs, SyntheticVehicle

EXTRA = [float_param("TST_F", 1.5, -10.0, 10.0, "m", "a float")]


def set_f(value: float) -> mavlink.MAVLink_param_set_message:
    return mavlink.MAVLink_param_set_message(1, 1, b"TST_F", value, param_codec.T_REAL32)


def read_f() -> mavlink.MAVLink_param_request_read_message:
    return mavlink.MAVLink_param_request_read_message(1, 1, b"TST_F", -1)


@contextmanager
def signed_vehicle(tmp_path: Path, *settings: str) -> Iterator[tuple[SyntheticVehicle, bytes, list[int]]]:
    key_file = tmp_path / "mavlink.key"
    passphrase = new_key_file(key_file)
    ports = [free_udp_port() for _ in settings]
    endpoints = [f"udpin:127.0.0.1:{p}{s}" for p, s in zip(ports, settings, strict=True)]
    with SyntheticVehicle(endpoints, key_file=key_file, extra_params=EXTRA,
                          flight_dir=tmp_path) as v:
        yield v, key_from_text(passphrase), ports


def test_writes_need_a_signature_reads_do_not(tmp_path: Path) -> None:
    with signed_vehicle(tmp_path, "") as (v, key, (port,)):
        unsigned = MiniGcs(connect=("127.0.0.1", port), sysid=200)
        signed = MiniGcs(connect=("127.0.0.1", port), key=key)
        try:
            # unsigned read: allowed by default; the answer itself is signed and authentic
            unsigned.send(read_f())
            m = unsigned.recv(3.0, "PARAM_VALUE")
            assert m is not None and m.get_msgbuf()[2] & 0x01
            checker = SignatureChecker(key, lambda: signing_timestamp(time.time_ns()))
            assert checker.check(m.get_msgbuf()) is None
            # unsigned write: refused, counted, reported, not applied
            unsigned.send(set_f(2.0))
            text = unsigned.seen(3.0, "STATUSTEXT", lambda t: "refused" in t.text)
            assert text is not None and "unsigned" in text.text and "PARAM_SET" in text.text
            assert v.params.get("TST_F") == 1.5
            unsigned.send(mavlink.MAVLink_command_long_message(
                1, 1, mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 0, 2, 0, 0, 0, 0, 0, 0))
            assert unsigned.recv(0.5, "COMMAND_ACK") is None and v.run_reason is None
            # an unsigned information request is a read
            unsigned.send(mavlink.MAVLink_command_long_message(
                1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0))
            assert unsigned.recv(2.0, "AUTOPILOT_VERSION") is not None
            # signed write: applied
            signed.send(set_f(2.5))
            assert signed.recv(3.0, "PARAM_VALUE", lambda p: p.param_value == 2.5) is not None
            assert v.params.get("TST_F") == 2.5
            # the same signed frame again is a replay
            frame = signed.send(set_f(3.0))
            assert wait_for(lambda: v.params.get("TST_F") == 3.0, 2.0)
            v.params.set("TST_F", 1.0)
            signed.send_raw(frame)
            assert wait_for(lambda: v.bridge.links[0].refusals.get("replayed (old timestamp)") == 1, 2.0)
            assert v.params.get("TST_F") == 1.0
            # a wrong key is refused even for reads
            forger = MiniGcs(connect=("127.0.0.1", port), key=key_from_text("guessed passphrase"))
            try:
                forger.send(read_f())
                assert forger.recv(0.5, "PARAM_VALUE") is None
            finally:
                forger.close()
            stats = v.bridge.stats()[0]
            assert stats["refusals"]["unsigned"] == 2 and stats["refusals"]["bad signature"] == 1
            assert stats["refused"] == 4
            # the refusal count reaches the ground in SYS_STATUS (errors_count1)
            st = signed.recv(3.0, "SYS_STATUS")
            assert st is not None and st.errors_count1 == 4
        finally:
            unsigned.close()
            signed.close()


def test_setup_signing_is_refused_and_never_logged(tmp_path: Path) -> None:
    with signed_vehicle(tmp_path, "") as (v, key, (port,)):
        gcs = MiniGcs(connect=("127.0.0.1", port), key=key)
        try:
            new_key = bytes(range(32))
            gcs.send(mavlink.MAVLink_setup_signing_message(1, 1, new_key, 12345))
            assert wait_for(lambda: v.bridge.stats()[0]["refused"] == 1, 2.0)
            gcs.send(read_f())
            assert gcs.recv(3.0, "PARAM_VALUE") is not None  # the old key is still the key
        finally:
            gcs.close()
    data = (tmp_path / "mavlink-0.tlog").read_bytes()
    assert new_key not in data and key not in data
    log = mavutil.mavlink_connection(str(tmp_path / "mavlink-0.tlog"), dialect="common")
    try:
        types = []
        while (m := log.recv_match()) is not None:
            types.append(m.get_type())
            assert not m.get_signed()
    finally:
        log.close()
    assert "PARAM_REQUEST_READ" in types and "SETUP_SIGNING" not in types


@pytest.mark.parametrize("setting,read_ok,write_ok", [
    ("?unsigned_reads=0", False, False),
    ("?signing=off", True, True),
])
def test_per_link_policies(tmp_path: Path, setting: str, read_ok: bool, write_ok: bool) -> None:
    with signed_vehicle(tmp_path, "", setting) as (v, _key, (_p0, port)):
        gcs = MiniGcs(connect=("127.0.0.1", port))
        try:
            gcs.send(read_f())
            assert (gcs.recv(1.0 if read_ok else 0.5, "PARAM_VALUE") is not None) == read_ok
            gcs.send(set_f(-2.0))
            assert wait_for(lambda: v.params.get("TST_F") == -2.0, 1.0 if write_ok else 0.3) == write_ok
            frames = [m.get_msgbuf() for m in gcs.history]
            assert all(bool(f[2] & 1) != (setting == "?signing=off") for f in frames if f[0] == 0xFD)
        finally:
            gcs.close()


def test_raw_value_of_a_signed_param_set_is_intact(tmp_path: Path) -> None:
    with signed_vehicle(tmp_path, "") as (v, key, (port,)):
        gcs = MiniGcs(connect=("127.0.0.1", port), key=key)
        try:
            msg = set_f(0.0)
            raw = struct.pack("<f", 7.25)
            payload = struct.pack("<4sBB16sB", raw, 1, 1, b"TST_F", param_codec.T_REAL32)
            frame = msg._pack(gcs.mav, msg.crc_extra, payload)
            gcs.mav.seq += 1
            gcs.send_raw(frame)
            assert wait_for(lambda: v.params.get("TST_F") == 7.25, 2.0)
        finally:
            gcs.close()
