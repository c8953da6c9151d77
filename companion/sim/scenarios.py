"""The scenarios a scripted pilot flies, and the manoeuvres they are built from.

A scenario is a generator of `Demand`s (what the current manoeuvre wants: a bank, a heading, an
altitude, a load factor ...) reading a shared `Context` (the pilot's references and the latest
true state); a manoeuvre returns when it is done. The stick laws that turn a demand into stick
positions are the pilot's (`companion.sim.pilot`); this module is the catalogue of what it is
asked to fly, each entry a few lines, read as a whole.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from companion.core.mathutil import wrap_pi
from companion.sim.aircraft import AircraftSpec
from companion.sim.truth import TruthState

__all__ = ["DEFAULT_SCENARIO", "SCENARIOS", "SCENARIO_PLANS", "Context", "Demand"]

SCENARIOS = ("level", "turns", "climb", "aerobatic", "mixed", "auto")
DEFAULT_SCENARIO = "mixed"


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
class Context:
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


def _hold(ctx: Context, duration_s: float, **demand: float) -> Iterator[Demand]:
    t_end = ctx.t_s + duration_s
    while ctx.t_s < t_end:
        yield Demand(**demand)


def _cruise(ctx: Context, duration_s: float, alt_m: float, heading_rad: float) -> Iterator[Demand]:
    yield from _hold(
        ctx, duration_s, alt_m=alt_m, heading_rad=heading_rad, airspeed_m_s=ctx.cruise_m_s
    )


def _bank(ctx: Context, duration_s: float, bank_deg: float, alt_m: float) -> Iterator[Demand]:
    yield from _hold(
        ctx,
        duration_s,
        bank_rad=math.radians(bank_deg),
        alt_m=alt_m,
        airspeed_m_s=ctx.cruise_m_s,
    )


def _change_altitude(
    ctx: Context, alt_m: float, heading_rad: float, timeout_s: float = 90.0
) -> Iterator[Demand]:
    t_end = ctx.t_s + timeout_s
    while ctx.t_s < t_end and abs(ctx.truth.alt_m - alt_m) > 3.0:
        yield Demand(alt_m=alt_m, heading_rad=heading_rad, airspeed_m_s=ctx.cruise_m_s)


def _loop(ctx: Context) -> Iterator[Demand]:
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


def _roll(ctx: Context, direction: float) -> Iterator[Demand]:
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


def _recover(ctx: Context) -> Iterator[Demand]:
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


def _distance_home_m(ctx: Context) -> float:
    return math.hypot(ctx.truth.north_m, ctx.truth.east_m)


def _return_home(ctx: Context, alt_m: float, radius_m: float) -> Iterator[Demand]:
    t_end = ctx.t_s + 300.0
    while _distance_home_m(ctx) > radius_m and ctx.t_s < t_end:
        home = math.atan2(-ctx.truth.east_m, -ctx.truth.north_m)
        yield Demand(alt_m=alt_m, heading_rad=home, airspeed_m_s=ctx.cruise_m_s)


def _scenario_level(ctx: Context, rng: random.Random) -> Iterator[Demand]:
    while True:
        yield from _cruise(ctx, 60.0, ctx.alt_ref_m, ctx.heading_ref_rad)


def _scenario_turns(ctx: Context, rng: random.Random) -> Iterator[Demand]:
    while True:
        yield from _bank(ctx, 8.0, 0.0, ctx.alt_ref_m)
        yield from _bank(ctx, 20.0, 30.0, ctx.alt_ref_m)
        yield from _bank(ctx, 8.0, 0.0, ctx.alt_ref_m)
        yield from _bank(ctx, 20.0, -30.0, ctx.alt_ref_m)


def _scenario_climb(ctx: Context, rng: random.Random) -> Iterator[Demand]:
    while True:
        heading = ctx.heading_ref_rad
        yield from _cruise(ctx, 5.0, ctx.alt_ref_m, heading)
        yield from _change_altitude(ctx, ctx.alt_ref_m + 60.0, heading)
        yield from _cruise(ctx, 8.0, ctx.alt_ref_m + 60.0, heading)
        yield from _change_altitude(ctx, ctx.alt_ref_m, heading)
        # Turn round so that repeated climbs stay near the start.
        ctx.heading_ref_rad = wrap_pi(ctx.heading_ref_rad + math.pi)
        yield from _change_altitude(ctx, ctx.alt_ref_m, ctx.heading_ref_rad, timeout_s=30.0)


def _scenario_aerobatic(ctx: Context, rng: random.Random) -> Iterator[Demand]:
    direction = 1.0
    while True:
        safe_alt = ctx.alt_ref_m + 60.0
        yield from _change_altitude(ctx, safe_alt, ctx.truth.yaw_rad)
        yield from _loop(ctx)
        yield from _roll(ctx, direction)
        direction = -direction
        yield from _change_altitude(ctx, ctx.alt_ref_m, ctx.truth.yaw_rad)
        yield from _return_home(ctx, ctx.alt_ref_m, 800.0)


def _scenario_auto(ctx: Context, rng: random.Random) -> Iterator[Demand]:
    yield from _bank(ctx, 5.0, 0.0, ctx.alt_ref_m)
    while True:
        yield from _bank(ctx, 60.0, 30.0, ctx.alt_ref_m)


def _scenario_mixed(ctx: Context, rng: random.Random) -> Iterator[Demand]:
    """Random segments of everything above, kept within a few km of the start point."""
    fence_m = 1500.0
    alt_m = ctx.alt_ref_m

    def heading() -> float:
        # Far out, new headings lean homewards so that no single segment strays far.
        if _distance_home_m(ctx) > 0.5 * fence_m:
            home = math.atan2(-ctx.truth.east_m, -ctx.truth.north_m)
            return wrap_pi(home + math.radians(rng.uniform(-45.0, 45.0)))
        return wrap_pi(ctx.truth.yaw_rad + math.radians(rng.uniform(-60.0, 60.0)))

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


SCENARIO_PLANS: dict[str, Callable[[Context, random.Random], Iterator[Demand]]] = {
    "level": _scenario_level,
    "turns": _scenario_turns,
    "climb": _scenario_climb,
    "aerobatic": _scenario_aerobatic,
    "mixed": _scenario_mixed,
    "auto": _scenario_auto,
}

