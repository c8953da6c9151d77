"""GPS wire protocol: NMEA 0183 (GGA, RMC, VTG, GSA, GST) and Ashtech ``$PASHR,POS``.

The decoder turns a raw, possibly messy byte stream into one :class:`GpsSolution` per receiver
epoch (sentences sharing one UTC time), timing each epoch from the arrival of its first byte to its
hand-off. pynmea2 splits sentences and names their fields; this module adds what pynmea2 1.19
lacks for a flight driver: byte-level framing of a damaged stream, strict field conversion
(pynmea2 silently returns the raw text when a number does not parse, and reads a missing
hemisphere as 0 degrees), epoch grouping, unit conversion, and the Ashtech POS sentence read per
the contract (speed in knots, altitude above the ellipsoid, a firmware tag, not a station id, last).

Altitudes: ``GpsSolution.alt_m`` is above mean sea level (GGA). ``$PASHR,POS`` reports height
above the WGS84 ellipsoid (kept in ``alt_ellipsoid_m``); it is turned into MSL only with a geoid
separation from a GGA, of this epoch or the last one that had it.

Size: six sentence parsers, the epoch assembly and the encoder the simulator uses, all
bound to one reading of the NMEA and Ashtech formats.
"""

from __future__ import annotations

import datetime as dt
import math
import re
from collections.abc import Callable, Collection, Iterable
from dataclasses import dataclass
from functools import reduce
from operator import xor
from typing import Any

import pynmea2
from pynmea2.nmea_utils import dm_to_sd

from companion.core.fastinit import fast_frozen

__all__ = [
    "DEFAULT_SENTENCES",
    "GpsSolution",
    "KNOTS_TO_M_S",
    "MAX_LINE_CHARS",
    "NmeaCounters",
    "NmeaDecoder",
    "TALKERS",
    "encode_epoch",
    "nmea_sentence",
]

KNOTS_TO_M_S = 1852.0 / 3600.0
KMH_TO_M_S = 1.0 / 3.6
MAX_LINE_CHARS = 120
"""Longest accepted sentence, counted from ``$`` through the checksum digits."""

TALKERS = ("GN", "GP", "GL", "GA", "GB")
"""Accepted talker IDs, in order of preference when two talkers send the same sentence."""
USED_SENTENCES = frozenset({"GGA", "RMC", "VTG", "GSA", "GST", "HDT"})
"""Sentence types decoded; ``HDT`` (true heading) comes from dual-antenna receivers."""
DEFAULT_SENTENCES = ("GGA", "RMC", "VTG", "GSA", "GST")
_TIMED = frozenset({"GGA", "RMC", "GST", "POS"})

# Where a sentence ends: CR/LF, the start of another sentence, a checksum, or a byte that no
# text sentence contains (an Ashtech binary chunk, line noise).
_STOP = re.compile(rb"[\r\n$*]|[^\x20-\x7e]")
_HEX = re.compile(rb"[0-9A-Fa-f]{2}")
_TIME = re.compile(r"(\d\d)(\d\d)(\d\d(?:\.\d*)?)")
_DATE = re.compile(r"(\d\d)(\d\d)(\d\d)")
_GGA_FIX = {0: 0, 1: 1, 2: 2, 3: 1, 4: 3, 5: 3, 6: 0, 7: 0, 8: 0}
_FIX_GGA = {0: 0, 1: 1, 2: 2, 3: 4}
_RMC_MODE_FIX = {"D": 2, "R": 3, "F": 3, "N": 0, "E": 0}
_FIX_MODE = {0: "N", 1: "A", 2: "D", 3: "R"}


