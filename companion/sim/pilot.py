"""Scripted safety pilot for SITL: flies a scenario through the servo board's pilot channels.

The pilot sees the true state (as a human sees the aircraft) and moves the sticks of an 8-channel
radio. Its output is pulse widths, not surfaces, so that the simulated servo board can pass them
to the on-board runtime exactly as a receiver would, and so that the pilot's and the computer's
commands reach the flight model through one mapping, :func:`surfaces_from_channels`.

Channel convention (pulse widths in microseconds, 1000..2000, 1500 centre; a pulse above centre
moves the aircraft the positive way about the body axis of the channel):

=======  ==========  ==========================================================
channel  function    above centre
=======  ==========  ==========================================================
1        aileron     roll right (positive p)
2        elevator    stick back, nose up (positive q)
3        throttle    1000 idle .. 2000 full
4        rudder      right pedal, nose right (positive r)
5        mode        > 1700 us: automatic mode requested by the pilot
6..8     spare       centred
=======  ==========  ==========================================================

The stick laws are cascaded PID loops of the kind a human pilot approximates: bank angle ->
roll rate -> aileron; altitude -> climb rate -> pitch attitude -> pitch rate -> elevator; speed
-> throttle; side force -> rudder (keep the ball centred). Manoeuvres switch loops (a loop is
flown on load factor, a roll on the aileron alone) and a small seeded random stick jitter keeps
the flight from being unnaturally clean while staying reproducible.

What it flies is a scenario of `companion.sim.scenarios`; this module is the pilot's hands (the
stick laws and their state) and the one mapping between channels and surfaces.
"""

from __future__ import annotations

import math
import operator
import random
from collections.abc import Callable, Iterator, Sequence
from dataclasses import fields
from typing import NamedTuple, Protocol

from companion.core.mathutil import clamp, wrap_pi
from companion.drivers.servo_protocol import (
    CENTRE_US,
    MODE_AUTO_US,
    MODE_MANUAL_US,
    channels_to_surfaces,
    stick_to_us,
    throttle_to_us,
)
from companion.sim.aircraft import DEFAULT_AIRCRAFT, AircraftSpec, resolve_aircraft
from companion.sim.scenarios import (
    DEFAULT_SCENARIO,
    SCENARIO_PLANS,
    SCENARIOS,
    Context,
    Demand,
)
from companion.sim.truth import TruthState

__all__ = ["CHANNEL_COUNT", "FlightModelLike", "Pilot", "Surfaces", "channels_from_surfaces",
           "fly", "surfaces_from_channels"]

G_M_S2 = 9.80665
"""Standard gravity."""

CHANNEL_COUNT = 8
_ACCEPT_MIN_US = 500
_ACCEPT_MAX_US = 2500


class FlightModelLike(Protocol):
    """The part of :class:`companion.sim.flight.FlightModel` that :func:`fly` uses."""

    rate_hz: int
    dt_s: float

    @property
    def time_s(self) -> float: ...

    def truth(self) -> TruthState: ...

    def set_controls(
        self, aileron: float, elevator: float, rudder: float, throttle: float
    ) -> None: ...

    def step(self, dt_s: float) -> int: ...


class Surfaces(NamedTuple):
    """Normalised commands in JSBSim's convention, ready for ``FlightModel.set_controls``.

    aileron +1 rolls right, elevator +1 pitches nose down, rudder +1 yaws nose left,
    throttle 0 idle .. 1 full.
    """

    aileron: float
    elevator: float
    rudder: float
    throttle: float


def surfaces_from_channels(ch_us: Sequence[int]) -> Surfaces:
    """Map channels 1..4 (pulse widths, us) to JSBSim's normalised surface commands.

    Pulse widths are clipped to 1000..2000 as a servo's travel would clip them; values that no
    receiver or board would produce (outside 500..2500, non-numbers, fewer than four channels)
    raise ``ValueError`` naming the channel, rather than turning into full deflection.
    """
    if len(ch_us) < 4:
        raise ValueError(f"surfaces_from_channels: need channels 1..4, got {len(ch_us)} values")
    clipped = []
    for i in range(4):
        value = ch_us[i]
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
        ):
            raise ValueError(f"surfaces_from_channels: channel {i + 1} is not a number: {value!r}")
        if not _ACCEPT_MIN_US <= value <= _ACCEPT_MAX_US:
            raise ValueError(
                f"surfaces_from_channels: channel {i + 1} pulse width {value!r} us is outside "
                f"{_ACCEPT_MIN_US}..{_ACCEPT_MAX_US}"
            )
        clipped.append(float(value))
    return Surfaces(*channels_to_surfaces(clipped))


