"""Servo-board wire protocol: 21-byte command frames out, 23-byte pilot frames back, at 50 Hz.

Pure encode/decode plus incremental decoders for both directions: the driver reads pilot frames,
the board simulator reads command frames. The 8-bit XOR checksum is weak, so decoders also reject
frames whose pulse widths no RC receiver could produce; that keeps garbage that happens to pass
the XOR (1 in 256 false syncs) from ever reaching the servos.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from functools import reduce
from operator import xor

from companion.core.fastinit import fast_frozen
from companion.core.mathutil import clamp
from companion.drivers.imu_protocol import DecoderCounters, SyncFrameDecoder

__all__ = [
    "AUTO_SWITCH_THRESHOLD_US",
    "CHANNELS",
    "CH_AILERON",
    "CH_ELEVATOR",
    "CH_MODE",
    "CH_RUDDER",
    "CH_THROTTLE",
    "COMMAND_LEN",
    "COMMAND_SYNC",
    "CommandDecoder",
    "DecoderCounters",
    "MAX_PLAUSIBLE_US",
    "PILOT_LEN",
    "PILOT_SYNC",
    "PilotDecoder",
    "PilotFrame",
    "ServoCommand",
    "decode_command",
    "decode_pilot",
    "encode_command",
    "encode_pilot",
    "pilot_switch_auto",
    "stick_to_us",
    "us_to_stick",
    "throttle_to_us",
    "us_to_throttle",
    "surfaces_to_channels",
    "channels_to_surfaces",
]

COMMAND_SYNC = b"\xa5\x5a"
PILOT_SYNC = b"\x5a\xa5"
COMMAND_LEN = 21
PILOT_LEN = 23
CHANNELS = 8

# Channel indices (0-based) into channels_us; the contract numbers them 1..8.
CH_AILERON = 0
CH_ELEVATOR = 1
CH_THROTTLE = 2
CH_RUDDER = 3
CH_MODE = 4

AUTO_SWITCH_THRESHOLD_US = 1700
"""The pilot's mode switch (channel 5) above this pulse width selects automatic mode."""
COMMAND_MIN_US = 1000
COMMAND_MAX_US = 2000
CENTRE_US = 1500
HALF_TRAVEL_US = 500
MODE_MANUAL_US = 1000
MODE_AUTO_US = 2000
"""What a two-position mode switch sends on channel 5."""
MAX_PLAUSIBLE_US = 3000
"""Pulse widths above this cannot come from a receiver; a frame holding one is garbage."""

FLAG_AUTO = 0x01
FLAG_FAILSAFE = 0x02

_COMMAND = struct.Struct("<2sBB8HB")
_PILOT = struct.Struct("<2sBB8HBBB")


@fast_frozen
@dataclass(frozen=True)
class ServoCommand:
    """What the computer asks of the board; a channel at 0 us means 'no command'."""

    seq: int
    auto_requested: bool
    channels_us: tuple[int, ...]
    t_ns: int = 0
    """Arrival time of the completing chunk when decoded; unused when encoding."""


@fast_frozen
@dataclass(frozen=True)
class PilotFrame:
    """The board's answer: the pilot's receiver channels, switch state and battery levels."""

    seq: int
    auto_engaged: bool
    failsafe: bool
    channels_us: tuple[int, ...]
    avionics_batt_raw: int
    """Logic battery, raw board units (about 100 = full)."""
    servo_batt_raw: int
    """Servo battery, raw board units (about 100 = full)."""
    t_ns: int = 0
    """Arrival time of the completing chunk when decoded; unused when encoding."""


def pilot_switch_auto(channels_us: Sequence[int]) -> bool:
    """True when the pilot's mode switch (channel 5) selects automatic mode."""
    return channels_us[CH_MODE] > AUTO_SWITCH_THRESHOLD_US