@dataclass(slots=True)
class NmeaCounters:
    """Running tallies for the operator: what the line delivered and what had to be thrown away."""

    sentences_good: int = 0
    bad_checksum: int = 0
    """Checksum mismatch, non-hex checksum, or no checksum when ``allow_no_checksum`` is off."""
    unknown: int = 0
    """Well-formed sentences this decoder does not use (other talkers, GSV, other $PASHR...)."""
    too_long: int = 0
    cut: int = 0
    """Sentences interrupted by another ``$`` or by a non-text byte (e.g. Ashtech binary)."""
    malformed: int = 0
    """Checksum fine but a field does not parse (e.g. a latitude without hemisphere)."""
    late: int = 0
    """Sentences whose epoch had already been handed off."""
    bytes_discarded: int = 0
    """Bytes outside accepted sentences, line ends excepted."""
    epochs: int = 0


@fast_frozen
@dataclass(frozen=True)
class GpsSolution:
    """One receiver epoch, in SI units; None where no sentence of the epoch carried the value."""

    utc: float | None = None
    """Seconds since UTC midnight."""
    date: dt.date | None = None
    lat_deg: float | None = None
    lon_deg: float | None = None
    alt_m: float | None = None
    """Altitude above mean sea level."""
    alt_ellipsoid_m: float | None = None
    """Height above the WGS84 ellipsoid."""
    geoid_sep_m: float | None = None
    """Ellipsoid minus MSL (GGA); encode_epoch uses it to write the PASHR ellipsoid height."""
    fix: int = 0
    """0 none, 1 GPS, 2 DGPS, 3 RTK."""
    sats: int | None = None
    hdop: float | None = None
    pdop: float | None = None
    vdop: float | None = None
    tdop: float | None = None
    speed_m_s: float | None = None
    """Speed over ground."""
    course_deg: float | None = None
    """Course over ground, true, 0..360."""
    vn_m_s: float | None = None
    ve_m_s: float | None = None
    vd_m_s: float | None = None
    """Down velocity (from PASHR's vertical velocity, which is positive up)."""
    alt_std_m: float | None = None
    lat_std_m: float | None = None
    lon_std_m: float | None = None
    heading_deg: float | None = None
    """True heading of the antenna baseline, 0..360 (HDT: a dual-antenna receiver's; the
    course over ground says where the aircraft goes, this where it points)."""
    latency_s: float | None = None
    """Hand-off time minus arrival time of the epoch's first byte (decoder's clock)."""
    first_byte_t_ns: int | None = None
    handoff_t_ns: int | None = None
    sentences: tuple[str, ...] = ()
    """Addresses that made up the epoch, in arrival order (``GPGGA``, ``PASHR,POS``...)."""

    @property
    def utc_datetime(self) -> dt.datetime | None:
        """Full UTC timestamp, when an RMC gave the date."""
        if self.utc is None or self.date is None:
            return None
        midnight = dt.datetime.combine(self.date, dt.time(), tzinfo=dt.UTC)
        return midnight + dt.timedelta(seconds=self.utc)

    def to_json_dict(self) -> dict[str, Any]:
        """The fixed set of keys the tools and logs exchange (null where absent)."""
        return {
            "utc": self.utc,
            "lat_deg": self.lat_deg,
            "lon_deg": self.lon_deg,
            "alt_m": self.alt_m,
            "fix": self.fix,
            "sats": self.sats,
            "hdop": self.hdop,
            "pdop": self.pdop,
            "vdop": self.vdop,
            "speed_m_s": self.speed_m_s,
            "course_deg": self.course_deg,
            "alt_std_m": self.alt_std_m,
        }


class _Malformed(ValueError):
    pass


Record = dict[str, Any]


def _field(msg: pynmea2.NMEASentence, name: str) -> str:
    index = type(msg).name_to_idx[name]
    data = msg.data
    return data[index].strip() if index < len(data) else ""


def _float(msg: pynmea2.NMEASentence, name: str) -> float | None:
    text = _field(msg, name)
    if not text:
        return None
    try:
        value = float(text)
    except ValueError:
        raise _Malformed(f"field {name}={text!r} is not a number") from None
    if not math.isfinite(value):
        raise _Malformed(f"field {name}={text!r} is not finite")
    return value


