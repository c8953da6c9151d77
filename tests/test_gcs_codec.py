"""Bridge building blocks without threads: endpoints, parameter bytes, signing, tlog, FTP, keys."""

from __future__ import annotations

import os
import stat
import struct
import time

import pytest
from pymavlink import mavutil
from pymavlink.generator.mavcrc import x25crc

from companion.core.params import float_param, int_param
from companion.logs import LogService
from gcs_bridge.dialect import (
    MSG_ID_PROTOCOL_VERSION,
    ProtocolVersionMessage,
    crc_extra_of,
    mavlink,
)
from gcs_bridge.params import codec as param_codec
from gcs_bridge.signing import (
    KeyFileError,
    SignatureChecker,
    is_write,
    key_from_text,
    new_key_file,
    read_key_file,
    signing_timestamp,
)
from gcs_bridge.status import statustext
from gcs_bridge.tlog import TlogWriter, strip_signature, tlog_length
from gcs_bridge.transports.endpoints import EndpointError, parse_endpoint

INT_SPEC = int_param("TST_INT", 0, -(2**31), 2**31 - 1)
FLOAT_SPEC = float_param("TST_FLT", 0.0, -1e6, 1e6)
KEY = key_from_text("correct horse battery staple")


def _signed_mav(key: bytes = KEY, sysid: int = 255, compid: int = 190,
                link_id: int = 1) -> mavlink.MAVLink:
    mav = mavlink.MAVLink(None, sysid, compid)
    mav.signing.secret_key = key
    mav.signing.sign_outgoing = True
    mav.signing.link_id = link_id
    mav.signing.timestamp = signing_timestamp(time.time_ns())
    return mav


# ------------------------------------------------------------------------------------ endpoints
@pytest.mark.parametrize("text,kind,host,port", [
    ("udpout:127.0.0.1:14550", "udpout", "127.0.0.1", 14550),
    ("udpin:0.0.0.0:14550", "udpin", "0.0.0.0", 14550),
    ("udp:0.0.0.0:14551", "udpin", "0.0.0.0", 14551),
    ("tcpin:0.0.0.0:5760", "tcpin", "0.0.0.0", 5760),
    ("tcp:localhost:5760", "tcp", "localhost", 5760),
    ("127.0.0.1:14550", "udpin", "127.0.0.1", 14550),
])
def test_network_endpoints_parse_like_pymavlink(text: str, kind: str, host: str, port: int) -> None:
    ep = parse_endpoint(text)
    assert (ep.kind, ep.host, ep.port) == (kind, host, port)
    assert ep.url == text and ep.signing is None and ep.unsigned_reads is None


def test_serial_endpoints_and_settings() -> None:
    ep = parse_endpoint("/dev/ttyUSB0,57600?signing=off&unsigned_reads=0&ATTITUDE=10&GPS_RAW_INT=0")
    assert ep.kind == "serial" and ep.device == "/dev/ttyUSB0" and ep.baud == 57600
    assert ep.signing is False and ep.unsigned_reads is False
    assert ep.rates_hz == {mavlink.MAVLINK_MSG_ID_ATTITUDE: 10.0,
                           mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 0.0}
    assert ep.url == "/dev/ttyUSB0,57600"
    assert parse_endpoint("loop://").kind == "serial"
    assert parse_endpoint("/dev/ttyS2").baud == 57600


@pytest.mark.parametrize("text,fragment", [
    ("", "empty"),
    ("udpout:127.0.0.1", "HOST:PORT"),
    ("udpout:127.0.0.1:abc", "not a number"),
    ("udpout:127.0.0.1:70000", "outside"),
    ("udpout:127.0.0.1:0", "cannot be 0"),
    ("/dev/ttyUSB0,fast", "baud rate"),
    ("udpin:0.0.0.0:14550?ATTITUDE=fast", "not a number"),
    ("udpin:0.0.0.0:14550?ATTITUDE=-1", "outside"),
    ("udpin:0.0.0.0:14550?NOPE=1", "unknown setting"),
    ("udpin:0.0.0.0:14550?signing=maybe", "on/off"),
    ("udpin:0.0.0.0:14550?signing", "KEY=VALUE"),
    ("bogus", "not a connection string"),
])
def test_bad_endpoints_name_the_problem(text: str, fragment: str) -> None:
    with pytest.raises(EndpointError) as info:
        parse_endpoint(text)
    assert fragment in str(info.value)
    assert repr(text.strip()) in str(info.value) or text == ""


