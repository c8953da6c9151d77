"""Fuzzing of every parser that takes bytes or text from outside the process.

Each section feeds hostile input (random bytes, sync-rich garbage, valid frames cut and mixed
with garbage, checksummed sentences with absurd fields, mutated files) to one parser and checks
what its contract promises: the documented error type and nothing else, outputs of the documented
types, internal buffers that stay bounded, counters that add up, and valid data that survives
the garbage around it whenever the parser's resynchronisation can guarantee it.

Tests marked ``xfail(strict=True)`` demonstrate product bugs found by this fuzzing; each reason
names the input and the line that fails. They turn into failures (XPASS) once the bug is fixed,
so the mark must then be removed.
"""

from __future__ import annotations

import json
import logging
import math
import re
import struct
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import pytest
from conftest import free_udp_port, wait_for
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support.synthetic_vehicle import MiniGcs, SyntheticVehicle

from companion.core.config import (
    Config,
    ConfigError,
    VehicleConfig,
    apply_override,
    load_config,
)
from companion.core.geo import NedFrame
from companion.core.params import (
    FileIssue,
    ParamRegistry,
    ParamSpec,
    float_param,
    int_param,
    parse_param_file,
)
from companion.drivers.gps_encoder import encode_epoch
from companion.drivers.gps_protocol import MAX_LINE_CHARS, NmeaDecoder
from companion.drivers.gps_solution import GpsSolution
from companion.drivers.imu_protocol import (
    FAST_FRAME_LEN,
    SYNC,
    ImuDecoder,
    ImuFast,
    ImuSlow,
    SyncFrameDecoder,
    decode_fast_frame,
    encode_fast_frame,
)
from companion.drivers.nmea_fields import nmea_sentence
from companion.drivers.servo_protocol import (
    COMMAND_LEN,
    COMMAND_SYNC,
    MAX_PLAUSIBLE_US,
    PILOT_LEN,
    PILOT_SYNC,
    CommandDecoder,
    PilotDecoder,
    PilotFrame,
    ServoCommand,
    decode_command,
    decode_pilot,
    encode_command,
    encode_pilot,
)
from companion.logs.reader import read_log_bytes
from companion.logs.streams import LogFormatError
from companion.logs.writer import LogService
from companion.vehicle import load_vehicle_config
from gcs_bridge.dialect import mavlink
from gcs_bridge.params import codec as param_codec
from gcs_bridge.signing import SignatureChecker, signing_timestamp
from legacy_protocol import codec, messages
from legacy_protocol.monitor_link import Fleet, Received

# ---------------------------------------------------------------------------------------------
# Shared helpers


def split_at(data: bytes, cuts: Sequence[int]) -> list[bytes]:
    """`data` cut at the given offsets (any order, duplicates and out-of-range ones allowed)."""
    points = sorted({min(max(c, 0), len(data)) for c in cuts} | {0, len(data)})
    return [data[a:b] for a, b in zip(points, points[1:], strict=False)]


def is_subsequence(needles: Sequence[Any], haystack: Sequence[Any]) -> bool:
    it = iter(haystack)
    return all(any(n == h for h in it) for n in needles)


def counters_non_negative(counters: object) -> None:
    for f in fields(counters):  # type: ignore[arg-type]
        value = getattr(counters, f.name)
        assert isinstance(value, int) and value >= 0, f"counter {f.name} = {value!r}"


# ---------------------------------------------------------------------------------------------
# 1 + 3. Fixed-length sync-framed byte decoders: IMU fast frames, servo pilot and command frames
#
# SyncFrameDecoder.feed scans for the two sync bytes, decodes a frame there, and on success
# jumps over the whole frame, on failure drops one byte only. So a valid frame at offset r is
# missed only when the scanner accepted a (false) frame starting at some p in (r - len, r): that
# needs a sync pattern at p whose len bytes pass the frame checks. It cannot happen if every sync
# pattern starting in the len - 1 bytes before r either fails the checks (a false sync, dropped
# one byte at a time) or lies strictly inside an earlier guaranteed frame (the scanner jumps over
# that frame's interior). That is the property checked below; it holds for any chunking because
# the scanner keeps everything from its position on between calls. A decoder that skipped more
# than one byte after a false sync would lose frames this property protects.


@dataclass(frozen=True)
class FrameProtocol:
    name: str
    new_decoder: Callable[[], SyncFrameDecoder[Any]]
    sync: bytes
    frame_len: int
    item_types: tuple[type, ...]
    frame_type: type
    frames: st.SearchStrategy[bytes]
    """Valid frames produced by the module's own encoder."""
    reference: Callable[[bytes], Any]
    """The module's single-frame decoder (t_ns = 0), the expected item of a valid frame."""


_finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
_triple = st.tuples(_finite, _finite, _finite)

_imu_frames = st.builds(
    encode_fast_frame,
    counter=st.integers(0, 99),
    status=st.integers(0, 255),
    rates_rad_s=_triple,
    accel_m_s2=_triple,
    slow_word=st.integers(0, 0xFFFF),
)
_pulse = st.one_of(st.just(0), st.integers(0, MAX_PLAUSIBLE_US))
_pilot_frames = st.builds(
    lambda seq, auto, fs, ch, b1, b2: encode_pilot(PilotFrame(seq, auto, fs, tuple(ch), b1, b2)),
    st.integers(0, 255),
    st.booleans(),
    st.booleans(),
    st.lists(_pulse, min_size=8, max_size=8),
    st.integers(0, 255),
    st.integers(0, 255),
)
_command_frames = st.builds(
    lambda seq, auto, ch: encode_command(ServoCommand(seq, auto, tuple(ch))),
    st.integers(0, 255),
    st.booleans(),
    st.lists(st.one_of(st.just(0), st.integers(1000, 2000)), min_size=8, max_size=8),
)

PROTOCOLS = [
    FrameProtocol("imu", ImuDecoder, SYNC, FAST_FRAME_LEN, (ImuFast, ImuSlow), ImuFast,
                  _imu_frames, decode_fast_frame),
    FrameProtocol("servo-pilot", PilotDecoder, PILOT_SYNC, PILOT_LEN, (PilotFrame,), PilotFrame,
                  _pilot_frames, decode_pilot),
    FrameProtocol("servo-command", CommandDecoder, COMMAND_SYNC, COMMAND_LEN, (ServoCommand,),
                  ServoCommand, _command_frames, decode_command),
]


def sync_rich_garbage(sync: bytes, max_size: int = 80) -> st.SearchStrategy[bytes]:
    """Random bytes, and bytes made mostly of sync patterns and zeros (zero bodies pass the
    IMU's additive checksum, so this also produces false frames that decode)."""
    return st.one_of(
        st.binary(max_size=max_size),
        st.lists(st.sampled_from([sync[0], sync[1], 0x00, 0xFF, 0x55]), max_size=max_size).map(
            bytes
        ),
        st.lists(st.one_of(st.just(sync), st.binary(max_size=6)), max_size=12).map(b"".join),
    )


def check_items(proto: FrameProtocol, items: Sequence[Any]) -> None:
    for item in items:
        assert isinstance(item, proto.item_types), f"{proto.name}: unexpected {item!r}"
        if isinstance(item, ImuFast):
            assert 0 <= item.counter < 100 and 0 <= item.status <= 0xFF
            assert all(math.isfinite(v) for v in (*item.rates_rad_s, *item.accel_m_s2))
        elif isinstance(item, ImuSlow):
            assert all(math.isfinite(v) for v in (*item.rates_rad_s, *item.accel_m_s2))
            assert math.isfinite(item.temperature_c) and 0 <= item.bit_word <= 0xFFFF
        elif isinstance(item, PilotFrame | ServoCommand):
            assert len(item.channels_us) == 8 and max(item.channels_us) <= MAX_PLAUSIBLE_US


