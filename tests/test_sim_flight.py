"""JSBSim flight model, scripted pilot and geodesy for SITL.

The flights are real JSBSim runs (a 60 s flight costs about 0.2 s), cached per module so that
several assertions can look at one flight.
"""

from __future__ import annotations

import dataclasses
import math
from functools import cache

import pytest

from companion.core.geo import NedFrame, ecef_to_geodetic, geodetic_to_ecef
from companion.drivers.servo_protocol import AUTO_SWITCH_THRESHOLD_US
from companion.sim.aircraft import AIRCRAFT, DEFAULT_AIRCRAFT, resolve_aircraft
from companion.sim.flight import FlightModel, FlightModelError
from companion.sim.pilot import (
    CHANNEL_COUNT,
    Pilot,
    channels_from_surfaces,
    fly,
    surfaces_from_channels,
)
from companion.sim.scenarios import SCENARIOS
from companion.sim.truth import TruthState

G = 9.80665
START_ALT_M = 300.0


@dataclasses.dataclass
class Flight:
    truths: list[TruthState]
    channels: list[list[int]]  # pilot channels, one per model step (held between frames)
    start: TruthState
    model: FlightModel


@cache
def flown(aircraft: str, scenario: str, duration_s: float, seed: int = 1) -> Flight:
    """Fly a scenario with the pilot at 50 Hz, recording every 100 Hz model step."""
    model = FlightModel(aircraft, alt_m=START_ALT_M)
    pilot = Pilot(scenario, seed, aircraft=aircraft, trim_throttle=model.trim_controls.throttle)
    start = model.truth()
    truths: list[TruthState] = []
    channels: list[list[int]] = []
    ch = [0] * CHANNEL_COUNT
    for k in range(int(round(duration_s * model.rate_hz))):
        truth = model.truth()
        if k % 2 == 0:
            ch = pilot.channels_us(truth.time_s, truth)
            model.set_controls(*surfaces_from_channels(ch))
        model.step(model.dt_s)
        truths.append(model.truth())
        channels.append(ch)
    return Flight(truths, channels, start, model)


def window(flight: Flight, t0_s: float, t1_s: float) -> list[TruthState]:
    return [s for s in flight.truths if t0_s <= s.time_s <= t1_s]


# --------------------------------------------------------------------------------------------
# flight model: trim, conventions, time


@pytest.mark.parametrize("aircraft", sorted(AIRCRAFT))
def test_trim_holds_level_flight_hands_off(aircraft: str) -> None:
    model = FlightModel(aircraft, alt_m=START_ALT_M, heading_deg=30.0)
    assert model.trim_method == "full"
    start = model.truth()
    assert start.time_s == 0.0
    assert abs(start.alt_m - START_ALT_M) < 0.01
    assert abs(start.airspeed_m_s - AIRCRAFT[aircraft].cruise_airspeed_m_s) < 0.05
    # Centred controls are the trim: the trim offsets live in the trim tabs.
    assert model.controls().aileron == 0.0 and model.controls().elevator == 0.0
    worst_alt = worst_roll = 0.0
    for _ in range(30):
        model.step(1.0)
        s = model.truth()
        worst_alt = max(worst_alt, abs(s.alt_m - start.alt_m))
        worst_roll = max(worst_roll, abs(s.roll_rad))
    assert model.time_s == pytest.approx(30.0)
    assert worst_alt < 3.0
    assert math.degrees(worst_roll) < 2.0
    assert abs(s.airspeed_m_s - start.airspeed_m_s) < 1.0
    assert math.degrees(abs(s.yaw_rad - math.radians(30.0))) < 3.0


def test_level_flight_sign_conventions() -> None:
    model = FlightModel(DEFAULT_AIRCRAFT, alt_m=START_ALT_M, heading_deg=30.0)
    start = model.truth()
    model.step(20.0)
    s = model.truth()
    # An accelerometer in level flight reads the reaction to gravity: up, i.e. -z body.
    assert s.az_m_s2 == pytest.approx(-G, abs=0.15)
    assert abs(s.ay_m_s2) < 0.2 and abs(s.ax_m_s2) < 0.5
    assert abs(s.vd_m_s) < 0.2
    # Flying at heading 30 deg: north and east both grow, in the ratio of the heading.
    assert s.north_m > 0 and s.east_m > 0
    assert math.degrees(math.atan2(s.east_m, s.north_m)) == pytest.approx(30.0, abs=1.0)
    assert math.degrees(math.atan2(s.ve_m_s, s.vn_m_s)) == pytest.approx(30.0, abs=1.0)
    assert math.hypot(s.north_m, s.east_m) == pytest.approx(20.0 * start.airspeed_m_s, rel=0.02)
    # Down is minus the altitude change (plus earth curvature, 8 cm per km squared).
    assert s.down_m == pytest.approx(-(s.alt_m - start.alt_m), abs=0.2)