def channels_from_surfaces(
    aileron: float, elevator: float, rudder: float, throttle: float, *, auto: bool = False
) -> list[int]:
    """The inverse of :func:`surfaces_from_channels`: 8 pulse widths for JSBSim-style commands.

    Channel 5 is the mode switch (automatic if ``auto``), 6..8 are centred. Commands are clipped
    to their ranges; non-finite ones raise ``ValueError``.
    """
    for name, value in (
        ("aileron", aileron),
        ("elevator", elevator),
        ("rudder", rudder),
        ("throttle", throttle),
    ):
        if not math.isfinite(value):
            raise ValueError(f"channels_from_surfaces: {name} must be finite, got {value!r}")
    return _channels(roll=aileron, pull=-elevator, yaw_right=-rudder, throttle=throttle, auto=auto)


def _channels(roll: float, pull: float, yaw_right: float, throttle: float, auto: bool) -> list[int]:
    return [
        stick_to_us(roll),
        stick_to_us(pull),
        throttle_to_us(throttle),
        stick_to_us(yaw_right),
        MODE_AUTO_US if auto else MODE_MANUAL_US,
        CENTRE_US,
        CENTRE_US,
        CENTRE_US,
    ]



def _clip(x: float, limit: float) -> float:
    return clamp(x, -limit, limit)



class _Pi:
    """Proportional-integral term with a clamped integrator (anti-windup)."""

    def __init__(self, kp: float, ki: float, i_min: float, i_max: float) -> None:
        self.kp = kp
        self.ki = ki
        self.i_min = i_min
        self.i_max = i_max
        self.integral = 0.0

    def step(self, error: float, dt_s: float, hold: bool = False) -> float:
        """Output for ``error``; ``hold`` freezes the integrator while another law flies."""
        if not hold:
            self.integral = clamp(self.integral + self.ki * error * dt_s, self.i_min, self.i_max)
        return self.kp * error + self.integral