def run_chunks(proto: FrameProtocol, chunks: Sequence[bytes]) -> tuple[list[Any], Any]:
    """Feed `chunks` (all at t_ns 0) checking the per-call invariants; (items, decoder)."""
    decoder = proto.new_decoder()
    items: list[Any] = []
    for chunk in chunks:
        out = decoder.feed(chunk, 0)
        assert isinstance(out, list)
        check_items(proto, out)
        items += out
        assert len(decoder._buf) < proto.frame_len, "buffer holds more than one frame"
        counters_non_negative(decoder.counters)
    return items, decoder


@pytest.mark.parametrize("proto", PROTOCOLS, ids=lambda p: p.name)
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_frame_decoder_any_bytes_any_chunking(proto: FrameProtocol, data: st.DataObject) -> None:
    stream = data.draw(
        st.lists(st.one_of(sync_rich_garbage(proto.sync), proto.frames), max_size=12).map(
            b"".join
        )
    )
    cuts = data.draw(st.lists(st.integers(0, len(stream)), max_size=20))
    whole, dec_whole = run_chunks(proto, [stream])
    pieces, dec_pieces = run_chunks(proto, split_at(stream, cuts))
    # chunking changes nothing: same items, same counters, same leftover
    assert pieces == whole
    assert dec_pieces.counters == dec_whole.counters
    assert dec_pieces._buf == dec_whole._buf
    c = dec_whole.counters
    # every byte is accounted for exactly once: a good frame, discarded, or still buffered
    assert c.bytes_discarded + proto.frame_len * c.frames_good + len(dec_whole._buf) == len(stream)
    assert c.frames_good == sum(isinstance(i, proto.frame_type) for i in whole)
    if proto.name == "imu":
        assert c.slow_good == sum(isinstance(i, ImuSlow) for i in whole)


def _decodes(proto: FrameProtocol, raw: bytes) -> bool:
    try:
        proto.reference(raw)
    except ValueError:
        return False
    return True


def _guaranteed(proto: FrameProtocol, stream: bytes, starts: Sequence[int]) -> list[bool]:
    """Which embedded frames the resynchronisation logic guarantees to decode (see above)."""
    flen = proto.frame_len
    syncs = [p for p in range(len(stream) - 1) if stream[p : p + 2] == proto.sync]
    interiors: list[tuple[int, int]] = []
    out = []
    for r in starts:
        threats = [p for p in syncs if r - flen < p < r and _decodes(proto, stream[p : p + flen])]
        ok = all(any(q < p < q + flen for q, _ in interiors) for p in threats)
        out.append(ok)
        if ok:
            interiors.append((r, r + flen))
    return out


@pytest.mark.parametrize("proto", PROTOCOLS, ids=lambda p: p.name)
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_frame_decoder_finds_valid_frames_between_garbage(
    proto: FrameProtocol, data: st.DataObject
) -> None:
    segments = data.draw(
        st.lists(st.tuples(sync_rich_garbage(proto.sync, 50), proto.frames), max_size=8)
    )
    tail = data.draw(sync_rich_garbage(proto.sync, 30))
    stream = b""
    starts: list[int] = []
    frames: list[bytes] = []
    for garbage, frame in segments:
        stream += garbage
        starts.append(len(stream))
        frames.append(frame)
        stream += frame
    stream += tail
    cuts = data.draw(st.lists(st.integers(0, len(stream)), max_size=20))
    items, decoder = run_chunks(proto, split_at(stream, cuts))
    decoded = [i for i in items if isinstance(i, proto.frame_type)]
    guaranteed = _guaranteed(proto, stream, starts)
    expected = [proto.reference(f) for f, ok in zip(frames, guaranteed, strict=True) if ok]
    assert is_subsequence(expected, decoded), "a guaranteed frame was lost in the garbage"
    # No sync pattern outside the frames: exactly the frames come out, garbage is all discarded.
    syncs = {p for p in range(len(stream) - 1) if stream[p : p + 2] == proto.sync}
    inside = {p for r in starts for p in range(r, r + proto.frame_len)}
    if syncs <= inside and all(guaranteed):
        assert decoded == [proto.reference(f) for f in frames]
        garbage_len = len(stream) - proto.frame_len * len(frames)
        assert decoder.counters.bytes_discarded + len(decoder._buf) == garbage_len
        assert decoder.counters.bad_checksum == decoder.counters.bad_field == 0


@pytest.mark.parametrize("proto", PROTOCOLS, ids=lambda p: p.name)
@settings(max_examples=40, deadline=None)
@given(frame=st.data())
def test_single_frame_decoders_raise_only_value_error(
    proto: FrameProtocol, frame: st.DataObject
) -> None:
    valid = frame.draw(proto.frames)
    raw = bytearray(frame.draw(st.one_of(st.just(valid), st.binary(max_size=2 * proto.frame_len))))
    for pos, bit in frame.draw(st.lists(st.tuples(st.integers(0, 255), st.integers(0, 7)),
                                        max_size=3)):
        if raw:
            raw[pos % len(raw)] ^= 1 << bit
    try:
        item = proto.reference(bytes(raw))
    except ValueError as exc:
        assert str(exc)
    else:
        check_items(proto, [item])


# ---------------------------------------------------------------------------------------------
# 2. GPS: NMEA 0183 and Ashtech $PASHR,POS


_ADDRESSES = ["GPGGA", "GNGGA", "GLGGA", "GPRMC", "GNRMC", "GPVTG", "GNVTG", "GPGSA", "GPGST",
              "PASHR,POS", "PASHR,ATT", "GPGSV", "XXGGA", "GPGGAX", "gpgga", "P"]
_PRINTABLE = "".join(chr(c) for c in range(0x20, 0x7F) if chr(c) not in "$*")
_nmea_field = st.one_of(
    st.text(alphabet="0123456789.", max_size=12),
    st.sampled_from(["", "N", "S", "E", "W", "A", "V", "D", "M", "K", "T", "0", "1", "4", "9",
                     "1e308", "-1e308", "nan", "inf", "1_0", "235960.00", "240000", "123519",
                     "4807.038", "01131.000", "310299", "000000", "99999", "-0"]),
    st.text(alphabet=_PRINTABLE, max_size=8),
)
_nmea_body = st.builds(
    lambda address, parts: ",".join([address, *parts]),
    st.sampled_from(_ADDRESSES),
    st.lists(_nmea_field, max_size=20),
).filter(lambda body: len(body) <= MAX_LINE_CHARS - 4)

_FLOAT_FIELDS = ("utc", "lat_deg", "lon_deg", "hdop", "pdop", "vdop", "tdop", "speed_m_s",
                 "course_deg", "vn_m_s", "ve_m_s", "vd_m_s", "alt_std_m", "lat_std_m",
                 "lon_std_m", "latency_s", "geoid_sep_m")