# ------------------------------------------------------------------------------------ params
@pytest.mark.parametrize("value", [0, 1, -1, 2**24 + 1, 2**31 - 1, -(2**31),
                                   0x7F800001, 0x7FBFFFFF, -8388607, -4194305])
def test_bytewise_int32_survives_every_bit_pattern(value: int) -> None:
    """Values whose bytes are a signalling NaN are the ones a Python float would corrupt."""
    msg = param_codec.param_value_message(INT_SPEC, value, 3, 10, bytewise=True)
    frame = msg.pack(mavlink.MAVLink(None, 1, 1))
    parsed = mavlink.MAVLink(None, 0, 0).parse_char(frame)
    raw = param_codec.raw_value_of(parsed)
    assert raw == struct.pack("<i", value)
    assert param_codec.decode(raw, param_codec.T_INT32, bytewise=True) == value
    assert (parsed.param_index, parsed.param_count, parsed.param_id) == (3, 10, "TST_INT")


def test_c_cast_encoding_and_decoding() -> None:
    raw = param_codec.encode(INT_SPEC, 1234, bytewise=False)
    assert struct.unpack("<f", raw)[0] == 1234.0
    assert param_codec.decode(raw, param_codec.T_INT32, bytewise=False) == 1234
    with pytest.raises(param_codec.WireValueError, match="not an integer"):
        param_codec.decode(struct.pack("<f", 2.5), param_codec.T_INT32, bytewise=False)


def test_decode_types() -> None:
    assert param_codec.decode(struct.pack("<f", 2.5), param_codec.T_REAL32, bytewise=True) == 2.5
    assert param_codec.decode(b"\xff\x00\x00\x00", param_codec.T_UINT8, bytewise=True) == 255
    assert param_codec.decode(b"\xff\xff\x00\x00", param_codec.T_INT16, bytewise=True) == -1
    with pytest.raises(param_codec.WireValueError, match="not supported"):
        param_codec.decode(b"\0\0\0\0", mavlink.MAV_PARAM_TYPE_INT64, bytewise=True)
    with pytest.raises(param_codec.WireValueError, match="4"):
        param_codec.decode(b"\0\0", param_codec.T_INT32, bytewise=True)
    assert param_codec.type_matches(INT_SPEC, param_codec.T_UINT8)
    assert param_codec.type_matches(INT_SPEC, param_codec.T_REAL32)
    assert not param_codec.type_matches(FLOAT_SPEC, param_codec.T_INT32)


def test_mavlink2_trimmed_payload_is_repadded() -> None:
    frame = mavlink.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(
        mavlink.MAVLink(None, 255, 190))
    assert frame[1] < 33  # MAVLink 2 dropped the trailing zeros
    payload = param_codec.frame_payload(frame, 33)
    assert len(payload) == 33 and struct.unpack("<7fHBBB", payload)[7:] == (400, 1, 1, 0)


# ------------------------------------------------------------------------------------ signing
def test_signature_checker_accepts_good_and_refuses_the_rest() -> None:
    now = signing_timestamp(time.time_ns())
    checker = SignatureChecker(KEY, lambda: now)
    mav = _signed_mav()
    f1 = mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(mav)
    assert checker.check(f1) is None
    assert checker.check(f1) == "replayed (old timestamp)"
    f2 = bytearray(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(mav))
    f2[-1] ^= 0x01
    assert checker.check(f2) == "bad signature"
    other = _signed_mav(key_from_text("another passphrase"))
    assert checker.check(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(other)) == \
        "bad signature"
    unsigned = mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(mavlink.MAVLink(None, 1, 1))
    assert checker.check(unsigned) == "unsigned"
    old = _signed_mav(link_id=2)
    old.signing.timestamp = now - 10 * 60 * 100_000  # ten minutes behind
    assert checker.check(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(old)) == \
        "stale timestamp"


def test_forged_frame_does_not_poison_the_stream() -> None:
    """pymavlink stores a stream's timestamp before checking the signature; we do not."""
    now = signing_timestamp(time.time_ns())
    checker = SignatureChecker(KEY, lambda: now)
    forger = _signed_mav(key_from_text("not the key at all"))
    forger.signing.timestamp = now + 10**9
    assert checker.check(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(forger)) == \
        "bad signature"
    assert checker.check(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(_signed_mav())) is None


