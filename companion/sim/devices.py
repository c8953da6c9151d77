"""Byte generators for the simulated IMU, GPS receiver and servo board, plus fault injection.

Everything here is pure and deterministic given a ``numpy.random.Generator``: callers pass the
true state and get back exactly the bytes the real device would send (per the device contract),
so the same driver code runs in SITL and in flight. Writing the bytes to pseudo-terminals at the
real rates is the SITL runner's job, not this module's.

Size: the three devices and the faults applied to their bytes share one set of conventions (a
chunk is a frame or an epoch, everything deterministic from one generator); split, each part
would restate them.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from companion.drivers.gps_protocol import DEFAULT_SENTENCES, TALKERS, GpsSolution, encode_epoch
from companion.drivers.imu_protocol import (
    CYCLE_FRAMES,
    STATUS_ACCEL_OK,
    STATUS_GYRO_OK,
    STATUS_SELF_TEST,
    encode_fast_frame,
    encode_slow_block,
    slow_block_words,
)
from companion.drivers.servo_protocol import (
    CH_MODE,
    CHANNELS,
    COMMAND_MAX_US,
    COMMAND_MIN_US,
    CommandDecoder,
    PilotFrame,
    ServoCommand,
    encode_pilot,
    pilot_switch_auto,
)

__all__ = [
    "FaultCounts",
    "FaultInjector",
    "FaultPlan",
    "GpsSim",
    "GpsSimConfig",
    "ImuSim",
    "ImuSimConfig",
    "ServoBoardConfig",
    "ServoBoardSim",
    "uart_misread",
]

_WGS84_A_M = 6378137.0
_WGS84_E2 = 6.69437999014e-3


def _metres_to_degrees(lat_deg: float, north_m: float, east_m: float) -> tuple[float, float]:
    """Small NED offsets to latitude/longitude offsets with the WGS84 radii of curvature."""
    lat = math.radians(lat_deg)
    sin2 = math.sin(lat) ** 2
    meridian_m = _WGS84_A_M * (1 - _WGS84_E2) / (1 - _WGS84_E2 * sin2) ** 1.5
    normal_m = _WGS84_A_M / math.sqrt(1 - _WGS84_E2 * sin2)
    east_radius_m = max(normal_m * math.cos(lat), 1.0)
    return math.degrees(north_m / meridian_m), math.degrees(east_m / east_radius_m)


def _vector3(values: Sequence[float], what: str) -> np.ndarray:
    array = np.asarray(values, dtype=float)
    if array.shape != (3,):
        raise ValueError(f"{what} needs 3 values, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{what} must be finite, got {values!r}")
    return array


# ---------------------------------------------------------------------------------------------
# IMU


@dataclass(frozen=True, slots=True)
class ImuSimConfig:
    """Error model of the simulated IMU (1-sigma values; each frame is one 10 ms sample)."""

    gyro_noise_rad_s: float = 0.003
    accel_noise_m_s2: float = 0.03
    gyro_bias_sigma_rad_s: float = 0.005
    """Spread of the turn-on gyro bias, drawn once per simulator."""
    accel_bias_sigma_m_s2: float = 0.05
    gyro_bias_walk_rad_s_sqrt_s: float = 5e-5
    accel_bias_walk_m_s2_sqrt_s: float = 5e-4
    temperature_c: float = 35.0
    self_test_frames: int = 0
    """Frames at start-up flagged 'self-test running' with gyro/accel not yet ok."""
    bit_word: int = 0


class ImuSim:
    """100 Hz fast frames from true body rates and specific force, with noise, bias, quantisation.

    Each counter cycle's slow block carries the mean of the previous cycle's (unquantised)
    measurements: the block must be complete before its first word goes out.
    """

    RATE_HZ = 100

    def __init__(self, rng: np.random.Generator, config: ImuSimConfig | None = None) -> None:
        self.rng = rng
        self.config = cfg = config or ImuSimConfig()
        self.gyro_bias_rad_s = rng.normal(0.0, cfg.gyro_bias_sigma_rad_s, 3)
        self.accel_bias_m_s2 = rng.normal(0.0, cfg.accel_bias_sigma_m_s2, 3)
        self.frames = 0
        self.last_rates_rad_s = np.zeros(3)
        """Measured (biased, noisy, not yet quantised) rates of the last frame."""
        self.last_accel_m_s2 = np.zeros(3)
        self._sum = np.zeros(6)
        self._count = 0
        self._words: tuple[int, ...] = ()

    def frame(self, rates_rad_s: Sequence[float], accel_m_s2: Sequence[float]) -> bytes:
        """Advance 10 ms and return the next 20-byte fast frame."""
        cfg = self.config
        rates = _vector3(rates_rad_s, "rates_rad_s")
        accel = _vector3(accel_m_s2, "accel_m_s2")
        dt_s = 1.0 / self.RATE_HZ
        draw = self.rng.standard_normal(12)
        self.gyro_bias_rad_s += draw[0:3] * cfg.gyro_bias_walk_rad_s_sqrt_s * math.sqrt(dt_s)
        self.accel_bias_m_s2 += draw[3:6] * cfg.accel_bias_walk_m_s2_sqrt_s * math.sqrt(dt_s)
        measured_rates = rates + self.gyro_bias_rad_s + draw[6:9] * cfg.gyro_noise_rad_s
        measured_accel = accel + self.accel_bias_m_s2 + draw[9:12] * cfg.accel_noise_m_s2
        counter = self.frames % CYCLE_FRAMES
        if counter == 0:
            self._start_cycle(measured_rates, measured_accel)
        if self.frames < cfg.self_test_frames:
            status = STATUS_SELF_TEST
        else:
            status = STATUS_GYRO_OK | STATUS_ACCEL_OK
        self._sum[:3] += measured_rates
        self._sum[3:] += measured_accel
        self._count += 1
        self.last_rates_rad_s = measured_rates
        self.last_accel_m_s2 = measured_accel
        self.frames += 1
        return encode_fast_frame(
            counter, status, measured_rates.tolist(), measured_accel.tolist(), self._words[counter]
        )

    def _start_cycle(self, rates: np.ndarray, accel: np.ndarray) -> None:
        if self._count:
            mean = self._sum / self._count
        else:
            mean = np.concatenate([rates, accel])
        self._sum[:] = 0.0
        self._count = 0
        block = encode_slow_block(
            mean[:3].tolist(), mean[3:].tolist(), self.config.temperature_c, self.config.bit_word
        )
        self._words = slow_block_words(block)


# ---------------------------------------------------------------------------------------------
# GPS


@dataclass(frozen=True, slots=True)
class GpsSimConfig:
    """What the simulated receiver outputs and how wrong it is (1-sigma values)."""

    talker: str = "GP"
    sentences: tuple[str, ...] = DEFAULT_SENTENCES
    ashtech_pos: bool = False
    fix: int = 1
    sats: int = 9
    hdop: float = 0.9
    pdop: float = 1.6
    vdop: float = 1.3
    tdop: float = 0.8
    horiz_white_m: float = 0.8
    vert_white_m: float = 1.5
    horiz_walk_m_sqrt_s: float = 0.1
    """Random-walk part of the position error (slowly wandering, like real GPS)."""
    vert_walk_m_sqrt_s: float = 0.15
    vel_noise_m_s: float = 0.05
    geoid_sep_m: float = 0.0
    """Ellipsoid minus MSL; 0 matches a flight model whose altitudes are ellipsoidal."""
    date: dt.date = field(default_factory=lambda: dt.date(2003, 6, 1))
    """UTC date of second 0 of the simulation."""

    @property
    def expected_sentences(self) -> tuple[str, ...]:
        """The sentence set one epoch holds: pass it to ``NmeaDecoder(expected_sentences=...)``."""
        return tuple(self.sentences) + (("POS",) if self.ashtech_pos else ())


class GpsSim:
    """10 Hz receiver epochs from the true position and NED velocity."""

    RATE_HZ = 10

    def __init__(self, rng: np.random.Generator, config: GpsSimConfig | None = None) -> None:
        self.rng = rng
        self.config = cfg = config or GpsSimConfig()
        if cfg.talker not in TALKERS:
            raise ValueError(f"GpsSimConfig.talker must be one of {TALKERS}, got {cfg.talker!r}")
        self._walk_m = np.zeros(3)
        self._last_utc_s: float | None = None
        self.last_solution: GpsSolution | None = None
        """The solution encoded by the last call, before the text rounding."""

    def epoch(
        self,
        utc_s: float,
        lat_deg: float,
        lon_deg: float,
        alt_m: float,
        vn_m_s: float,
        ve_m_s: float,
        vd_m_s: float,
    ) -> bytes:
        """Return one epoch's sentences; ``utc_s`` counts seconds from midnight of ``config.date``."""
        cfg = self.config
        truth = (utc_s, lat_deg, lon_deg, alt_m, vn_m_s, ve_m_s, vd_m_s)
        if not all(math.isfinite(v) for v in truth):
            raise ValueError(f"GpsSim.epoch: inputs must be finite, got {truth!r}")
        dt_s = (
            1.0 / self.RATE_HZ if self._last_utc_s is None else max(utc_s - self._last_utc_s, 0.0)
        )
        self._last_utc_s = utc_s
        draw = self.rng.standard_normal(9)
        walk_sigma = np.array([cfg.horiz_walk_m_sqrt_s] * 2 + [cfg.vert_walk_m_sqrt_s])
        white_sigma = np.array([cfg.horiz_white_m] * 2 + [cfg.vert_white_m])
        self._walk_m += draw[0:3] * walk_sigma * math.sqrt(dt_s)
        error_m = self._walk_m + draw[3:6] * white_sigma
        velocity = np.array([vn_m_s, ve_m_s, vd_m_s]) + draw[6:9] * cfg.vel_noise_m_s
        days, seconds = divmod(utc_s, 86400.0)
        common = GpsSolution(
            utc=seconds,
            date=cfg.date + dt.timedelta(days=int(days)),
            geoid_sep_m=cfg.geoid_sep_m,
            fix=cfg.fix,
            sats=cfg.sats,
            hdop=cfg.hdop,
            pdop=cfg.pdop,
            vdop=cfg.vdop,
            tdop=cfg.tdop,
            alt_std_m=math.hypot(cfg.vert_white_m, cfg.vert_walk_m_sqrt_s),
            lat_std_m=math.hypot(cfg.horiz_white_m, cfg.horiz_walk_m_sqrt_s),
            lon_std_m=math.hypot(cfg.horiz_white_m, cfg.horiz_walk_m_sqrt_s),
        )
        if cfg.fix == 0:
            solution = common  # a receiver without a fix leaves position and velocity empty
        else:
            north_deg, east_deg = _metres_to_degrees(lat_deg, error_m[0], error_m[1])
            vn, ve, vd = (float(v) for v in velocity)
            solution = dataclasses.replace(
                common,
                lat_deg=min(max(lat_deg + north_deg, -90.0), 90.0),
                lon_deg=(lon_deg + east_deg + 180.0) % 360.0 - 180.0,
                alt_m=alt_m - float(error_m[2]),
                speed_m_s=math.hypot(vn, ve),
                course_deg=math.degrees(math.atan2(ve, vn)) % 360.0,
                vn_m_s=vn,
                ve_m_s=ve,
                vd_m_s=vd,
            )
        self.last_solution = solution
        return encode_epoch(solution, cfg.talker, cfg.sentences, cfg.ashtech_pos)