def check_solution(sol: object, derived_altitudes_finite: bool = False) -> None:
    assert isinstance(sol, GpsSolution)
    names = _FLOAT_FIELDS + (("alt_m", "alt_ellipsoid_m") if derived_altitudes_finite else ())
    for name in names:
        value = getattr(sol, name)
        assert value is None or math.isfinite(value), f"{name} = {value!r}"
    assert sol.lat_deg is None or -90.0 <= sol.lat_deg <= 90.0
    assert sol.lon_deg is None or -180.0 <= sol.lon_deg <= 180.0
    assert sol.utc is None or 0.0 <= sol.utc < 86401.0
    assert 0 <= sol.fix <= 3
    assert sol.sats is None or sol.sats >= 0
    assert sol.latency_s is None or sol.latency_s >= 0.0
    assert sol.sentences and all(isinstance(s, str) for s in sol.sentences)


def _gps_feed(decoder: NmeaDecoder, chunks: Sequence[bytes], t_step: int) -> list[GpsSolution]:
    out: list[GpsSolution] = []
    for k, chunk in enumerate(chunks):
        got = decoder.feed(chunk, k * t_step)
        got += decoder.poll(k * t_step)
        out += got
        # a partial sentence of at most MAX_LINE_CHARS, plus the 2 checksum digits awaited
        assert len(decoder._buf) <= MAX_LINE_CHARS + 2
        counters_non_negative(decoder.counters)
    return out


@settings(max_examples=120, deadline=None)
@given(
    parts=st.lists(
        st.one_of(
            st.binary(max_size=60),
            st.lists(st.sampled_from(list(b"$*,.0123456789ABCDEFGNPRSTV\r\n\x00\xff")),
                     max_size=60).map(bytes),
            _nmea_body.map(nmea_sentence),
            _nmea_body.map(lambda b: b"$" + b.encode() + b"\r\n"),
            # over-long lines: no stop character for more than MAX_LINE_CHARS
            st.text(alphabet=_PRINTABLE, min_size=MAX_LINE_CHARS - 10,
                    max_size=2 * MAX_LINE_CHARS).map(lambda t: b"$" + t.encode()),
            st.text(alphabet=_PRINTABLE, min_size=MAX_LINE_CHARS - 10,
                    max_size=MAX_LINE_CHARS + 5).map(lambda t: b"$" + t.encode() + b"*"),
        ),
        max_size=12,
    ),
    allow=st.booleans(),
    data=st.data(),
)
def test_gps_decoder_any_bytes_any_chunking(
    parts: list[bytes], allow: bool, data: st.DataObject
) -> None:
    stream = b"".join(parts)
    cuts = data.draw(st.lists(st.integers(0, len(stream)), max_size=20))
    results = []
    for chunks in ([stream], split_at(stream, cuts)):
        decoder = NmeaDecoder(allow_no_checksum=allow)
        out = _gps_feed(decoder, chunks, 0)
        out += decoder.flush(0)
        assert decoder.flush(0) == [], "a second flush handed off an epoch again"
        for sol in out:
            check_solution(sol)
        assert decoder.counters.epochs == len(out)
        results.append((out, decoder.counters, bytes(decoder._buf)))
    assert results[0] == results[1], "chunking changed what was decoded"


@settings(max_examples=150, deadline=None)
@given(
    bodies=st.lists(_nmea_body, max_size=25),
    epochs=st.lists(
        st.builds(GpsSolution, utc=st.floats(0, 86399.99), fix=st.integers(0, 3),
                  sats=st.integers(0, 40), lat_deg=st.floats(-89.9, 89.9),
                  lon_deg=st.floats(-179.9, 179.9), alt_m=st.floats(-400, 30000)),
        max_size=3,
    ),
    expected=st.sampled_from([None, ["GGA"], ["GGA", "RMC", "VTG", "GSA", "GST"], ["POS"]]),
    data=st.data(),
)
def test_gps_checksummed_sentences_with_hostile_fields(
    bodies: list[str], epochs: list[GpsSolution], expected: list[str] | None, data: st.DataObject
) -> None:
    """Sentences that pass the checksum reach pynmea2 and the field conversion: every one is
    counted exactly once (good, unknown or malformed) and nothing but GpsSolutions comes out."""
    sentences = [nmea_sentence(b) for b in bodies]
    sentences += [encode_epoch(e, ashtech_pos=True) for e in epochs]
    order = data.draw(st.permutations(range(len(sentences))))
    stream = b"".join(sentences[i] for i in order)
    cuts = data.draw(st.lists(st.integers(0, len(stream)), max_size=15))
    decoder = NmeaDecoder(expected_sentences=expected, idle_handoff_ms=5)
    out = _gps_feed(decoder, split_at(stream, cuts), 1_000_000)
    out += decoder.flush(10**12)
    c = decoder.counters
    assert c.bad_checksum == c.cut == c.too_long == 0
    assert c.sentences_good + c.unknown + c.malformed == len(bodies) + 6 * len(epochs)
    assert c.epochs == len(out)
    for sol in out:
        check_solution(sol)


def test_gps_derived_altitudes_are_finite() -> None:
    cases = [
        [nmea_sentence("GPGGA,000000,,,,,1,,,1e308,M,1e308,M,,")],
        [nmea_sentence("GPGGA,000000,,,,,1,,,,M,-1e308,M,,"),
         nmea_sentence("PASHR,POS,0,05,000001,,,,,1e308,,,,,,,,,X")],
    ]
    for sentences in cases:
        decoder = NmeaDecoder()
        out = [sol for s in sentences for sol in decoder.feed(s, 0)] + decoder.flush(1)
        assert out
        for sol in out:
            check_solution(sol, derived_altitudes_finite=True)


def test_gps_empty_coordinate_with_hemisphere_is_no_position() -> None:
    decoder = NmeaDecoder()
    out = decoder.feed(nmea_sentence("GPGGA,123519.00,,N,,E,1,08,0.9,545.4,M,46.9,M,,"), 0)
    out += decoder.flush(1)
    (sol,) = out
    assert sol.lat_deg is None and sol.lon_deg is None


def test_gps_epoch_state_stays_bounded_under_untimed_flood() -> None:
    decoder = NmeaDecoder(expected_sentences=["GGA", "RMC", "VTG", "GSA", "GST"],
                          idle_handoff_ms=20)
    sentence = nmea_sentence("GPVTG,,T,,M,,N,,K,N")
    for k in range(2000):
        decoder.feed(sentence, k * 1000)  # a line that is never quiet for 20 ms
        decoder.poll(k * 1000)
    held = 0 if decoder._open is None else len(decoder._open.addresses)
    assert held <= 64, f"the open epoch holds {held} sentence addresses"


# ---------------------------------------------------------------------------------------------
# 4. Legacy UDP protocol: codec.decode and the monitor's Fleet.apply


def _header(type_code: int, vehicle: int, size: int, seq: int, sec: int, nsec: int) -> bytes:
    return struct.pack("<BBHIiI", type_code, vehicle, size, seq, sec, nsec)


