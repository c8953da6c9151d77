from __future__ import annotations

import json
import math
import struct

import pytest
from conftest import data_file
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.drivers.imu_protocol import (
    ACCEL_LSB_M_S2,
    FAST_FRAME_LEN,
    RATE_LSB_RAD_S,
    SLOW_BLOCK_LEN,
    ImuDecoder,
    ImuFast,
    ImuSlow,
    crc16_ccitt_false,
    decode_fast_frame,
    decode_slow_block,
    encode_fast_frame,
    encode_slow_block,
    slow_block_words,
)

SPEC = json.loads(data_file("vectors", "devices.json").read_text())
CYCLE_BIN = data_file("vectors", "imu-cycle.bin").read_bytes()
FAST = SPEC["fast_values_quantised"]
SLOW = SPEC["slow_values"]
SLOW_BLOCK = bytes.fromhex(SPEC["slow_block_hex"])


def cycle_frames(block: bytes, start: int = 0, stop: int = 100, status: int = 3) -> list[bytes]:
    words = slow_block_words(block)
    return [
        encode_fast_frame(n, status, FAST["rates_rad_s"], FAST["specific_force_m_s2"], words[n])
        for n in range(start, stop)
    ]


def feed_all(decoder: ImuDecoder, data: bytes, t_ns: int = 0) -> list[ImuFast | ImuSlow]:
    return decoder.feed(data, t_ns)


def test_crc_is_ccitt_false() -> None:
    assert crc16_ccitt_false(b"123456789") == 0x29B1  # the catalogue check value


def test_fast_frame_vector_encodes_exactly() -> None:
    frame = encode_fast_frame(
        0, FAST["status"], FAST["rates_rad_s"], FAST["specific_force_m_s2"], 0
    )
    assert frame.hex() == SPEC["fast_frame_0_hex"]


def test_fast_frame_vector_decodes_exactly() -> None:
    frame = decode_fast_frame(bytes.fromhex(SPEC["fast_frame_0_hex"]), t_ns=7)
    assert frame.counter == 0 and frame.status == 3 and frame.slow_word == 0 and frame.t_ns == 7
    assert frame.gyro_ok and frame.accel_ok and not frame.self_test
    assert frame.rates_rad_s == pytest.approx(FAST["rates_rad_s"], abs=1e-9)
    assert frame.accel_m_s2 == pytest.approx(FAST["specific_force_m_s2"], abs=1e-9)


def test_slow_block_vector_encodes_and_decodes_exactly() -> None:
    block = encode_slow_block(
        SLOW["rates_rad_s"], SLOW["specific_force_m_s2"], SLOW["temperature_c"], SLOW["bit"]
    )
    assert block.hex() == SPEC["slow_block_hex"]
    slow = decode_slow_block(SLOW_BLOCK)
    assert slow.rates_rad_s == pytest.approx(SLOW["rates_rad_s"], abs=1e-12)
    assert slow.accel_m_s2 == pytest.approx(SLOW["specific_force_m_s2"], abs=1e-12)
    assert slow.temperature_c == pytest.approx(36.25)
    assert slow.bit_word == 0


def check_cycle_output(out: list[ImuFast | ImuSlow], decoder: ImuDecoder) -> None:
    fast = [x for x in out if isinstance(x, ImuFast)]
    slow = [x for x in out if isinstance(x, ImuSlow)]
    assert [f.counter for f in fast] == list(range(100))
    for f in fast:
        assert f.rates_rad_s == pytest.approx(FAST["rates_rad_s"], abs=1e-9)
        assert f.accel_m_s2 == pytest.approx(FAST["specific_force_m_s2"], abs=1e-9)
        assert f.status == FAST["status"]
    assert len(slow) == 1 and out[-1] is slow[0]
    assert slow[0].rates_rad_s == pytest.approx(SLOW["rates_rad_s"], abs=1e-12)
    assert slow[0].accel_m_s2 == pytest.approx(SLOW["specific_force_m_s2"], abs=1e-12)
    assert slow[0].temperature_c == pytest.approx(SLOW["temperature_c"])
    assert slow[0].bit_word == SLOW["bit"]
    c = decoder.counters
    # 4 garbage bytes + the 9-byte cut frame; the cut frame's sync is tried once and fails.
    assert (c.frames_good, c.bad_checksum, c.bad_field) == (100, 1, 0)
    assert (c.resyncs, c.bytes_discarded, c.slow_good, c.slow_dropped) == (1, 13, 1, 0)


def test_cycle_capture_decodes_in_one_chunk() -> None:
    decoder = ImuDecoder()
    check_cycle_output(decoder.feed(CYCLE_BIN, 5), decoder)


def test_cycle_capture_decodes_one_byte_at_a_time() -> None:
    decoder = ImuDecoder()
    out: list[ImuFast | ImuSlow] = []
    for i in range(len(CYCLE_BIN)):
        out += decoder.feed(CYCLE_BIN[i : i + 1], i)
    check_cycle_output(out, decoder)
    # each frame is stamped with the arrival time of the byte that completed it
    assert out[0].t_ns == 13 + FAST_FRAME_LEN - 1