def _int(msg: pynmea2.NMEASentence, name: str) -> int | None:
    text = _field(msg, name)
    if not text:
        return None
    if not text.isdigit():
        raise _Malformed(f"field {name}={text!r} is not an unsigned integer")
    return int(text)


def _utc(msg: pynmea2.NMEASentence) -> float | None:
    text = _field(msg, "timestamp")
    if not text:
        return None
    match = _TIME.fullmatch(text)
    if not match:
        raise _Malformed(f"time {text!r} is not hhmmss.ss")
    hours, minutes, seconds = int(match[1]), int(match[2]), float(match[3])
    if hours > 23 or minutes > 59 or seconds >= 61.0:
        raise _Malformed(f"time {text!r} out of range")
    return hours * 3600 + minutes * 60 + seconds


def _coord(
    msg: pynmea2.NMEASentence, value_name: str, hemi_name: str, limit: float
) -> float | None:
    text = _field(msg, value_name)
    hemi = _field(msg, hemi_name)
    if not text:
        # no value, with or without a hemisphere letter: no position (pynmea2 would read an
        # empty value as 0.0, a false fix at 0 N 0 E)
        return None
    try:
        value = dm_to_sd(text)
    except ValueError:
        raise _Malformed(f"field {value_name}={text!r} is not (d)ddmm.mmmm") from None
    if hemi in ("S", "W"):
        value = -value
    elif hemi not in ("N", "E"):
        raise _Malformed(f"field {hemi_name}={hemi!r} is not a hemisphere")
    if abs(value) > limit:
        raise _Malformed(f"field {value_name}={text!r} exceeds {limit} degrees")
    return value


def _latlon(msg: pynmea2.NMEASentence, record: Record) -> None:
    record["lat_deg"] = _coord(msg, "lat", "lat_dir", 90.0)
    record["lon_deg"] = _coord(msg, "lon", "lon_dir", 180.0)


def _gga(msg: pynmea2.NMEASentence) -> Record:
    record: Record = {"utc": _utc(msg)}
    _latlon(msg, record)
    quality = _int(msg, "gps_qual")
    if quality is not None:
        record["fix"] = _GGA_FIX.get(quality, 0)
    record["sats"] = _int(msg, "num_sats")
    record["hdop"] = _float(msg, "horizontal_dil")
    record["alt_m"] = _float(msg, "altitude")
    record["geoid_sep_m"] = _float(msg, "geo_sep")
    return record


def _rmc(msg: pynmea2.NMEASentence) -> Record:
    record: Record = {"utc": _utc(msg)}
    _latlon(msg, record)
    knots = _float(msg, "spd_over_grnd")
    record["speed_m_s"] = None if knots is None else knots * KNOTS_TO_M_S
    record["course_deg"] = _float(msg, "true_course")
    status = _field(msg, "status")
    if status == "A":
        record["fix"] = _RMC_MODE_FIX.get(_field(msg, "mode_indicator"), 1)
    elif status == "V":
        record["fix"] = 0
    date_text = _field(msg, "datestamp")
    if date_text:
        match = _DATE.fullmatch(date_text)
        try:
            if not match:
                raise ValueError(date_text)
            year = int(match[3])  # GPS began in 1980: 80..99 are the 1900s
            year += 1900 if year >= 80 else 2000
            record["date"] = dt.date(year, int(match[2]), int(match[1]))
        except ValueError:
            raise _Malformed(f"date {date_text!r} is not a valid ddmmyy") from None
    return record


def _vtg(msg: pynmea2.NMEASentence) -> Record:
    knots = _float(msg, "spd_over_grnd_kts")
    kmh = _float(msg, "spd_over_grnd_kmph")
    if knots is not None:
        speed: float | None = knots * KNOTS_TO_M_S
    else:
        speed = None if kmh is None else kmh * KMH_TO_M_S
    return {"speed_m_s": speed, "course_deg": _float(msg, "true_track")}