@st.composite
def legacy_datagrams(draw: st.DrawFn) -> bytes:
    """A well-formed datagram of any type (random body bytes), then maybe some damage."""
    type_code = draw(st.sampled_from(sorted(messages.MESSAGE_TYPES | messages.COMMAND_TYPES)))
    _, size = codec.layout_of(type_code)
    raw = bytearray(_header(type_code, draw(st.integers(1, 255)), size,
                            draw(st.integers(0, 2**32 - 1)), draw(st.integers(-(2**31), 2**31 - 1)),
                            draw(st.integers(0, 10**9 - 1))))
    raw += draw(st.binary(min_size=size - codec.HEADER_SIZE, max_size=size - codec.HEADER_SIZE))
    for _ in range(draw(st.integers(0, 3))):
        op = draw(st.sampled_from(["flip", "cut", "insert", "byte"]))
        pos = draw(st.integers(0, max(0, len(raw) - 1)))
        if op == "flip" and raw:
            raw[pos] ^= 1 << draw(st.integers(0, 7))
        elif op == "cut":
            del raw[pos:]
        elif op == "insert":
            raw[pos:pos] = draw(st.binary(min_size=1, max_size=8))
        elif raw:
            raw[pos] = draw(st.sampled_from([0x00, 0xFF, 0x80]))
    return bytes(raw)


@settings(max_examples=300, deadline=None)
@given(raw=st.one_of(st.binary(max_size=200), legacy_datagrams()))
def test_legacy_decode_never_raises_and_reencodes(raw: bytes) -> None:
    result = codec.decode(raw)
    assert isinstance(result, codec.Decoded | codec.DecodeError)
    if isinstance(result, codec.DecodeError):
        assert 0 <= result.offset <= len(raw)
        assert str(result).endswith(f"(at byte {result.offset})") and result.reason
        return
    h = result.header
    assert len(raw) == h.size and 1 <= h.vehicle_id <= 255 and 0 <= h.tv_nsec < 10**9
    assert result.name == messages.MsgType(h.type_code).name
    # what was decoded can be sent again (the monitor and adapter re-encode decoded payloads)
    again = codec.encode(result.payload, vehicle_id=h.vehicle_id, seq=h.seq, t_ns=h.t_ns)
    assert again[: codec.HEADER_SIZE] == raw[: codec.HEADER_SIZE]
    second = codec.decode(again)
    assert isinstance(second, codec.Decoded)
    assert codec.encode(second.payload, vehicle_id=h.vehicle_id, seq=h.seq, t_ns=h.t_ns) == again
    json.dumps(codec.as_dict(result.payload), allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(datagrams=st.lists(st.tuples(st.one_of(st.binary(max_size=120), legacy_datagrams()),
                                    st.sampled_from([("10.0.0.1", 5500), ("10.0.0.2", 40000)])),
                          max_size=40))
def test_legacy_monitor_fleet_folds_any_datagram(
    datagrams: list[tuple[bytes, tuple[str, int]]],
) -> None:
    fleet = Fleet(history_len=5)
    for k, (raw, source) in enumerate(datagrams):
        rx = Received(source, float(k), float(k), len(raw), codec.decode(raw))
        state = fleet.apply(rx)
        assert state is None or state.source == source
    assert fleet.received == len(datagrams)
    assert fleet.malformed == sum(isinstance(codec.decode(r), codec.DecodeError)
                                  for r, _ in datagrams)
    for state in fleet.vehicles.values():
        assert all(len(h) <= 5 for h in state._history.values())


def test_legacy_monitor_malformed_reasons_stay_bounded() -> None:
    fleet = Fleet()
    _, size = codec.layout_of(messages.MsgType.IMU)
    body = bytes(size - codec.HEADER_SIZE)
    for k in range(1000):
        raw = _header(messages.MsgType.IMU, 1, size, k, 0, 10**9 + k) + body
        fleet.apply(Received(("10.0.0.1", 5500), float(k), float(k), len(raw), codec.decode(raw)))
    assert fleet.malformed == 1000
    # at most one key per kind of problem (the 256 type codes of "unknown type 0x.." included)
    assert len(fleet.malformed_reasons) <= 300, f"{len(fleet.malformed_reasons)} reason keys"


# ---------------------------------------------------------------------------------------------
# 6. Binary log reader


_LOG_KINDS = {"unknown_type", "past_eof", "undefined_index", "length_mismatch", "bad_definition"}


def write_fuzz_log(folder: Path) -> bytes:
    """A valid log written by the runtime's own LogService (3 formats, arrays, 2 Begin/End
    pairs): the seed the log-reader fuzzing mutates, here and in bench/fuzz_bench.py."""
    t = [1_700_000_000 * 10**9]

    def clock() -> int:
        t[0] += 1_000_000
        return t[0]

    with LogService(folder, flush_period_ms=5, clock_ns=clock) as svc:
        lg = svc.open("fuzz")
        lg.define(1, "%d,%f,%lf", ["n", "x", "y"])
        lg.define(2, "%hhu", ["px"])
        lg.define(3, "%hhu,%lld", ["a", "b"])
        lg.begin()
        for k in range(12):
            assert lg.log(1, k, k / 4, k / 3)
            assert lg.log_array(2, bytes(range(k % 5)))
            assert lg.log(3, k, -k * 10**12)
        lg.end()
        lg.begin()
        assert lg.log(1, 99, 0.5, 0.25)
        lg.end()
    raw = (folder / "fuzz.bin").read_bytes()
    lf = read_log_bytes(raw)
    assert lf.closed_cleanly and not lf.damage and lf.indexes == [1, 2, 3]
    return raw


@pytest.fixture(scope="module")
def written_log(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    return write_fuzz_log(tmp_path_factory.mktemp("fuzzlog"))


@st.composite
def log_mutations(draw: st.DrawFn, raw: bytes) -> bytes:
    data = bytearray(raw)
    for _ in range(draw(st.integers(1, 6))):
        op = draw(st.sampled_from(["flip", "set", "truncate", "insert", "delete", "duplicate"]))
        pos = draw(st.integers(0, max(0, len(data) - 1)))
        if op == "flip" and data:
            data[pos] ^= 1 << draw(st.integers(0, 7))
        elif op == "set" and data:
            data[pos] = draw(st.sampled_from([0x00, 0xFF, 0xBD, 0xED, 0xFC, 0xFD, 0xDB, 0xBA,
                                              0xDA, 0x01]))
        elif op == "truncate":
            del data[pos:]
        elif op == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=24))
        elif op == "delete":
            del data[pos : pos + draw(st.integers(1, 24))]
        elif op == "duplicate":
            data[pos:pos] = data[pos : pos + draw(st.integers(1, 40))]
    return bytes(data)


def check_log_read(raw: bytes) -> None:
    start = time.monotonic()
    strict = None
    try:
        strict = read_log_bytes(raw, strict=True)
    except LogFormatError as exc:
        assert 0 <= exc.offset <= len(raw)
        assert f"byte offset {exc.offset}:" in str(exc), str(exc)
        assert exc.kind in _LOG_KINDS and exc.reason
    salvaged = read_log_bytes(raw, salvage=True)  # never raises
    last = -1
    for d in salvaged.damage:
        assert last < d.offset < len(raw) and d.skipped_bytes >= 1 and d.kind in _LOG_KINDS
        last = d.offset
    assert salvaged.record_count <= len(raw) // 4
    assert salvaged.truncated_bytes <= len(raw)
    for s in salvaged.streams:
        assert s.n_records <= len(raw) // 12
        if s.kind == "block":
            assert s.data.shape[0] == s.n_records
        else:
            assert s.lengths is not None and s.data.shape[0] == int(s.lengths.sum())
    if strict is not None:  # nothing corrupt: salvage reads exactly the same
        assert not salvaged.damage
        assert salvaged.record_count == strict.record_count
        assert [(s.index, s.n_records, s.data.tobytes()) for s in salvaged.streams] == [
            (s.index, s.n_records, s.data.tobytes()) for s in strict.streams
        ]
    assert time.monotonic() - start < 5.0


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_log_reader_mutated_written_log(written_log: bytes, data: st.DataObject) -> None:
    check_log_read(data.draw(log_mutations(written_log)))