def test_stick_directions_move_the_aircraft_the_documented_way() -> None:
    def response(channel: int, pulse_us: int) -> TruthState:
        model = FlightModel(DEFAULT_AIRCRAFT, alt_m=START_ALT_M)
        ch = channels_from_surfaces(*dataclasses.astuple(model.trim_controls))
        ch[channel - 1] = pulse_us
        model.set_controls(*surfaces_from_channels(ch))
        model.step(1.0)
        return model.truth()

    right = response(1, 1700)
    assert right.p_rad_s > 0.05 and right.roll_rad > math.radians(5.0)  # right bank: roll > 0
    left = response(1, 1300)
    assert left.p_rad_s < -0.05 and left.roll_rad < -math.radians(5.0)
    up = response(2, 1650)
    assert up.pitch_rad > math.radians(3.0) and up.vd_m_s < 0.0  # nose up, climbing: vd < 0
    down = response(2, 1350)
    assert down.pitch_rad < -math.radians(3.0) and down.vd_m_s > 0.0
    yaw_right = response(4, 1800)
    assert yaw_right.r_rad_s > 0.0 and yaw_right.yaw_rad > 0.0
    # Pedal alone skids: the nose points right of the airflow (beta < 0) and the fuselage's
    # side force pushes right (positive y).
    assert yaw_right.beta_rad < 0.0 and yaw_right.ay_m_s2 > 0.0


def test_climb_has_negative_down_velocity_and_coordinated_turn_loads() -> None:
    climb = flown(DEFAULT_AIRCRAFT, "climb", 60.0)
    climbing = window(climb, 10.0, 20.0)
    assert climbing[-1].alt_m - climbing[0].alt_m > 10.0
    assert all(s.vd_m_s < 0.0 for s in climbing)
    assert all(s.down_m < 0.0 for s in climbing)
    assert sum(s.pitch_rad for s in climbing) / len(climbing) > 0.0

    turns = flown(DEFAULT_AIRCRAFT, "turns", 60.0)
    right = window(turns, 18.0, 26.0)  # steady right turn at 30 deg
    for s in right:
        assert s.roll_rad > math.radians(25.0)
        assert s.r_rad_s > 0.0  # heading increasing
        # Level turn: load factor 1/cos(bank), felt along -z body; the ball stays centred.
        assert -s.az_m_s2 == pytest.approx(G / math.cos(s.roll_rad), rel=0.06)
        assert abs(s.ay_m_s2) < 0.3
    heading_change = math.degrees(right[-1].yaw_rad - right[0].yaw_rad)
    expected = math.degrees(G * math.tan(math.radians(30.0)) / 50.0) * (8.0 - 0.01)
    assert heading_change == pytest.approx(expected, rel=0.15)


def test_ned_position_is_the_integral_of_ned_velocity() -> None:
    flight = flown(DEFAULT_AIRCRAFT, "turns", 60.0)
    dt = flight.model.dt_s
    n = e = d = 0.0
    prev = flight.start
    for s in flight.truths:
        n += 0.5 * (prev.vn_m_s + s.vn_m_s) * dt
        e += 0.5 * (prev.ve_m_s + s.ve_m_s) * dt
        d += 0.5 * (prev.vd_m_s + s.vd_m_s) * dt
        prev = s
    last = flight.truths[-1]
    assert math.hypot(last.north_m, last.east_m) > 1000.0
    assert last.north_m == pytest.approx(n, abs=1.5)
    assert last.east_m == pytest.approx(e, abs=1.5)
    assert last.down_m == pytest.approx(d, abs=1.5)
    back = flight.model.frame.to_geodetic(last.north_m, last.east_m, last.down_m)
    assert back[0] == pytest.approx(last.lat_deg, abs=1e-9)
    assert back[1] == pytest.approx(last.lon_deg, abs=1e-9)
    assert back[2] == pytest.approx(last.alt_m, abs=1e-3)


