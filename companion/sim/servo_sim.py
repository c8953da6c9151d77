"""The simulated servo board: answers each command frame with a pilot frame, drives the servos.

One module per simulated device (see `companion.sim.imu_sim`). The board decides whether the
pilot's sticks or the computer's commands reach the surfaces; the world
(`companion.sim.world`) feeds it the pilot's channels and the computer's bytes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from companion.core.mathutil import clamp
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

__all__ = ["NOISE_BLOCK", "ServoBoardConfig", "ServoBoardSim"]


@dataclass(frozen=True, slots=True)
class ServoBoardConfig:
    avionics_batt_start_raw: float = 100.0
    servo_batt_start_raw: float = 98.0
    avionics_drain_raw_per_h: float = 8.0
    servo_drain_raw_per_h: float = 20.0
    batt_noise_raw: float = 0.3
    command_timeout_s: float = 0.1
    """With no command frame for this long the board stops obeying the computer."""


NOISE_BLOCK = 256
"""Battery-reading noise draws taken from the board's generator at a time."""


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
        self._noise: list[float] = []  # standard normal draws, taken in blocks
        self._noise_at = 0

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
        # the same numbers as one rng.normal(0, sigma) call per reading (numpy draws a block
        # and single values from one stream), without numpy's per-call cost at 100 readings/s
        at = self._noise_at
        if at >= len(self._noise):
            self._noise = self.rng.standard_normal(NOISE_BLOCK).tolist()
            at = 0
        self._noise_at = at + 1
        level = (
            start_raw
            - drain_per_h * t_s / 3600.0
            + (0.0 + self.config.batt_noise_raw * self._noise[at])
        )
        return clamp(round(level), 0, 255)

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
                out[index] = clamp(value, COMMAND_MIN_US, COMMAND_MAX_US)
        return tuple(out)