# ---------------------------------------------------------------------------------------------
# Servo board


@dataclass(frozen=True, slots=True)
class ServoBoardConfig:
    avionics_batt_start_raw: float = 100.0
    servo_batt_start_raw: float = 98.0
    avionics_drain_raw_per_h: float = 8.0
    servo_drain_raw_per_h: float = 20.0
    batt_noise_raw: float = 0.3
    command_timeout_s: float = 0.1
    """With no command frame for this long the board stops obeying the computer."""


class ServoBoardSim:
    """The board's side of the exchange: one pilot frame answers each command frame.

    The surfaces follow the computer only while the pilot's switch selects automatic mode and
    the latest (fresh) command asked for it; channels the computer leaves at 0 and the mode
    switch itself always follow the pilot.
    """

    def __init__(self, rng: np.random.Generator, config: ServoBoardConfig | None = None) -> None:
        self.rng = rng
        self.config = config or ServoBoardConfig()
        self.decoder = CommandDecoder()
        self.pilot_us: tuple[int, ...] = (1500, 1500, 1000, 1500, 1000, 1500, 1500, 1500)
        self.failsafe = False
        self.last_command: ServoCommand | None = None
        self._last_command_t_s = -math.inf
        self.answered = 0

    def set_pilot(self, channels_us: Sequence[int], failsafe: bool = False) -> None:
        """Set what the RC receiver currently outputs (the scripted pilot's sticks)."""
        if len(channels_us) != CHANNELS:
            raise ValueError(f"channels_us needs {CHANNELS} values, got {len(channels_us)}")
        self.pilot_us = tuple(int(v) for v in channels_us)
        self.failsafe = failsafe

    def feed(self, data: bytes, t_s: float) -> bytes:
        """Consume bytes from the computer (at sim time ``t_s``); return the board's answers."""
        out = bytearray()
        for command in self.decoder.feed(data, int(t_s * 1e9)):
            self.last_command = command
            self._last_command_t_s = t_s
            out += encode_pilot(
                PilotFrame(
                    seq=command.seq,
                    auto_engaged=pilot_switch_auto(self.pilot_us),
                    failsafe=self.failsafe,
                    channels_us=self.pilot_us,
                    avionics_batt_raw=self._battery(
                        self.config.avionics_batt_start_raw,
                        self.config.avionics_drain_raw_per_h,
                        t_s,
                    ),
                    servo_batt_raw=self._battery(
                        self.config.servo_batt_start_raw, self.config.servo_drain_raw_per_h, t_s
                    ),
                )
            )
            self.answered += 1
        return bytes(out)

    def _battery(self, start_raw: float, drain_per_h: float, t_s: float) -> int:
        level = (
            start_raw
            - drain_per_h * t_s / 3600.0
            + self.rng.normal(0.0, self.config.batt_noise_raw)
        )
        return int(min(max(round(level), 0), 255))

    def auto_active(self, t_s: float) -> bool:
        """Whether the computer drives the surfaces at sim time ``t_s``."""
        command = self.last_command
        return (
            command is not None
            and command.auto_requested
            and t_s - self._last_command_t_s <= self.config.command_timeout_s
            and pilot_switch_auto(self.pilot_us)
        )

    def effective_channels_us(self, t_s: float) -> tuple[int, ...]:
        """The pulse widths the servos get at sim time ``t_s``."""
        if not self.auto_active(t_s):
            return self.pilot_us
        assert self.last_command is not None
        out = list(self.pilot_us)
        for index, value in enumerate(self.last_command.channels_us):
            if value and index != CH_MODE:
                out[index] = min(max(value, COMMAND_MIN_US), COMMAND_MAX_US)
        return tuple(out)