def _gsa(msg: pynmea2.NMEASentence) -> Record:
    record: Record = {
        "pdop": _float(msg, "pdop"),
        "hdop": _float(msg, "hdop"),
        "vdop": _float(msg, "vdop"),
    }
    if _field(msg, "mode_fix_type") == "1":
        record["fix"] = 0
    return record


def _gst(msg: pynmea2.NMEASentence) -> Record:
    return {
        "utc": _utc(msg),
        "lat_std_m": _float(msg, "std_dev_latitude"),
        "lon_std_m": _float(msg, "std_dev_longitude"),
        "alt_std_m": _float(msg, "std_dev_altitude"),
    }


def _hdt(msg: pynmea2.NMEASentence) -> Record:
    heading = _float(msg, "heading")
    flag = _field(msg, "hdg_true")
    if flag != "T":
        raise _Malformed(f"field hdg_true={flag!r} is not T")
    if heading is not None and not 0.0 <= heading <= 360.0:
        raise _Malformed(f"field heading={heading!r} is not within 0..360")
    return {"heading_deg": None if heading is None else heading % 360.0}


def _pos(msg: pynmea2.NMEASentence) -> Record:
    record: Record = {"utc": _utc(msg)}
    _latlon(msg, record)
    mode = _int(msg, "mode")
    record["fix"] = 0 if mode is None else min(mode + 1, 3)
    record["sats"] = _int(msg, "sat_count")
    record["alt_ellipsoid_m"] = _float(msg, "altitude")
    record["course_deg"] = _float(msg, "course")
    knots = _float(msg, "spd_over_grnd")
    record["speed_m_s"] = None if knots is None else knots * KNOTS_TO_M_S
    up = _float(msg, "vertical_velocity")
    record["vd_m_s"] = None if up is None else -up
    for name in ("pdop", "hdop", "vdop", "tdop"):
        record[name] = _float(msg, name)
    return record


_EXTRACT: dict[str, Callable[[pynmea2.NMEASentence], Record]] = {
    "GGA": _gga,
    "RMC": _rmc,
    "VTG": _vtg,
    "GSA": _gsa,
    "GST": _gst,
    "HDT": _hdt,
    "POS": _pos,
}


MAX_EPOCH_SENTENCES = 64
"""Sentence addresses kept per epoch (a receiver sends about ten)."""


class _Epoch:
    __slots__ = ("key_ms", "utc", "first_t_ns", "parts", "addresses")

    def __init__(self, first_t_ns: int) -> None:
        self.key_ms: int | None = None
        self.utc: float | None = None
        self.first_t_ns = first_t_ns
        self.parts: dict[str, tuple[int, Record]] = {}
        self.addresses: list[str] = []

    def add(self, kind: str, priority: int, record: Record, address: str) -> None:
        held = self.parts.get(kind)
        if held is None or priority < held[0]:
            self.parts[kind] = (priority, record)
        if len(self.addresses) < MAX_EPOCH_SENTENCES:  # an epoch that never completes
            self.addresses.append(address)          # (no time in it) stays bounded


def _pick(name: str, *records: Record) -> Any:
    for record in records:
        value = record.get(name)
        if value is not None:
            return value
    return None


