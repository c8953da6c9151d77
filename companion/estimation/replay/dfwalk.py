"""A streaming walk over an ArduPilot DataFlash log: its FMT table, and the raw bytes of the
message types asked for.

Why not pymavlink's `DFReader`: it maps the whole file, builds a Python object per message, and
resynchronises in silence, so a reader built on it can neither say where a log was damaged nor
stay small on a long log, and it is several times slower than what a replay needs. This walk
reads the file in fixed-size chunks, follows the record chain by the lengths the log's own FMT
messages give, keeps the bytes of the wanted types only (one `bytearray` a type, decoded later
with one numpy call) and, where the chain breaks, searches for the next place where two records
in a row make sense, reporting the skipped bytes with their offsets.

Format letters (ArduPilot's `LogStructure.h`): b/B int8/uint8, h/H int16/uint16, i/I
int32/uint32, q/Q int64/uint64, f float, d double, n/N/Z char[4]/[16]/[64], c/C int16/uint16
in hundredths, e/E int32/uint32 in hundredths, L int32 degrees*1e7, M uint8 (flight mode),
a int16[32], g half-float.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np

from companion.estimation.replay.series import SkippedRegion

log = logging.getLogger(__name__)

HEAD = b"\xa3\x95"
FMT_TYPE = 0x80
FMT_LEN = 89
CHUNK_BYTES = 1 << 20
MAX_REGIONS = 1000  # regions kept in detail; the rest are only counted

LETTERS: dict[str, str] = {
    "b": "i1", "B": "u1", "M": "u1", "h": "i2", "H": "u2", "c": "i2", "C": "u2", "i": "i4",
    "I": "u4", "e": "i4", "E": "u4", "L": "i4", "q": "i8", "Q": "u8", "f": "f4", "d": "f8",
    "g": "f2", "n": "S4", "N": "S16", "Z": "S64", "a": "(32,)i2",
}
SCALES: dict[str, float] = {"c": 0.01, "C": 0.01, "e": 0.01, "E": 0.01, "L": 1e-7}


@dataclass
class DfFormat:
    """One FMT message: a type's name, format letters and columns, and its numpy layout (None
    when the FMT is unusable; `problem` says why)."""

    type_id: int
    length: int
    name: str
    letters: str
    columns: tuple[str, ...]
    dtype: np.dtype | None
    problem: str = ""

    def column(self, data: np.ndarray, name: str) -> np.ndarray | None:
        """A column by name as floats in the log's units (hundredths and 1e-7 applied)."""
        if name not in self.columns:
            return None
        i = self.columns.index(name)
        letter = self.letters[i]
        if letter in "nNZa":
            return None
        v = data[f"f{i}"].astype(np.float64)
        scale = SCALES.get(letter)
        return v * scale if scale is not None else v


def parse_fmt(body: bytes) -> DfFormat:
    """An FMT message's 86 bytes after its header, checked: letters known, columns one a letter,
    and the length the letters add up to."""
    type_id, length = body[0], body[1]
    name = body[2:6].split(b"\0", 1)[0].decode("ascii", "replace")
    letters = body[6:22].split(b"\0", 1)[0].decode("ascii", "replace")
    columns = tuple(c for c in body[22:86].split(b"\0", 1)[0].decode("ascii", "replace")
                    .split(",") if c)
    problem = ""
    dtype: np.dtype | None = None
    if not name.isprintable() or not name:
        problem = "name is not text"
    elif any(c not in LETTERS for c in letters):
        problem = f"unknown format letter(s) in {letters!r}"
    else:
        dtype = np.dtype([(f"f{i}", "<" + LETTERS[c] if LETTERS[c][0] not in "(S" else
                           LETTERS[c].replace("i2", "<i2")) for i, c in enumerate(letters)])
        if dtype.itemsize + 3 != length:
            problem = f"length {length} but its format letters make {dtype.itemsize + 3}"
            dtype = None
        elif len(columns) != len(letters):
            # a firmware slip (seen in ArduCopter 3.2's EKF5): the record still frames, and
            # its names are read as naming the first fields, as pymavlink reads them
            problem = (f"{len(columns)} column names for {len(letters)} format letters: names "
                       "taken for the first fields")
            columns = columns[:len(letters)]
    return DfFormat(type_id, length, name, letters, columns, dtype, problem)


