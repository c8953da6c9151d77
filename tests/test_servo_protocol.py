from __future__ import annotations

import json

import pytest
from conftest import data_file
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.drivers.servo_protocol import (
    COMMAND_LEN,
    PILOT_LEN,
    CommandDecoder,
    PilotDecoder,
    PilotFrame,
    ServoCommand,
    decode_command,
    decode_pilot,
    encode_command,
    encode_pilot,
    pilot_switch_auto,
)

SPEC = json.loads(data_file("vectors", "devices.json").read_text())
CMD = SPEC["servo_command"]
PILOT = SPEC["servo_pilot"]
CMD_HEX = SPEC["servo_command_hex"]
PILOT_HEX = SPEC["servo_pilot_hex"]


def vector_command() -> ServoCommand:
    return ServoCommand(CMD["seq"], CMD["auto_requested"], tuple(CMD["channels_us"]))


def vector_pilot() -> PilotFrame:
    return PilotFrame(
        seq=PILOT["seq"],
        auto_engaged=PILOT["auto_engaged"],
        failsafe=PILOT["failsafe"],
        channels_us=tuple(PILOT["channels_us"]),
        avionics_batt_raw=PILOT["battery_logic"],
        servo_batt_raw=PILOT["battery_servo"],
    )


def pilot(seq: int, ch1: int = 1500) -> PilotFrame:
    return PilotFrame(seq, False, False, (ch1, 1500, 1000, 1500, 1000, 1500, 1500, 1500), 99, 88)


def test_command_vector_round_trips_exactly() -> None:
    assert encode_command(vector_command()).hex() == CMD_HEX
    assert decode_command(bytes.fromhex(CMD_HEX)) == vector_command()


def test_pilot_vector_round_trips_exactly() -> None:
    assert encode_pilot(vector_pilot()).hex() == PILOT_HEX
    assert decode_pilot(bytes.fromhex(PILOT_HEX), t_ns=0) == vector_pilot()


def test_switch_threshold() -> None:
    assert pilot_switch_auto(PILOT["channels_us"])  # 1900 us
    assert not pilot_switch_auto([1500] * 4 + [1700] + [1500] * 3)


def test_pilot_decoder_one_byte_at_a_time_with_garbage_and_a_cut_frame() -> None:
    frames = [encode_pilot(pilot(seq)) for seq in range(5)]
    stream = b"\x5a\x00\x5a" + frames[0] + frames[1][:11] + frames[2] + b"\xa5\x5a\xa5" + frames[3]
    stream += frames[4]
    decoder = PilotDecoder()
    out: list[PilotFrame] = []
    for i in range(len(stream)):
        out += decoder.feed(stream[i : i + 1], i)
    assert [f.seq for f in out] == [0, 2, 3, 4]
    c = decoder.counters
    assert c.frames_good == 4 and c.bytes_discarded == 3 + 11 + 3
    assert c.bad_checksum + c.bad_field == 2 and c.resyncs == 3
    assert out[0].t_ns == 3 + PILOT_LEN - 1


def test_command_decoder_handles_cut_and_corruption() -> None:
    commands = [
        encode_command(ServoCommand(seq, seq % 2 == 0, (1000 + seq, 0, 0, 0, 0, 0, 0, 2000)))
        for seq in range(4)
    ]
    corrupted = bytearray(commands[1])
    corrupted[7] ^= 0x01
    decoder = CommandDecoder()
    out = decoder.feed(commands[0] + bytes(corrupted) + commands[2][:5] + commands[3], 9)
    assert [c.seq for c in out] == [0, 3]
    assert out[1].channels_us[0] == 1003 and out[1].t_ns == 9
    assert decoder.counters.bad_checksum >= 1


def test_frame_passing_xor_but_with_impossible_pulse_width_is_rejected() -> None:
    frame = bytearray(encode_pilot(pilot(1)))
    # put 0xFFFF in channel 1 and keep the XOR right by flipping the same bits elsewhere in ch1
    frame[4] ^= 0xFF
    frame[5] ^= 0xFF
    frame[6] ^= 0xFF
    frame[7] ^= 0xFF
    decoder = PilotDecoder()
    assert decoder.feed(bytes(frame), 0) == []
    assert decoder.counters.bad_field == 1 and decoder.counters.bad_checksum == 0
    with pytest.raises(ValueError, match="pulse width"):
        decode_pilot(bytes(frame))


