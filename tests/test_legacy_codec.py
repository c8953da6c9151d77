"""Legacy UDP codec against the contract's vectors, round trips and malformed input."""

from __future__ import annotations

import dataclasses
import json
import math
import struct
from typing import Any

import pytest
from conftest import data_file
from hypothesis import given, settings
from hypothesis import strategies as st

from legacy_protocol import codec, messages
from legacy_protocol.codec import HEADER_SIZE, Decoded, DecodeError, decode, encode
from legacy_protocol.messages import (
    COMMAND_TYPES,
    MESSAGE_TYPES,
    UNCHANGED,
    MsgType,
    SetThreadParams,
    ThreadFlag,
    ThreadStatus,
)

VECTORS_PATH = data_file("vectors", "legacy-udp.json")
VECTORS: list[dict[str, Any]] = json.loads(VECTORS_PATH.read_text())

# The vector files list a lone "uint16 zero" reserved field as a value (0) but leave out the
# "uint8[n] zero" ones; the codec carries no reserved fields, so drop those positions here.
RESERVED_IN_VECTORS = {"GPS": [14], "COMMAND_ACK": [2]}

# Fixed total sizes from the contract's tables, written out independently of the codec.
CONTRACT_SIZES = {
    0x01: 48,
    0x02: 36,
    0x03: 24,
    0x10: 48,
    0x11: 76,
    0x12: 52,
    0x13: 64,
    0x14: 36,
    0x81: 28,
    0x82: 28,
    0x83: 20,
    0x84: 36,
    0x85: 20,
}
ALL_CLASSES = [codec.payload_class(t) for t in CONTRACT_SIZES]


def _flat_fields(payload: Any) -> list[Any]:
    out: list[Any] = []
    for f in dataclasses.fields(payload):
        v = getattr(payload, f.name)
        out.extend(v if isinstance(v, tuple) else [v])
    return out


def _t_ns(header: dict[str, int]) -> int:
    return header["tv_sec"] * 1_000_000_000 + header["tv_nsec"]


def test_vectors_cover_every_type() -> None:
    assert {v["type"] for v in VECTORS} == set(CONTRACT_SIZES) == {int(t) for t in MsgType}


@pytest.mark.parametrize("vec", VECTORS, ids=[v["name"] for v in VECTORS])
def test_vector_decodes_to_table_fields(vec: dict[str, Any]) -> None:
    result = decode(bytes.fromhex(vec["hex"]))
    assert isinstance(result, Decoded), result
    assert result.name == vec["name"]
    h = result.header
    assert (h.type_code, h.vehicle_id, h.size) == (
        vec["type"],
        vec["header"]["vehicle"],
        vec["size"],
    )
    assert (h.seq, h.tv_sec, h.tv_nsec) == (
        vec["header"]["seq"],
        vec["header"]["tv_sec"],
        vec["header"]["tv_nsec"],
    )
    assert h.t_ns == _t_ns(vec["header"])
    expected = list(vec["fields_in_table_order"])
    for pos in sorted(RESERVED_IN_VECTORS.get(vec["name"], []), reverse=True):
        assert expected.pop(pos) == 0
    assert _flat_fields(result.payload) == expected


@pytest.mark.parametrize("vec", VECTORS, ids=[v["name"] for v in VECTORS])
def test_vector_encodes_to_exact_bytes(vec: dict[str, Any]) -> None:
    decoded = decode(bytes.fromhex(vec["hex"]))
    assert isinstance(decoded, Decoded)
    cls = type(decoded.payload)
    # Build the payload from the vector's values, not from our own decode.
    values = list(vec["fields_in_table_order"])
    for pos in sorted(RESERVED_IN_VECTORS.get(vec["name"], []), reverse=True):
        values.pop(pos)
    kwargs: dict[str, Any] = {}
    for name, wire in codec.wire_fields(cls):
        if wire.count > 1:
            kwargs[name] = tuple(values[: wire.count])
            del values[: wire.count]
        else:
            kwargs[name] = values.pop(0)
    assert not values
    datagram = encode(
        cls(**kwargs),
        vehicle_id=vec["header"]["vehicle"],
        seq=vec["header"]["seq"],
        t_ns=_t_ns(vec["header"]),
    )
    assert datagram.hex() == vec["hex"]
    assert len(datagram) == vec["size"]


def test_sizes_match_contract_tables() -> None:
    for type_code, size in CONTRACT_SIZES.items():
        assert codec.layout_of(type_code)[1] == size
    assert HEADER_SIZE == 16
    assert MESSAGE_TYPES | COMMAND_TYPES == set(MsgType)
    assert not MESSAGE_TYPES & COMMAND_TYPES


