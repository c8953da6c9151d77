"""Per-sentence parsers of the NMEA 0183 sentences the decoder uses: GGA, RMC, VTG, GSA, GST, HDT.

Each turns one parsed sentence into a record (field name to SI value, None where empty) and
raises :class:`~companion.drivers.nmea_fields.Malformed` when a field does not parse. Which
sentences and talkers exist is defined here; how records become an epoch is the decoder's job.
"""

from __future__ import annotations

import datetime as dt
import re

import pynmea2

from companion.drivers.nmea_fields import (
    KMH_TO_M_S,
    KNOTS_TO_M_S,
    Malformed,
    Record,
    float_field,
    int_field,
    latlon_fields,
    text_field,
    utc_field,
)

__all__ = [
    "DEFAULT_SENTENCES",
    "TALKERS",
    "USED_SENTENCES",
    "parse_gga",
    "parse_gsa",
    "parse_gst",
    "parse_hdt",
    "parse_rmc",
    "parse_vtg",
]

TALKERS = ("GN", "GP", "GL", "GA", "GB")
"""Accepted talker IDs, in order of preference when two talkers send the same sentence."""
USED_SENTENCES = frozenset({"GGA", "RMC", "VTG", "GSA", "GST", "HDT"})
"""Sentence types decoded; ``HDT`` (true heading) comes from dual-antenna receivers."""
DEFAULT_SENTENCES = ("GGA", "RMC", "VTG", "GSA", "GST")
_DATE = re.compile(r"(\d\d)(\d\d)(\d\d)")
_GGA_FIX = {0: 0, 1: 1, 2: 2, 3: 1, 4: 3, 5: 3, 6: 0, 7: 0, 8: 0}
_RMC_MODE_FIX = {"D": 2, "R": 3, "F": 3, "N": 0, "E": 0}


def parse_gga(msg: pynmea2.NMEASentence) -> Record:
    record: Record = {"utc": utc_field(msg)}
    latlon_fields(msg, record)
    quality = int_field(msg, "gps_qual")
    if quality is not None:
        record["fix"] = _GGA_FIX.get(quality, 0)
    record["sats"] = int_field(msg, "num_sats")
    record["hdop"] = float_field(msg, "horizontal_dil")
    record["alt_m"] = float_field(msg, "altitude")
    record["geoid_sep_m"] = float_field(msg, "geo_sep")
    return record


def parse_rmc(msg: pynmea2.NMEASentence) -> Record:
    record: Record = {"utc": utc_field(msg)}
    latlon_fields(msg, record)
    knots = float_field(msg, "spd_over_grnd")
    record["speed_m_s"] = None if knots is None else knots * KNOTS_TO_M_S
    record["course_deg"] = float_field(msg, "true_course")
    status = text_field(msg, "status")
    if status == "A":
        record["fix"] = _RMC_MODE_FIX.get(text_field(msg, "mode_indicator"), 1)
    elif status == "V":
        record["fix"] = 0
    date_text = text_field(msg, "datestamp")
    if date_text:
        match = _DATE.fullmatch(date_text)
        try:
            if not match:
                raise ValueError(date_text)
            year = int(match[3])  # GPS began in 1980: 80..99 are the 1900s
            year += 1900 if year >= 80 else 2000
            record["date"] = dt.date(year, int(match[2]), int(match[1]))
        except ValueError:
            raise Malformed(f"date {date_text!r} is not a valid ddmmyy") from None
    return record


def parse_vtg(msg: pynmea2.NMEASentence) -> Record:
    knots = float_field(msg, "spd_over_grnd_kts")
    kmh = float_field(msg, "spd_over_grnd_kmph")
    if knots is not None:
        speed: float | None = knots * KNOTS_TO_M_S
    else:
        speed = None if kmh is None else kmh * KMH_TO_M_S
    return {"speed_m_s": speed, "course_deg": float_field(msg, "true_track")}


def parse_gsa(msg: pynmea2.NMEASentence) -> Record:
    record: Record = {
        "pdop": float_field(msg, "pdop"),
        "hdop": float_field(msg, "hdop"),
        "vdop": float_field(msg, "vdop"),
    }
    if text_field(msg, "mode_fix_type") == "1":
        record["fix"] = 0
    return record


def parse_gst(msg: pynmea2.NMEASentence) -> Record:
    return {
        "utc": utc_field(msg),
        "lat_std_m": float_field(msg, "std_dev_latitude"),
        "lon_std_m": float_field(msg, "std_dev_longitude"),
        "alt_std_m": float_field(msg, "std_dev_altitude"),
    }


def parse_hdt(msg: pynmea2.NMEASentence) -> Record:
    heading = float_field(msg, "heading")
    flag = text_field(msg, "hdg_true")
    if flag != "T":
        raise Malformed(f"field hdg_true={flag!r} is not T")
    if heading is not None and not 0.0 <= heading <= 360.0:
        raise Malformed(f"field heading={heading!r} is not within 0..360")
    return {"heading_deg": None if heading is None else heading % 360.0}