def test_decoders_raise_clear_errors_on_single_frames() -> None:
    with pytest.raises(ValueError, match="21 bytes"):
        decode_command(bytes.fromhex(CMD_HEX)[:-1])
    with pytest.raises(ValueError, match="sync"):
        decode_command(bytes.fromhex(PILOT_HEX)[:COMMAND_LEN])
    with pytest.raises(ValueError, match="checksum"):
        decode_pilot(bytes.fromhex(PILOT_HEX)[:-1] + b"\x00")


def test_encoders_validate_inputs() -> None:
    with pytest.raises(ValueError, match="channel 2 pulse width 2100"):
        encode_command(ServoCommand(0, True, (1500, 2100, 0, 0, 0, 0, 0, 0)))
    with pytest.raises(ValueError, match="8 values"):
        encode_command(ServoCommand(0, True, (1500,)))
    with pytest.raises(ValueError, match="seq"):
        encode_command(ServoCommand(256, True, (0,) * 8))
    with pytest.raises(ValueError, match="servo_batt_raw"):
        encode_pilot(PilotFrame(0, False, False, (1500,) * 8, 100, 300))
    # a pilot frame may carry receiver values outside the command range
    assert decode_pilot(encode_pilot(pilot(0, ch1=900))).channels_us[0] == 900


command_channels = st.tuples(*[st.one_of(st.just(0), st.integers(1000, 2000))] * 8)
pilot_channels = st.tuples(*[st.integers(0, 3000)] * 8)


@settings(max_examples=200, deadline=None)
@given(seq=st.integers(0, 255), auto=st.booleans(), channels=command_channels)
def test_command_round_trip(seq: int, auto: bool, channels: tuple[int, ...]) -> None:
    command = ServoCommand(seq, auto, channels)
    frame = encode_command(command)
    assert len(frame) == COMMAND_LEN
    assert decode_command(frame) == command
    assert CommandDecoder().feed(frame, 0) == [command]


@settings(max_examples=200, deadline=None)
@given(
    seq=st.integers(0, 255),
    auto=st.booleans(),
    failsafe=st.booleans(),
    channels=pilot_channels,
    batteries=st.tuples(st.integers(0, 255), st.integers(0, 255)),
)
def test_pilot_round_trip(
    seq: int, auto: bool, failsafe: bool, channels: tuple[int, ...], batteries: tuple[int, int]
) -> None:
    frame = PilotFrame(seq, auto, failsafe, channels, *batteries)
    data = encode_pilot(frame)
    assert len(data) == PILOT_LEN
    assert decode_pilot(data) == frame
    assert PilotDecoder().feed(data, 0) == [frame]


@settings(max_examples=300, deadline=None)
@given(chunks=st.lists(st.binary(max_size=64), max_size=30))
def test_fuzz_random_bytes_never_raise(chunks: list[bytes]) -> None:
    for decoder_type, length in ((PilotDecoder, PILOT_LEN), (CommandDecoder, COMMAND_LEN)):
        decoder = decoder_type()
        for chunk in chunks:
            decoder.feed(chunk, 0)
            assert len(decoder._buf) < length
        c = decoder.counters
        assert c.bytes_discarded + length * c.frames_good + len(decoder._buf) == sum(
            map(len, chunks)
        )


@settings(max_examples=50, deadline=None)
@given(garbage=st.lists(st.binary(max_size=40), min_size=6, max_size=6))
def test_real_frames_survive_any_garbage_between_them(garbage: list[bytes]) -> None:
    frames = [encode_pilot(pilot(seq, 1100 + seq)) for seq in range(5)]
    stream = b"".join(g + f for g, f in zip(garbage, [*frames, b""], strict=True))
    out = PilotDecoder().feed(stream, 0)
    assert [f.seq for f in out if f == pilot(f.seq, 1100 + f.seq)] == list(range(5))


def test_the_channel_convention_round_trips_with_the_wire_signs() -> None:
    """One mapping for the transmitter, the control law, the servo driver and the pilot: a pull
    (elevator -1, nose up) and right pedal (rudder -1) raise the pulse width."""
    from companion.drivers.servo_protocol import channels_to_surfaces, surfaces_to_channels

    assert surfaces_to_channels(0.0, 0.0, 0.0, 0.0) == (1500, 1500, 1000, 1500)
    assert surfaces_to_channels(1.0, -1.0, -1.0, 1.0) == (2000, 2000, 2000, 2000)
    assert surfaces_to_channels(3.0, 3.0, 3.0, -1.0) == (2000, 1000, 1000, 1000)  # clipped
    for surfaces in [(0.25, -0.5, 0.1, 0.6), (-1.0, 1.0, -1.0, 0.0)]:
        back = channels_to_surfaces(surfaces_to_channels(*surfaces))
        a, e, r, t = surfaces
        assert back == pytest.approx((a, e, r, t), abs=1e-3)