# ---------------------------------------------------------------------------------------------
# Faults


@dataclass(frozen=True, slots=True)
class FaultPlan:
    """Faults to inject into a device's byte stream, chunk by chunk (a chunk = one frame/epoch)."""

    silence_s: tuple[tuple[float, float], ...] = ()
    """Windows [start, end) of sim time during which the device sends nothing."""
    garbage_prob: float = 0.0
    """Chance that random bytes precede a chunk."""
    garbage_len: tuple[int, int] = (1, 16)
    """Inclusive length range of a garbage burst."""
    cut_prob: float = 0.0
    """Chance that a chunk is cut short (its tail never sent)."""
    bad_checksum_prob: float = 0.0
    """Chance that one byte of a chunk (past its first two, before a trailing CR/LF) is altered,
    so its checksum no longer matches."""
    flood_s: tuple[tuple[float, float], ...] = ()
    """Windows [start, end) of sim time during which every chunk is sent `flood_factor` times:
    a babbling device, `flood_factor` times its byte rate, every copy valid."""
    flood_factor: int = 10
    wrong_baud_s: tuple[tuple[float, float], ...] = ()
    """Windows [start, end) during which the device sends at `baud_ratio` times the baud rate
    the computer's UART expects, so the computer receives what a mismatched UART makes of the
    bytes (see :func:`uart_misread`)."""
    baud_ratio: float = 2.0
    utc_step_s: tuple[tuple[float, float], ...] = ()
    """(at sim time, seconds) steps of the device's own clock: the GPS receiver's UTC jumps
    (a receiver reset, a leap second, a week-number rollover) while its fixes stay right."""

    def __post_init__(self) -> None:
        for name in ("garbage_prob", "cut_prob", "bad_checksum_prob"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"FaultPlan.{name} must be within 0..1, got {value}")
        if not 2 <= self.flood_factor <= 100:
            raise ValueError(f"FaultPlan.flood_factor must be within 2..100, got {self.flood_factor}")
        if not (0.05 <= self.baud_ratio <= 20.0) or abs(self.baud_ratio - 1.0) < 0.02:
            raise ValueError(f"FaultPlan.baud_ratio must be within 0.05..20 and not 1, got "
                             f"{self.baud_ratio}")
        for what, windows in (("flood_s", self.flood_s), ("wrong_baud_s", self.wrong_baud_s)):
            for start, end in windows:
                if not start <= end:
                    raise ValueError(f"FaultPlan.{what} window ({start}, {end}) ends before it "
                                     "starts")
        low, high = self.garbage_len
        if not 1 <= low <= high <= 4096:
            raise ValueError(
                f"FaultPlan.garbage_len must satisfy 1 <= min <= max <= 4096, got {self.garbage_len}"
            )
        for start, end in self.silence_s:
            if not start <= end:
                raise ValueError(
                    f"FaultPlan.silence_s window ({start}, {end}) ends before it starts"
                )


