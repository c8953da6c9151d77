"""NMEA 0183 field syntax, both ways: strict reading of one field, writing it, and framing.

pynmea2 splits sentences and names their fields; these readers add what pynmea2 1.19 lacks for a
flight driver: strict conversion (pynmea2 silently returns the raw text when a number does not
parse, and reads a missing hemisphere as 0 degrees). The writers are the same syntax (hhmmss.ss
time, (d)ddmm.mmmm coordinates) read the other way, kept beside the readers so the two agree.
Every sentence parser and writer, NMEA or Ashtech, builds on this module.
"""

from __future__ import annotations

import math
import re
from typing import Any

import pynmea2
from pynmea2.nmea_utils import dm_to_sd

__all__ = [
    "KMH_TO_M_S",
    "KNOTS_TO_M_S",
    "Malformed",
    "Record",
    "float_field",
    "fmt_coord",
    "fmt_time",
    "fmt_value",
    "int_field",
    "latlon_fields",
    "nmea_sentence",
    "text_field",
    "utc_field",
]

KNOTS_TO_M_S = 1852.0 / 3600.0
KMH_TO_M_S = 1.0 / 3.6
TIME_RE = re.compile(r"(\d\d)(\d\d)(\d\d(?:\.\d*)?)")


class Malformed(ValueError):
    """A field that does not parse: the decoder counts the sentence as malformed."""


Record = dict[str, Any]
"""One sentence read: field name to SI value, None where the field was empty."""


def text_field(msg: pynmea2.NMEASentence, name: str) -> str:
    index = type(msg).name_to_idx[name]
    data = msg.data
    return data[index].strip() if index < len(data) else ""


def float_field(msg: pynmea2.NMEASentence, name: str) -> float | None:
    text = text_field(msg, name)
    if not text:
        return None
    try:
        value = float(text)
    except ValueError:
        raise Malformed(f"field {name}={text!r} is not a number") from None
    if not math.isfinite(value):
        raise Malformed(f"field {name}={text!r} is not finite")
    return value


def int_field(msg: pynmea2.NMEASentence, name: str) -> int | None:
    text = text_field(msg, name)
    if not text:
        return None
    if not text.isdigit():
        raise Malformed(f"field {name}={text!r} is not an unsigned integer")
    return int(text)


def utc_field(msg: pynmea2.NMEASentence) -> float | None:
    text = text_field(msg, "timestamp")
    if not text:
        return None
    match = TIME_RE.fullmatch(text)
    if not match:
        raise Malformed(f"time {text!r} is not hhmmss.ss")
    hours, minutes, seconds = int(match[1]), int(match[2]), float(match[3])
    if hours > 23 or minutes > 59 or seconds >= 61.0:
        raise Malformed(f"time {text!r} out of range")
    return hours * 3600 + minutes * 60 + seconds


def _coord(
    msg: pynmea2.NMEASentence, value_name: str, hemi_name: str, limit: float
) -> float | None:
    text = text_field(msg, value_name)
    hemi = text_field(msg, hemi_name)
    if not text:
        # no value, with or without a hemisphere letter: no position (pynmea2 would read an
        # empty value as 0.0, a false fix at 0 N 0 E)
        return None
    try:
        value = dm_to_sd(text)
    except ValueError:
        raise Malformed(f"field {value_name}={text!r} is not (d)ddmm.mmmm") from None
    if hemi in ("S", "W"):
        value = -value
    elif hemi not in ("N", "E"):
        raise Malformed(f"field {hemi_name}={hemi!r} is not a hemisphere")
    if abs(value) > limit:
        raise Malformed(f"field {value_name}={text!r} exceeds {limit} degrees")
    return value


def latlon_fields(msg: pynmea2.NMEASentence, record: Record) -> None:
    record["lat_deg"] = _coord(msg, "lat", "lat_dir", 90.0)
    record["lon_deg"] = _coord(msg, "lon", "lon_dir", 180.0)



def nmea_sentence(body: str) -> bytes:
    """Frame ``body`` (without ``$``) as ``$body*hh\\r\\n``."""
    return b"$%s*%02X\r\n" % (body.encode("ascii"), pynmea2.NMEASentence.checksum(body))


def fmt_value(value: float | None, spec: str) -> str:
    return "" if value is None else format(value, spec)


def fmt_time(utc: float) -> str:
    centis = round(utc * 100) % 8_640_000
    seconds, centi = divmod(centis, 100)
    return f"{seconds // 3600:02d}{seconds // 60 % 60:02d}{seconds % 60:02d}.{centi:02d}"


def fmt_coord(
    value: float | None, degree_digits: int, decimals: int, hemis: str
) -> tuple[str, str]:
    if value is None:
        return "", ""
    magnitude = abs(value)
    degrees = int(magnitude)
    minutes = round((magnitude - degrees) * 60.0, decimals)
    if minutes >= 60.0:
        degrees += 1
        minutes -= 60.0
    width = 3 + decimals
    text = f"{degrees:0{degree_digits}d}{minutes:0{width}.{decimals}f}"
    return text, hemis[1] if value < 0 else hemis[0]