@settings(max_examples=40, deadline=None)
@given(cuts=st.lists(st.integers(0, len(CYCLE_BIN)), max_size=60))
def test_cycle_capture_any_chunking(cuts: list[int]) -> None:
    bounds = [0, *sorted(cuts), len(CYCLE_BIN)]
    decoder = ImuDecoder()
    out: list[ImuFast | ImuSlow] = []
    for a, b in zip(bounds, bounds[1:], strict=False):
        out += decoder.feed(CYCLE_BIN[a:b], 0)
    check_cycle_output(out, decoder)


def test_false_sync_in_garbage_does_not_lose_following_frame() -> None:
    frames = cycle_frames(SLOW_BLOCK, 0, 3)
    # a false sync right before a real frame: its 20-byte window swallows the real frame's start
    for garbage in (b"\x7e\x49", b"\x7e\x49\x01\x02\x03", b"\x7e\x7e\x49\x7e", b"\x7e"):
        decoder = ImuDecoder()
        out = decoder.feed(frames[0] + garbage + frames[1] + frames[2], 0)
        assert [f.counter for f in out if isinstance(f, ImuFast)] == [0, 1, 2], garbage
        assert decoder.counters.bytes_discarded == len(garbage)


def test_bad_checksum_frame_is_dropped_and_breaks_the_slow_cycle() -> None:
    frames = cycle_frames(SLOW_BLOCK)
    bad = bytearray(frames[40])
    bad[6] ^= 0x10
    frames[40] = bytes(bad)
    decoder = ImuDecoder()
    out = decoder.feed(b"".join(frames) + b"".join(cycle_frames(SLOW_BLOCK)), 0)
    fast = [f for f in out if isinstance(f, ImuFast)]
    assert len(fast) == 199 and 40 not in [f.counter for f in fast[:99]]
    assert decoder.counters.bad_checksum == 1
    assert decoder.counters.slow_dropped == 1 and decoder.counters.slow_good == 1
    assert sum(isinstance(x, ImuSlow) for x in out) == 1


def test_out_of_order_cycle_is_dropped() -> None:
    frames = cycle_frames(SLOW_BLOCK)
    frames[10], frames[11] = frames[11], frames[10]
    decoder = ImuDecoder()
    out = decoder.feed(b"".join(frames), 0)
    assert len(out) == 100 and not any(isinstance(x, ImuSlow) for x in out)
    assert decoder.counters.slow_dropped == 1


def test_slow_block_with_bad_crc_is_dropped() -> None:
    block = bytearray(SLOW_BLOCK)
    block[30] = 1  # in the zero padding, CRC left alone
    decoder = ImuDecoder()
    out = decoder.feed(b"".join(cycle_frames(bytes(block))), 0)
    assert len(out) == 100
    assert (decoder.counters.slow_good, decoder.counters.slow_dropped) == (0, 1)


def test_joining_mid_cycle_waits_for_counter_zero_without_counting_a_drop() -> None:
    decoder = ImuDecoder()
    data = b"".join(cycle_frames(SLOW_BLOCK, 50)) + b"".join(cycle_frames(SLOW_BLOCK))
    out = decoder.feed(data, 0)
    assert sum(isinstance(x, ImuSlow) for x in out) == 1
    assert (decoder.counters.slow_good, decoder.counters.slow_dropped) == (1, 0)


def test_silence_inside_a_cycle_drops_the_block() -> None:
    frames = cycle_frames(SLOW_BLOCK)
    decoder = ImuDecoder()
    decoder.feed(b"".join(frames[:50]), 0)
    out = decoder.feed(b"".join(frames[50:]), 2_000_000_000)  # 2 s later, counters still line up
    assert len(out) == 50 and decoder.counters.slow_dropped == 1


def test_counter_above_99_with_good_checksum_is_a_bad_field() -> None:
    frame = bytearray(encode_fast_frame(5, 3, (0, 0, 0), (0, 0, 0), 0))
    frame[2] = 120
    struct.pack_into("<H", frame, 18, sum(frame[2:18]) & 0xFFFF)
    decoder = ImuDecoder()
    assert decoder.feed(bytes(frame), 0) == []
    assert decoder.counters.bad_field == 1 and decoder.counters.frames_good == 0
    with pytest.raises(ValueError, match="counter 120"):
        decode_fast_frame(bytes(frame))


def test_reset_forgets_partial_frame_and_cycle() -> None:
    frames = cycle_frames(SLOW_BLOCK)
    decoder = ImuDecoder()
    decoder.feed(b"".join(frames[:10]) + frames[10][:7], 0)
    decoder.reset()
    assert decoder.counters.slow_dropped == 1
    out = decoder.feed(frames[10][7:] + b"".join(frames), 0)  # tail of the cut frame is garbage
    assert sum(isinstance(x, ImuSlow) for x in out) == 1
    assert decoder.counters.bytes_discarded == FAST_FRAME_LEN - 7