@settings(max_examples=100, deadline=None)
@given(raw=st.one_of(
    st.binary(max_size=2000),
    st.lists(st.sampled_from([b"\xbd\x00\x00\x00", b"\xed\x00\x00\x00", b"\xfd\x01\x02\x00%d",
                              b"\xfc\x01\x01\x00n", b"\xdb\x01\x04\x00", b"\xba\x01\x03\x00",
                              b"\x00" * 8, b"\xff"]), max_size=60).map(b"".join),
))
def test_log_reader_random_bytes(raw: bytes) -> None:
    check_log_read(raw)


# ---------------------------------------------------------------------------------------------
# 7. Parameter files


_PARAM_SPECS: list[ParamSpec] = [
    int_param("TST_INT", 3, -100, 100),
    int_param("TST_BIG", 0, -(2**31), 2**31 - 1),
    float_param("TST_F", 1.5, -10.0, 10.0, "m"),
    float_param("TST_G", 0.0, 0.0, 1e6),
]
_BAD_VALUES = {
    "TST_INT": ["1.5", "101", "-101", "nan", "inf", "1e10", "x", "0x10"],
    "TST_BIG": ["2147483648", "-2147483649", "0.5", "nan", "-inf", "1e300"],
    "TST_F": ["10.5", "-11", "nan", "inf", "1e40", "abc", "1,5,"],
    "TST_G": ["-1", "1e7", "nan", "-inf", "--1"],
}


def _registry() -> ParamRegistry:
    reg = ParamRegistry()
    reg.declare_all(_PARAM_SPECS)
    return reg


_garbage_line = st.one_of(
    st.text(alphabet=st.characters(blacklist_characters="\n_", blacklist_categories=["Cs"]),
            max_size=40).map(str.encode),
    st.binary(max_size=40).filter(lambda b: b"\n" not in b and b"_" not in b),
    st.sampled_from(sorted(_BAD_VALUES)).flatmap(
        lambda name: st.tuples(
            st.sampled_from(_BAD_VALUES[name]),
            st.sampled_from(["{n} {v}", "{n},{v}", "1\t1\t{n}\t{v}\t9", "  {n}   {v}  ", "{n}"]),
        ).map(lambda vt: vt[1].format(n=name, v=vt[0]).encode())
    ),
)


def _expect_issue(line: bytes) -> bool:
    try:
        text = line.decode("utf-8")
    except UnicodeDecodeError:
        return True
    stripped = text.strip()
    return bool(stripped) and not stripped.startswith("#")


def _check_issues(issues: Sequence[FileIssue], path: Path, n_lines: int) -> None:
    last = 0
    for issue in issues:
        assert isinstance(issue, FileIssue) and issue.path == str(path)
        assert last < issue.line <= n_lines, f"issue on line {issue.line} of {n_lines}"
        assert issue.reason and f":{issue.line}: " in str(issue)
        last = issue.line


# "1e40" for a float32 parameter overflows numpy's cast to inf (a RuntimeWarning) before the
# registry refuses it as out of range, as it should
_FLOAT32_OVERFLOW = "ignore:overflow encountered in cast:RuntimeWarning"


@pytest.mark.filterwarnings(_FLOAT32_OVERFLOW)
@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(raw=st.one_of(
    st.binary(max_size=400),
    st.lists(_garbage_line, max_size=20).map(b"\n".join),
    st.text(max_size=300).map(str.encode),
))
def test_param_file_any_bytes_gives_issues_never_exceptions(tmp_path: Path, raw: bytes) -> None:
    path = tmp_path / "fuzz.parm"
    path.write_bytes(raw)
    n_lines = raw.count(b"\n") + 1
    for lineno, name, text, value, problem in parse_param_file(path):
        assert 1 <= lineno <= n_lines and isinstance(text, str)
        assert (name is None) == (problem is not None)
        assert problem is not None or isinstance(value, float)
    reg = _registry()
    before = reg.snapshot()
    issues = reg.load(path)
    _check_issues(issues, path, n_lines)
    for spec in reg.specs():  # whatever was applied went through validation
        assert spec.validate(reg.get(spec.name)) == reg.get(spec.name)
    if not any(name.encode() in raw for name in before):
        assert reg.snapshot() == before


@pytest.mark.filterwarnings(_FLOAT32_OVERFLOW)
@settings(max_examples=100, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    values=st.tuples(st.integers(-100, 100), st.integers(-(2**31), 2**31 - 1),
                     st.floats(-10, 10, width=32), st.floats(0, 1e6, width=32)),
    fmt=st.sampled_from(["parm", "params"]),
    garbage=st.lists(st.tuples(st.integers(0, 100), _garbage_line), max_size=12),
)
def test_param_file_garbage_lines_do_not_hide_valid_ones(
    tmp_path: Path, values: tuple[int, int, float, float], fmt: str,
    garbage: list[tuple[int, bytes]],
) -> None:
    source = _registry()
    chosen = dict(zip((s.name for s in _PARAM_SPECS), values, strict=True))
    source.set_many(chosen)
    lines = source.render(fmt).encode().split(b"\n")
    bad_lines: set[int] = set()
    for where, line in garbage:
        at = where % (len(lines) + 1)
        lines.insert(at, line)
        bad_lines = {n + 1 if n >= at + 1 else n for n in bad_lines}
        if _expect_issue(line):
            bad_lines.add(at + 1)
    path = tmp_path / f"fuzz.{fmt}"
    path.write_bytes(b"\n".join(lines))
    target = _registry()
    issues = target.load(path)
    _check_issues(issues, path, len(lines))
    assert {i.line for i in issues} == bad_lines
    assert target.snapshot() == source.snapshot()


# ---------------------------------------------------------------------------------------------
# 8. TOML configuration


_SECTIONS = ["vehicle", "devices", "devices.imu", "devices.gps", "devices.servo", "logs",
             "params", "mavlink", "legacy", "rerun", "nope", "vehicle.extra", "devices.imu.deep"]
_KEYS = ["id", "home", "port", "baud", "enabled", "dir", "file", "endpoints", "key_file",
         "allow_unsigned_reads", "identity", "dest", "listen", "bind", "allow", "save", "imu",
         "gps", "vehicle", "bogus", '"quoted key"', "id.x"]
_toml_value = st.one_of(
    st.integers(-(2**63), 2**63 - 1).map(str),
    st.floats().map(repr),
    st.sampled_from(["true", "false", "inf", "-inf", "nan", "1979-05-27T07:32:00Z", "07:32:00",
                     "1979-05-27", "[]", "{}", '"yes"', '"0x10"', '" 12 "', '"1,2,3"',
                     '"91,0,0"', '"nan,nan,1"', '"1,2"', '"1,2,nan"', "'lit'", '"""multi\nline"""',
                     '["a", 1]', '["udpout:1.2.3.4:5"]', "[[1]]", "{a = 1}", "[1, [2, [3]]]",
                     '"' + "9" * 5000 + '"', "0b101", "0o17", "0x_1", "1__0", "+1", "--1"]),
    st.text(max_size=20).map(json.dumps),
    st.text(max_size=12),
)
_toml_line = st.one_of(
    st.sampled_from(_SECTIONS).map(lambda s: f"[{s}]"),
    st.sampled_from(_SECTIONS).map(lambda s: f"[[{s}]]"),
    st.tuples(st.sampled_from(_KEYS), _toml_value).map(lambda kv: f"{kv[0]} = {kv[1]}"),
    st.tuples(st.sampled_from(_SECTIONS), st.sampled_from(_KEYS), _toml_value).map(
        lambda skv: f"{skv[0]}.{skv[1]} = {skv[2]}"
    ),
    st.text(max_size=30),
)
_EXPECTED_TYPES = {"id": int, "baud": int, "listen": int, "enabled": bool, "port": str,
                   "endpoints": list, "allow": list, "home": str, "allow_unsigned_reads": bool}