def test_constants() -> None:
    assert UNCHANGED == 0xFFFFFFFF
    assert [int(t) for t in messages.ThreadId] == [1, 2, 3, 4, 5]
    assert [int(f) for f in ThreadFlag] == [1, 2, 4, 8]
    assert [int(r) for r in messages.AckResult] == [0, 1, 2, 3]
    assert messages.DEFAULT_COMMAND_PORT == 5500 and messages.DEFAULT_MONITOR_PORT == 5501
    status = ThreadStatus(1, 0b0101, 0, 0, 0, 0, "x")
    assert status.has(ThreadFlag.INITIALISED) and status.has(ThreadFlag.IN_PERIODIC)
    assert not status.has(ThreadFlag.RUNNING) and not status.has(ThreadFlag.ALIVE)


# ---------------------------------------------------------------------------------------------
# Round trips for every layout, values drawn from each field's wire type.

_INT_RANGES = {"B": (0, 255), "H": (0, 65535), "I": (0, 2**32 - 1), "i": (-(2**31), 2**31 - 1)}


def _strategy_for(code: str) -> st.SearchStrategy[Any]:
    if code in _INT_RANGES:
        return st.integers(*_INT_RANGES[code])
    if code == "f":
        return st.floats(width=32, allow_nan=False)
    if code == "d":
        return st.floats(allow_nan=False)
    assert code == "16s"
    # Latin-1 without NUL: NUL ends the name on the wire.
    return st.text(st.characters(min_codepoint=1, max_codepoint=0xFF), max_size=16)


def _payload_strategy(cls: type[Any]) -> st.SearchStrategy[Any]:
    parts: dict[str, st.SearchStrategy[Any]] = {}
    for name, wire in codec.wire_fields(cls):
        one = _strategy_for(wire.code)
        parts[name] = st.tuples(*[one] * wire.count) if wire.count > 1 else one
    return st.builds(cls, **parts)


@pytest.mark.parametrize("cls", ALL_CLASSES, ids=[c.__name__ for c in ALL_CLASSES])
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_round_trip_every_layout(cls: type[Any], data: st.DataObject) -> None:
    payload = data.draw(_payload_strategy(cls))
    vehicle = data.draw(st.integers(1, 255))
    seq = data.draw(st.integers(0, 2**32 - 1))
    t_ns = data.draw(st.integers(-(2**31) * 10**9, (2**31 - 1) * 10**9 + 999_999_999))
    datagram = encode(payload, vehicle_id=vehicle, seq=seq, t_ns=t_ns)
    assert len(datagram) == CONTRACT_SIZES[cls.TYPE]
    result = decode(datagram)
    assert isinstance(result, Decoded), result
    assert result.payload == payload
    assert (result.header.vehicle_id, result.header.seq, result.header.t_ns) == (vehicle, seq, t_ns)
    assert encode(result.payload, vehicle_id=vehicle, seq=seq, t_ns=t_ns) == datagram


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=120))
def test_decode_never_raises_on_random_bytes(data: bytes) -> None:
    result = decode(data)
    assert isinstance(result, (Decoded, DecodeError))


@settings(max_examples=200, deadline=None)
@given(type_code=st.sampled_from(sorted(CONTRACT_SIZES)), body=st.data())
def test_any_body_of_the_right_size_decodes(type_code: int, body: st.DataObject) -> None:
    size = CONTRACT_SIZES[type_code]
    raw = body.draw(st.binary(min_size=size - HEADER_SIZE, max_size=size - HEADER_SIZE))
    header = struct.pack("<BBHIiI", type_code, 3, size, 9, 0, 5)
    result = decode(header + raw)
    assert isinstance(result, Decoded), result
    # Re-encoding gives back the same values.  Bytes can differ in reserved bytes and in NaN
    # payloads (float32 -> float -> float32 quiets a signalling NaN), so compare values.
    again = decode(encode(result.payload, vehicle_id=3, seq=9, t_ns=5))
    assert isinstance(again, Decoded)
    assert _same(_flat_fields(again.payload), _flat_fields(result.payload))


def _same(a: list[Any], b: list[Any]) -> bool:
    def key(v: Any) -> Any:
        return "nan" if isinstance(v, float) and math.isnan(v) else v

    return [key(v) for v in a] == [key(v) for v in b]


# ---------------------------------------------------------------------------------------------
# Malformed datagrams: every one is a value with a reason and an offset.


@pytest.mark.parametrize("vec", VECTORS, ids=[v["name"] for v in VECTORS])
def test_rejects_short_long_and_size_field_mismatch(vec: dict[str, Any]) -> None:
    good = bytes.fromhex(vec["hex"])
    size = len(good)
    for n in range(size):  # every truncation, down to the empty datagram
        err = decode(good[:n])
        assert isinstance(err, DecodeError), n
        assert err.offset == n
        assert ("short" in err.reason) if n else ("empty" in err.reason)
    for extra in (1, 3, 200):
        err = decode(good + b"\0" * extra)
        assert isinstance(err, DecodeError)
        assert "long" in err.reason and err.offset == size
    for wrong in (0, size - 1, size + 1, 0xFFFF):
        bad = good[:2] + struct.pack("<H", wrong) + good[4:]
        err = decode(bad)
        assert isinstance(err, DecodeError)
        assert err.offset == 2 and str(wrong) in err.reason