@dataclass(slots=True)
class FaultCounts:
    """What the injector actually did, so a test can compare it with the decoder's counters."""

    chunks: int = 0
    silenced: int = 0
    garbage_bursts: int = 0
    garbage_bytes: int = 0
    cut: int = 0
    corrupted: int = 0
    flooded: int = 0
    """Extra copies sent (chunks times flood_factor - 1)."""
    misread: int = 0
    """Chunks sent at the wrong baud rate."""


class FaultInjector:
    """Applies a :class:`FaultPlan` to successive chunks of a generated byte stream."""

    def __init__(self, plan: FaultPlan, rng: np.random.Generator) -> None:
        self.plan = plan
        self.rng = rng
        self.counts = FaultCounts()

    def apply(self, chunk: bytes, t_s: float) -> bytes:
        """Return the bytes actually sent for ``chunk`` generated at sim time ``t_s``."""
        plan = self.plan
        counts = self.counts
        counts.chunks += 1
        if any(start <= t_s < end for start, end in plan.silence_s):
            counts.silenced += 1
            return b""
        rng = self.rng
        data = bytearray(chunk)
        if plan.bad_checksum_prob and rng.random() < plan.bad_checksum_prob:
            stop = len(data.rstrip(b"\r\n"))
            if stop > 2:
                index = int(rng.integers(2, stop))
                data[index] ^= int(rng.integers(1, 256))
                counts.corrupted += 1
        if plan.cut_prob and len(data) > 1 and rng.random() < plan.cut_prob:
            del data[int(rng.integers(1, len(data))) :]
            counts.cut += 1
        if plan.garbage_prob and rng.random() < plan.garbage_prob:
            size = int(rng.integers(plan.garbage_len[0], plan.garbage_len[1] + 1))
            data[0:0] = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
            counts.garbage_bursts += 1
            counts.garbage_bytes += size
        if any(start <= t_s < end for start, end in plan.wrong_baud_s):
            counts.misread += 1
            data = bytearray(uart_misread(bytes(data), plan.baud_ratio))
        if any(start <= t_s < end for start, end in plan.flood_s):
            counts.flooded += plan.flood_factor - 1
            return bytes(data) * plan.flood_factor
        return bytes(data)


