"""IMU wire protocol: 20-byte fast frames at 100 Hz and the 200-byte slow block they carry.

Pure code (no I/O, no threads) so the driver thread, the simulator and the log tools share one
reading of the device contract (docs/devices.md). The module also holds the resynchronising frame
scanner and the counters that the servo protocol reuses, because both devices frame the same way:
two sync bytes, a fixed length, a trailing checksum.
"""

from __future__ import annotations

import binascii
import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Generic, TypeVar

from companion.core.fastinit import fast_frozen
from companion.core.mathutil import clamp

__all__ = [
    "ACCEL_LSB_M_S2",
    "CYCLE_FRAMES",
    "DecoderCounters",
    "FAST_FRAME_LEN",
    "ImuDecoder",
    "ImuFast",
    "ImuSlow",
    "RATE_LSB_RAD_S",
    "SLOW_BLOCK_LEN",
    "STATUS_ACCEL_OK",
    "STATUS_GYRO_OK",
    "STATUS_SELF_TEST",
    "SYNC",
    "SyncFrameDecoder",
    "crc16_ccitt_false",
    "decode_fast_frame",
    "decode_slow_block",
    "encode_fast_frame",
    "encode_slow_block",
    "slow_block_words",
]

SYNC = b"\x7e\x49"
FAST_FRAME_LEN = 20
SLOW_BLOCK_LEN = 200
CYCLE_FRAMES = 100

STATUS_GYRO_OK = 0x01
STATUS_ACCEL_OK = 0x02
STATUS_SELF_TEST = 0x04

STANDARD_GRAVITY_M_S2 = 9.80665
RATE_LSB_RAD_S = math.radians(0.02)
ACCEL_LSB_M_S2 = 0.001 * STANDARD_GRAVITY_M_S2
SLOW_RATE_LSB_RAD_S = 1e-6
SLOW_ACCEL_LSB_M_S2 = 1e-6
TEMPERATURE_LSB_C = 0.01

# A frame gap longer than this inside a counter cycle means the device went silent: the slow
# words on either side of the gap cannot belong to the same block even if the counters line up.
MAX_CYCLE_GAP_NS = 500_000_000

_FAST = struct.Struct("<2sBB3h3hHH")
_SLOW_HEAD = struct.Struct("<3i3ihH")
_INT16 = (-32768, 32767)
_INT32 = (-(2**31), 2**31 - 1)


@dataclass(slots=True)
class DecoderCounters:
    """Running tallies a driver publishes so an operator can tell a noisy line from a dead one."""

    frames_good: int = 0
    bad_checksum: int = 0
    bad_field: int = 0
    """Frames whose checksum matched but whose content is impossible (e.g. IMU counter > 99)."""
    resyncs: int = 0
    """Times the decoder regained sync on a good frame after discarding bytes."""
    bytes_discarded: int = 0
    slow_good: int = 0
    slow_dropped: int = 0


@fast_frozen
@dataclass(frozen=True)
class ImuFast:
    """One 100 Hz sample in SI units (body axes: x forward, y right, z down)."""

    counter: int
    status: int
    rates_rad_s: tuple[float, float, float]
    accel_m_s2: tuple[float, float, float]
    slow_word: int = 0
    t_ns: int = 0
    """Arrival time of the chunk that completed the frame (the clock passed to ``feed``)."""

    @property
    def gyro_ok(self) -> bool:
        return bool(self.status & STATUS_GYRO_OK)

    @property
    def accel_ok(self) -> bool:
        return bool(self.status & STATUS_ACCEL_OK)

    @property
    def self_test(self) -> bool:
        return bool(self.status & STATUS_SELF_TEST)


@fast_frozen
@dataclass(frozen=True)
class ImuSlow:
    """The once-a-second high-resolution block, in SI units."""

    rates_rad_s: tuple[float, float, float]
    accel_m_s2: tuple[float, float, float]
    temperature_c: float
    bit_word: int
    """Built-in-test word; 0 means every test passed."""
    t_ns: int = 0


