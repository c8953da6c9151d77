"""The Ashtech ``$PASHR,POS`` sentence, read and written per the contract.

Speed is in knots, the altitude is above the WGS84 ellipsoid, and the last field is a firmware
tag, not a station id. Reading and writing live together so the two agree on that contract.
"""

from __future__ import annotations

import pynmea2

from companion.drivers.gps_solution import GpsSolution
from companion.drivers.nmea_fields import (
    KNOTS_TO_M_S,
    Record,
    float_field,
    fmt_coord,
    fmt_value,
    int_field,
    latlon_fields,
    utc_field,
)

__all__ = ["pashr_pos_body", "parse_pos"]


def parse_pos(msg: pynmea2.NMEASentence) -> Record:
    record: Record = {"utc": utc_field(msg)}
    latlon_fields(msg, record)
    mode = int_field(msg, "mode")
    record["fix"] = 0 if mode is None else min(mode + 1, 3)
    record["sats"] = int_field(msg, "sat_count")
    record["alt_ellipsoid_m"] = float_field(msg, "altitude")
    record["course_deg"] = float_field(msg, "course")
    knots = float_field(msg, "spd_over_grnd")
    record["speed_m_s"] = None if knots is None else knots * KNOTS_TO_M_S
    up = float_field(msg, "vertical_velocity")
    record["vd_m_s"] = None if up is None else -up
    for name in ("pdop", "hdop", "vdop", "tdop"):
        record[name] = float_field(msg, name)
    return record



def pashr_pos_body(
    solution: GpsSolution, time_text: str, speed: float | None, course: float | None
) -> str:
    lat, ns = fmt_coord(solution.lat_deg, 2, 4, "NS")
    lon, ew = fmt_coord(solution.lon_deg, 3, 4, "EW")
    alt_ell = solution.alt_ellipsoid_m
    if alt_ell is None and solution.alt_m is not None:
        alt_ell = solution.alt_m + (solution.geoid_sep_m or 0.0)
    up = None if solution.vd_m_s is None else -solution.vd_m_s
    knots = None if speed is None else speed / KNOTS_TO_M_S
    position_type = "" if solution.fix == 0 else str(solution.fix - 1)
    return (
        f"PASHR,POS,{position_type},{fmt_value(solution.sats, '02d')},{time_text},{lat},{ns},{lon},{ew},"
        f"{fmt_value(alt_ell, '.2f')},,{fmt_value(course, '.2f')},{fmt_value(knots, '.3f')},{fmt_value(up, '+.3f')},"
        f"{fmt_value(solution.pdop, '.1f')},{fmt_value(solution.hdop, '.1f')},{fmt_value(solution.vdop, '.1f')},"
        f"{fmt_value(solution.tdop, '.1f')},SIM1"
    )