def uart_misread(data: bytes, ratio: float) -> bytes:
    """What a UART receives when the sender runs at `ratio` times its baud rate (8N1 both).

    The bytes go out back to back, with the line idle (high) before and after; the receiver
    waits for a falling edge, samples the middle of its own bit times, and hands up each byte
    whose stop bit reads high. A byte whose stop bit reads low is a framing error, which a Linux
    tty without IGNPAR or PARMRK delivers as a NUL; the receiver then waits for the line to go
    high again before it looks for the next start bit. A real receiver behaves this way, so the
    garbage it produces (its length, its NULs, its accidental sync bytes) is what the driver
    meets when a device is configured for the wrong rate.
    """
    if not data:
        return b""
    bits: list[int] = []
    for byte in data:
        bits.append(0)
        bits.extend((byte >> i) & 1 for i in range(8))
        bits.append(1)
    n_tx = len(bits)
    rx_bit = ratio  # one receiver bit time, in sender bit times

    def level(t: float) -> int:
        k = math.floor(t)
        return bits[k] if 0 <= k < n_tx else 1

    out = bytearray()
    t = 0.0
    step = min(rx_bit, 1.0) / 4.0  # edge search resolution, finer than either bit time
    while t < n_tx:
        # find the next falling edge (line low while it was high just before)
        while t < n_tx and not (level(t) == 0 and level(t - step) == 1):
            t += step
        if t >= n_tx:
            break
        if level(t + 0.5 * rx_bit) != 0:  # a glitch, not a start bit
            t += step
            continue
        value = 0
        for i in range(8):
            value |= level(t + (1.5 + i) * rx_bit) << i
        stop_t = t + 9.5 * rx_bit
        if level(stop_t) == 1:
            out.append(value)
            t = stop_t
        else:
            out.append(0)  # framing error
            t = stop_t
            while t < n_tx and level(t) == 0:  # wait for the line to go idle (high)
                t += step
    return bytes(out)
