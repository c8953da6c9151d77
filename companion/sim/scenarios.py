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

Size: a library of manoeuvres and the scenarios built from them, each a few lines; one file
keeps the catalogue readable as a whole.
"""

from __future__ import annotations

import math
import operator
import random
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, fields
from typing import NamedTuple, Protocol

from companion.core.mathutil import clamp
from companion.drivers.servo_protocol import (
    CENTRE_US,
    MODE_AUTO_US,
    MODE_MANUAL_US,
    channels_to_surfaces,
    stick_to_us,
    throttle_to_us,
)
from companion.sim.flight import DEFAULT_AIRCRAFT, AircraftSpec, TruthState, resolve_aircraft

G_M_S2 = 9.80665
"""Standard gravity."""

CHANNEL_COUNT = 8
_ACCEPT_MIN_US = 500
_ACCEPT_MAX_US = 2500

SCENARIOS = ("level", "turns", "climb", "aerobatic", "mixed", "auto")
DEFAULT_SCENARIO = "mixed"


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


def _wrap(angle_rad: float) -> float:
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


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


@dataclass
class Demand:
    """What the current manoeuvre wants; the stick laws turn it into stick positions.

    One roll source (``roll_stick``, else ``heading_rad``, else ``bank_rad``, else wings
    level), one pitch source (``pitch_rate_rad_s``, else ``load_factor``, else ``pitch_rad``,
    else ``alt_m``, else the current altitude) and one throttle source (``throttle``, else
    ``airspeed_m_s``, else cruise speed) is used.
    """

    bank_rad: float | None = None
    heading_rad: float | None = None
    roll_stick: float | None = None
    alt_m: float | None = None
    pitch_rad: float | None = None
    load_factor: float | None = None
    pitch_rate_rad_s: float | None = None
    airspeed_m_s: float | None = None
    throttle: float | None = None
    climb_limit_m_s: float = 2.5
    max_bank_rad: float = math.radians(30.0)


@dataclass
class _Context:
    """What manoeuvres may read: the pilot's references and the latest state."""

    t_s: float
    dt_s: float
    truth: TruthState
    spec: AircraftSpec
    alt_ref_m: float
    heading_ref_rad: float
    cruise_m_s: float


# Manoeuvres and scenarios are generators: the pilot updates the shared context each tick and
# asks for the next Demand; a manoeuvre returns when it is done. Generators keep each
# manoeuvre's little state machine readable top to bottom.


def _hold(ctx: _Context, duration_s: float, **demand: float) -> Iterator[Demand]:
    t_end = ctx.t_s + duration_s
    while ctx.t_s < t_end:
        yield Demand(**demand)


def _cruise(ctx: _Context, duration_s: float, alt_m: float, heading_rad: float) -> Iterator[Demand]:
    yield from _hold(
        ctx, duration_s, alt_m=alt_m, heading_rad=heading_rad, airspeed_m_s=ctx.cruise_m_s
    )


def _bank(ctx: _Context, duration_s: float, bank_deg: float, alt_m: float) -> Iterator[Demand]:
    yield from _hold(
        ctx,
        duration_s,
        bank_rad=math.radians(bank_deg),
        alt_m=alt_m,
        airspeed_m_s=ctx.cruise_m_s,
    )


def _change_altitude(
    ctx: _Context, alt_m: float, heading_rad: float, timeout_s: float = 90.0
) -> Iterator[Demand]:
    t_end = ctx.t_s + timeout_s
    while ctx.t_s < t_end and abs(ctx.truth.alt_m - alt_m) > 3.0:
        yield Demand(alt_m=alt_m, heading_rad=heading_rad, airspeed_m_s=ctx.cruise_m_s)


def _loop(ctx: _Context) -> Iterator[Demand]:
    """An inside loop: dive for entry speed, pull as hard as the wing allows, recover level."""
    spec = ctx.spec
    heading = ctx.truth.yaw_rad
    t_end = ctx.t_s + 40.0
    while ctx.truth.airspeed_m_s < spec.loop_entry_airspeed_m_s and ctx.t_s < t_end:
        yield Demand(pitch_rad=math.radians(-12.0), heading_rad=heading, throttle=1.0)
    if ctx.truth.airspeed_m_s < spec.loop_entry_airspeed_m_s:
        return  # never reached entry speed: give up on the loop
    turned_rad = 0.0
    t_end = ctx.t_s + 30.0
    while turned_rad < 2.0 * math.pi - 0.5 and ctx.t_s < t_end:
        v = max(ctx.truth.airspeed_m_s, 1.0)
        # The wing stalls at (V/Vs)^2 g: pull to most of that, never past the pilot's limit.
        n_max = 0.8 * (v / spec.stall_airspeed_m_s) ** 2
        over_top = math.pi * 0.6 < turned_rad < math.pi * 1.4
        yield Demand(
            roll_stick=0.0,
            load_factor=max(min(spec.max_load_factor, n_max), 1.0 if over_top else 2.0),
            throttle=0.0 if turned_rad > math.pi * 1.2 else 1.0,
        )
        turned_rad += ctx.truth.q_rad_s * ctx.dt_s
    yield from _recover(ctx)