class NmeaDecoder:
    """Incremental NMEA/Ashtech decoder producing one :class:`GpsSolution` per epoch.

    An epoch is handed off when a sentence with a different UTC time arrives, when every type in
    ``expected_sentences`` (talker-free names: ``GGA``, ``RMC``, ``VTG``, ``GSA``, ``GST``,
    ``HDT``, ``POS``) has arrived, on :meth:`flush`, or on :meth:`poll` once the line has been quiet for
    ``idle_handoff_ms``. Sentences without a time (VTG, GSA, HDT) join the open epoch, or the next one
    if none is open; so ``expected_sentences`` should list every type the receiver sends, or a
    trailing untimed sentence is credited to the following epoch. When two talkers send the same
    sentence type in one epoch, the one earlier in :data:`TALKERS` wins (GN before GP).
    """

    def __init__(
        self,
        *,
        allow_no_checksum: bool = False,
        expected_sentences: Iterable[str] | None = None,
        idle_handoff_ms: float | None = None,
        talkers: Collection[str] = TALKERS,
    ) -> None:
        self.counters = NmeaCounters()
        self.allow_no_checksum = allow_no_checksum
        self.expected: frozenset[str] = frozenset(expected_sentences or ())
        unknown = self.expected - USED_SENTENCES - {"POS"}
        if unknown:
            raise ValueError(f"expected_sentences: unknown sentence types {sorted(unknown)}")
        self.idle_handoff_ns = None if idle_handoff_ms is None else int(idle_handoff_ms * 1e6)
        self._priority = {talker: index for index, talker in enumerate(talkers)}
        self._buf = bytearray()
        self._buf_t_ns = 0
        self._scanned = 0  # bytes of the kept partial sentence known to hold no stop character
        self._open: _Epoch | None = None
        self._last_key_ms: int | None = None
        self._last_addresses: frozenset[str] = frozenset()
        self._last_sentence_t_ns = 0
        self._geoid_sep_m: float | None = None

    def reset(self) -> None:
        """Drop a half-received sentence (e.g. the port was reopened); the open epoch stays."""
        self.counters.bytes_discarded += len(self._buf)
        self._buf.clear()
        self._scanned = 0

    def feed(self, data: bytes, t_ns: int) -> list[GpsSolution]:
        """Consume ``data`` that arrived at ``t_ns``; return the epochs it completed."""
        counters = self.counters
        nul = data.count(0)
        if nul:
            data = data.replace(b"\x00", b"")
            counters.bytes_discarded += nul
        buf = self._buf
        carried = len(buf)
        buf += data
        out: list[GpsSolution] = []
        pos = 0
        size = len(buf)
        while pos < size:
            if buf[pos] != 0x24:  # not '$': skip to the next sentence start
                start = buf.find(b"$", pos)
                end = size if start < 0 else start
                junk = buf[pos:end]
                counters.bytes_discarded += len(junk) - junk.count(b"\r") - junk.count(b"\n")
                pos = end
                continue
            window_end = min(size, pos + MAX_LINE_CHARS + 1)
            scan_from = max(pos + 1, self._scanned) if pos == 0 else pos + 1
            self._scanned = 0
            stop = _STOP.search(buf, scan_from, window_end)
            if stop is None:
                if window_end - pos > MAX_LINE_CHARS:
                    counters.too_long += 1
                    counters.bytes_discarded += 1
                    pos += 1  # the rest of the line is skipped as junk
                    continue
                self._scanned = size - pos
                break  # wait for the rest of the sentence
            j = stop.start()
            char = buf[j]
            start_t_ns = self._buf_t_ns if pos < carried else t_ns
            if char == 0x2A:  # '*'
                if j + 3 > size:
                    self._scanned = j - pos
                    break
                if j - pos + 3 > MAX_LINE_CHARS:
                    counters.too_long += 1
                    counters.bytes_discarded += 1
                    pos += 1
                    continue
                body = bytes(buf[pos + 1 : j])
                digits = bytes(buf[j + 1 : j + 3])
                if not _HEX.fullmatch(digits):
                    # not a checksum: keep what follows '*', it may start the next sentence
                    counters.bad_checksum += 1
                    counters.bytes_discarded += j + 1 - pos
                    pos = j + 1
                    continue
                if int(digits, 16) == reduce(xor, body, 0):
                    self._sentence(body.decode("ascii"), j + 3 - pos, start_t_ns, t_ns, out)
                else:
                    counters.bad_checksum += 1
                    counters.bytes_discarded += j + 3 - pos
                pos = j + 3
            elif char in (0x0D, 0x0A):
                if self.allow_no_checksum:
                    body = bytes(buf[pos + 1 : j])
                    self._sentence(body.decode("ascii"), j - pos, start_t_ns, t_ns, out)
                else:
                    counters.bad_checksum += 1
                    counters.bytes_discarded += j - pos
                pos = j
            elif char == 0x24:  # '$': cut by the next sentence ('$$' is just a doubled start)
                if j > pos + 1:
                    counters.cut += 1
                counters.bytes_discarded += j - pos
                pos = j
            else:  # a byte no text sentence holds: binary chunk or noise
                counters.cut += 1
                counters.bytes_discarded += j + 1 - pos
                pos = j + 1
        if pos >= carried:  # otherwise the partial sentence kept began in an earlier chunk
            self._buf_t_ns = t_ns
        del buf[:pos]
        return out

    @property
    def holds_epoch(self) -> bool:
        """An epoch is open: only :meth:`poll` after silence can still hand it off."""
        return self._open is not None

    def poll(self, t_ns: int) -> list[GpsSolution]:
        """Hand off the open epoch if the line has been quiet for ``idle_handoff_ms``."""
        if (
            self.idle_handoff_ns is not None
            and self._open is not None
            and t_ns - self._last_sentence_t_ns >= self.idle_handoff_ns
        ):
            return [self._handoff(t_ns)]
        return []

    def flush(self, t_ns: int) -> list[GpsSolution]:
        """Hand off the open epoch now (end of a capture, or the caller knows it is complete)."""
        return [] if self._open is None else [self._handoff(t_ns)]

    def _sentence(
        self, body: str, raw_len: int, start_t_ns: int, t_ns: int, out: list[GpsSolution]
    ) -> None:
        counters = self.counters
        address, _, rest = body.partition(",")
        if address == "PASHR":
            if not rest.startswith("POS,"):
                counters.unknown += 1
                return
            kind, priority, address = "POS", 0, "PASHR,POS"
        else:
            kind = address[2:]
            priority_or_none = self._priority.get(address[:2])
            if len(address) != 5 or priority_or_none is None or kind not in USED_SENTENCES:
                counters.unknown += 1
                return
            priority = priority_or_none
        try:
            record = _EXTRACT[kind](pynmea2.parse(body))
        except (pynmea2.ParseError, ValueError, IndexError, KeyError):
            counters.malformed += 1
            counters.bytes_discarded += raw_len
            return
        counters.sentences_good += 1
        self._last_sentence_t_ns = t_ns
        self._merge(kind, priority, record, address, start_t_ns, t_ns, out)

    def _merge(
        self,
        kind: str,
        priority: int,
        record: Record,
        address: str,
        start_t_ns: int,
        t_ns: int,
        out: list[GpsSolution],
    ) -> None:
        utc = record.get("utc") if kind in _TIMED else None
        epoch = self._open
        if utc is not None:
            key_ms = round(utc * 1000)
            # Same time as the epoch just handed off: a straggler, unless that sentence was
            # already in it (then the receiver's clock repeats and this is a new epoch).
            late = key_ms == self._last_key_ms and address not in self._last_addresses
            if epoch is not None and epoch.key_ms is not None and epoch.key_ms != key_ms:
                if late:
                    self.counters.late += 1
                    return
                out.append(self._handoff(t_ns))
                epoch = None
            elif late and (epoch is None or epoch.key_ms is None):
                self.counters.late += 1
                return
            if epoch is None:
                epoch = self._open = _Epoch(start_t_ns)
            if epoch.key_ms is None:
                epoch.key_ms = key_ms
                epoch.utc = utc
        elif epoch is None:
            epoch = self._open = _Epoch(start_t_ns)
        epoch.add(kind, priority, record, address)
        if self.expected and epoch.key_ms is not None and self.expected.issubset(epoch.parts):
            out.append(self._handoff(t_ns))

    def _handoff(self, t_ns: int) -> GpsSolution:
        epoch = self._open
        assert epoch is not None
        self._open = None
        self._last_key_ms = epoch.key_ms
        self._last_addresses = frozenset(epoch.addresses)
        self.counters.epochs += 1
        parts = {kind: record for kind, (_, record) in epoch.parts.items()}
        return self._solution(epoch, parts, t_ns)

    def _solution(self, epoch: _Epoch, parts: dict[str, Record], t_ns: int) -> GpsSolution:
        empty: Record = {}
        gga = parts.get("GGA", empty)
        rmc = parts.get("RMC", empty)
        vtg = parts.get("VTG", empty)
        gsa = parts.get("GSA", empty)
        gst = parts.get("GST", empty)
        hdt = parts.get("HDT", empty)
        pos = parts.get("POS", empty)

        lat = lon = None
        for source in (gga, rmc, pos):
            if source.get("lat_deg") is not None and source.get("lon_deg") is not None:
                lat, lon = source["lat_deg"], source["lon_deg"]
                break
        geoid = gga.get("geoid_sep_m")
        if geoid is not None:
            self._geoid_sep_m = geoid
        else:
            geoid = self._geoid_sep_m
        alt = gga.get("alt_m")
        alt_ell = pos.get("alt_ellipsoid_m")
        if alt is None and alt_ell is not None and geoid is not None:
            alt = alt_ell - geoid
        if alt_ell is None and alt is not None and geoid is not None:
            alt_ell = alt + geoid
        if alt is not None and not math.isfinite(alt):  # sums of huge but finite fields
            alt = None
        if alt_ell is not None and not math.isfinite(alt_ell):
            alt_ell = None
        fix = _pick("fix", gga, pos, rmc, gsa)
        speed = _pick("speed_m_s", rmc, vtg, pos)
        course = _pick("course_deg", rmc, vtg, pos)
        vn = ve = None
        if speed is not None and course is not None:
            vn = speed * math.cos(math.radians(course))
            ve = speed * math.sin(math.radians(course))
        return GpsSolution(
            utc=epoch.utc,
            date=rmc.get("date"),
            lat_deg=lat,
            lon_deg=lon,
            alt_m=alt,
            alt_ellipsoid_m=alt_ell,
            geoid_sep_m=geoid,
            fix=0 if fix is None else fix,
            sats=_pick("sats", gga, pos),
            hdop=_pick("hdop", gsa, gga, pos),
            pdop=_pick("pdop", gsa, pos),
            vdop=_pick("vdop", gsa, pos),
            tdop=pos.get("tdop"),
            speed_m_s=speed,
            course_deg=course,
            vn_m_s=vn,
            ve_m_s=ve,
            vd_m_s=pos.get("vd_m_s"),
            alt_std_m=gst.get("alt_std_m"),
            lat_std_m=gst.get("lat_std_m"),
            lon_std_m=gst.get("lon_std_m"),
            heading_deg=hdt.get("heading_deg"),
            latency_s=(t_ns - epoch.first_t_ns) / 1e9,
            first_byte_t_ns=epoch.first_t_ns,
            handoff_t_ns=t_ns,
            sentences=tuple(epoch.addresses),
        )