def test_write_classification() -> None:
    assert is_write(mavlink.MAVLINK_MSG_ID_PARAM_SET)
    assert is_write(mavlink.MAVLINK_MSG_ID_COMMAND_LONG, mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN)
    assert is_write(mavlink.MAVLINK_MSG_ID_COMMAND_INT, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL)
    assert not is_write(mavlink.MAVLINK_MSG_ID_COMMAND_LONG, mavlink.MAV_CMD_REQUEST_MESSAGE)
    assert not is_write(mavlink.MAVLINK_MSG_ID_PARAM_REQUEST_LIST)
    assert not is_write(mavlink.MAVLINK_MSG_ID_HEARTBEAT)


def test_key_file_round_trip_and_errors(tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "keys" / "mavlink.key"
    passphrase = new_key_file(path)
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    key, read_back = read_key_file(path)
    assert read_back == passphrase and key == key_from_text(passphrase) and len(key) == 32
    with pytest.raises(KeyFileError, match="exists already"):
        new_key_file(path)
    assert new_key_file(path, force=True) != passphrase
    hex_file = tmp_path / "hex.key"
    hex_file.write_text("ab" * 32 + "\n")
    for mode in (0o644, 0o640, 0o602):  # group or others may read or write it: refused
        os.chmod(hex_file, mode)
        with pytest.raises(KeyFileError, match="chmod 600") as info:
            read_key_file(hex_file)
        assert str(hex_file) in str(info.value) and f"{mode:o}" in str(info.value)
    os.chmod(hex_file, 0o600)
    assert read_key_file(hex_file)[0] == bytes.fromhex("ab" * 32)
    for content, fragment in [("", "exactly one"), ("a\nb\n", "exactly one"),
                              ("short", "shorter than 8")]:
        bad = tmp_path / "bad.key"
        bad.write_text(content)
        with pytest.raises(KeyFileError, match=fragment) as info:
            read_key_file(bad)
        assert str(bad) in str(info.value)
    binary = tmp_path / "bin.key"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(KeyFileError, match="UTF-8"):
        read_key_file(binary)
    with pytest.raises(KeyFileError, match="cannot read"):
        read_key_file(tmp_path / "missing.key")


# ------------------------------------------------------------------------------------ tlog
def test_strip_signature_gives_a_valid_unsigned_frame() -> None:
    frame = mavlink.MAVLink_attitude_message(1, 0.1, 0.2, 0.3, 0, 0, 0).pack(_signed_mav())
    assert frame[2] & 0x01
    stripped = strip_signature(frame)
    assert len(stripped) == len(frame) - 13 and not stripped[2] & 0x01
    parsed = mavlink.MAVLink(None, 0, 0).parse_char(stripped)
    assert parsed.get_type() == "ATTITUDE" and abs(parsed.roll - 0.1) < 1e-6


def test_tlog_is_read_by_mavutil_without_signatures_or_keys(tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "link.tlog"
    w = TlogWriter(path)
    w.open()
    mav = _signed_mav()
    t0 = 1_700_000_000_000_000
    w.write(t0, mavlink.MAVLink_heartbeat_message(1, 12, 0, 0, 4, 3).pack(mav))
    w.write(t0 + 1000, mavlink.MAVLink_setup_signing_message(1, 1, KEY, 5).pack(mav))
    w.write(t0 + 2000, mavlink.MAVLink_attitude_message(1, 0.5, 0, 0, 0, 0, 0).pack(mav))
    w.close()
    assert KEY not in path.read_bytes()
    log = mavutil.mavlink_connection(str(path), dialect="common")
    try:
        msgs = []
        while (m := log.recv_match()) is not None:
            msgs.append(m)
    finally:
        log.close()
    assert [m.get_type() for m in msgs] == ["HEARTBEAT", "ATTITUDE"]
    assert abs(msgs[1]._timestamp - (t0 + 2000) / 1e6) < 1e-6
    assert not any(m.get_signed() for m in msgs)


def test_tlog_write_after_close_is_ignored(tmp_path) -> None:  # type: ignore[no-untyped-def]
    w = TlogWriter(tmp_path / "x.tlog")
    w.open()
    w.close()
    w.write(0, b"\xfd\x00")
    assert w.frames == 0


def test_tlog_through_the_log_service_is_written_by_its_thread_and_survives_restarts(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """In a runtime the link threads only queue tlog records; the service's writer thread
    writes them, and a link thread restart (close, open) keeps appending to the same file."""
    service = LogService(tmp_path)
    service.start()
    w = TlogWriter(tmp_path / "mavlink-0.tlog", service)
    w.open()
    mav = mavlink.MAVLink(None, 1, 1)
    t0 = 1_700_000_000_000_000
    w.write(t0, mavlink.MAVLink_heartbeat_message(1, 12, 0, 0, 4, 3).pack(mav))
    w.close()
    w.write(t0 + 500, mavlink.MAVLink_heartbeat_message(1, 12, 0, 0, 4, 3).pack(mav))  # ignored
    w.open()
    w.write(t0 + 1000, mavlink.MAVLink_attitude_message(1, 0.5, 0, 0, 0, 0, 0).pack(mav))
    service.close()
    assert w.frames == 2 and w.dropped == 0
    log = mavutil.mavlink_connection(str(tmp_path / "mavlink-0.tlog"), dialect="common")
    try:
        types = []
        while (m := log.recv_match()) is not None:
            types.append(m.get_type())
    finally:
        log.close()
    assert types == ["HEARTBEAT", "ATTITUDE"]


def test_tlog_cut_short_by_a_crash_is_trimmed_to_whole_records(tmp_path) -> None:  # type: ignore[no-untyped-def]
    mav = mavlink.MAVLink(None, 1, 1)
    one = struct.pack(">Q", 1) + mavlink.MAVLink_heartbeat_message(1, 12, 0, 0, 4, 3).pack(mav)
    v1_heartbeat = b"\xfe\x09" + bytes(4) + bytes(9) + bytes(2)  # MAVLink 1: 6 + 9 + 2 bytes
    two = struct.pack(">Q", 2) + v1_heartbeat
    whole = one + two + one
    assert tlog_length(whole) == len(whole)
    for cut in range(len(whole)):
        keep = tlog_length(whole[:cut])
        assert keep in (0, len(one), len(one + two)) and keep <= cut
    assert tlog_length(one + b"\x00" * 30) == len(one)  # not a frame: stop there
    (tmp_path / "mavlink-0.tlog").write_bytes(whole[:-3])
    service = LogService(tmp_path)
    service.start()
    w = TlogWriter(tmp_path / "mavlink-0.tlog", service)
    w.open()
    w.write(3, mavlink.MAVLink_heartbeat_message(1, 12, 0, 0, 4, 3).pack(mav))
    service.close()
    assert (tmp_path / "mavlink-0.tlog").read_bytes() == one + two + struct.pack(">Q", 3) + one[8:]


# ------------------------------------------------------------------------------------ misc
def test_protocol_version_crc_extra_matches_its_definition() -> None:
    crc = x25crc(b"PROTOCOL_VERSION ")
    for ftype, name, alen in [("uint16_t", "version", 0), ("uint16_t", "min_version", 0),
                              ("uint16_t", "max_version", 0), ("uint8_t", "spec_version_hash", 8),
                              ("uint8_t", "library_version_hash", 8)]:
        crc.accumulate_str(ftype + " ")
        crc.accumulate_str(name + " ")
        if alen:
            crc.accumulate([alen])
    assert crc_extra_of(MSG_ID_PROTOCOL_VERSION) == (crc.crc & 0xFF) ^ (crc.crc >> 8)
    frame = ProtocolVersionMessage(200, 100, 200).pack(mavlink.MAVLink(None, 1, 1))
    assert frame[7] | frame[8] << 8 == 300
    assert struct.unpack("<HHH", param_codec.frame_payload(frame, 22)[:6]) == (200, 100, 200)


def test_statustext_chunks() -> None:
    from gcs_bridge.status import StatusTextIds

    ids = StatusTextIds()
    assert len(statustext(4, "short", ids)) == 1
    parts = statustext(4, "x" * 120, ids)
    assert [len(p.text) for p in parts] == [50, 50, 20]
    assert len({p.id for p in parts}) == 1 and parts[0].id != 0
    assert [p.chunk_seq for p in parts] == [0, 1, 2]
    exact = statustext(4, "y" * 100, ids)
    assert [len(p.text) for p in exact] == [50, 50, 0]