def test_steady_wind_carries_the_aircraft() -> None:
    wind = (5.0, -3.0, 0.0)
    model = FlightModel(DEFAULT_AIRCRAFT, alt_m=START_ALT_M, heading_deg=90.0, wind_ned_m_s=wind)
    assert model.trim_method == "full"
    model.step(10.0)
    s = model.truth()
    assert s.airspeed_m_s == pytest.approx(50.0, abs=0.3)
    assert s.yaw_rad == pytest.approx(math.radians(90.0), abs=math.radians(1.0))
    # Ground velocity = air velocity along the heading + wind.
    assert s.vn_m_s == pytest.approx(wind[0], abs=0.5)
    assert s.ve_m_s == pytest.approx(50.0 + wind[1], abs=0.5)
    assert abs(s.alt_m - START_ALT_M) < 1.0


def test_turbulence_is_off_by_default_and_seeded_when_on() -> None:
    def max_rate(severity: int, seed: int) -> tuple[float, float]:
        model = FlightModel(DEFAULT_AIRCRAFT, turbulence_severity=severity, seed=seed)
        worst = 0.0
        for _ in range(500):
            model.step(0.01)
            worst = max(worst, abs(model.truth().p_rad_s))
        return worst, model.truth().roll_rad

    calm = max_rate(0, 1)
    assert calm[0] < 0.005
    rough = max_rate(4, 7)
    assert rough[0] > 0.02
    assert max_rate(4, 7) == rough  # same seed, same air


def test_step_time_accounting_and_imu_rate() -> None:
    model = FlightModel(DEFAULT_AIRCRAFT)
    assert model.rate_hz == 100 and model.dt_s == 0.01
    steps = [model.step(1.0 / 30.0) for _ in range(30)]
    assert sum(steps) == 100  # frames of 1/30 s: no drift, no lost step
    assert set(steps) <= {3, 4}
    assert model.time_s == pytest.approx(1.0)
    assert model.step(0.0) == 0
    fast = FlightModel(DEFAULT_AIRCRAFT, rate_hz=200)
    assert fast.step(0.01) == 2  # two model steps per IMU sample
    with pytest.raises(ValueError, match="multiple of 100"):
        FlightModel(DEFAULT_AIRCRAFT, rate_hz=120)


