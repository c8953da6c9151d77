"""Encoding of a :class:`GpsSolution` as a receiver's epoch of NMEA sentences (simulator side).

The simulator and the fuzz tests write GPS bytes with it; the flight driver never does, which is
why it is apart from the decoder.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from companion.drivers.ashtech_pos import pashr_pos_body
from companion.drivers.gps_solution import GpsSolution
from companion.drivers.nmea_fields import (
    KMH_TO_M_S,
    KNOTS_TO_M_S,
    fmt_coord,
    fmt_time,
    fmt_value,
    nmea_sentence,
)
from companion.drivers.nmea_sentences import DEFAULT_SENTENCES, TALKERS, USED_SENTENCES

__all__ = ["encode_epoch"]

_FIX_GGA = {0: 0, 1: 1, 2: 2, 3: 4}
_FIX_MODE = {0: "N", 1: "A", 2: "D", 3: "R"}


def _ground_track(sol: GpsSolution) -> tuple[float | None, float | None]:
    speed, course = sol.speed_m_s, sol.course_deg
    if speed is None and sol.vn_m_s is not None and sol.ve_m_s is not None:
        speed = math.hypot(sol.vn_m_s, sol.ve_m_s)
        course = math.degrees(math.atan2(sol.ve_m_s, sol.vn_m_s))
    if course is not None:
        course = round(course % 360.0, 2) % 360.0
    return speed, course


def _check_finite(sol: GpsSolution) -> None:
    for name in ("utc", "lat_deg", "lon_deg", "alt_m", "speed_m_s", "course_deg", "vd_m_s",
                 "heading_deg"):
        value = getattr(sol, name)
        if value is not None and not math.isfinite(value):
            raise ValueError(f"GpsSolution.{name} must be finite, got {value!r}")
    if sol.lat_deg is not None and abs(sol.lat_deg) > 90.0:
        raise ValueError(f"GpsSolution.lat_deg {sol.lat_deg} outside -90..90")
    if sol.lon_deg is not None and abs(sol.lon_deg) > 180.0:
        raise ValueError(f"GpsSolution.lon_deg {sol.lon_deg} outside -180..180")
    if sol.date is not None and not 1980 <= sol.date.year <= 2079:
        raise ValueError(f"GpsSolution.date {sol.date} outside what ddmmyy can carry (1980..2079)")
    if sol.fix not in _FIX_GGA:
        raise ValueError(f"GpsSolution.fix must be 0..3, got {sol.fix}")


def encode_epoch(
    solution: GpsSolution,
    talker: str = "GP",
    sentences: Iterable[str] = DEFAULT_SENTENCES,
    ashtech_pos: bool = False,
) -> bytes:
    """Write one epoch as checksummed sentences, in the order given, PASHR,POS last if asked.

    Latitude/longitude carry 5 decimals of minutes (PASHR: 4, as the contract spells it), speed
    3 decimals of knots, altitude 2 decimals of metres.
    """
    if talker not in TALKERS:
        raise ValueError(f"talker must be one of {TALKERS}, got {talker!r}")
    if solution.utc is None:
        raise ValueError("GpsSolution.utc is required to encode an epoch")
    _check_finite(solution)
    time_text = fmt_time(solution.utc)
    lat, ns = fmt_coord(solution.lat_deg, 2, 5, "NS")
    lon, ew = fmt_coord(solution.lon_deg, 3, 5, "EW")
    speed, course = _ground_track(solution)
    knots = None if speed is None else speed / KNOTS_TO_M_S
    fix = solution.fix
    sats = fmt_value(solution.sats, "02d")
    mode = _FIX_MODE[fix]
    out = bytearray()
    for kind in sentences:
        if kind == "GGA":
            body = (
                f"GGA,{time_text},{lat},{ns},{lon},{ew},{_FIX_GGA[fix]},{sats},"
                f"{fmt_value(solution.hdop, '.2f')},{fmt_value(solution.alt_m, '.2f')},M,"
                f"{fmt_value(solution.geoid_sep_m, '.2f')},M,,"
            )
        elif kind == "RMC":
            date = "" if solution.date is None else solution.date.strftime("%d%m%y")
            body = (
                f"RMC,{time_text},{'A' if fix else 'V'},{lat},{ns},{lon},{ew},"
                f"{fmt_value(knots, '.3f')},{fmt_value(course, '.2f')},{date},,,{mode}"
            )
        elif kind == "VTG":
            kmh = None if speed is None else speed / KMH_TO_M_S
            body = (
                f"VTG,{fmt_value(course, '.2f')},T,,M,{fmt_value(knots, '.3f')},N,{fmt_value(kmh, '.3f')},K,{mode}"
            )
        elif kind == "GSA":
            count = min(solution.sats or 0, 12)
            ids = [f"{n:02d}" for n in range(1, count + 1)] + [""] * (12 - count)
            body = (
                f"GSA,A,{3 if fix else 1},{','.join(ids)},{fmt_value(solution.pdop, '.2f')},"
                f"{fmt_value(solution.hdop, '.2f')},{fmt_value(solution.vdop, '.2f')}"
            )
        elif kind == "GST":
            body = (
                f"GST,{time_text},,,,,{fmt_value(solution.lat_std_m, '.3f')},"
                f"{fmt_value(solution.lon_std_m, '.3f')},{fmt_value(solution.alt_std_m, '.3f')}"
            )
        elif kind == "HDT":  # empty heading: the receiver has no heading solution
            body = f"HDT,{fmt_value(solution.heading_deg, '.2f')},T"
        else:
            raise ValueError(f"sentences: cannot encode {kind!r}; use "
                             f"{', '.join(sorted(USED_SENTENCES))}")
        out += nmea_sentence(talker + body)
    if ashtech_pos:
        out += nmea_sentence(pashr_pos_body(solution, time_text, speed, course))
    return bytes(out)