# The channel convention, in one place: the transmitter, the control law, the servo driver, the
# simulated pilot and the flight report all use these. On the wire a stick right, a pull (nose
# up) and right pedal raise the pulse width; JSBSim's surfaces (what `ControlOutput` carries)
# have elevator +1 nose down and rudder +1 nose left, hence the signs below.
def stick_to_us(x: float) -> int:
    """A normalised stick (-1..+1, clipped) as a pulse width, 1500 us centred."""
    return int(round(CENTRE_US + HALF_TRAVEL_US * clamp(x, -1.0, 1.0)))


def us_to_stick(us: float) -> float:
    """A pulse width (clipped to 1000..2000 us) as a normalised stick, -1..+1."""
    return (clamp(float(us), COMMAND_MIN_US, COMMAND_MAX_US) - CENTRE_US) / HALF_TRAVEL_US


def throttle_to_us(t: float) -> int:
    """Throttle 0..1 (clipped) as a pulse width, 1000..2000 us."""
    return int(round(COMMAND_MIN_US + (COMMAND_MAX_US - COMMAND_MIN_US) * clamp(t, 0.0, 1.0)))


def us_to_throttle(us: float) -> float:
    """A throttle pulse width (clipped to 1000..2000 us) as 0..1."""
    clipped = clamp(float(us), COMMAND_MIN_US, COMMAND_MAX_US)
    return (clipped - COMMAND_MIN_US) / (COMMAND_MAX_US - COMMAND_MIN_US)


def surfaces_to_channels(aileron: float, elevator: float, rudder: float,
                         throttle: float) -> tuple[int, int, int, int]:
    """JSBSim-convention surfaces as channels 1..4 (aileron, elevator, throttle, rudder), us."""
    return (stick_to_us(aileron), stick_to_us(-elevator), throttle_to_us(throttle),
            stick_to_us(-rudder))


def channels_to_surfaces(channels_us: Sequence[float]) -> tuple[float, float, float, float]:
    """Channels 1..4 (us) as JSBSim-convention (aileron, elevator, rudder, throttle)."""
    return (us_to_stick(channels_us[CH_AILERON]), -us_to_stick(channels_us[CH_ELEVATOR]),
            -us_to_stick(channels_us[CH_RUDDER]), us_to_throttle(channels_us[CH_THROTTLE]))


def _xor(data: bytes | bytearray, start: int, stop: int) -> int:
    return reduce(xor, data[start:stop], 0)


def _check_byte(value: int, what: str) -> int:
    if not 0 <= value <= 0xFF:
        raise ValueError(f"{what} must be in 0..255, got {value}")
    return value


def _check_channels(channels_us: Sequence[int], low: int, high: int) -> tuple[int, ...]:
    if len(channels_us) != CHANNELS:
        raise ValueError(f"channels_us needs {CHANNELS} values, got {len(channels_us)}")
    out = tuple(int(v) for v in channels_us)
    for index, value in enumerate(out):
        if value != 0 and not low <= value <= high:
            raise ValueError(
                f"channel {index + 1} pulse width {value} us outside {low}..{high} (or 0)"
            )
    return out


def encode_command(command: ServoCommand) -> bytes:
    """Build a command frame; pulse widths must be 0 or 1000..2000 us (clamp before calling)."""
    seq = _check_byte(command.seq, "seq")
    channels = _check_channels(command.channels_us, COMMAND_MIN_US, COMMAND_MAX_US)
    body = bytearray(
        _COMMAND.pack(COMMAND_SYNC, seq, FLAG_AUTO if command.auto_requested else 0, *channels, 0)
    )
    body[-1] = _xor(body, 2, COMMAND_LEN - 1)
    return bytes(body)


def encode_pilot(frame: PilotFrame) -> bytes:
    """Build a pilot frame (what the board sends); pulse widths must fit 0..3000 us."""
    seq = _check_byte(frame.seq, "seq")
    channels = _check_channels(frame.channels_us, 0, MAX_PLAUSIBLE_US)
    flags = (FLAG_AUTO if frame.auto_engaged else 0) | (FLAG_FAILSAFE if frame.failsafe else 0)
    body = bytearray(
        _PILOT.pack(
            PILOT_SYNC,
            seq,
            flags,
            *channels,
            _check_byte(frame.avionics_batt_raw, "avionics_batt_raw"),
            _check_byte(frame.servo_batt_raw, "servo_batt_raw"),
            0,
        )
    )
    body[-1] = _xor(body, 2, PILOT_LEN - 1)
    return bytes(body)