def test_truth_contract() -> None:
    names = [f.name for f in dataclasses.fields(TruthState)]
    assert names[:20] == [
        "time_s",
        "lat_deg",
        "lon_deg",
        "alt_m",
        "north_m",
        "east_m",
        "down_m",
        "vn_m_s",
        "ve_m_s",
        "vd_m_s",
        "roll_rad",
        "pitch_rad",
        "yaw_rad",
        "p_rad_s",
        "q_rad_s",
        "r_rad_s",
        "ax_m_s2",
        "ay_m_s2",
        "az_m_s2",
        "airspeed_m_s",
    ]
    model = FlightModel("j3cub", lat_deg=-33.9, lon_deg=151.2, alt_m=120.0, heading_deg=200.0)
    s = model.truth()
    assert s.lat_deg == pytest.approx(-33.9) and s.lon_deg == pytest.approx(151.2)
    assert -math.pi < s.yaw_rad <= math.pi
    assert s.yaw_rad == pytest.approx(math.radians(200.0 - 360.0), abs=1e-3)
    assert (s.north_m, s.east_m) == (pytest.approx(0.0, abs=1e-6), pytest.approx(0.0, abs=1e-6))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"aircraft": "b52"}, "unknown aircraft"),
        ({"alt_m": 5.0}, "alt_m"),
        ({"alt_m": float("nan")}, "alt_m must be finite"),
        ({"lat_deg": 95.0}, "lat_deg"),
        ({"airspeed_m_s": 200.0}, "airspeed_m_s"),
        ({"wind_ned_m_s": (1.0, 2.0)}, "3 components"),
        ({"wind_ned_m_s": (45.0, 0.0, 0.0)}, "too strong"),
        ({"turbulence_severity": 9}, "turbulence_severity"),
        ({"trim_methods": ("magic",)}, "trim_methods"),
    ],
)
def test_bad_configuration_is_a_clear_error(kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        FlightModel(**kwargs)  # type: ignore[arg-type]


def test_bad_runtime_input_is_a_clear_error() -> None:
    model = FlightModel(DEFAULT_AIRCRAFT)
    with pytest.raises(ValueError, match="dt_s"):
        model.step(float("nan"))
    with pytest.raises(ValueError, match="dt_s"):
        model.step(-0.01)
    with pytest.raises(ValueError, match="elevator"):
        model.set_controls(0.0, float("inf"), 0.0, 0.5)
    model.set_controls(3.0, -3.0, 0.5, 7.0)  # out of range is clipped like servo travel
    assert model.controls().aileron == 1.0 and model.controls().throttle == 1.0
    assert resolve_aircraft("C172P").jsbsim_model == "c172p"
    with pytest.raises(KeyError, match="no property"):
        model.property("no/such-property")


def test_settle_fallback_when_jsbsim_trim_fails() -> None:
    # At 70 m/s a c172p needs all its power: JSBSim's trim gives up, the settle fallback finds
    # the steady state and no second JSBSim trim succeeds either.
    model = FlightModel(DEFAULT_AIRCRAFT, alt_m=START_ALT_M, airspeed_m_s=70.0)
    assert model.trim_method == "settle"
    start = model.truth()
    assert start.airspeed_m_s == pytest.approx(70.0, abs=2.0)
    assert abs(math.degrees(start.roll_rad)) < 1.0
    pilot = Pilot("level", 1, trim_throttle=model.trim_controls.throttle)
    worst = max(abs(s.alt_m - start.alt_m) for s in fly(model, pilot, 30.0))
    assert worst < 25.0


def test_settle_only_trim_agrees_with_jsbsim_trim() -> None:
    full = FlightModel("j3cub")
    settled = FlightModel("j3cub", trim_methods=("settle",))
    assert settled.trim_method in ("settle+full", "settle")
    assert settled.trim_controls.throttle == pytest.approx(full.trim_controls.throttle, abs=0.05)
    settled.step(20.0)
    assert abs(settled.truth().alt_m - 300.0) < 10.0


def test_untrimmable_start_is_a_clear_error() -> None:
    with pytest.raises(FlightModelError, match="could not trim c172p"):
        FlightModel(DEFAULT_AIRCRAFT, airspeed_m_s=80.0)


# --------------------------------------------------------------------------------------------
# scenarios


@pytest.mark.parametrize("aircraft", sorted(AIRCRAFT))
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_scenario_stays_within_sane_bounds(aircraft: str, scenario: str) -> None:
    spec = AIRCRAFT[aircraft]
    flight = flown(aircraft, scenario, 60.0)
    assert len(flight.truths) == 6000
    for s in flight.truths:
        for f in dataclasses.fields(s):
            assert math.isfinite(getattr(s, f.name)), (f.name, s.time_s)
        assert s.alt_m > max(START_ALT_M - 100.0, 50.0), s
        assert 0.5 * spec.stall_airspeed_m_s < s.airspeed_m_s < spec.never_exceed_m_s, s
    for ch in flight.channels:
        assert len(ch) == CHANNEL_COUNT
        assert all(1000 <= us <= 2000 for us in ch)


@pytest.mark.parametrize("aircraft", sorted(AIRCRAFT))
def test_turns_reach_thirty_degrees_both_ways(aircraft: str) -> None:
    flight = flown(aircraft, "turns", 60.0)
    rolls = [math.degrees(s.roll_rad) for s in flight.truths]
    assert 27.0 < max(rolls) < 37.0
    assert -37.0 < min(rolls) < -27.0
    alts = [s.alt_m for s in flight.truths]
    assert max(alts) - min(alts) < 15.0  # a pilot holds altitude through the turns


@pytest.mark.parametrize("aircraft", sorted(AIRCRAFT))
def test_aerobatic_flies_a_loop_and_a_roll(aircraft: str) -> None:
    flight = flown(aircraft, "aerobatic", 90.0)
    start = flight.start
    pitches = [math.degrees(s.pitch_rad) for s in flight.truths]
    assert max(pitches) > 70.0 and min(pitches) < -45.0  # through the vertical both ways
    assert max(-s.az_m_s2 / G for s in flight.truths) > 2.5  # pulled g
    inverted = [s for s in flight.truths if abs(s.roll_rad) > math.radians(160.0)]
    assert inverted
    rolled_right = [s for s in flight.truths if 60.0 < math.degrees(s.roll_rad) < 120.0]
    assert rolled_right  # the roll passes through knife edge
    spec = AIRCRAFT[aircraft]
    for s in flight.truths:
        assert s.alt_m > start.alt_m - 100.0
        assert s.airspeed_m_s < spec.never_exceed_m_s


def test_level_scenario_holds_altitude_speed_and_heading() -> None:
    flight = flown(DEFAULT_AIRCRAFT, "level", 60.0)
    for s in flight.truths:
        assert abs(s.alt_m - flight.start.alt_m) < 3.0
        assert abs(s.airspeed_m_s - 50.0) < 1.5
        assert abs(math.degrees(s.yaw_rad)) < 3.0
    # The pilot's hand is not perfectly still.
    assert len({ch[0] for ch in flight.channels}) > 5


def test_auto_scenario_switches_to_automatic_at_twenty_seconds() -> None:
    flight = flown(DEFAULT_AIRCRAFT, "auto", 60.0)
    for s, ch in zip(flight.truths, flight.channels, strict=True):
        if s.time_s <= 19.98:
            assert ch[4] < AUTO_SWITCH_THRESHOLD_US
        elif s.time_s >= 20.02:
            assert ch[4] > AUTO_SWITCH_THRESHOLD_US
    banked = window(flight, 15.0, 20.0)
    assert all(abs(math.degrees(s.roll_rad) - 30.0) < 4.0 for s in banked)


def test_mixed_long_flight_stays_near_home() -> None:
    model = FlightModel(DEFAULT_AIRCRAFT, alt_m=START_ALT_M)
    pilot = Pilot("mixed", 3, trim_throttle=model.trim_controls.throttle)
    alts, speeds, distances = [], [], []
    for s in fly(model, pilot, 600.0):
        alts.append(s.alt_m)
        speeds.append(s.airspeed_m_s)
        distances.append(math.hypot(s.north_m, s.east_m))
    assert min(alts) > START_ALT_M - 100.0 and max(alts) < START_ALT_M + 400.0
    assert min(speeds) > 0.5 * 25.0 and max(speeds) < 82.0
    assert max(distances) < 6000.0
    assert max(alts) - min(alts) > 50.0  # it does climb and descend


def test_pilot_is_deterministic_per_seed() -> None:
    def channels(seed: int) -> list[list[int]]:
        model = FlightModel(DEFAULT_AIRCRAFT)
        pilot = Pilot("mixed", seed)
        out = []
        for k in range(3000):
            truth = model.truth()
            if k % 2 == 0:
                out.append(pilot.channels_us(truth.time_s, truth))
                model.set_controls(*surfaces_from_channels(out[-1]))
            model.step(0.01)
        return out

    first = channels(5)
    assert channels(5) == first
    assert channels(6) != first


def test_pilot_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="unknown scenario"):
        Pilot("barrel-roll")
    with pytest.raises(ValueError, match="trim_throttle"):
        Pilot("level", trim_throttle=1.5)
    model = FlightModel(DEFAULT_AIRCRAFT)
    pilot = Pilot("level")
    truth = model.truth()
    first = pilot.channels_us(1.0, truth)
    assert pilot.channels_us(1.0, truth) == first  # same instant, same sticks
    with pytest.raises(ValueError, match="backwards"):
        pilot.channels_us(0.5, truth)
    with pytest.raises(ValueError, match="truth.roll_rad"):
        pilot.channels_us(2.0, dataclasses.replace(truth, roll_rad=float("nan")))
    with pytest.raises(ValueError, match="t_s"):
        pilot.channels_us(float("inf"), truth)