def test_single_frame_decoder_errors_name_the_problem() -> None:
    good = bytes.fromhex(SPEC["fast_frame_0_hex"])
    with pytest.raises(ValueError, match="20 bytes"):
        decode_fast_frame(good[:-1])
    with pytest.raises(ValueError, match="sync"):
        decode_fast_frame(b"\x00" + good[1:])
    with pytest.raises(ValueError, match="checksum"):
        decode_fast_frame(good[:5] + b"\x01" + good[6:])
    with pytest.raises(ValueError, match="200 bytes"):
        decode_slow_block(SLOW_BLOCK[:-1])
    with pytest.raises(ValueError, match="CRC"):
        decode_slow_block(SLOW_BLOCK[:-1] + b"\x00")


def test_encoders_validate_and_saturate() -> None:
    with pytest.raises(ValueError, match="counter"):
        encode_fast_frame(100, 0, (0, 0, 0), (0, 0, 0), 0)
    with pytest.raises(ValueError, match="finite"):
        encode_fast_frame(0, 0, (math.nan, 0, 0), (0, 0, 0), 0)
    with pytest.raises(ValueError, match="3 values"):
        encode_fast_frame(0, 0, (0, 0), (0, 0, 0), 0)
    with pytest.raises(ValueError, match="bit"):
        encode_slow_block((0, 0, 0), (0, 0, 0), 20.0, 70000)
    frame = decode_fast_frame(encode_fast_frame(0, 0, (100.0, -100.0, 0), (1e4, 0, 0), 0))
    assert frame.rates_rad_s[0] == pytest.approx(32767 * RATE_LSB_RAD_S)
    assert frame.rates_rad_s[1] == pytest.approx(-32768 * RATE_LSB_RAD_S)
    assert frame.accel_m_s2[0] == pytest.approx(32767 * ACCEL_LSB_M_S2)


int16 = st.integers(-32768, 32767)
int32 = st.integers(-(2**31), 2**31 - 1)


@settings(max_examples=200, deadline=None)
@given(
    counter=st.integers(0, 99),
    status=st.integers(0, 255),
    rates=st.tuples(int16, int16, int16),
    accel=st.tuples(int16, int16, int16),
    word=st.integers(0, 0xFFFF),
)
def test_fast_frame_round_trip_is_exact_in_raw_units(
    counter: int,
    status: int,
    rates: tuple[int, int, int],
    accel: tuple[int, int, int],
    word: int,
) -> None:
    frame = encode_fast_frame(
        counter,
        status,
        [r * RATE_LSB_RAD_S for r in rates],
        [a * ACCEL_LSB_M_S2 for a in accel],
        word,
    )
    assert struct.unpack_from("<3h3h", frame, 4) == rates + accel
    decoded = decode_fast_frame(frame)
    assert (decoded.counter, decoded.status, decoded.slow_word) == (counter, status, word)
    assert tuple(round(v / RATE_LSB_RAD_S) for v in decoded.rates_rad_s) == rates
    assert tuple(round(v / ACCEL_LSB_M_S2) for v in decoded.accel_m_s2) == accel


@settings(max_examples=100, deadline=None)
@given(
    rates=st.tuples(int32, int32, int32),
    accel=st.tuples(int32, int32, int32),
    temp=st.integers(-32768, 32767),
    bit=st.integers(0, 0xFFFF),
)
def test_slow_block_round_trip_through_a_cycle(
    rates: tuple[int, int, int], accel: tuple[int, int, int], temp: int, bit: int
) -> None:
    block = encode_slow_block(
        [r * 1e-6 for r in rates], [a * 1e-6 for a in accel], temp * 0.01, bit
    )
    assert len(block) == SLOW_BLOCK_LEN
    assert struct.unpack_from("<3i3ihH", block) == rates + accel + (temp, bit)
    decoder = ImuDecoder()
    out = decoder.feed(b"".join(cycle_frames(block)), 0)
    slow = out[-1]
    assert isinstance(slow, ImuSlow) and slow.bit_word == bit
    assert tuple(round(v * 1e6) for v in slow.rates_rad_s) == rates
    assert tuple(round(v * 1e6) for v in slow.accel_m_s2) == accel
    assert round(slow.temperature_c * 100) == temp


@settings(max_examples=300, deadline=None)
@given(chunks=st.lists(st.binary(max_size=64), max_size=30))
def test_fuzz_random_bytes_never_raise_and_buffer_stays_bounded(chunks: list[bytes]) -> None:
    decoder = ImuDecoder()
    for i, chunk in enumerate(chunks):
        for item in decoder.feed(chunk, i):
            assert isinstance(item, ImuFast | ImuSlow)
        assert len(decoder._buf) < FAST_FRAME_LEN
    c = decoder.counters
    consumed = c.bytes_discarded + FAST_FRAME_LEN * c.frames_good + len(decoder._buf)
    assert consumed == sum(map(len, chunks))


def test_huge_garbage_chunk_is_discarded_then_frames_decode() -> None:
    decoder = ImuDecoder()
    garbage = bytes(range(256)) * 4000  # ~1 MB, contains 0x7e but never 0x7e 0x49
    out = decoder.feed(garbage + b"".join(cycle_frames(SLOW_BLOCK)), 0)
    assert len(out) == 101
    assert decoder.counters.bytes_discarded == len(garbage)
    assert len(decoder._buf) == 0
