"""The simulated IMU: true body rates and specific force in, the contract's 100 Hz frames out.

One module per simulated device (`imu_sim`, `gps_sim`, `servo_sim`), flat beside the IMU's
error model (`companion.sim.imu_model`) it uses: each device's byte generator changes for its
own reasons (its contract, its error terms) and is read alone. Everything here is pure and
deterministic given a ``numpy.random.Generator``: callers pass the true state and get back
exactly the bytes the real part would send, so the same driver code runs in SITL and in flight.
Writing the bytes to a port at the real rate is the world's job (`companion.sim.world`), and
the faults applied to them are `companion.sim.byte_faults`'.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from companion.drivers.imu_protocol import (
    CYCLE_FRAMES,
    STATUS_ACCEL_OK,
    STATUS_GYRO_OK,
    STATUS_SELF_TEST,
    ImuDecoder,
    ImuFast,
    encode_fast_frame,
    encode_slow_block,
    slow_block_words,
)
from companion.estimation.level import LevelTrim, level_trim
from companion.estimation.quat import GRAVITY_M_S2
from companion.sim.imu_model import ImuErrorModel, ImuSimConfig

__all__ = ["LEVEL_CALIBRATION_S", "ImuSim", "SimLevelCalibration"]


LEVEL_CALIBRATION_S = 5.0
"""How long the simulated level calibration reads the still part."""


@dataclass(frozen=True)
class SimLevelCalibration:
    """A simulated pre-flight level calibration: what it measured and the truth behind it."""

    trim: LevelTrim
    level_error_rad: tuple[float, float]
    """How far off level (roll, pitch) the aircraft stood: what the trim cannot know."""

    def params(self, prefix: str = "EST") -> dict[str, float]:
        return self.trim.params(prefix)

    def metadata(self) -> dict[str, float]:
        return {"trim_roll_deg": round(math.degrees(self.trim.roll_rad), 4),
                "trim_pitch_deg": round(math.degrees(self.trim.pitch_rad), 4),
                "level_error_roll_deg": round(math.degrees(self.level_error_rad[0]), 4),
                "level_error_pitch_deg": round(math.degrees(self.level_error_rad[1]), 4)}


class ImuSim:
    """100 Hz fast frames from true body rates and specific force, with the part's errors
    (`companion.sim.imu_model`) and the wire format's quantisation.

    Each counter cycle's slow block carries the mean of the previous cycle's measurements (the
    part's output before the wire format's quantisation): the block must be complete before its
    first word goes out.
    """

    RATE_HZ = 100

    def __init__(self, rng: np.random.Generator, config: ImuSimConfig | None = None) -> None:
        self.rng = rng
        self.config = cfg = config or ImuSimConfig()
        self.errors = ImuErrorModel(cfg, rng, self.RATE_HZ)
        self.frames = 0
        self._last_out: list[float] = [0.0] * 6
        self._sum = [0.0] * 6
        self._count = 0
        self._words: tuple[int, ...] = ()
        self._temperature_c = cfg.temperature_at(0.0)

    @classmethod
    def of_part(cls, rng: np.random.Generator, config: ImuSimConfig,
                part_seed: int | None = None) -> ImuSim:
        """The flight's IMU, drawn from ``rng``; with ``part_seed`` the part of the flight with
        that seed instead, switched on again (`ImuErrorModel.power_on_again`: its own turn-on
        bias and noise from ``rng``), so one part can fly on several days."""
        if part_seed is None:
            return cls(rng, config)
        imu = cls(np.random.default_rng(np.random.default_rng(part_seed).integers(2**63)),
                  config)
        imu.errors = imu.errors.power_on_again(rng)
        return imu

    @property
    def last_rates_rad_s(self) -> np.ndarray:
        """Measured (biased, noisy, not yet wire-quantised) rates of the last frame, rad/s."""
        return np.array(self._last_out[:3])

    @property
    def last_accel_m_s2(self) -> np.ndarray:
        """Measured specific force of the last frame (as the rates), m/s^2."""
        return np.array(self._last_out[3:])

    @property
    def gyro_bias_rad_s(self) -> np.ndarray:
        """The gyro bias now (turn-on, walk, instability, temperature), rad/s per axis."""
        return np.array(self.errors.total_bias(self._temperature_c)[0])

    @property
    def accel_bias_m_s2(self) -> np.ndarray:
        """The accelerometer bias now, m/s^2 per axis."""
        return np.array(self.errors.total_bias(self._temperature_c)[1])

    def temperature_at(self, t_s: float) -> float:
        """The part's temperature ``t_s`` after switch-on (its warm-up profile)."""
        return self.config.temperature_at(t_s)

    def level_calibration(self, rng: np.random.Generator,
                          seconds: float = LEVEL_CALIBRATION_S) -> SimLevelCalibration | None:
        """The level calibration a user makes before the flight, on this part (None when the
        configuration has none: `ImuSimConfig.level_error_sigma_rad`).

        The aircraft stands still, engine off, ``rng``'s draw of the levelling error off level,
        the part at its switch-on temperature. A twin of this simulator (same drawn errors,
        noise from ``rng``, so the flight's own draws do not move) sends ``seconds`` of frames;
        the driver's decoder reads them and the runtime's own calibration
        (`companion.estimation.level.level_trim`) turns them into the trims.
        """
        sigma = self.config.level_error_sigma_rad
        if sigma is None:
            return None
        roll, pitch = (float(v) for v in rng.normal(0.0, sigma, 2))
        g = GRAVITY_M_S2
        accel = (g * math.sin(pitch), -g * math.sin(roll) * math.cos(pitch),
                 -g * math.cos(roll) * math.cos(pitch))
        twin = copy.copy(self)
        twin.errors = self.errors.spare(rng)
        twin.frames, twin._sum, twin._count, twin._words = 0, [0.0] * 6, 0, ()
        decoder = ImuDecoder()
        temperature_c = self.config.temperature_at(0.0)
        rates: list[tuple[float, float, float]] = []
        accels: list[tuple[float, float, float]] = []
        for k in range(int(round(seconds * self.RATE_HZ))):
            data = twin.frame((0.0, 0.0, 0.0), accel, 0.0, temperature_c)
            for item in decoder.feed(data, k * 10_000_000):
                if isinstance(item, ImuFast) and item.gyro_ok and item.accel_ok:
                    rates.append(item.rates_rad_s)
                    accels.append(item.accel_m_s2)
        return SimLevelCalibration(level_trim(accels, rates), (roll, pitch))

    def frame(self, rates_rad_s: Sequence[float], accel_m_s2: Sequence[float],
              rpm: float = 0.0, temperature_c: float | None = None) -> bytes:
        """Advance 10 ms and return the next 20-byte fast frame.

        ``rpm`` is the propeller's (drives the vibration); ``temperature_c`` the part's now
        (None: its own warm-up profile at this frame's time).
        """
        cfg = self.config
        r0, r1, r2 = _finite3(rates_rad_s, "rates_rad_s")
        a0, a1, a2 = _finite3(accel_m_s2, "accel_m_s2")
        if temperature_c is None:
            temperature_c = cfg.temperature_at(self.frames / self.RATE_HZ)
        self._temperature_c = temperature_c
        out = self.errors.measure(r0, r1, r2, a0, a1, a2, rpm, temperature_c)
        counter = self.frames % CYCLE_FRAMES
        if counter == 0:
            self._start_cycle(out)
        if self.frames < cfg.self_test_frames:
            status = STATUS_SELF_TEST
        else:
            status = STATUS_GYRO_OK | STATUS_ACCEL_OK
        total = self._sum
        for i in range(6):
            total[i] += out[i]
        self._count += 1
        self._last_out = out  # arrays only when asked for (the properties): not per frame
        self.frames += 1
        return encode_fast_frame(counter, status, out[:3], out[3:], self._words[counter])

    def _start_cycle(self, out: list[float]) -> None:
        if self._count:
            mean = [v / self._count for v in self._sum]
        else:
            mean = list(out)
        self._sum = [0.0] * 6
        self._count = 0
        block = encode_slow_block(mean[:3], mean[3:], self._temperature_c, self.config.bit_word)
        self._words = slow_block_words(block)


def _finite3(values: Sequence[float], what: str) -> tuple[float, float, float]:
    """Three finite floats, or a ValueError naming ``what`` (scalar: numpy is slower here)."""
    try:
        x, y, z = values
        x, y, z = float(x), float(y), float(z)
    except (TypeError, ValueError):
        raise ValueError(f"{what} needs 3 values, got {values!r}") from None
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise ValueError(f"{what} must be finite, got {values!r}")
    return x, y, z