@dataclass
class DfWalk:
    """What a walk found: the formats by type id, the wanted types' raw message bodies (by FMT,
    so a type redefined mid-log keeps its two layouts apart), counts and skipped regions."""

    formats: dict[int, DfFormat] = field(default_factory=dict)
    bodies: list[tuple[DfFormat, bytearray]] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    skipped: list[SkippedRegion] = field(default_factory=list)
    regions_dropped: int = 0
    bytes_dropped: int = 0
    fmt_problems: list[str] = field(default_factory=list)
    size: int = 0
    messages: int = 0

    def data(self, name: str) -> list[tuple[DfFormat, np.ndarray]]:
        """The wanted type `name`'s messages as structured arrays, one a layout."""
        out = []
        for fmt, raw in self.bodies:
            if fmt.name == name and fmt.dtype is not None and raw:
                out.append((fmt, np.frombuffer(raw, dtype=fmt.dtype)))
        return out


class _Walker:
    def __init__(self, wanted: frozenset[str]) -> None:
        self.wanted = wanted
        self.lengths = [0] * 256
        self.lengths[FMT_TYPE] = FMT_LEN
        self.sinks: list[bytearray | None] = [None] * 256
        self.counts = [0] * 256
        self.result = DfWalk()
        self.bad_start: int | None = None  # absolute offset where unreadable bytes began
        self.fmt_bodies: dict[int, bytes] = {}

    def _fmt(self, body: bytes) -> None:
        if self.fmt_bodies.get(body[0]) == body:
            return  # repeated word for word (a log concatenated with another, or a restart)
        self.fmt_bodies[body[0]] = body
        f = parse_fmt(body)
        if f.type_id == FMT_TYPE:
            return  # the FMT of FMT itself: its length is fixed
        known = self.result.formats.get(f.type_id)
        if known is not None and (known.letters, known.columns, known.length) == (
                f.letters, f.columns, f.length):
            return  # repeated (a log concatenated with another, or a restart)
        if f.length < 3:
            self.result.fmt_problems.append(f"FMT of type {f.type_id} ({f.name}) has length "
                                            f"{f.length}: its messages cannot be followed")
            return
        if f.problem:
            state = "unusable" if f.dtype is None else "irregular"
            self.result.fmt_problems.append(f"FMT of type {f.type_id} ({f.name}) {state}: "
                                            f"{f.problem}")
        self.result.formats[f.type_id] = f
        self.lengths[f.type_id] = f.length
        self.sinks[f.type_id] = None
        if f.name in self.wanted and f.dtype is not None:
            sink = bytearray()
            self.sinks[f.type_id] = sink
            self.result.bodies.append((f, sink))

    def _plausible(self, buf: bytes, p: int, final: bool) -> bool | None:
        """Does a record start at `p` with another one right after it (or the end of the file)?
        None: not enough bytes in `buf` to tell yet."""
        n = len(buf)
        if p + 3 > n:
            return None if not final else False
        ln = self.lengths[buf[p + 2]]
        if ln == 0:
            return False
        q = p + ln
        if q + 3 > n:
            if final:
                return q <= n  # the last record, whole or cut short
            return None
        return buf[q] == 0xA3 and buf[q + 1] == 0x95 and self.lengths[buf[q + 2]] != 0

    def _resync(self, buf: bytes, off: int, base: int, final: bool) -> tuple[int, bool]:
        """Search from `off` for a plausible record; (its offset, True), or (where the search
        must go on when more bytes come, False)."""
        p = off
        while True:
            p = buf.find(HEAD, p)
            if p < 0:
                return max(off, len(buf) - 1), False
            ok = self._plausible(buf, p, final)
            if ok is None:
                return p, False
            if ok:
                return p, True
            p += 1

    def _region(self, start: int, end: int, what: str, tail: bool = False) -> None:
        r = self.result
        if len(r.skipped) < MAX_REGIONS:
            r.skipped.append(SkippedRegion(start, end - start, what, tail))
        else:
            r.regions_dropped += 1
            r.bytes_dropped += end - start

    def walk(self, buf: bytes, base: int, final: bool) -> int:
        """Walk `buf` (file bytes from absolute offset `base`); returns the offset in `buf`
        where the next chunk must continue."""
        lengths, sinks, counts = self.lengths, self.sinks, self.counts
        n = len(buf)
        off = 0
        messages = 0
        while True:
            if self.bad_start is not None:
                off, found = self._resync(buf, off, base, final)
                if not found:
                    break
                self._region(self.bad_start, base + off, "unreadable bytes (no record header "
                             "where the previous record ended)")
                self.bad_start = None
            if off + 3 > n:
                break
            typ = buf[off + 2]
            ln = lengths[typ]
            if buf[off] != 0xA3 or buf[off + 1] != 0x95 or ln == 0:
                self.bad_start = base + off
                off += 1
                continue
            end = off + ln
            if end > n:
                break
            messages += 1
            counts[typ] += 1
            if typ == FMT_TYPE:
                self._fmt(buf[off + 3:end])
            else:
                sink = sinks[typ]
                if sink is not None:
                    sink += buf[off + 3:end]
            off = end
        self.result.messages += messages
        return off

    def finish(self, buf: bytes, base: int) -> None:
        """The bytes left at the end of the file: a cut-short last record, or damage that runs
        to the end."""
        n = len(buf)
        r = self.result
        if self.bad_start is not None:
            tail = buf[self.bad_start - base:] if self.bad_start >= base else buf
            fill = set(tail)
            what = (f"padding (0x{next(iter(fill)):02X}) after the last record"
                    if len(fill) == 1 else "unreadable bytes up to the end of the file")
            self._region(self.bad_start, base + n, what, tail=True)
        elif n > 0:
            if n >= 3 and buf[0] == 0xA3 and buf[1] == 0x95 and self.lengths[buf[2]]:
                f = r.formats.get(buf[2])
                name = f" ({f.name})" if f else (" (FMT)" if buf[2] == FMT_TYPE else "")
                what = (f"file cut short inside a message of type {buf[2]}{name}, "
                        f"{n} of its {self.lengths[buf[2]]} bytes")
            else:
                what = "file cut short inside a message header"
            self._region(base, base + n, what, tail=True)
        for t, c in enumerate(self.counts):
            if c:
                f = r.formats.get(t)
                name = f.name if f else ("FMT" if t == FMT_TYPE else str(t))
                r.counts[name] = r.counts.get(name, 0) + c


def walk_dataflash(fh: BinaryIO, wanted: frozenset[str], chunk_bytes: int = CHUNK_BYTES
                   ) -> DfWalk:
    """Walk an open DataFlash file from its start, in chunks of `chunk_bytes`."""
    w = _Walker(wanted)
    carry = b""
    base = 0
    while True:
        chunk = fh.read(chunk_bytes)
        final = not chunk
        buf = carry + chunk if carry else chunk
        if final:
            used = w.walk(carry, base, final=True)
            w.finish(carry[used:], base + used)
            break
        used = w.walk(buf, base, final=False)
        carry = buf[used:]
        base += used
    w.result.size = base + len(carry)
    return w.result


def walk_dataflash_file(path: Path, wanted: frozenset[str]) -> DfWalk:
    with path.open("rb") as fh:
        return walk_dataflash(fh, wanted)