class Pilot:
    """A scripted human-like pilot flying ``scenario`` through the radio channels.

    The pilot takes its references (altitude, heading, home) from the first state it is
    shown and flies relative to them, so the same scenario works from any start. ``seed``
    drives the stick jitter and the choices of the ``mixed`` scenario: same seed, same flight.
    ``trim_throttle`` is where the throttle stick starts (best: ``FlightModel.trim_controls``;
    by default the aircraft's typical cruise setting). In the ``auto`` scenario the mode switch (channel 5) goes to automatic at ``auto_switch_s``
    and stays there; the pilot keeps flying its own stick law, so the channels stay meaningful
    whenever the computer does not ask for control.
    """

    def __init__(
        self,
        scenario: str = DEFAULT_SCENARIO,
        seed: int = 0,
        *,
        aircraft: str | AircraftSpec = DEFAULT_AIRCRAFT,
        trim_throttle: float | None = None,
        auto_switch_s: float = 20.0,
        stick_noise: float = 0.01,
    ) -> None:
        if scenario not in SCENARIO_PLANS:
            raise ValueError(f"unknown scenario {scenario!r}: choose one of {', '.join(SCENARIOS)}")
        self.spec = resolve_aircraft(aircraft)
        if trim_throttle is None:
            trim_throttle = self.spec.cruise_throttle
        for name, value, lo, hi in (
            ("trim_throttle", trim_throttle, 0.0, 1.0),
            ("auto_switch_s", auto_switch_s, 0.0, 1e9),
            ("stick_noise", stick_noise, 0.0, 0.2),
        ):
            if not (math.isfinite(value) and lo <= value <= hi):
                raise ValueError(f"Pilot: {name} must be within {lo}..{hi}, got {value!r}")
        self.scenario = scenario
        self.seed = seed
        self._trim_throttle = trim_throttle
        self._auto_switch_s = auto_switch_s
        self._noise_sigma = stick_noise
        self._rng = random.Random(seed)
        self._noise_rng = random.Random(seed + 0x5EED)
        self._noise = [0.0, 0.0, 0.0]
        self._ctx: Context | None = None
        self._plan: Iterator[Demand] | None = None
        self._last_t_s: float | None = None
        self._last_channels = _channels(0.0, 0.0, 0.0, trim_throttle, auto=False)
        self._auto = False
        self.demand = Demand()
        # Cascade gains: stick units per rad, rad/s per rad, and so on. Tuned on c172p and
        # J3Cub; they are the same for both because their control power per unit stick is close.
        self._roll_rate = _Pi(kp=0.8, ki=0.2, i_min=-0.3, i_max=0.3)
        self._pitch_rate = _Pi(kp=1.2, ki=1.0, i_min=-0.6, i_max=0.6)
        self._climb = _Pi(kp=0.02, ki=0.01, i_min=-0.15, i_max=0.15)
        self._speed = _Pi(kp=0.06, ki=0.02, i_min=0.0, i_max=1.0)
        self._yaw = _Pi(kp=0.15, ki=0.05, i_min=-0.3, i_max=0.3)

    @property
    def auto_requested(self) -> bool:
        """Whether channel 5 currently asks for automatic mode."""
        return self._auto

    def channels_us(self, t_s: float, truth: TruthState) -> list[int]:
        """The 8 pilot channels (us) at time ``t_s`` given the true state.

        Call it at the servo board's rate (50 Hz) or faster; time must not go backwards. A
        repeated time returns the previous sticks unchanged.
        """
        if not math.isfinite(t_s):
            raise ValueError(f"Pilot.channels_us: t_s must be finite, got {t_s!r}")
        if not math.isfinite(sum(_truth_values(truth))):  # one check: NaN and inf propagate
            for f in fields(truth):
                value = getattr(truth, f.name)
                if not math.isfinite(value):
                    raise ValueError(
                        f"Pilot.channels_us: truth.{f.name} is not finite ({value!r})")
        if self._last_t_s is not None:
            if t_s < self._last_t_s:
                raise ValueError(
                    f"Pilot.channels_us: time went backwards ({t_s} s after {self._last_t_s} s)"
                )
            if t_s == self._last_t_s:
                return list(self._last_channels)
        dt_s = 0.0 if self._last_t_s is None else min(t_s - self._last_t_s, 0.1)
        self._last_t_s = t_s
        ctx = self._context(t_s, dt_s, truth)
        assert self._plan is not None
        self.demand = next(self._plan)
        roll, pull, yaw_right, throttle = self._sticks(self.demand, ctx)
        self._auto = self.scenario == "auto" and t_s >= self._auto_switch_s
        self._last_channels = _channels(roll, pull, yaw_right, throttle, self._auto)
        return list(self._last_channels)

    def _context(self, t_s: float, dt_s: float, truth: TruthState) -> Context:
        if self._ctx is None:
            self._ctx = Context(
                t_s=t_s,
                dt_s=dt_s,
                truth=truth,
                spec=self.spec,
                alt_ref_m=truth.alt_m,
                heading_ref_rad=truth.yaw_rad,
                cruise_m_s=self.spec.cruise_airspeed_m_s,
            )
            self._speed.integral = self._trim_throttle
            self._plan = SCENARIO_PLANS[self.scenario](self._ctx, self._rng)
        else:
            self._ctx.t_s = t_s
            self._ctx.dt_s = dt_s
            self._ctx.truth = truth
        return self._ctx

    def _sticks(self, d: Demand, ctx: Context) -> tuple[float, float, float, float]:
        s = ctx.truth
        dt = ctx.dt_s
        v = max(s.airspeed_m_s, 0.5 * self.spec.stall_airspeed_m_s)

        # Roll: bank (or heading, through a bank demand) -> roll rate -> aileron.
        if d.roll_stick is not None:
            roll = d.roll_stick
            self._roll_rate.step(0.0, dt, hold=True)
        else:
            if d.heading_rad is not None:
                bank_cmd = _clip(1.0 * wrap_pi(d.heading_rad - s.yaw_rad), d.max_bank_rad)
            else:
                bank_cmd = d.bank_rad if d.bank_rad is not None else 0.0
            p_cmd = _clip(1.5 * wrap_pi(bank_cmd - s.roll_rad), 1.0)
            roll = self._roll_rate.step(p_cmd - s.p_rad_s, dt)

        # Pitch: altitude -> climb rate -> pitch attitude -> pitch rate -> elevator; or a pitch
        # attitude directly; or a load factor (loops), turned into the pitch rate it needs.
        cos_phi = math.cos(s.roll_rad)
        if d.pitch_rate_rad_s is not None:
            q_cmd = d.pitch_rate_rad_s
        elif d.load_factor is not None:
            q_cmd = G_M_S2 * (d.load_factor - math.cos(s.pitch_rad) * cos_phi) / v
        else:
            if d.pitch_rad is not None:
                theta_cmd = d.pitch_rad
                self._climb.step(0.0, dt, hold=True)
            else:
                alt_cmd = d.alt_m if d.alt_m is not None else s.alt_m
                climb_cmd = _clip(0.25 * (alt_cmd - s.alt_m), d.climb_limit_m_s)
                climb_err = climb_cmd - (-s.vd_m_s)
                gamma_cmd = math.asin(_clip(climb_cmd / v, 0.5))
                theta_cmd = s.alpha_rad * cos_phi + gamma_cmd + self._climb.step(climb_err, dt)
            theta_cmd = _clip(theta_cmd, math.radians(30.0))
            # A level turn needs a steady pitch rate of g sin(phi) tan(phi) / V.
            phi_ff = _clip(s.roll_rad, math.radians(60.0))
            q_turn = G_M_S2 * math.sin(phi_ff) * math.tan(phi_ff) / v
            q_cmd = 1.0 * (theta_cmd - s.pitch_rad) * max(cos_phi, 0.5) + q_turn
        # Buffet limit: never pull the wing past most of its stall angle of attack.
        q_cmd = min(q_cmd, 0.5 + 3.0 * (math.radians(12.0) - s.alpha_rad))
        # Trim learnt upright means nothing inverted or vertical: freeze it there.
        aerobatic = abs(s.roll_rad) > math.radians(70.0) or abs(s.pitch_rad) > math.radians(50.0)
        pull = self._pitch_rate.step(q_cmd - s.q_rad_s, dt, hold=aerobatic)

        # Rudder: keep the ball centred (zero side force).
        yaw_right = self._yaw.step(-s.ay_m_s2, dt)

        # Throttle: speed.
        if d.throttle is not None:
            throttle = d.throttle
            self._speed.step(0.0, dt, hold=True)
        else:
            target = d.airspeed_m_s if d.airspeed_m_s is not None else ctx.cruise_m_s
            throttle = self._speed.step(target - s.airspeed_m_s, dt)

        roll, pull, yaw_right = self._jitter(roll, pull, yaw_right, dt)
        return _clip(roll, 1.0), _clip(pull, 1.0), _clip(yaw_right, 1.0), throttle

    def _jitter(
        self, roll: float, pull: float, yaw: float, dt_s: float
    ) -> tuple[float, float, float]:
        """Add a slowly wandering hand error (first-order Gauss-Markov, ~0.5 s correlation)."""
        if self._noise_sigma <= 0.0 or dt_s <= 0.0:
            return roll, pull, yaw
        a = math.exp(-dt_s / 0.5)
        b = self._noise_sigma * math.sqrt(1.0 - a * a)
        n = self._noise
        for i in range(3):
            n[i] = a * n[i] + b * self._noise_rng.gauss(0.0, 1.0)
        return roll + n[0], pull + n[1], yaw + n[2]