def crc16_ccitt_false(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF); ``binascii.crc_hqx`` is exactly that CRC."""
    return binascii.crc_hqx(data, 0xFFFF)


def _quantise(value: float, lsb: float, bounds: tuple[int, int], what: str) -> int:
    """Round to the nearest LSB and saturate like the sensor's own output register would."""
    if not math.isfinite(value):
        raise ValueError(f"{what} must be finite, got {value!r}")
    raw = round(value / lsb)
    return clamp(raw, bounds[0], bounds[1])


def _triple(values: Sequence[float], what: str) -> tuple[float, float, float]:
    if len(values) != 3:
        raise ValueError(f"{what} needs 3 values, got {len(values)}")
    return (float(values[0]), float(values[1]), float(values[2]))


def _check_range(value: int, low: int, high: int, what: str) -> int:
    if not low <= value <= high:
        raise ValueError(f"{what} must be in {low}..{high}, got {value}")
    return value


def encode_fast_frame(
    counter: int,
    status: int,
    rates_rad_s: Sequence[float],
    accel_m_s2: Sequence[float],
    slow_word: int,
) -> bytes:
    """Build a 20-byte fast frame; values beyond the int16 range saturate as on the device."""
    if not (0 <= counter < CYCLE_FRAMES and 0 <= status <= 0xFF and 0 <= slow_word <= 0xFFFF):
        _check_range(counter, 0, CYCLE_FRAMES - 1, "counter")
        _check_range(status, 0, 0xFF, "status")
        _check_range(slow_word, 0, 0xFFFF, "slow_word")
    r0, r1, r2 = _triple(rates_rad_s, "rates_rad_s")
    a0, a1, a2 = _triple(accel_m_s2, "accel_m_s2")
    # the simulator's 100 Hz path: one expression instead of six _quantise calls, which then
    # name the culprit when a value is not finite
    raw: tuple[int, ...]
    try:
        raw = (round(r0 / RATE_LSB_RAD_S), round(r1 / RATE_LSB_RAD_S), round(r2 / RATE_LSB_RAD_S),
               round(a0 / ACCEL_LSB_M_S2), round(a1 / ACCEL_LSB_M_S2), round(a2 / ACCEL_LSB_M_S2))
    except (ValueError, OverflowError):
        raw = tuple([_quantise(v, RATE_LSB_RAD_S, _INT16, "rates_rad_s") for v in (r0, r1, r2)]
                    + [_quantise(v, ACCEL_LSB_M_S2, _INT16, "accel_m_s2") for v in (a0, a1, a2)])
    lo, hi = _INT16
    body = bytearray(_FAST.pack(SYNC, counter, status,
                                *[lo if v < lo else hi if v > hi else v for v in raw],
                                slow_word, 0))
    struct.pack_into("<H", body, 18, sum(body[2:18]) & 0xFFFF)
    return bytes(body)


def _unpack_fast(buf: bytes | bytearray, offset: int, t_ns: int) -> ImuFast | None:
    """Decode a frame whose sync is known to be at ``offset``; None if its checksum fails."""
    fields = _FAST.unpack_from(buf, offset)
    if sum(buf[offset + 2 : offset + 18]) & 0xFFFF != fields[10]:
        return None
    rl = RATE_LSB_RAD_S
    al = ACCEL_LSB_M_S2
    return ImuFast(
        counter=fields[1],
        status=fields[2],
        rates_rad_s=(fields[3] * rl, fields[4] * rl, fields[5] * rl),
        accel_m_s2=(fields[6] * al, fields[7] * al, fields[8] * al),
        slow_word=fields[9],
        t_ns=t_ns,
    )


def decode_fast_frame(frame: bytes, t_ns: int = 0) -> ImuFast:
    """Decode exactly one fast frame; raises ValueError naming the failed check."""
    if len(frame) != FAST_FRAME_LEN:
        raise ValueError(f"IMU fast frame must be {FAST_FRAME_LEN} bytes, got {len(frame)}")
    if frame[:2] != SYNC:
        raise ValueError(f"IMU fast frame: bad sync {frame[:2].hex()} at byte 0 (want 7e49)")
    decoded = _unpack_fast(frame, 0, t_ns)
    if decoded is None:
        raise ValueError("IMU fast frame: checksum at byte 18 does not match bytes 2..17")
    if decoded.counter >= CYCLE_FRAMES:
        raise ValueError(f"IMU fast frame: counter {decoded.counter} at byte 2 exceeds 99")
    return decoded