def _check_config_error(exc: ConfigError, path: Path, text: str) -> None:
    message = str(exc)
    assert message.startswith(f"{path}: "), message
    if "'" in message and ("unknown setting" in message or "must be" in message):
        key = message.split("'")[1]
        assert key.split(".")[-1].strip('"') in text, f"{message!r} names a key not in the file"


@settings(max_examples=200, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=st.one_of(st.lists(_toml_line, max_size=12).map("\n".join), st.text(max_size=200)))
def test_config_toml_ish_text_gives_config_or_config_error(tmp_path: Path, text: str) -> None:
    path = tmp_path / "fuzz.toml"
    path.write_text(text, encoding="utf-8")
    try:
        cfg = load_vehicle_config(path)
    except ConfigError as exc:
        _check_config_error(exc, path, text)
        return
    assert set(cfg.devices) == {"imu", "gps", "servo", "autopilot"}  # the vehicle's, no other
    for section in fields(cfg):
        obj = getattr(cfg, section.name)
        for sub in (list(obj.values()) if isinstance(obj, dict) else [obj]):
            for f in fields(sub):
                value = getattr(sub, f.name)
                want = _EXPECTED_TYPES.get(f.name)
                if want is not None and not hasattr(value, "__dataclass_fields__"):
                    assert isinstance(value, want), f"{f.name} = {value!r}"
                    if want is int:
                        assert not isinstance(value, bool)
    try:
        home = cfg.vehicle.home_lla()
    except ConfigError as exc:
        assert "vehicle.home" in str(exc)
    else:  # (the altitude is not checked: see test_config_home_altitude_is_validated)
        assert home is None or (-90 <= home[0] <= 90 and -180 <= home[1] <= 360)


@settings(max_examples=150, deadline=None)
@given(assignment=st.one_of(
    st.text(max_size=40),
    st.tuples(st.sampled_from(_SECTIONS + ["", "vehicle.id.x"]), st.sampled_from(_KEYS),
              st.text(max_size=20)).map(lambda t: f"{t[0]}.{t[1]}={t[2]}"),
))
def test_config_override_gives_config_or_config_error(assignment: str) -> None:
    cfg = Config()
    try:
        apply_override(cfg, assignment)
    except ConfigError as exc:
        assert str(exc).startswith("--set")
    assert isinstance(cfg.vehicle.id, int) and isinstance(cfg.mavlink.endpoints, list)


def test_config_home_altitude_is_validated() -> None:
    for home in ("43.7,10.4,nan", "43.7,10.4,inf", "43.7,10.4,1e7"):
        try:
            lla = VehicleConfig(home=home).home_lla()
        except ConfigError as exc:
            assert "vehicle.home" in str(exc)
            continue
        assert lla is not None
        NedFrame(*lla)  # what the estimator does with it: must not raise for a valid home