def _plausible(channels: Sequence[int]) -> bool:
    return max(channels) <= MAX_PLAUSIBLE_US


def _unpack_command(buf: bytes | bytearray, offset: int, t_ns: int) -> ServoCommand | str:
    """Decode at ``offset``; on failure return the name of the failed check instead."""
    fields = _COMMAND.unpack_from(buf, offset)
    if _xor(buf, offset + 2, offset + COMMAND_LEN - 1) != fields[-1]:
        return "checksum"
    channels = fields[3:11]
    if not _plausible(channels):
        return "pulse width"
    return ServoCommand(
        seq=fields[1], auto_requested=bool(fields[2] & FLAG_AUTO), channels_us=channels, t_ns=t_ns
    )


def _unpack_pilot(buf: bytes | bytearray, offset: int, t_ns: int) -> PilotFrame | str:
    fields = _PILOT.unpack_from(buf, offset)
    if _xor(buf, offset + 2, offset + PILOT_LEN - 1) != fields[-1]:
        return "checksum"
    channels = fields[3:11]
    if not _plausible(channels):
        return "pulse width"
    return PilotFrame(
        seq=fields[1],
        auto_engaged=bool(fields[2] & FLAG_AUTO),
        failsafe=bool(fields[2] & FLAG_FAILSAFE),
        channels_us=channels,
        avionics_batt_raw=fields[11],
        servo_batt_raw=fields[12],
        t_ns=t_ns,
    )


def _check_whole(frame: bytes, sync: bytes, length: int, what: str) -> None:
    if len(frame) != length:
        raise ValueError(f"{what} frame must be {length} bytes, got {len(frame)}")
    if frame[:2] != sync:
        raise ValueError(f"{what} frame: bad sync {frame[:2].hex()} at byte 0 (want {sync.hex()})")


def decode_command(frame: bytes, t_ns: int = 0) -> ServoCommand:
    """Decode exactly one command frame; raises ValueError naming the failed check."""
    _check_whole(frame, COMMAND_SYNC, COMMAND_LEN, "servo command")
    result = _unpack_command(frame, 0, t_ns)
    if isinstance(result, str):
        raise ValueError(f"servo command frame: bad {result}")
    return result


def decode_pilot(frame: bytes, t_ns: int = 0) -> PilotFrame:
    """Decode exactly one pilot frame; raises ValueError naming the failed check."""
    _check_whole(frame, PILOT_SYNC, PILOT_LEN, "servo pilot")
    result = _unpack_pilot(frame, 0, t_ns)
    if isinstance(result, str):
        raise ValueError(f"servo pilot frame: bad {result}")
    return result


def _count_failure(counters: DecoderCounters, reason: str) -> None:
    if reason == "checksum":
        counters.bad_checksum += 1
    else:
        counters.bad_field += 1


class PilotDecoder(SyncFrameDecoder[PilotFrame]):
    """Incremental decoder for the board-to-computer stream (the driver side)."""

    sync = PILOT_SYNC
    frame_len = PILOT_LEN

    def _decode_frame(self, buf: bytearray, offset: int, t_ns: int, out: list[PilotFrame]) -> bool:
        result = _unpack_pilot(buf, offset, t_ns)
        if isinstance(result, str):
            _count_failure(self.counters, result)
            return False
        out.append(result)
        return True


class CommandDecoder(SyncFrameDecoder[ServoCommand]):
    """Incremental decoder for the computer-to-board stream (the simulator side)."""

    sync = COMMAND_SYNC
    frame_len = COMMAND_LEN

    def _decode_frame(
        self, buf: bytearray, offset: int, t_ns: int, out: list[ServoCommand]
    ) -> bool:
        result = _unpack_command(buf, offset, t_ns)
        if isinstance(result, str):
            _count_failure(self.counters, result)
            return False
        out.append(result)
        return True