def test_rejects_unknown_types() -> None:
    known = set(CONTRACT_SIZES)
    for type_code in range(256):
        if type_code in known:
            continue
        err = decode(bytes([type_code]) + b"\x07\x30\x00" + b"\0" * 44)
        assert isinstance(err, DecodeError)
        assert err.offset == 0 and f"0x{type_code:02x}" in err.reason


def test_rejects_vehicle_zero_and_bad_nanoseconds() -> None:
    good = bytearray(bytes.fromhex(VECTORS[0]["hex"]))
    bad = bytes(good[:1]) + b"\0" + bytes(good[2:])
    err = decode(bad)
    assert isinstance(err, DecodeError) and err.offset == 1 and "vehicle" in err.reason
    good[12:16] = struct.pack("<I", 1_000_000_000)
    err = decode(bytes(good))
    assert isinstance(err, DecodeError) and err.offset == 12 and "nsec" in err.reason


def test_decode_error_text_names_offset() -> None:
    err = decode(b"\x01\x07")
    assert isinstance(err, DecodeError)
    assert str(err) == "short datagram: 2 bytes, THREAD_STATUS is 48 (at byte 2)"


def test_reserved_bytes_are_ignored_when_reading_and_zero_when_writing() -> None:
    vec = next(v for v in VECTORS if v["name"] == "SET_THREAD_PARAMS")
    raw = bytearray(bytes.fromhex(vec["hex"]))
    raw[17:20] = b"\xaa\xbb\xcc"
    result = decode(bytes(raw))
    assert isinstance(result, Decoded)
    assert result.payload == SetThreadParams(1, UNCHANGED, 250)
    again = encode(
        result.payload, vehicle_id=7, seq=vec["header"]["seq"], t_ns=_t_ns(vec["header"])
    )
    assert again.hex() == vec["hex"]


# ---------------------------------------------------------------------------------------------
# Encoding mistakes are the caller's bugs: ValueError naming the field.


def test_encode_names_the_bad_field() -> None:
    with pytest.raises(ValueError, match=r"THREAD_STATUS\.restarts=70000"):
        encode(ThreadStatus(1, 0, 70000, 0, 0, 0, "imu"), vehicle_id=1, seq=0, t_ns=0)
    with pytest.raises(ValueError, match=r"THREAD_STATUS\.name: 17 bytes"):
        encode(ThreadStatus(1, 0, 0, 0, 0, 0, "x" * 17), vehicle_id=1, seq=0, t_ns=0)
    with pytest.raises(ValueError, match=r"THREAD_STATUS\.name: .*not in range"):
        encode(ThreadStatus(1, 0, 0, 0, 0, 0, "imu→"), vehicle_id=1, seq=0, t_ns=0)
    with pytest.raises(ValueError, match=r"SERVO\.pilot_us: expected 8 values"):
        encode(messages.Servo((1500,) * 7, (1500,) * 8, 0, 0, 0), vehicle_id=1, seq=0, t_ns=0)
    with pytest.raises(ValueError, match=r"IMU\.p_rad_s=1e\+300"):
        encode(messages.Imu(1e300, 0, 0, 0, 0, 0, 0, 0), vehicle_id=1, seq=0, t_ns=0)
    with pytest.raises(ValueError, match="vehicle_id 0"):
        encode(messages.Stop(), vehicle_id=0, seq=0, t_ns=0)
    with pytest.raises(ValueError, match="int32 seconds"):
        encode(messages.Stop(), vehicle_id=1, seq=0, t_ns=2**31 * 10**9)
    with pytest.raises(ValueError, match="not a legacy protocol payload"):
        encode("hello", vehicle_id=1, seq=0, t_ns=0)  # type: ignore[arg-type]


def test_sequence_wraps_and_defaults_mean_unchanged() -> None:
    datagram = encode(SetThreadParams(2), vehicle_id=1, seq=2**32 + 5, t_ns=-1)
    result = decode(datagram)
    assert isinstance(result, Decoded)
    assert result.header.seq == 5
    assert (result.header.tv_sec, result.header.tv_nsec) == (-1, 999_999_999)
    assert result.payload == SetThreadParams(2, UNCHANGED, UNCHANGED)


def test_as_dict_is_json_safe() -> None:
    d = codec.as_dict(messages.Imu(math.nan, math.inf, 0.5, 0, 0, 0, 20.0, 3))
    assert d["p_rad_s"] is None and d["q_rad_s"] is None and d["r_rad_s"] == 0.5
    servo = codec.as_dict(messages.Servo((1,) * 8, (2,) * 8, 3, 4, 1))
    assert servo["pilot_us"] == [1] * 8
    json.dumps(d, allow_nan=False)