def test_config_non_utf8_file_is_a_config_error(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_bytes(b"[vehicle]\nhome = \"\xff\"\n")
    with pytest.raises(ConfigError, match=re.escape(str(path))):
        load_config(path)


def test_config_deeply_nested_value_is_a_config_error(tmp_path: Path) -> None:
    path = tmp_path / "deep.toml"
    path.write_text("a = " + "[" * 1000 + "]" * 1000 + "\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=re.escape(str(path))):
        load_config(path)


# ---------------------------------------------------------------------------------------------
# 5. MAVLink bridge receive path (Link.receive -> _on_message -> Dispatcher -> handlers)
#
# A real SyntheticVehicle (bridge under a ThreadManager) on udpin 127.0.0.1, one per test,
# reused by every example. A ground station sends arbitrary messages of the common dialect with
# hypothesis-chosen fields (and chosen source ids, MAVLink 1 or 2), an attacker socket sends raw
# bytes and damaged frames; after each example the vehicle must still answer a PING and a
# PARAM_REQUEST_READ, and at the end no managed thread may have crashed or restarted and no
# handler may have raised (the dispatcher logs that at ERROR and carries on).


VEHICLE_ID = 1
_LIVE = "TST_LIVE"
_FUZZ_PARAMS = [
    int_param(_LIVE, 7, 0, 100, "", "liveness probe of the fuzz tests"),
    int_param("TST_FZI", 0, -1000, 1000),
    float_param("TST_FZF", 0.5, -1.0, 1.0),
]
_m = mavlink
_HANDLED_IDS = [
    _m.MAVLINK_MSG_ID_HEARTBEAT, _m.MAVLINK_MSG_ID_PARAM_REQUEST_LIST,
    _m.MAVLINK_MSG_ID_PARAM_REQUEST_READ, _m.MAVLINK_MSG_ID_PARAM_SET,
    _m.MAVLINK_MSG_ID_COMMAND_LONG, _m.MAVLINK_MSG_ID_COMMAND_INT,
    _m.MAVLINK_MSG_ID_REQUEST_DATA_STREAM, _m.MAVLINK_MSG_ID_PING, _m.MAVLINK_MSG_ID_TIMESYNC,
    _m.MAVLINK_MSG_ID_FILE_TRANSFER_PROTOCOL, _m.MAVLINK_MSG_ID_MISSION_REQUEST_LIST,
    _m.MAVLINK_MSG_ID_MISSION_COUNT, _m.MAVLINK_MSG_ID_SETUP_SIGNING, _m.MAVLINK_MSG_ID_ATTITUDE,
    _m.MAVLINK_MSG_ID_NAMED_VALUE_FLOAT,
]
_HANDLED = [_m.mavlink_map[i] for i in _HANDLED_IDS]
# (a message with a field named "id", e.g. AIRSPEED, overwrites pymavlink's message id
# attribute and cannot be packed by pymavlink at all: left out)
_OTHERS = [_m.mavlink_map[i] for i in sorted(set(_m.mavlink_map) - set(_HANDLED_IDS))
           if "id" not in _m.mavlink_map[i].fieldnames]
# Commands that legitimately stop the vehicle or restart a thread: not sent at random.
_DISRUPTIVE = {int(_m.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN), int(_m.MAV_CMD_USER_1)}
_COMMANDS = [int(c) for c in (
    _m.MAV_CMD_REQUEST_MESSAGE, _m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
    _m.MAV_CMD_REQUEST_PROTOCOL_VERSION, _m.MAV_CMD_GET_HOME_POSITION,
    _m.MAV_CMD_SET_MESSAGE_INTERVAL, _m.MAV_CMD_GET_MESSAGE_INTERVAL, _m.MAV_CMD_LOGGING_START,
    _m.MAV_CMD_LOGGING_STOP, 0, 65535)]
_INT_RANGES = {
    "uint8_t": (0, 2**8 - 1), "int8_t": (-(2**7), 2**7 - 1),
    "uint16_t": (0, 2**16 - 1), "int16_t": (-(2**15), 2**15 - 1),
    "uint32_t": (0, 2**32 - 1), "int32_t": (-(2**31), 2**31 - 1),
    "uint64_t": (0, 2**64 - 1), "int64_t": (-(2**63), 2**63 - 1),
}


def _mostly(common: st.SearchStrategy[Any], rest: st.SearchStrategy[Any]) -> Any:
    """`common` three times in four, `rest` otherwise."""
    return st.integers(0, 3).flatmap(lambda k: rest if k == 0 else common)


def _scalar(msgname: str, name: str, ftype: str) -> st.SearchStrategy[Any]:
    if ftype == "float":
        if msgname in ("COMMAND_LONG", "COMMAND_INT"):
            # NaN means "not given" and is handled; infinities: see the xfail test below.
            # Small whole numbers too: message ids, intervals, thread ids, yes/no flags.
            return st.one_of(st.integers(-2, 400).map(float),
                             st.floats(width=32, allow_infinity=False))
        return st.floats(width=32)
    if ftype == "double":
        return st.floats()
    lo, hi = _INT_RANGES[ftype]
    if name == "target_system":
        return _mostly(st.sampled_from([0, VEHICLE_ID]), st.integers(lo, hi))
    if name == "target_component":
        return _mostly(st.sampled_from([0, 1]), st.integers(lo, hi))
    if name == "command" and msgname in ("COMMAND_LONG", "COMMAND_INT"):
        return _mostly(st.sampled_from(_COMMANDS), st.integers(lo, hi)).filter(
            lambda c: c not in _DISRUPTIVE
        )
    return st.one_of(st.sampled_from(sorted({lo, hi, max(lo, 0), min(hi, 1)})),
                     st.integers(lo, hi))


def _chars(msgname: str, name: str, length: int, names: Sequence[str]) -> st.SearchStrategy[bytes]:
    random_bytes = st.binary(max_size=length)
    if name == "param_id":
        # PARAM_SET only on the test's own parameters: setting the manager's watchdog periods
        # at random would legitimately restart threads
        known = [n for n in names if msgname != "PARAM_SET" or n.startswith("TST_")]
        return st.one_of(st.sampled_from([n.encode() for n in known]), random_bytes)
    if name == "name":
        return st.one_of(st.just(b"HZN_QUAL"), random_bytes)
    return random_bytes


@st.composite
def mavlink_messages(draw: st.DrawFn, param_names: Sequence[str]) -> Any:
    cls = draw(_mostly(st.sampled_from(_HANDLED), st.sampled_from(_OTHERS)))
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
    kwargs: dict[str, Any] = {}
    for name, ftype in zip(cls.fieldnames, cls.fieldtypes, strict=True):
        n = lengths[name]
        if ftype == "char":
            kwargs[name] = draw(_chars(cls.msgname, name, n, param_names))
        elif n:
            kwargs[name] = draw(st.lists(_scalar(cls.msgname, name, ftype), min_size=n,
                                         max_size=n))
        else:
            kwargs[name] = draw(_scalar(cls.msgname, name, ftype))
    return cls(**kwargs)


@st.composite
def frames_from(draw: st.DrawFn, param_names: Sequence[str]) -> bytes:
    """One datagram of whole frames, packed with hypothesis-chosen source ids and version."""
    out = b""
    for msg in draw(st.lists(mavlink_messages(param_names), min_size=1, max_size=5)):
        src = draw(st.one_of(st.sampled_from([255, VEHICLE_ID, 42]), st.integers(0, 255)))
        comp = draw(st.one_of(st.sampled_from([190, 1, int(_m.MAV_COMP_ID_CAMERA)]),
                              st.integers(0, 255)))
        mav = mavlink.MAVLink(None, src, comp)
        mav.seq = draw(st.integers(0, 255))
        v1 = type(msg).id < 256 and draw(st.booleans())
        out += msg.pack(mav, force_mavlink1=v1)
    return out


@st.composite
def damaged_bytes(draw: st.DrawFn, param_names: Sequence[str]) -> bytes:
    kind = draw(st.sampled_from(["random", "cut", "flipped", "header"]))
    if kind == "random":
        return draw(st.binary(min_size=1, max_size=600))
    if kind == "header":  # a header promising a long frame that never comes
        return bytes([draw(st.sampled_from([0xFD, 0xFE])), draw(st.integers(0, 255))]) + draw(
            st.binary(max_size=20))
    frame = bytearray(draw(frames_from(param_names)))
    if kind == "cut":
        return bytes(frame[: draw(st.integers(1, len(frame)))])
    for _ in range(draw(st.integers(1, 4))):
        frame[draw(st.integers(0, len(frame) - 1))] ^= 1 << draw(st.integers(0, 7))
    return bytes(frame)


@contextmanager
def fuzz_vehicle() -> Iterator[tuple[SyntheticVehicle, MiniGcs, MiniGcs]]:
    """(vehicle, ground station, attacker) on loopback UDP; both clients are udpin peers."""
    port = free_udp_port()
    with SyntheticVehicle([f"udpin:127.0.0.1:{port}"], vehicle_id=VEHICLE_ID,
                          extra_params=_FUZZ_PARAMS) as vehicle:
        gcs = MiniGcs(connect=("127.0.0.1", port))
        attacker = MiniGcs(connect=("127.0.0.1", port), sysid=66)
        try:
            gcs.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS,
                                                       mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3))
            assert gcs.recv(5.0, "HEARTBEAT") is not None, "the vehicle never answered"
            yield vehicle, gcs, attacker
        finally:
            attacker.close()
            gcs.close()


class Probe:
    """Liveness checks with fresh answers only: every PING carries a new time_usec."""

    def __init__(self, vehicle: SyntheticVehicle, gcs: MiniGcs) -> None:
        self.vehicle = vehicle
        self.gcs = gcs
        self.marker = 10**15

    def ping(self, timeout_s: float = 2.0, tries: int = 3) -> bool:
        """A PING answered within `tries` x `timeout_s`: UDP may lose one datagram on a loaded
        machine (the fuzz input can turn every stream up to 500 Hz), the vehicle must answer."""
        for _ in range(tries):
            self.marker += 1
            t = self.marker
            self.gcs.send(mavlink.MAVLink_ping_message(t, 0, 0, 0))
            if self.gcs.recv(timeout_s, "PING", lambda m, t=t: m.time_usec == t) is not None:
                return True
        return False

    def check(self) -> None:
        """The vehicle answers a PING, then (once any parameter list in progress is over and
        flushed by a second PING) a PARAM_REQUEST_READ by name."""
        assert self.ping(), "no PING answer after the fuzz input"
        assert wait_for(lambda: all(link._param_cursor is None
                                    for link in self.vehicle.bridge.links), 5.0)
        assert self.ping(), "no PING answer after the parameter list"
        self.gcs.send(mavlink.MAVLink_param_request_read_message(VEHICLE_ID, 1, _LIVE.encode(),
                                                                 -1))
        answer = self.gcs.recv(2.0, "PARAM_VALUE", lambda m: m.param_id == _LIVE)
        assert answer is not None, "no PARAM_VALUE answer after the fuzz input"


def _threads_healthy(vehicle: SyntheticVehicle) -> None:
    for status in vehicle.manager.thread_status():
        assert status.restarts == 0 and status.crashes == 0 and not status.failed, status