# --------------------------------------------------------------------------------------------
# channel mapping


def test_channel_mapping_conventions_and_round_trip() -> None:
    assert surfaces_from_channels([1500, 1500, 1000, 1500]) == (0.0, 0.0, 0.0, 0.0)
    full = surfaces_from_channels([2000, 2000, 2000, 2000, 2000, 1500, 1500, 1500])
    # Above centre: roll right (+aileron), nose up (JSBSim elevator -), nose right (rudder -).
    assert full == (1.0, -1.0, -1.0, 1.0)
    assert surfaces_from_channels([2200, 800, 2400, 600]) == (1.0, 1.0, 1.0, 1.0)  # clipped
    for surfaces in [(0.3, -0.2, 0.1, 0.65), (-1.0, 1.0, -0.5, 0.0), (0.002, 0.0, 0.0, 1.0)]:
        ch = channels_from_surfaces(*surfaces)
        assert len(ch) == CHANNEL_COUNT and ch[4] < AUTO_SWITCH_THRESHOLD_US
        assert surfaces_from_channels(ch) == pytest.approx(surfaces, abs=0.002)
    assert channels_from_surfaces(0, 0, 0, 0, auto=True)[4] > AUTO_SWITCH_THRESHOLD_US
    assert channels_from_surfaces(5.0, -5.0, 0.0, -1.0)[:4] == [2000, 2000, 1000, 1500]