def encode_slow_block(
    rates_rad_s: Sequence[float],
    accel_m_s2: Sequence[float],
    temperature_c: float,
    bit: int,
) -> bytes:
    """Build the 200-byte slow block, CRC included; out-of-range values saturate."""
    _check_range(bit, 0, 0xFFFF, "bit")
    rates = [
        _quantise(v, SLOW_RATE_LSB_RAD_S, _INT32, "rates_rad_s")
        for v in _triple(rates_rad_s, "rates_rad_s")
    ]
    accel = [
        _quantise(v, SLOW_ACCEL_LSB_M_S2, _INT32, "accel_m_s2")
        for v in _triple(accel_m_s2, "accel_m_s2")
    ]
    temp = _quantise(temperature_c, TEMPERATURE_LSB_C, _INT16, "temperature_c")
    block = bytearray(SLOW_BLOCK_LEN)
    _SLOW_HEAD.pack_into(block, 0, *rates, *accel, temp, bit)
    struct.pack_into("<H", block, SLOW_BLOCK_LEN - 2, crc16_ccitt_false(bytes(block[:-2])))
    return bytes(block)


def decode_slow_block(block: bytes, t_ns: int = 0) -> ImuSlow:
    """Decode a reconstructed slow block; raises ValueError if its length or CRC is wrong."""
    if len(block) != SLOW_BLOCK_LEN:
        raise ValueError(f"IMU slow block must be {SLOW_BLOCK_LEN} bytes, got {len(block)}")
    (want,) = struct.unpack_from("<H", block, SLOW_BLOCK_LEN - 2)
    got = crc16_ccitt_false(bytes(block[:-2]))
    if want != got:
        raise ValueError(f"IMU slow block: CRC at byte 198 is {want:#06x}, computed {got:#06x}")
    f = _SLOW_HEAD.unpack_from(block, 0)
    return ImuSlow(
        rates_rad_s=(
            f[0] * SLOW_RATE_LSB_RAD_S,
            f[1] * SLOW_RATE_LSB_RAD_S,
            f[2] * SLOW_RATE_LSB_RAD_S,
        ),
        accel_m_s2=(
            f[3] * SLOW_ACCEL_LSB_M_S2,
            f[4] * SLOW_ACCEL_LSB_M_S2,
            f[5] * SLOW_ACCEL_LSB_M_S2,
        ),
        temperature_c=f[6] * TEMPERATURE_LSB_C,
        bit_word=f[7],
        t_ns=t_ns,
    )


def slow_block_words(block: bytes) -> tuple[int, ...]:
    """Split a slow block into the 100 words that frames 0..99 carry (word n = bytes 2n, 2n+1)."""
    if len(block) != SLOW_BLOCK_LEN:
        raise ValueError(f"IMU slow block must be {SLOW_BLOCK_LEN} bytes, got {len(block)}")
    return struct.unpack(f"<{CYCLE_FRAMES}H", block)


T = TypeVar("T")