def _handler_errors(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.levelno >= logging.ERROR and r.name.startswith("gcs_bridge.dispatch")]


def test_mavlink_receive_path_survives_arbitrary_messages(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.ERROR)
    with fuzz_vehicle() as (vehicle, gcs, attacker):
        names = [s.name for s in vehicle.params.specs()]
        probe = Probe(vehicle, gcs)
        probe.check()

        # Derandomized: a live vehicle on real sockets has timing, and one fresh-random run
        # failed a PING once in a way hypothesis could not reproduce (see the #16 note); the
        # same 50 examples every run keep `make test` deterministic.
        @settings(max_examples=50, deadline=None, derandomize=True,
                  suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
        @given(data=st.data())
        def fuzz(data: st.DataObject) -> None:
            senders = st.sampled_from([False, False, True])  # two datagrams in three: the GCS
            for from_attacker in data.draw(st.lists(senders, min_size=3, max_size=10)):
                if from_attacker:
                    attacker.send_raw(data.draw(damaged_bytes(names)))
                else:
                    gcs.send_raw(data.draw(frames_from(names)))
            probe.check()

        fuzz()
        _threads_healthy(vehicle)
        stats = vehicle.bridge.stats()[0]
        assert stats["rx_frames"] > 50 and len(stats["peers"]) <= 32
        assert len(vehicle.bridge.links[0]._parsers) <= 32
    assert _handler_errors(caplog) == []


def test_mavlink_command_with_infinite_param_is_acknowledged(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.ERROR)
    commands = [int(_m.MAV_CMD_REQUEST_MESSAGE), int(_m.MAV_CMD_SET_MESSAGE_INTERVAL),
                int(_m.MAV_CMD_GET_MESSAGE_INTERVAL), int(_m.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN),
                int(_m.MAV_CMD_USER_1)]
    with fuzz_vehicle() as (vehicle, gcs, _attacker):
        probe = Probe(vehicle, gcs)
        for command in commands:
            gcs.send(mavlink.MAVLink_command_long_message(VEHICLE_ID, 1, command, 0, math.inf,
                                                          math.inf, 0, 0, 0, 0, 0))
        acked: set[int] = set()
        deadline = time.monotonic() + 3.0
        while acked != set(commands) and time.monotonic() < deadline:
            ack = gcs.recv(0.5, "COMMAND_ACK")  # (recv drops other messages: no PING first)
            if ack is not None:
                acked.add(ack.command)
        assert probe.ping()
        # (if a fix accepted the reboot, the vehicle may be stopping: nothing else is checked)
        assert acked == set(commands), f"no COMMAND_ACK for {sorted(set(commands) - acked)}"
    assert _handler_errors(caplog) == []


def test_mavlink_get_message_interval_answers_or_refuses_any_id(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.ERROR)
    command = int(_m.MAV_CMD_GET_MESSAGE_INTERVAL)
    with fuzz_vehicle() as (_vehicle, gcs, _attacker):
        for msg_id in (70000.0, -5.0):
            gcs.send(mavlink.MAVLink_command_long_message(VEHICLE_ID, 1, command, 0, msg_id,
                                                          0, 0, 0, 0, 0, 0))
            ack = gcs.recv(2.0, "COMMAND_ACK", lambda m: m.command == command)
            assert ack is not None
            if ack.result == _m.MAV_RESULT_ACCEPTED:
                answer = gcs.recv(1.0, "MESSAGE_INTERVAL")
                assert answer is not None, f"ACCEPTED but no MESSAGE_INTERVAL for id {msg_id}"
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []


def test_mavlink_message_interval_beyond_int32_is_answered(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Found by bench/fuzz_bench.py: SET_MESSAGE_INTERVAL accepted any interval, so a later
    MESSAGE_INTERVAL (int32 interval_us) could not be packed and was never sent."""
    caplog.set_level(logging.ERROR)
    attitude = float(_m.MAVLINK_MSG_ID_ATTITUDE)
    with fuzz_vehicle() as (_vehicle, gcs, _attacker):
        gcs.send(mavlink.MAVLink_command_long_message(
            VEHICLE_ID, 1, int(_m.MAV_CMD_SET_MESSAGE_INTERVAL), 0, attitude, 3e9, 0, 0, 0, 0, 0))
        assert gcs.recv(2.0, "COMMAND_ACK") is not None
        get = int(_m.MAV_CMD_GET_MESSAGE_INTERVAL)
        gcs.send(mavlink.MAVLink_command_long_message(VEHICLE_ID, 1, get, 0, attitude, 0, 0, 0,
                                                      0, 0, 0))
        ack = gcs.recv(2.0, "COMMAND_ACK", lambda m: m.command == get)
        assert ack is not None and ack.result == _m.MAV_RESULT_ACCEPTED
        answer = gcs.recv(1.0, "MESSAGE_INTERVAL")
        assert answer is not None, "ACCEPTED but no MESSAGE_INTERVAL (it could not be packed)"
        assert answer.interval_us == -1 or 0 < answer.interval_us <= 2**31 - 1
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []


def test_mavlink_cut_frame_in_one_datagram_does_not_eat_the_next() -> None:
    with fuzz_vehicle() as (vehicle, gcs, _attacker):
        probe = Probe(vehicle, gcs)
        gcs.send_raw(b"\xfd\xff\x00\x00")
        assert probe.ping(1.0), "the PING after a cut frame (next datagram) was lost"


@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_signature_checker_only_accepts_the_untouched_signed_frame(data: st.DataObject) -> None:
    """SignatureChecker.check runs on every frame of a signing link before dispatch."""
    key = bytes(range(32))
    now = signing_timestamp(time.time_ns())
    mav = mavlink.MAVLink(None, 255, 190)
    mav.signing.secret_key = key
    mav.signing.link_id = 1
    mav.signing.sign_outgoing = True
    mav.signing.timestamp = now
    frame = mavlink.MAVLink_ping_message(1, 2, 0, 0).pack(mav)
    raw = bytearray(data.draw(st.one_of(st.just(frame), st.binary(max_size=80))))
    for pos, bit in data.draw(st.lists(st.tuples(st.integers(0, 300), st.integers(0, 7)),
                                       max_size=3)):
        if raw:
            raw[pos % len(raw)] ^= 1 << bit
    if data.draw(st.booleans()):
        del raw[data.draw(st.integers(0, len(raw))):]
    checker = SignatureChecker(key, lambda: now)
    why = checker.check(bytes(raw))
    assert why is None or isinstance(why, str)
    if bytes(raw) == frame:
        assert why is None and checker.check(bytes(raw)) == "replayed (old timestamp)"
    else:
        assert why is not None, "a damaged frame passed the signature check"
    assert len(checker._streams) <= 1


@settings(max_examples=200, deadline=None)
@given(raw=st.binary(max_size=8), mav_type=st.integers(0, 255), bytewise=st.booleans())
def test_param_set_value_decoder_raises_only_wire_value_error(
    raw: bytes, mav_type: int, bytewise: bool
) -> None:
    check_param_decode(raw, mav_type, bytewise)


def check_param_decode(raw: bytes, mav_type: int, bytewise: bool) -> None:
    """A PARAM_SET value decodes to a number or raises WireValueError with a reason (also the
    fuzz bench's check)."""
    try:
        value = param_codec.decode(raw, mav_type, bytewise=bytewise)
    except param_codec.WireValueError as exc:
        assert exc.reason
    else:
        assert isinstance(value, int | float)
