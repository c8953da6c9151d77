"""GPS decoder: a raw NMEA 0183 / Ashtech byte stream in, one :class:`GpsSolution` per epoch out.

The decoder turns a raw, possibly messy byte stream into one solution per receiver epoch
(sentences sharing one UTC time), timing each epoch from the arrival of its first byte to its
hand-off. It owns the byte-level framing of a damaged stream, the checksums, the epoch grouping
and the merge of an epoch's records (with unit conversion already done) into one solution. The
sentences themselves are read by :mod:`companion.drivers.nmea_sentences` and
:mod:`companion.drivers.ashtech_pos`; the simulator's encoder is :mod:`companion.drivers.gps_encoder`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Collection, Iterable
from dataclasses import dataclass
from functools import reduce
from operator import xor
from typing import Any

import pynmea2

from companion.drivers.ashtech_pos import parse_pos
from companion.drivers.gps_solution import GpsSolution
from companion.drivers.nmea_fields import Record
from companion.drivers.nmea_sentences import (
    TALKERS,
    USED_SENTENCES,
    parse_gga,
    parse_gsa,
    parse_gst,
    parse_hdt,
    parse_rmc,
    parse_vtg,
)

__all__ = ["MAX_LINE_CHARS", "NmeaCounters", "NmeaDecoder"]

MAX_LINE_CHARS = 120
"""Longest accepted sentence, counted from ``$`` through the checksum digits."""

_TIMED = frozenset({"GGA", "RMC", "GST", "POS"})

# Where a sentence ends: CR/LF, the start of another sentence, a checksum, or a byte that no
# text sentence contains (an Ashtech binary chunk, line noise).
_STOP = re.compile(rb"[\r\n$*]|[^\x20-\x7e]")
_HEX = re.compile(rb"[0-9A-Fa-f]{2}")


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



_EXTRACT: dict[str, Callable[[pynmea2.NMEASentence], Record]] = {
    "GGA": parse_gga,
    "RMC": parse_rmc,
    "VTG": parse_vtg,
    "GSA": parse_gsa,
    "GST": parse_gst,
    "HDT": parse_hdt,
    "POS": parse_pos,
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