_TRUTH_FIELDS = tuple(f.name for f in fields(TruthState))
_truth_values: Callable[[TruthState], tuple[float, ...]] = operator.attrgetter(*_TRUTH_FIELDS)
"""Every field of a truth state, in one call (``dataclasses.fields`` at 50 Hz cost more than
the pilot's arithmetic)."""


def fly(
    model: FlightModelLike, pilot: Pilot, duration_s: float, pilot_rate_hz: int = 50
) -> Iterator[TruthState]:
    """Fly ``pilot`` on ``model`` alone (no devices, no computer) and yield every model step.

    The pilot's channels reach the model through :func:`surfaces_from_channels`, at the servo
    board's frame rate, as they would through the simulated board in manual mode.
    """
    if not (math.isfinite(duration_s) and duration_s >= 0.0):
        raise ValueError(f"fly: duration_s must be finite and >= 0, got {duration_s!r}")
    steps_per_frame = max(1, round(model.rate_hz / pilot_rate_hz))
    n_steps = int(round(duration_s * model.rate_hz))
    t0_s = model.time_s
    for k in range(n_steps):
        truth = model.truth()
        if k % steps_per_frame == 0:
            model.set_controls(
                *surfaces_from_channels(pilot.channels_us(truth.time_s - t0_s, truth))
            )
        model.step(model.dt_s)
        yield model.truth()