def _roll(ctx: _Context, direction: float) -> Iterator[Demand]:
    """An aileron roll: gain speed, raise the nose, full aileron with the elevator holding the
    nose's direction (no pitch rate) until upright again, recover."""
    entry_m_s = 0.9 * ctx.spec.loop_entry_airspeed_m_s
    heading = ctx.truth.yaw_rad
    t_end = ctx.t_s + 40.0
    while ctx.truth.airspeed_m_s < entry_m_s and ctx.t_s < t_end:
        yield Demand(pitch_rad=math.radians(-10.0), heading_rad=heading, throttle=1.0)
    t_end = ctx.t_s + 15.0
    while ctx.truth.pitch_rad < math.radians(25.0) and ctx.t_s < t_end:
        yield Demand(pitch_rad=math.radians(30.0), bank_rad=0.0, throttle=1.0)
    rolled_rad = 0.0
    t_end = ctx.t_s + 15.0
    while abs(rolled_rad) < 2.0 * math.pi - 0.4 and ctx.t_s < t_end:
        yield Demand(roll_stick=direction, pitch_rate_rad_s=0.0, throttle=1.0)
        rolled_rad += ctx.truth.p_rad_s * ctx.dt_s
    yield from _recover(ctx)


def _recover(ctx: _Context) -> Iterator[Demand]:
    """Roll wings level, pull out of any dive at a safe load factor, then hold altitude."""
    t_end = ctx.t_s + 20.0
    while ctx.t_s < t_end:
        truth = ctx.truth
        if abs(truth.roll_rad) > math.radians(60.0):
            yield Demand(bank_rad=0.0, load_factor=1.0, throttle=0.0)
        elif truth.pitch_rad < math.radians(-5.0) or truth.vd_m_s > 3.0:
            yield Demand(bank_rad=0.0, load_factor=2.5, throttle=0.3)
        else:
            break
    yield from _hold(ctx, 3.0, bank_rad=0.0, alt_m=ctx.truth.alt_m, airspeed_m_s=ctx.cruise_m_s)


def _distance_home_m(ctx: _Context) -> float:
    return math.hypot(ctx.truth.north_m, ctx.truth.east_m)


def _return_home(ctx: _Context, alt_m: float, radius_m: float) -> Iterator[Demand]:
    t_end = ctx.t_s + 300.0
    while _distance_home_m(ctx) > radius_m and ctx.t_s < t_end:
        home = math.atan2(-ctx.truth.east_m, -ctx.truth.north_m)
        yield Demand(alt_m=alt_m, heading_rad=home, airspeed_m_s=ctx.cruise_m_s)


def _scenario_level(ctx: _Context, rng: random.Random) -> Iterator[Demand]:
    while True:
        yield from _cruise(ctx, 60.0, ctx.alt_ref_m, ctx.heading_ref_rad)


def _scenario_turns(ctx: _Context, rng: random.Random) -> Iterator[Demand]:
    while True:
        yield from _bank(ctx, 8.0, 0.0, ctx.alt_ref_m)
        yield from _bank(ctx, 20.0, 30.0, ctx.alt_ref_m)
        yield from _bank(ctx, 8.0, 0.0, ctx.alt_ref_m)
        yield from _bank(ctx, 20.0, -30.0, ctx.alt_ref_m)


def _scenario_climb(ctx: _Context, rng: random.Random) -> Iterator[Demand]:
    while True:
        heading = ctx.heading_ref_rad
        yield from _cruise(ctx, 5.0, ctx.alt_ref_m, heading)
        yield from _change_altitude(ctx, ctx.alt_ref_m + 60.0, heading)
        yield from _cruise(ctx, 8.0, ctx.alt_ref_m + 60.0, heading)
        yield from _change_altitude(ctx, ctx.alt_ref_m, heading)
        # Turn round so that repeated climbs stay near the start.
        ctx.heading_ref_rad = _wrap(ctx.heading_ref_rad + math.pi)
        yield from _change_altitude(ctx, ctx.alt_ref_m, ctx.heading_ref_rad, timeout_s=30.0)