# ---------------------------------------------------------------------------------------------
# Encoding (simulator side)


def nmea_sentence(body: str) -> bytes:
    """Frame ``body`` (without ``$``) as ``$body*hh\\r\\n``."""
    return b"$%s*%02X\r\n" % (body.encode("ascii"), pynmea2.NMEASentence.checksum(body))


def _fmt(value: float | None, spec: str) -> str:
    return "" if value is None else format(value, spec)


def _fmt_time(utc: float) -> str:
    centis = round(utc * 100) % 8_640_000
    seconds, centi = divmod(centis, 100)
    return f"{seconds // 3600:02d}{seconds // 60 % 60:02d}{seconds % 60:02d}.{centi:02d}"


def _fmt_coord(
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
    time_text = _fmt_time(solution.utc)
    lat, ns = _fmt_coord(solution.lat_deg, 2, 5, "NS")
    lon, ew = _fmt_coord(solution.lon_deg, 3, 5, "EW")
    speed, course = _ground_track(solution)
    knots = None if speed is None else speed / KNOTS_TO_M_S
    fix = solution.fix
    sats = _fmt(solution.sats, "02d")
    mode = _FIX_MODE[fix]
    out = bytearray()
    for kind in sentences:
        if kind == "GGA":
            body = (
                f"GGA,{time_text},{lat},{ns},{lon},{ew},{_FIX_GGA[fix]},{sats},"
                f"{_fmt(solution.hdop, '.2f')},{_fmt(solution.alt_m, '.2f')},M,"
                f"{_fmt(solution.geoid_sep_m, '.2f')},M,,"
            )
        elif kind == "RMC":
            date = "" if solution.date is None else solution.date.strftime("%d%m%y")
            body = (
                f"RMC,{time_text},{'A' if fix else 'V'},{lat},{ns},{lon},{ew},"
                f"{_fmt(knots, '.3f')},{_fmt(course, '.2f')},{date},,,{mode}"
            )
        elif kind == "VTG":
            kmh = None if speed is None else speed / KMH_TO_M_S
            body = (
                f"VTG,{_fmt(course, '.2f')},T,,M,{_fmt(knots, '.3f')},N,{_fmt(kmh, '.3f')},K,{mode}"
            )
        elif kind == "GSA":
            count = min(solution.sats or 0, 12)
            ids = [f"{n:02d}" for n in range(1, count + 1)] + [""] * (12 - count)
            body = (
                f"GSA,A,{3 if fix else 1},{','.join(ids)},{_fmt(solution.pdop, '.2f')},"
                f"{_fmt(solution.hdop, '.2f')},{_fmt(solution.vdop, '.2f')}"
            )
        elif kind == "GST":
            body = (
                f"GST,{time_text},,,,,{_fmt(solution.lat_std_m, '.3f')},"
                f"{_fmt(solution.lon_std_m, '.3f')},{_fmt(solution.alt_std_m, '.3f')}"
            )
        elif kind == "HDT":  # empty heading: the receiver has no heading solution
            body = f"HDT,{_fmt(solution.heading_deg, '.2f')},T"
        else:
            raise ValueError(f"sentences: cannot encode {kind!r}; use "
                             f"{', '.join(sorted(USED_SENTENCES))}")
        out += nmea_sentence(talker + body)
    if ashtech_pos:
        out += nmea_sentence(_pashr_pos(solution, time_text, speed, course))
    return bytes(out)


def _pashr_pos(
    solution: GpsSolution, time_text: str, speed: float | None, course: float | None
) -> str:
    lat, ns = _fmt_coord(solution.lat_deg, 2, 4, "NS")
    lon, ew = _fmt_coord(solution.lon_deg, 3, 4, "EW")
    alt_ell = solution.alt_ellipsoid_m
    if alt_ell is None and solution.alt_m is not None:
        alt_ell = solution.alt_m + (solution.geoid_sep_m or 0.0)
    up = None if solution.vd_m_s is None else -solution.vd_m_s
    knots = None if speed is None else speed / KNOTS_TO_M_S
    position_type = "" if solution.fix == 0 else str(solution.fix - 1)
    return (
        f"PASHR,POS,{position_type},{_fmt(solution.sats, '02d')},{time_text},{lat},{ns},{lon},{ew},"
        f"{_fmt(alt_ell, '.2f')},,{_fmt(course, '.2f')},{_fmt(knots, '.3f')},{_fmt(up, '+.3f')},"
        f"{_fmt(solution.pdop, '.1f')},{_fmt(solution.hdop, '.1f')},{_fmt(solution.vdop, '.1f')},"
        f"{_fmt(solution.tdop, '.1f')},SIM1"
    )