@pytest.mark.parametrize(
    ("channels", "match"),
    [
        ([1500, 1500, 1000], "need channels 1..4"),
        ([1500, 0, 1000, 1500], "channel 2 pulse width 0"),
        ([1500, 1500, 3000, 1500], "channel 3"),
        ([1500, 1500, 1000, float("nan")], "channel 4 is not a number"),
        ([None, 1500, 1000, 1500], "channel 1 is not a number"),
    ],
)
def test_channel_mapping_rejects_impossible_pulses(channels: list[object], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        surfaces_from_channels(channels)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="rudder"):
        channels_from_surfaces(0.0, 0.0, float("nan"), 0.5)


# --------------------------------------------------------------------------------------------
# geodesy


def test_ecef_known_points_and_round_trip() -> None:
    assert geodetic_to_ecef(0.0, 0.0, 0.0) == pytest.approx((6378137.0, 0.0, 0.0))
    assert geodetic_to_ecef(90.0, 0.0, 0.0)[2] == pytest.approx(6356752.314245, abs=1e-3)
    for lat, lon, alt in [(43.68, 10.39, 300.0), (-33.9, 151.2, -20.0), (89.99, -120.0, 5000.0)]:
        back = ecef_to_geodetic(*geodetic_to_ecef(lat, lon, alt))
        assert back == pytest.approx((lat, lon, alt), abs=1e-6)
    assert ecef_to_geodetic(0.0, 0.0, 6356852.0)[0] == 90.0  # on the axis
    with pytest.raises(ValueError, match="lat_deg"):
        geodetic_to_ecef(91.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="z_m must be finite"):
        ecef_to_geodetic(1.0, 2.0, float("nan"))


def test_ned_frame() -> None:
    frame = NedFrame(43.68, 10.39, 300.0)
    assert frame.to_ned(43.68, 10.39, 400.0) == pytest.approx((0.0, 0.0, -100.0), abs=1e-6)
    north = frame.to_ned(43.69, 10.39, 300.0)
    assert north[0] == pytest.approx(1111.0, rel=0.005) and abs(north[1]) < 1e-6
    assert north[2] == pytest.approx(1111.0**2 / (2 * 6.37e6), rel=0.02)  # curvature
    east = frame.to_ned(43.68, 10.40, 300.0)
    assert east[1] == pytest.approx(1111.0 * math.cos(math.radians(43.68)), rel=0.005)
    for ned in [(1000.0, 0.0, 0.0), (-250.0, 3000.0, -120.0), (0.0, 0.0, 50.0)]:
        assert frame.to_ned(*frame.to_geodetic(*ned)) == pytest.approx(ned, abs=1e-3)
    with pytest.raises(ValueError, match="east_m"):
        frame.to_geodetic(0.0, float("inf"), 0.0)
    with pytest.raises(ValueError, match="NedFrame reference"):
        NedFrame(100.0, 0.0, 0.0)


def test_hitting_the_ground_ends_the_flight_with_a_clear_error() -> None:
    model = FlightModel(DEFAULT_AIRCRAFT, alt_m=60.0)
    model.set_controls(0.0, 0.6, 0.0, 0.0)  # stick forward, idle: straight into the ground
    with pytest.raises(FlightModelError, match="hit the ground at t="):
        model.step(60.0)
    assert model.time_s < 30.0