def _scenario_aerobatic(ctx: _Context, rng: random.Random) -> Iterator[Demand]:
    direction = 1.0
    while True:
        safe_alt = ctx.alt_ref_m + 60.0
        yield from _change_altitude(ctx, safe_alt, ctx.truth.yaw_rad)
        yield from _loop(ctx)
        yield from _roll(ctx, direction)
        direction = -direction
        yield from _change_altitude(ctx, ctx.alt_ref_m, ctx.truth.yaw_rad)
        yield from _return_home(ctx, ctx.alt_ref_m, 800.0)


def _scenario_auto(ctx: _Context, rng: random.Random) -> Iterator[Demand]:
    yield from _bank(ctx, 5.0, 0.0, ctx.alt_ref_m)
    while True:
        yield from _bank(ctx, 60.0, 30.0, ctx.alt_ref_m)


def _scenario_mixed(ctx: _Context, rng: random.Random) -> Iterator[Demand]:
    """Random segments of everything above, kept within a few km of the start point."""
    fence_m = 1500.0
    alt_m = ctx.alt_ref_m

    def heading() -> float:
        # Far out, new headings lean homewards so that no single segment strays far.
        if _distance_home_m(ctx) > 0.5 * fence_m:
            home = math.atan2(-ctx.truth.east_m, -ctx.truth.north_m)
            return _wrap(home + math.radians(rng.uniform(-45.0, 45.0)))
        return _wrap(ctx.truth.yaw_rad + math.radians(rng.uniform(-60.0, 60.0)))

    while True:
        if _distance_home_m(ctx) > fence_m:
            yield from _return_home(ctx, alt_m, fence_m / 3.0)
            continue
        high_enough = ctx.truth.alt_m > ctx.alt_ref_m + 30.0
        pick = rng.random()
        if pick < 0.30:
            ctx.cruise_m_s = ctx.spec.cruise_airspeed_m_s * rng.uniform(0.85, 1.15)
            yield from _cruise(ctx, rng.uniform(10.0, 30.0), alt_m, heading())
        elif pick < 0.60:
            bank = rng.choice((-1.0, 1.0)) * rng.uniform(15.0, 30.0)
            yield from _bank(ctx, rng.uniform(10.0, 25.0), bank, alt_m)
            yield from _bank(ctx, 3.0, 0.0, alt_m)
        elif pick < 0.80 or not high_enough:
            alt_m = ctx.alt_ref_m + rng.uniform(0.0 if high_enough else 60.0, 150.0)
            yield from _change_altitude(ctx, alt_m, heading())
        elif pick < 0.90:
            yield from _loop(ctx)
            yield from _change_altitude(ctx, alt_m, heading())
        else:
            yield from _roll(ctx, rng.choice((-1.0, 1.0)))
            yield from _change_altitude(ctx, alt_m, heading())


_SCENARIO_FUNCS = {
    "level": _scenario_level,
    "turns": _scenario_turns,
    "climb": _scenario_climb,
    "aerobatic": _scenario_aerobatic,
    "mixed": _scenario_mixed,
    "auto": _scenario_auto,
}


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
        if scenario not in _SCENARIO_FUNCS:
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
        self._ctx: _Context | None = None
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

    def _context(self, t_s: float, dt_s: float, truth: TruthState) -> _Context:
        if self._ctx is None:
            self._ctx = _Context(
                t_s=t_s,
                dt_s=dt_s,
                truth=truth,
                spec=self.spec,
                alt_ref_m=truth.alt_m,
                heading_ref_rad=truth.yaw_rad,
                cruise_m_s=self.spec.cruise_airspeed_m_s,
            )
            self._speed.integral = self._trim_throttle
            self._plan = _SCENARIO_FUNCS[self.scenario](self._ctx, self._rng)
        else:
            self._ctx.t_s = t_s
            self._ctx.dt_s = dt_s
            self._ctx.truth = truth
        return self._ctx

    def _sticks(self, d: Demand, ctx: _Context) -> tuple[float, float, float, float]:
        s = ctx.truth
        dt = ctx.dt_s
        v = max(s.airspeed_m_s, 0.5 * self.spec.stall_airspeed_m_s)

        # Roll: bank (or heading, through a bank demand) -> roll rate -> aileron.
        if d.roll_stick is not None:
            roll = d.roll_stick
            self._roll_rate.step(0.0, dt, hold=True)
        else:
            if d.heading_rad is not None:
                bank_cmd = _clip(1.0 * _wrap(d.heading_rad - s.yaw_rad), d.max_bank_rad)
            else:
                bank_cmd = d.bank_rad if d.bank_rad is not None else 0.0
            p_cmd = _clip(1.5 * _wrap(bank_cmd - s.roll_rad), 1.0)
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