class SyncFrameDecoder(Generic[T]):
    """Incremental scanner for fixed-length frames that start with a two-byte sync.

    On a failed frame only the first sync byte is dropped, so a false sync inside garbage (or
    inside a cut frame) never swallows the real frame that follows it. The buffer never holds
    more than one frame's worth of bytes between calls.
    """

    sync: bytes = b""
    frame_len: int = 0

    def __init__(self) -> None:
        self.counters = DecoderCounters()
        self._buf = bytearray()
        self._lost = False

    def reset(self) -> None:
        """Forget buffered bytes (e.g. after the port was reopened); counters are kept."""
        self._buf.clear()

    def feed(self, data: bytes, t_ns: int) -> list[T]:
        """Consume ``data`` (arrived at ``t_ns``) and return every good item it completed."""
        buf = self._buf
        buf += data
        out: list[T] = []
        pos = 0
        size = len(buf)
        sync = self.sync
        frame_len = self.frame_len
        counters = self.counters
        while True:
            start = buf.find(sync, pos)
            if start < 0:
                keep = size - 1 if size > pos and buf[size - 1] == sync[0] else size
                self._discard(keep - pos)
                pos = keep
                break
            if start > pos:
                self._discard(start - pos)
                pos = start
            if size - pos < frame_len:
                break
            if self._decode_frame(buf, pos, t_ns, out):
                counters.frames_good += 1
                if self._lost:
                    counters.resyncs += 1
                    self._lost = False
                pos += frame_len
            else:
                self._discard(1)
                pos += 1
        del buf[:pos]
        return out

    def _discard(self, count: int) -> None:
        if count > 0:
            self.counters.bytes_discarded += count
            self._lost = True

    def _decode_frame(self, buf: bytearray, offset: int, t_ns: int, out: list[T]) -> bool:
        """Validate the frame at ``offset``, append its items to ``out``; False drops it."""
        raise NotImplementedError


class ImuDecoder(SyncFrameDecoder[ImuFast | ImuSlow]):
    """Incremental IMU stream decoder: fast frames as they come, a slow block per full cycle.

    ``counters.slow_dropped`` counts counter cycles that could not be reconstructed (a frame
    missing, out of order, a bad CRC) once the decoder has seen a cycle start; the partial cycle
    it joins at start-up, after :meth:`reset` or after a silence is not counted. A silence
    spanning several cycles counts as one drop.
    """

    sync = SYNC
    frame_len = FAST_FRAME_LEN

    def __init__(self) -> None:
        super().__init__()
        self._block = bytearray(SLOW_BLOCK_LEN)
        self._collecting = False
        """True while every frame of the current cycle so far arrived in order."""
        self._tracking = False
        """True once a cycle start was seen, so a cycle that cannot be collected is a drop."""
        self._last_counter = 0
        self._last_t_ns = 0

    def reset(self) -> None:
        """Forget buffered bytes and any half-collected slow block (counted as dropped)."""
        super().reset()
        self._stop_tracking()

    def _stop_tracking(self) -> None:
        if self._collecting:
            self.counters.slow_dropped += 1
        self._collecting = self._tracking = False

    def _break_cycle(self) -> None:
        if self._collecting:
            self.counters.slow_dropped += 1
            self._collecting = False

    def _decode_frame(
        self, buf: bytearray, offset: int, t_ns: int, out: list[ImuFast | ImuSlow]
    ) -> bool:
        frame = _unpack_fast(buf, offset, t_ns)
        if frame is None:
            self.counters.bad_checksum += 1
            return False
        counter = frame.counter
        if counter >= CYCLE_FRAMES:
            self.counters.bad_field += 1
            return False
        out.append(frame)
        self._collect_slow_word(counter, buf, offset, t_ns, out)
        return True

    def _collect_slow_word(
        self, counter: int, buf: bytearray, offset: int, t_ns: int, out: list[ImuFast | ImuSlow]
    ) -> None:
        if self._tracking and t_ns - self._last_t_ns > MAX_CYCLE_GAP_NS:
            self._stop_tracking()  # the device went silent: where we are in a cycle is unknown
        last = self._last_counter
        self._last_counter = counter
        self._last_t_ns = t_ns
        if counter == 0:
            self._break_cycle()
            self._collecting = self._tracking = True
        elif counter < last - CYCLE_FRAMES // 2:  # wrapped, but frame 0 of this cycle was lost
            self._break_cycle()
            if self._tracking:
                self.counters.slow_dropped += 1
        elif counter != last + 1:
            self._break_cycle()
        if not self._collecting:
            return
        self._block[2 * counter : 2 * counter + 2] = buf[offset + 16 : offset + 18]
        if counter < CYCLE_FRAMES - 1:
            return
        self._collecting = False
        try:
            out.append(decode_slow_block(bytes(self._block), t_ns))
        except ValueError:
            self.counters.slow_dropped += 1
        else:
            self.counters.slow_good += 1
