"""The aircraft a SITL flight can fly: one JSBSim model each, with the speeds a pilot needs.

Its own module because the pilot (`companion.sim.pilot`), the scenarios and the tests read the
catalogue without loading JSBSim; the flight model (`companion.sim.flight`) loads the model a
spec names.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["AIRCRAFT", "DEFAULT_AIRCRAFT", "AircraftSpec", "resolve_aircraft"]


@dataclass(frozen=True)
class AircraftSpec:
    """One flyable JSBSim model and the speeds a pilot needs to know to fly it sensibly.

    Speeds are true airspeeds near sea level; the scripted pilot uses them as targets and
    limits, the tests as sanity bounds. ``cruise_throttle`` is the trimmed throttle at cruise
    speed near sea level, the pilot's starting guess when it is not told the actual trim.
    """

    name: str
    jsbsim_model: str
    description: str
    cruise_airspeed_m_s: float
    stall_airspeed_m_s: float
    never_exceed_m_s: float
    loop_entry_airspeed_m_s: float
    max_load_factor: float
    cruise_throttle: float


AIRCRAFT: dict[str, AircraftSpec] = {
    "c172p": AircraftSpec(
        name="c172p",
        jsbsim_model="c172p",
        description=(
            "Cessna 172P (the light aircraft FlightGear flies by default: conventional high-wing "
            "tractor layout with docile, well-damped modes; unlike c172x it models no 0.05 rad "
            "elevator backlash, which makes any closed-loop pitch control limit-cycle)"
        ),
        cruise_airspeed_m_s=50.0,
        stall_airspeed_m_s=25.0,
        never_exceed_m_s=82.0,
        loop_entry_airspeed_m_s=64.0,
        max_load_factor=4.0,
        cruise_throttle=0.68,
    ),
    "j3cub": AircraftSpec(
        name="j3cub",
        jsbsim_model="J3Cub",
        description=(
            "Piper J-3 Cub (light, slow, low wing loading: closest in speed range and gust "
            "response to a large research model aircraft among the shipped models)"
        ),
        cruise_airspeed_m_s=30.0,
        stall_airspeed_m_s=17.0,
        never_exceed_m_s=54.0,
        loop_entry_airspeed_m_s=48.0,
        max_load_factor=4.0,
        cruise_throttle=0.57,
    ),
}
DEFAULT_AIRCRAFT = "c172p"


def resolve_aircraft(aircraft: str | AircraftSpec) -> AircraftSpec:
    """Look an aircraft up by name (case-insensitive), or pass a spec through."""
    if isinstance(aircraft, AircraftSpec):
        return aircraft
    spec = AIRCRAFT.get(str(aircraft).lower())
    if spec is None:
        raise ValueError(
            f"unknown aircraft {aircraft!r}: choose one of {', '.join(sorted(AIRCRAFT))}"
        )
    return spec
