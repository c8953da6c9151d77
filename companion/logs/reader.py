"""Reader of binary flight logs: whole file in, one numpy structured array per format out.

How it stays fast: record boundaries are a chain (each header gives the size of its record),
followed without a Python step per record. A run of one repeating pattern of record headers
(one Data Block format, or a few interleaved) is predicted from its first records and every
predicted header is checked at once through strided views (`_verify_run`); elsewhere walkers
started every few kilobytes follow the chain in lockstep, one numpy step per record, and hand
over where one lands on the next one's start (`_walk_fast`); what neither proves (damage, the
end of the file) is walked record by record (`_scan_py`, the reference the others are tested
against). The walks hand over the headers they read, so no later pass reads them again.
Everything else (which definition applies to each record, validation, field extraction) is
done with numpy over all records at once: while one set of definitions is in force, one table
indexed by a record's type and index bytes gives the length it needs and its stream; each Data
Block format's rows come out of the file bytes with one gather of whole records (TIME and
fields already have the layout of a row, TIME becoming ``time_s`` in place), each Byte Array
format's elements with one block copy per record of its common lengths (the others in pieces
of power-of-two sizes). Every pass over all records costs about as much as reading the file
once, so the passes are few.

How it stays safe: every loop advances through the file, every allocation is proportional to
the file size, and anything the contract calls corruption raises `LogFormatError` with the byte
offset, or, with ``salvage=True``, is skipped up to the next offset where a plausible record
starts and recorded in `LogFile.damage`.

Layout of the results (see docs/logs.md):

* A Data Block format gives a structured array with ``time_s`` (float64 seconds) followed by one
  typed field per conversion, named from the Format Comment (else ``c1, c2, ...``).
* A Byte Array format gives a "long" structured array, one row per element: ``time_s``,
  ``record`` (the record's number in its stream), ``element`` (position in the record) and the
  value (named from a one-name comment, else ``value``). `Stream.arrays()` gives one 1-D array
  per record instead.
* Redefining an index: records are grouped into *streams* by (index, record kind, format string,
  column names); a redefinition that changes any of these starts a new stream, an identical one
  continues the old stream. `LogFile.data(index)` concatenates the streams of an index when they
  share one layout and otherwise refuses and points at `LogFile.streams_of(index)`.

Size: the fast path, the salvage path for damaged files and the per-format decoding share
the record-walking code; splitting it would duplicate that. The fast walks sit next to the
reference walk they must agree with, so a change to framing is made in one place.
"""

from __future__ import annotations

import logging
import os
from array import array
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from companion.logs.formats import FormatError, FormatSpec, parse_format
from companion.logs.records import (
    ARRAY,
    ARRAY_ALT,
    BEGIN,
    COMMENT,
    DATA,
    DEFINITION,
    END,
    HEADER_SIZE,
    KNOWN_TYPES,
    TIMED_SIZE,
    TYPE_NAMES,
)

if TYPE_CHECKING:
    import pandas as pd

__all__ = [
    "Damage",
    "LogFile",
    "LogFormatError",
    "Marker",
    "Stream",
    "column_names",
    "framed_length",
    "read_log",
    "read_log_bytes",
]

log = logging.getLogger(__name__)

_NS = 1_000_000_000
_UNKNOWN = 1 << 62  # size of an unknown record type in the boundary pass: always "past the end"
_SIZES = [_UNKNOWN] * 256
for _t in (BEGIN, END, DATA, ARRAY, ARRAY_ALT):
    _SIZES[_t] = TIMED_SIZE
for _t in (COMMENT, DEFINITION):
    _SIZES[_t] = HEADER_SIZE
_KNOWN_LUT = np.zeros(256, dtype=bool)
_KNOWN_LUT[list(KNOWN_TYPES)] = True
_SIZES_NP = np.minimum(np.array(_SIZES, dtype=np.int64), 1 << 40)  # no overflow in sums
_EMPTY = np.zeros(0, dtype=np.int64)
_NO_WORDS = np.zeros(0, dtype="<u4")
_NO_BAD = np.zeros(0, dtype=bool)
# The fast walk (`_walk_fast`): stretches shorter than _FAST_MIN bytes are walked in Python;
# a stretch starts at _FAST_CHUNK bytes and doubles while it is proved whole; one walker per
# _SEGMENT bytes starts at the first of the segment's first _PROBE (else _PROBE_WIDE) bytes
# from which _PROBE_STEPS headers chain onto known types; a failed hand-over is followed in
# Python for at most _RESYNC bytes; past what the fast walk proves, _SLOW_WINDOW bytes are
# walked in Python.
_FAST_MIN = 1 << 15
_FAST_CHUNK = 1 << 20
_FAST_CHUNK_MAX = 1 << 22
_SEGMENT = 4096
_PROBE = 128
_PROBE_WIDE = 1024
_PROBE_STEPS = 3
_HIGH = np.arange(256, dtype=np.int64) << 8  # the high byte of a length, shifted
_RESYNC = 4 * _SEGMENT
# Runs (`_verify_run`): the period (at most _RUN_PERIOD records) is learnt from the records of
# the first _RUN_LEARN bytes; _RUN_MISSES runs in a row shorter than _RUN_MIN records (the
# first may be the definitions at the start of a file) hand over to the walkers.
_RUN_PERIOD = 12
_RUN_LEARN = 4096
_RUN_MIN = 512
_RUN_MISSES = 2
_SLOW_WINDOW = 1 << 14
_KEYED_MIN = 4096  # at least this many data records: checked through a table of 16-bit keys
# Items gathered at record offsets (`_items`): a header, its type and index bytes, a TIME.
_HEADER = np.dtype("V4")
_KEY = np.dtype("V2")
_TIME_V = np.dtype("V8")
_TIME = np.dtype([("s", "<i4"), ("ns", "<u4")])
_ROW_GROUPS = 4  # Byte Array lengths copied as whole rows (the most common ones)
_FEW = 16  # at most this many formats/streams: group records by one pass per format
_SALVAGE_WINDOW = 1024  # bytes parsed after a resynchronisation before validating (doubles)
_SEARCH_WINDOW = 1 << 16  # most bytes examined at once when looking for a plausible record


class LogFormatError(ValueError):
    """A damaged or malformed log; carries the file name, the byte offset and the kind.

    kind is one of: unknown_type, past_eof, undefined_index, length_mismatch, bad_definition.
    """

    def __init__(self, path: str, offset: int, message: str, kind: str) -> None:
        self.path = path
        self.offset = offset
        self.reason = message
        self.kind = kind
        super().__init__(f"{path}: byte offset {offset}: {message}")


@dataclass(frozen=True)
class Marker:
    """A Begin Data or End Data record."""

    kind: str  # "begin" or "end"
    time_ns: int
    offset: int

    @property
    def time_s(self) -> float:
        return self.time_ns / _NS


@dataclass(frozen=True)
class Damage:
    """A corrupt region skipped by a salvaging read."""

    offset: int
    kind: str
    message: str
    skipped_bytes: int


@dataclass
class Stream:
    """The records of one format index under one definition (see the module docstring).

    A Byte Array stream keeps its elements as one flat array (`values`, record after record,
    with `lengths`); its long table `data` (one 15-byte row per element) is built on first use.
    """

    index: int
    kind: str  # "block" (Data Block) or "array" (Byte Array)
    spec: FormatSpec
    columns: tuple[str, ...]
    number: int  # 1 for the first stream of its index, 2 for the next...
    definition_offset: int
    time_ns: np.ndarray  # int64 per record, exact
    offsets: np.ndarray  # int64 byte offset of each record
    lengths: np.ndarray | None = None  # elements per record (arrays only)
    values: np.ndarray | None = None  # arrays: every element, in file order
    time_s: np.ndarray | None = None  # arrays: float64 seconds per record
    _data: np.ndarray | None = field(default=None, repr=False)

    @property
    def data(self) -> np.ndarray:
        """The structured array: one row per record (blocks) or per element (arrays)."""
        if self._data is None:
            self._data = self._long_table()
        return self._data

    def _long_table(self) -> np.ndarray:
        assert self.values is not None and self.lengths is not None and self.time_s is not None
        lens = self.lengths.astype(np.int64)
        total = int(self.values.size)
        out = np.empty(
            total,
            dtype=np.dtype(
                [
                    ("time_s", "<f8"),
                    ("record", "<u4"),
                    ("element", "<u2"),
                    (self.columns[0], self.values.dtype),
                ]
            ),
        )
        before = np.cumsum(lens) - lens
        out[self.columns[0]] = self.values
        out["time_s"] = np.repeat(self.time_s, lens)
        out["record"] = np.repeat(np.arange(self.offsets.size), lens)
        out["element"] = np.arange(total) - np.repeat(before, lens)
        return out

    def head(self, k: int) -> Stream:
        """The stream of its first `k` records."""
        if self.kind != "array":
            return replace(self, time_ns=self.time_ns[:k], offsets=self.offsets[:k],
                           _data=self.data[:k])
        assert self.lengths is not None and self.values is not None and self.time_s is not None
        n_values = int(self.lengths[:k].sum())
        return replace(
            self, time_ns=self.time_ns[:k], offsets=self.offsets[:k], lengths=self.lengths[:k],
            values=self.values[:n_values], time_s=self.time_s[:k],
            _data=None if self._data is None else self._data[:n_values],
        )

    @property
    def format(self) -> str:
        return self.spec.text

    @property
    def n_records(self) -> int:
        return int(self.offsets.size)

    @property
    def value_field(self) -> str:
        """For arrays, the name of the element field of `data`."""
        return self.columns[0]

    def arrays(self) -> list[np.ndarray]:
        """One 1-D array of elements per record (arrays only)."""
        if self.kind != "array" or self.lengths is None or self.values is None:
            raise ValueError(f"format index {self.index} holds Data Blocks, not Byte Arrays")
        return np.split(self.values, np.cumsum(self.lengths)[:-1]) if self.lengths.size else []

    def to_pandas(self) -> pd.DataFrame:
        import pandas as pd

        return pd.DataFrame({name: self.data[name] for name in self.data.dtype.names or ()})


@dataclass
class LogFile:
    """Everything read from one binary log."""

    path: str
    size_bytes: int
    streams: list[Stream]
    markers: list[Marker]
    damage: list[Damage]
    truncated_bytes: int
    record_count: int
    warnings: list[str] = field(default_factory=list)

    @property
    def indexes(self) -> list[int]:
        return sorted({s.index for s in self.streams})

    @property
    def closed_cleanly(self) -> bool:
        """True when the last marker is an End Data and no record was cut short."""
        return bool(self.markers) and self.markers[-1].kind == "end" and not self.truncated_bytes

    @property
    def skipped_bytes(self) -> int:
        return sum(d.skipped_bytes for d in self.damage)

    @property
    def skipped_records(self) -> int:
        """Corrupt records skipped by salvage (one per damaged region)."""
        return len(self.damage)

    def streams_of(self, index: int) -> list[Stream]:
        found = [s for s in self.streams if s.index == index]
        if not found:
            raise KeyError(f"{self.path}: no format index {index} (have {self.indexes})")
        return found

    def begin_end_pairs(self) -> list[tuple[Marker | None, Marker | None]]:
        """Begin/End markers paired in file order; a missing half is None."""
        pairs: list[tuple[Marker | None, Marker | None]] = []
        pending: Marker | None = None
        for m in self.markers:
            if m.kind == "begin":
                if pending is not None:
                    pairs.append((pending, None))
                pending = m
            else:
                pairs.append((pending, m))
                pending = None
        if pending is not None:
            pairs.append((pending, None))
        return pairs

    def data(self, index: int) -> np.ndarray:
        """The structured array of a format index (all its streams, when they share a layout)."""
        streams = self.streams_of(index)
        if len(streams) == 1:
            return streams[0].data
        first = streams[0]
        for s in streams[1:]:
            if s.data.dtype != first.data.dtype or s.kind != first.kind:
                raise ValueError(
                    f"{self.path}: format index {index} changes layout at byte offset "
                    f"{s.definition_offset} ({first.format!r} -> {s.format!r}); "
                    f"use streams_of({index}) or to_pandas({index})"
                )
        if first.kind == "array":
            raise ValueError(
                f"{self.path}: format index {index} has {len(streams)} array streams; "
                f"use streams_of({index})"
            )
        offsets = np.concatenate([s.offsets for s in streams])
        order = np.argsort(offsets, kind="stable")
        return np.concatenate([s.data for s in streams])[order]

    __getitem__ = data

    def time_ns(self, index: int) -> np.ndarray:
        """Exact record times (int64 ns) of a format index, in file order."""
        streams = self.streams_of(index)
        offsets = np.concatenate([s.offsets for s in streams])
        times = np.concatenate([s.time_ns for s in streams])
        return times[np.argsort(offsets, kind="stable")]

    def to_pandas(self, index: int) -> pd.DataFrame:
        """A DataFrame of a format index; streams with other columns are aligned (NaN-filled)."""
        import pandas as pd

        streams = self.streams_of(index)
        frames = [s.to_pandas() for s in streams]
        if len(frames) == 1:
            return frames[0]
        keys = np.concatenate(
            [s.offsets if s.lengths is None else np.repeat(s.offsets, s.lengths) for s in streams]
        )
        frame = pd.concat(frames, ignore_index=True)
        return frame.iloc[np.argsort(keys, kind="stable")].reset_index(drop=True)


# --------------------------------------------------------------------------------------------


@dataclass
class _Version:
    """The definition state of one index from one FD/FC record on."""

    index: int
    offset: int
    spec: FormatSpec | None
    comment: tuple[str, ...] | None


def _scan_py(buf: bytes, start: int, stop: int) -> tuple[array[int], int, str]:
    """Follow the record chain from `start` one record at a time (the reference walk).

    Returns the offsets of the records that fit in the file, the offset where it stopped, and
    why: "eof", "window" (reached `stop`), "unknown" (unknown type), "past_eof" (record longer
    than the rest of the file) or "cut_header" (fewer than 4 bytes left).
    """
    n = len(buf)
    sizes = _SIZES
    out: array[int] = array("q")
    app = out.append
    off = start
    limit = min(stop, n - 3)
    while off < limit:
        nxt = off + sizes[buf[off]] + (buf[off + 2] | (buf[off + 3] << 8))
        if nxt > n:
            break
        app(off)
        off = nxt
    else:
        if off == n:
            return out, off, "eof"
        if off >= stop:
            return out, off, "window"
        return out, off, "cut_header"
    return out, off, ("unknown" if sizes[buf[off]] == _UNKNOWN else "past_eof")


def _scan(buf: bytes, start: int, stop: int, *, fast: bool = True) -> tuple[np.ndarray, int, str]:
    """Follow the record chain from `start`; the hot loop of the reader.

    Same contract as `_scan_py` (offsets as an int64 array). Long stretches are walked by
    `_verify_run` and `_walk_fast`, which return only offsets they have proved to be on the
    chain; whatever they leave (damage, the end of the file, a stretch they could not prove) is
    walked by `_scan_py` a window at a time, so both give the same offsets and the same stop
    (tested).
    """
    offs, _, off, reason = _frame(buf, start, stop, fast=fast)
    return offs, off, reason


def _frame(
    buf: bytes, start: int, stop: int, *, fast: bool = True
) -> tuple[np.ndarray, np.ndarray, int, str]:
    """`_scan`, with the header of every record found (as `_headers` gives it): the fast walks
    have read them already, so the parser does not gather them again."""
    n = len(buf)
    arr = np.frombuffer(buf, dtype=np.uint8)
    limit = min(stop, n - 3)
    if not fast or limit - start < _FAST_MIN:
        found, off, reason = _scan_py(buf, start, stop)
        offs = _as_offsets(found)
        return offs, _headers(arr, offs), off, reason
    parts: list[np.ndarray] = []
    words: list[np.ndarray] = []
    pos = start
    chunk = _FAST_CHUNK
    while True:
        if limit - pos >= _FAST_MIN:
            end = min(limit, pos + chunk)
            misses = 0
            while True:  # runs of a repeating pattern first, verified whole
                nodes, heads, pos = _verify_run(buf, arr, pos, end)
                parts.append(nodes)
                words.append(heads)
                misses = misses + 1 if nodes.size < _RUN_MIN else 0
                if misses == _RUN_MISSES or pos >= end:
                    break
            whole = pos >= end
            if not whole:
                # walkers start on records like the data records just walked
                data = heads[(heads & 4) == 0]
                keys = np.unique(data & 0xFFFF) if data.size else None
                nodes, heads, pos, whole = _walk_fast(buf, arr, pos, end, keys)
                parts.append(nodes)
                words.append(heads)
            if whole:  # proved up to `end`: go on with a longer stretch
                chunk = min(2 * chunk, _FAST_CHUNK_MAX)
                if pos < limit:
                    continue
            else:
                chunk = _FAST_CHUNK
        # The reference walk: the end of the range, or past what the fast walk could not prove.
        found, pos, reason = _scan_py(buf, pos, min(stop, pos + _SLOW_WINDOW))
        if len(found):
            parts.append(_as_offsets(found))
            words.append(_headers(arr, parts[-1]))
        if reason != "window" or pos >= stop:
            return _join(parts), _join(words, _NO_WORDS), pos, reason


def _verify_run(
    buf: bytes, arr: np.ndarray, start: int, end: int
) -> tuple[np.ndarray, np.ndarray, int]:
    """The longest stretch from `start` (a record start) that repeats the headers of its first
    records, as far as it is proved: offsets, headers and the offset after the last one.

    Most logs are long runs of one pattern of records (one Data Block format, or a fast and a
    slow format interleaved), so the offsets of the whole stretch are predicted from the period
    and every predicted record's header is checked at once, one strided view per position in
    the period: a record whose header is the predicted one has the predicted size, so it proves
    the next offset, from `start` on, up to the first that differs (kept when it fits).
    """
    n = arr.size
    head, stop, _ = _scan_py(buf, start, min(end, start + _RUN_LEARN))
    first = _as_offsets(head)
    words = _headers(arr, first)
    if len(head) < 2 * _RUN_PERIOD:
        return first, words, stop
    period = 0
    for p in range(1, _RUN_PERIOD + 1):
        if np.array_equal(words[p:], words[:-p]):
            period = p
            break
    if not period:
        return first[:-1], words[:-1], int(first[-1])
    pattern = words[:period].tolist()
    cum = [0]
    for w in pattern:
        cum.append(cum[-1] + _SIZES[w & 0xFF] + (w >> 16))
    span = cum[-1]
    phase = np.array(cum[:-1], dtype=np.int64)

    def offsets(count: int) -> np.ndarray:  # of the first `count` records from pos
        rounds = -(-count // period)
        return np.add.outer(np.arange(rounds, dtype=np.int64) * span + pos, phase).ravel()[:count]

    proved: list[np.ndarray] = []
    heads: list[np.ndarray] = []
    pos = start
    periods = _RUN_MIN  # checked at once: grows while the run holds
    while pos < end:
        rounds = min(periods, -(-(end - pos) // span))
        # per position j in the period, the records of the `rounds` periods that start before end
        counts = [min(rounds, max(0, -(-(end - pos - cum[j]) // span))) for j in range(period)]
        total = sum(counts)
        bad = total
        for j, count in enumerate(counts):
            if not count:
                continue
            view = np.ndarray((count,), dtype="<u4", buffer=arr, offset=pos + cum[j], strides=(span,))
            differs = view != pattern[j]
            k = int(differs.argmax())
            if differs[k]:
                bad = min(bad, k * period + j)
        last = bad if bad < total else total - 1  # the last record on the chain
        at = pos + (last // period) * span + cum[last % period]
        after = at + _SIZES[buf[at]] + (buf[at + 2] | (buf[at + 3] << 8))
        kept = last + 1 if after <= n else last  # the last one is not proved if it does not fit
        proved.append(offsets(kept))
        heads.append(np.tile(words[:period], -(-kept // period))[:kept])
        if kept > last and bad < total:
            heads[-1][-1] = int.from_bytes(buf[at : at + 4], "little")
        if after > n:
            return _join(proved), _join(heads, _NO_WORDS), at
        pos = after
        if bad < total:
            break
        periods = min(periods * 4, (end - pos) // span + 1)
    return _join(proved), _join(heads, _NO_WORDS), pos


def _walk_fast(
    buf: bytes, arr: np.ndarray, start: int, end: int, keys: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, int, bool]:
    """The record chain from `start` (a record start) over [start, end), in numpy.

    The stretch is cut into segments of `_SEGMENT` bytes. In each segment (but the first) a
    walker starts at the first offset near its start from which `_PROBE_STEPS` headers in a
    row chain onto known record types (`_walker_starts`), and all walkers follow their chains
    in lockstep, one record per numpy step, past the next walker's start. A walker that lands
    exactly on the next one's start hands over to it: since the first walker starts on the
    chain, every walker reached by an unbroken series of hand-overs is on it too. Where a
    hand-over fails (a walker started inside a record, a record spans segments, damage) the
    chain is followed record by record from where the last good walker stopped until it meets
    a walker's start again (`_resync`). `keys`: see `_walker_starts`.

    Returns the offsets proved (records that fit, starting before `end`), their headers, the
    offset after the last of them (a record start, or the end of a record that reaches past
    `end`), and whether the whole stretch was proved. `end` must be at most len(buf) - 3.
    """
    n = arr.size
    k_seg = max(1, (end - start + _SEGMENT // 2) // _SEGMENT)  # the last: 1/2 to 3/2 segments
    starts = np.array([start], dtype=np.int64)
    if k_seg > 1:
        found = _walker_starts(arr, start + _SEGMENT, k_seg - 1, keys)
        starts = np.concatenate((starts, found[found >= 0]))
    stops = np.append(starts[1:], end)
    sizes = _SIZES_NP
    items = _items(arr, 0, _HEADER)  # the 4 header bytes at every offset, in one gather
    last = items.size - 1
    pos = starts
    steps = [pos]
    words: list[np.ndarray] = []
    for k in range(_SEGMENT // 4 + 1):
        # A walker past the end (or on an unknown type) reads garbage (the last header), but
        # it has passed its stop, and what it reads there is never used.
        word = items[np.minimum(pos, last)].view("<u4")
        words.append(word)
        nxt = sizes.take(word & 0xFF)
        nxt += pos
        nxt += word >> 16
        pos = nxt
        steps.append(pos)
        if k % 4 == 3:
            behind = int(np.count_nonzero(pos < stops))
            # the last few stragglers (a segment without a walker of its own) are resynced
            if not behind or (behind * 256 < pos.size and k >= _SEGMENT // 64):
                break
    words.append(items[np.minimum(pos, last)].view("<u4"))
    paths = np.stack(steps)  # (step, walker): walker k's offsets down column k
    heads = np.stack(words)  # and their headers
    inside = paths < stops
    count = inside.sum(axis=0)  # records of each walker before its stop
    reached = count < paths.shape[0]
    after = paths[np.minimum(count, paths.shape[0] - 1), np.arange(starts.size)]
    # where each walker stopped: its stop when it handed over, past it, or -1 (step bound)
    after = np.where(reached, after, -1)
    handed = after == stops
    handed[-1] = end <= after[-1] <= n
    bad = np.flatnonzero(~handed)
    if not bad.size:
        return paths.T[inside.T], heads.T[inside.T], int(after[-1]), True
    walked, read, mask = paths.T, heads.T, inside.T
    pieces: list[np.ndarray] = []
    pwords: list[np.ndarray] = []
    k = 0
    while True:
        j_at = int(np.searchsorted(bad, k))
        j = int(bad[j_at]) if j_at < bad.size else starts.size
        if j > k:
            pieces.append(walked[k:j][mask[k:j]])
            pwords.append(read[k:j][mask[k:j]])
        if j == starts.size:
            return _join(pieces), _join(pwords, _NO_WORDS), int(after[-1]), True
        # Walker j is on the chain but did not hand over: follow the chain from there.
        row, row_words = walked[j][mask[j]], read[j][mask[j]]
        if after[j] > n:  # its last record does not fit or has an unknown type: not proved
            pieces.append(row[:-1])
            pwords.append(row_words[:-1])
            return _join(pieces), _join(pwords, _NO_WORDS), int(row[-1]), False
        if after[j] < 0:  # cut by the step bound: go on from its last offset
            p = int(row[-1])
            row, row_words = row[:-1], row_words[:-1]
        else:
            p = int(after[j])
        pieces.append(row)
        pwords.append(row_words)
        nodes, p, k = _resync(buf, p, starts, j + 1, end)
        pieces.append(nodes)
        pwords.append(_headers(arr, nodes))
        if k < 0:
            return _join(pieces), _join(pwords, _NO_WORDS), p, p >= end


def _walker_starts(
    arr: np.ndarray, first: int, count: int, keys: np.ndarray | None = None
) -> np.ndarray:
    """Per segment (`count` of `_SEGMENT` bytes from `first`), the first offset of its first
    `_PROBE` bytes (else of its first `_PROBE_WIDE`, for long records) from which
    `_PROBE_STEPS` headers chain onto known types; -1 where none.

    With `keys` (the type and index bytes, as uint16, of the data records seen just before),
    only the first offset with one of them is probed: random bytes rarely have one, so that
    one is nearly always a record start.
    """
    n = arr.size
    found = np.full(count, -1, dtype=np.int64)
    segs: np.ndarray | None = None  # the segments still without a walker (None: all)
    lut = None
    if keys is not None:
        lut = np.zeros(1 << 16, dtype=bool)
        lut[keys] = True
    lo = 0
    for hi in (_PROBE, _PROBE_WIDE):
        grid = np.ndarray((count, hi - lo), dtype=np.uint8, buffer=arr, offset=first + lo,
                          strides=(_SEGMENT, 1))
        if segs is not None:
            grid = grid[segs]
        # Walkers start on Data Blocks and Byte Arrays (nearly every record; compares are
        # cheap). The candidates of all segments are probed at once, a few per segment.
        grid = np.ascontiguousarray(grid).reshape(-1)  # one row loop, then flat compares
        cell = np.flatnonzero((grid == DATA) | (grid == ARRAY) | (grid == ARRAY_ALT))
        seg = cell // (hi - lo) if segs is None else segs[cell // (hi - lo)]
        cand = seg * _SEGMENT + cell % (hi - lo) + (first + lo)
        if lut is not None:
            seen = lut.take(_items(arr, 0, _KEY)[cand].view("<u2"))
            seg, cand = seg[seen], cand[seen]
            if seg.size:
                head = np.ones(seg.size, dtype=bool)  # the first candidate of its segment
                np.not_equal(seg[1:], seg[:-1], out=head[1:])
                seg, cand = seg[head], cand[head]
        ok = np.ones(cand.size, dtype=bool)
        sizes, high, known = _SIZES_NP, _HIGH, _KNOWN_LUT
        q = cand
        for _ in range(_PROBE_STEPS):
            nxt = sizes.take(arr.take(q, mode="clip"))
            nxt += arr.take(q + 2, mode="clip")
            nxt += high.take(arr.take(q + 3, mode="clip"))
            nxt += q
            q = nxt
            ok &= (q == n) | ((q < n) & known.take(arr.take(q, mode="clip")))
        seg, cand = seg[ok], cand[ok]
        if seg.size:
            head = np.ones(seg.size, dtype=bool)  # the first candidate of its segment
            np.not_equal(seg[1:], seg[:-1], out=head[1:])
            found[seg[head]] = cand[head]
        segs = np.flatnonzero(found < 0)
        if not segs.size:
            break
        lo = hi
    return found


def _resync(buf: bytes, p: int, starts: np.ndarray, m: int, end: int) -> tuple[np.ndarray, int, int]:
    """Follow the chain record by record from `p` (on it) until it meets a walker's start.

    Returns the offsets walked, where it stopped, and the walker met (-1: none, at the end of
    the stretch, at a record that does not fit or after `_RESYNC` bytes).
    """
    n = len(buf)
    sizes = _SIZES
    out: array[int] = array("q")
    bound = min(end, p + _RESYNC)
    nxt_start = int(starts[m]) if m < starts.size else end + 1
    while p < bound:
        if p >= nxt_start:
            m = int(np.searchsorted(starts, p))
            if m < starts.size and int(starts[m]) == p:
                return _as_offsets(out), p, m
            nxt_start = int(starts[m]) if m < starts.size else end + 1
        nxt = p + sizes[buf[p]] + (buf[p + 2] | (buf[p + 3] << 8))
        if nxt > n:
            break
        out.append(p)
        p = nxt
    return _as_offsets(out), p, -1


def _as_offsets(offs: array[int]) -> np.ndarray:
    return np.frombuffer(offs, dtype=np.int64) if len(offs) else _EMPTY


def _join(pieces: list[np.ndarray], empty: np.ndarray = _EMPTY) -> np.ndarray:
    pieces = [x for x in pieces if x.size]
    if not pieces:
        return empty
    return pieces[0] if len(pieces) == 1 else np.concatenate(pieces)


def framed_length(buf: bytes) -> int:
    """Length of the longest prefix of `buf` made of whole records (framing only)."""
    _, off, reason = _scan(buf, 0, len(buf))
    return len(buf) if reason == "eof" else off


def _clean_names(names: list[str], count: int) -> tuple[str, ...]:
    out: list[str] = []
    seen = {"time_s"}
    for k in range(count):
        name = names[k].strip() if k < len(names) else ""
        if not name:
            name = f"c{k + 1}"
        base, n = name, 2
        while name in seen:
            name = f"{base}_{n}"
            n += 1
        seen.add(name)
        out.append(name)
    return tuple(out)


def column_names(comment: Sequence[str] | None, spec: FormatSpec, kind: str) -> tuple[str, ...]:
    """Field names of a stream from its Format Comment (shared with the text-mode writer).

    Data Blocks: the comment's names when there is one per field (blank ones become ``c<k>``,
    repeats and ``time_s`` get a ``_2`` suffix), else ``c1, c2, ...``. Byte Arrays: the single
    name of a one-name comment (unless it is time_s, record or element), else ``value``.
    """
    names = [n.strip() for n in comment] if comment is not None else []
    if kind == "array":
        name = names[0] if len(names) == 1 else ""
        return (name if name and name not in ("time_s", "record", "element") else "value",)
    if len(names) != spec.n_fields:
        names = []
    return _clean_names(names, spec.n_fields)


class _Parser:
    def __init__(self, buf: bytes, path: str, salvage: bool, fast: bool = True) -> None:
        self.fast = fast  # False: the reference walk only (tests compare the two)
        self.buf = buf
        self.n = len(buf)
        self.arr = np.frombuffer(buf, dtype=np.uint8)
        self.path = path
        self.salvage = salvage
        self.versions: list[_Version] = []
        self.current = np.full(256, -1, dtype=np.int64)  # version id in force per index
        self.markers: list[Marker] = []
        self.damage: list[Damage] = []
        self.warnings: list[str] = []
        self.truncated = 0
        self.record_count = 0
        # Kept data records: offsets, lengths, and their (version, kind) pairs (version * 2 + 1
        # for a Byte Array), one per record or as the positions of the records of each pair.
        self.chunks: list[
            tuple[np.ndarray, np.ndarray, np.ndarray | None, dict[int, np.ndarray | slice] | None]
        ] = []
        self._warned_columns: set[int] = set()
        # Per version id: data size (-1: comment only, no format yet) and Byte-Array fitness.
        self._vsize = np.full(16, -1, dtype=np.int64)
        self._vbytes = np.zeros(16, dtype=bool)

    # -- the main loop ---------------------------------------------------------------------

    def run(self) -> LogFile:
        pos = 0
        window = self.n  # unbounded until a resynchronisation
        while pos < self.n:
            stop = pos + window if window < self.n else self.n
            found, words, stop_off, reason = _frame(self.buf, pos, stop, fast=self.fast)
            err = self._commit(found, words)
            if err is not None:
                pos = self._corrupt(*err)
                window = _SALVAGE_WINDOW
                continue
            if reason == "eof":
                break
            if reason == "window":
                pos = stop_off
                window *= 2
                continue
            if reason == "unknown":
                pos = self._corrupt(
                    stop_off,
                    "unknown_type",
                    f"unknown record type 0x{self.buf[stop_off]:02X}",
                )
                window = _SALVAGE_WINDOW
                continue
            tail = self._tail(stop_off)
            if tail is None:
                self.truncated = self.n - stop_off
                msg = (
                    f"{self.path}: last record at byte offset {stop_off} is cut short "
                    f"({self.truncated} bytes dropped)"
                )
                self.warnings.append(msg)
                log.warning(msg)
                break
            pos = self._corrupt(stop_off, *tail)
            window = _SALVAGE_WINDOW
        return self._finish()

    def _corrupt(self, offset: int, kind: str, message: str) -> int:
        if not self.salvage:
            raise LogFormatError(self.path, offset, message, kind)
        nxt = self._find_plausible(offset + 1, self.n)
        self.damage.append(Damage(offset, kind, message, nxt - offset))
        log.warning(
            "%s: byte offset %d: %s; skipped %d bytes", self.path, offset, message, nxt - offset
        )
        return nxt

    # -- validation of a chunk of framed records -------------------------------------------

    def _time_at(self, off: int) -> int:
        sec = int.from_bytes(self.buf[off + 4 : off + 8], "little", signed=True)
        nsec = int.from_bytes(self.buf[off + 8 : off + 12], "little")
        return sec * _NS + nsec

    def _new_version(
        self, index: int, off: int, spec: FormatSpec | None, comment: tuple[str, ...] | None
    ) -> int:
        self.versions.append(_Version(index, off, spec, comment))
        vid = len(self.versions) - 1
        self.current[index] = vid
        if vid >= self._vsize.size:
            self._vsize = np.concatenate([self._vsize, np.full_like(self._vsize, -1)])
            self._vbytes = np.concatenate([self._vbytes, np.zeros_like(self._vbytes)])
        self._vsize[vid] = spec.size if spec is not None else -1
        self._vbytes[vid] = bool(spec is not None and spec.byte_array_ok)
        return vid

    def _control(self, off: int) -> tuple[str, str] | None:
        """Apply one control record; returns (kind, message) when it is corrupt."""
        buf = self.buf
        rtype, index = buf[off], buf[off + 1]
        length = buf[off + 2] | (buf[off + 3] << 8)
        if rtype in (BEGIN, END):
            if length:
                return "length_mismatch", f"{TYPE_NAMES[rtype]} with length {length} (must be 0)"
            kind = "begin" if rtype == BEGIN else "end"
            self.markers.append(Marker(kind, self._time_at(off), off))
            return None
        if index == 0:
            return "bad_definition", f"{TYPE_NAMES[rtype]} for format index 0 (must be 1..255)"
        body = buf[off + HEADER_SIZE : off + HEADER_SIZE + length].rstrip(b"\x00")
        cur = int(self.current[index])
        prev = self.versions[cur] if cur >= 0 else None
        if rtype == COMMENT:
            names = tuple(body.decode("utf-8", errors="replace").split(","))
            if prev is None or prev.comment != names:  # a repeat changes nothing
                self._new_version(index, off, prev.spec if prev else None, names)
            return None
        try:
            spec = parse_format(body.decode("latin-1"))
        except FormatError as exc:
            return "bad_definition", f"bad Format Definition for index {index}: {exc}"
        if prev is None or prev.spec != spec:
            self._new_version(index, off, spec, prev.comment if prev else None)
        return None

    def _commit(self, offs: np.ndarray, hdr: np.ndarray) -> tuple[int, str, str] | None:
        """Validate and keep framed records (offsets and headers) up to the first corrupt one
        (returned)."""
        if offs.size == 0:
            return None
        hdr = np.ascontiguousarray(hdr)  # as `_frame` gives it: the views below need that
        types, idx = hdr.view(np.uint8)[0::4], hdr.view(np.uint8)[1::4]
        lens = hdr.view("<u2")[1::2]
        # The records framed are of the seven known types, and only the four control types
        # (Begin/End Data, Format Comment/Definition) have bit 2 set.
        ctrl = np.flatnonzero((hdr & 4) != 0)
        start_current = self.current.copy()
        n_versions0 = len(self.versions)
        n_markers0 = len(self.markers)
        err_pos = offs.size
        n_ctrl = ctrl.size
        err: tuple[str, str] | None = None
        ev_pos: list[int] = []
        for j, p in enumerate(ctrl.tolist()):
            before = len(self.versions)
            err = self._control(int(offs[p]))
            if err is not None:
                err_pos, n_ctrl = p, j
                break
            if len(self.versions) > before:
                ev_pos.append(p)
        # The data records before err_pos are usually one contiguous run (controls at the start
        # and the end): then slices (views) stand for gathers by their positions.
        run = _between(ctrl[:n_ctrl], err_pos)
        dsel: slice | np.ndarray
        if run is not None:
            dsel = slice(*run)
            n_data, first = run[1] - run[0], run[0]
        else:
            is_data = np.ones(err_pos, dtype=bool)
            is_data[ctrl[:n_ctrl]] = False
            dsel = np.flatnonzero(is_data)
            n_data, first = dsel.size, (int(dsel[0]) if dsel.size else 0)
        vid: np.ndarray | None = None
        groups: dict[int, np.ndarray | slice] | None = None
        need = pairs = _EMPTY
        if n_data >= _KEYED_MIN and (not ev_pos or ev_pos[-1] < first):
            # One set of definitions for every data record: the records of each (type,
            # index) key a valid record can have are found with one compare each, and if
            # that is all of them, every one is valid; else tables over the key find the
            # first that is not.
            need16, pair16, valid = self._keyed(self.current)
            codes = hdr.view("<u2")[0::2][dsel]
            groups = _by_key(hdr[dsel], codes, need16, pair16, valid)
            if groups is None:  # some record is corrupt (or too many formats): find it
                need, pairs = need16.take(codes), pair16.take(codes)
        elif n_data:
            data_pos = np.arange(dsel.start, dsel.stop) if isinstance(dsel, slice) else dsel
            vid = self._versions_of(idx, dsel, data_pos, ev_pos, start_current, n_versions0,
                                    offs.size)
            need, pairs = self._needs(vid, types[dsel])
        bad = need != lens[dsel] if groups is None else _NO_BAD
        if bad.any():
            bad &= need != -1  # -1: a Byte Array of a 1-byte format, any length
        if bad.any():
            k = int(np.argmax(bad))
            p = dsel.start + k if isinstance(dsel, slice) else int(dsel[k])
            index = int(idx[p])
            name = TYPE_NAMES[int(types[p])]
            v = int(vid[k]) if vid is not None else int(self.current[index])
            vspec = self.versions[v].spec if v >= 0 else None
            text = vspec.text if vspec is not None else ""
            if need[k] == -3:
                err = "undefined_index", f"{name} for format index {index}, which has no definition"
            elif types[p] == DATA:
                err = (
                    "length_mismatch",
                    f"Data Block of {int(lens[p])} bytes for format index {index}, "
                    f"whose format {text!r} needs {int(need[k])}",
                )
            else:
                err = (
                    "length_mismatch",
                    f"{name} for format index {index}, whose format {text!r} "
                    f"is not one 1-byte conversion",
                )
            err_pos = p
            keep = k  # the data records before the bad one
        else:
            keep = n_data
        if err_pos < offs.size:
            self._rollback(int(offs[err_pos]), start_current, n_versions0, n_markers0)
        if keep:
            if keep < n_data:
                dsel = slice(dsel.start, dsel.start + keep) if isinstance(dsel, slice) else dsel[:keep]
            self.chunks.append(
                (offs[dsel], lens[dsel], None if groups is not None else pairs[:keep], groups)
            )
        self.record_count += err_pos
        if err is not None:
            return int(offs[err_pos]), err[0], err[1]
        return None

    def _keyed(self, current: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[int]]:
        """Per (type | index << 8) key of a data record, with the versions `current` in force:
        the length it needs (see `_needs`) and its pair (version * 2 + 1 for a Byte Array);
        and the keys a valid record can have."""
        have = current >= 0
        v = np.where(have, current, 0)
        size = np.where(have, self._vsize[v], -1)
        block = np.where(size >= 0, size, -3)
        array = np.where(size >= 0, np.where(self._vbytes[v], -1, -2), -3)
        need16 = np.full(1 << 16, -3, dtype=np.int32)
        pair16 = np.zeros(1 << 16, dtype=np.int32)
        keys = np.arange(256, dtype=np.int64) << 8
        need16[keys + DATA] = block
        pair16[keys + DATA] = v * 2
        for t in (ARRAY, ARRAY_ALT):
            need16[keys + t] = array
            pair16[keys + t] = v * 2 + 1
        valid = (keys[block >= 0] + DATA).tolist()
        for t in (ARRAY, ARRAY_ALT):
            valid += (keys[array == -1] + t).tolist()
        return need16, pair16, valid

    def _versions_of(
        self,
        idx: np.ndarray,
        dsel: slice | np.ndarray,
        data_pos: np.ndarray,
        ev_pos: list[int],
        start_current: np.ndarray,
        n_versions0: int,
        n_records: int,
    ) -> np.ndarray:
        """The version in force for each data record: the last event of its index before it."""
        d_idx = idx[dsel]
        first = int(data_pos[0])
        vid = (self.current if ev_pos and ev_pos[-1] < first else start_current)[d_idx]
        if ev_pos and ev_pos[-1] >= first:
            ev_p = np.asarray(ev_pos, dtype=np.int64)
            ev_vid = np.arange(n_versions0, len(self.versions), dtype=np.int64)
            ev_idx = idx[ev_p].astype(np.int64)
            span = n_records + 1
            ev_key = ev_idx * span + ev_p
            order = np.argsort(ev_key, kind="stable")
            ev_key, ev_vid, ev_idx = ev_key[order], ev_vid[order], ev_idx[order]
            j = np.searchsorted(ev_key, d_idx.astype(np.int64) * span + data_pos, side="right") - 1
            jc = np.clip(j, 0, None)
            hit = (j >= 0) & (ev_idx[jc] == d_idx)
            vid = np.where(hit, ev_vid[jc], vid)
        return vid

    def _needs(self, vid: np.ndarray, d_types: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per data record of version `vid`: the length its (version, kind) requires (-1 any: a
        Byte Array of a 1-byte format; -2 none: a Byte Array of another format; -3 no
        definition) and its pair (version * 2 + 1 for a Byte Array)."""
        sizes = self._vsize
        known_size = sizes >= 0
        lut = np.full(2 * sizes.size + 2, -3, dtype=np.int64)
        lut[2::2] = np.where(known_size, sizes, -3)
        lut[3::2] = np.where(known_size, np.where(self._vbytes, -1, -2), -3)
        pair = vid * 2 + (d_types != DATA)
        return lut[pair + 2], pair

    def _rollback(
        self, offset: int, start_current: np.ndarray, n_versions0: int, n_markers0: int
    ) -> None:
        """Forget definitions and markers read at or after `offset` (past a corrupt record)."""
        while len(self.versions) > n_versions0 and self.versions[-1].offset >= offset:
            self.versions.pop()
        self.current = start_current
        for vid in range(n_versions0, len(self.versions)):
            self.current[self.versions[vid].index] = vid
        while len(self.markers) > n_markers0 and self.markers[-1].offset >= offset:
            self.markers.pop()

    # -- the end of the file and resynchronisation -----------------------------------------

    def _spec_of(self, index: int) -> FormatSpec | None:
        vid = int(self.current[index])
        return self.versions[vid].spec if vid >= 0 else None

    def _tail(self, off: int) -> tuple[str, str] | None:
        """Classify a record that does not fit in the file: None for a cut-short last record."""
        buf, n = self.buf, self.n
        rtype = buf[off]
        if rtype not in KNOWN_TYPES:
            return "unknown_type", f"unknown record type 0x{rtype:02X}"
        if n - off < HEADER_SIZE:
            return None
        index = buf[off + 1]
        length = buf[off + 2] | (buf[off + 3] << 8)
        name = TYPE_NAMES[rtype]
        if rtype in (BEGIN, END):
            if length:
                return "length_mismatch", f"{name} with length {length} (must be 0)"
            return None
        if rtype in (DATA, ARRAY, ARRAY_ALT):
            spec = self._spec_of(index)
            if spec is None:
                return (
                    "undefined_index",
                    f"{name} for format index {index}, which has no definition",
                )
            if rtype == DATA:
                if length != spec.size:
                    return (
                        "length_mismatch",
                        f"Data Block of {length} bytes for format index {index}, whose format "
                        f"{spec.text!r} needs {spec.size}",
                    )
                return None
            if not spec.byte_array_ok:
                return (
                    "length_mismatch",
                    f"{name} for format index {index}, whose format {spec.text!r} "
                    f"is not one 1-byte conversion",
                )
        elif index == 0:
            return "bad_definition", f"{name} for format index 0 (must be 1..255)"
        # Variable-length record: cut short only if nothing plausible follows inside it.
        if self._find_plausible(off + 1, n) < n:
            return (
                "past_eof",
                f"{name} of length {length} runs past the end of the file ({n} bytes)",
            )
        return None

    def _plausible(self, p: int) -> bool:
        buf, n = self.buf, self.n
        if p + HEADER_SIZE > n:
            return False
        rtype, index = buf[p], buf[p + 1]
        length = buf[p + 2] | (buf[p + 3] << 8)
        if rtype in (COMMENT, DEFINITION):
            end = p + HEADER_SIZE + length
            if index == 0 or length == 0 or end > n:
                return False
            body = buf[p + HEADER_SIZE : end]
            if b"\x00" in body:
                return False
            try:
                text = body.decode("utf-8")
                if rtype == DEFINITION:
                    parse_format(text)
            except (UnicodeDecodeError, FormatError):
                return False
        else:
            if rtype in (BEGIN, END):
                if index or length:
                    return False
                end = p + TIMED_SIZE
            else:
                spec = self._spec_of(index)
                if spec is None:
                    return False
                if rtype == DATA and length != spec.size:
                    return False
                if rtype != DATA and not spec.byte_array_ok:
                    return False
                end = p + TIMED_SIZE + length
            if end > n or int.from_bytes(buf[p + 8 : p + 12], "little") >= _NS:
                return False
        return end == n or bool(_KNOWN_LUT[buf[end]])

    def _find_plausible(self, start: int, stop: int) -> int:
        """First offset in [start, stop) where a plausible record starts, else `stop`."""
        pos = start
        window = 64  # grows: damage is usually short, but the search must stay linear
        while pos < stop:
            end = min(stop, pos + window)
            cands = np.flatnonzero(_KNOWN_LUT[self.arr[pos:end]])
            for c in cands.tolist():
                if self._plausible(pos + c):
                    return pos + c
            pos = end
            window = min(window * 2, _SEARCH_WINDOW)
        return stop

    # -- building the arrays ---------------------------------------------------------------

    def _columns(self, vid: int, kind: str) -> tuple[str, ...]:
        v = self.versions[vid]
        assert v.spec is not None
        count = v.spec.n_fields
        if (
            kind == "block"
            and v.comment is not None
            and len(v.comment) != count
            and vid not in self._warned_columns
        ):
            self._warned_columns.add(vid)
            msg = (
                f"{self.path}: Format Comment of index {v.index} names {len(v.comment)} columns "
                f"for {count} fields; they are named c1..c{count} instead"
            )
            self.warnings.append(msg)
            log.warning(msg)
        return column_names(v.comment, v.spec, kind)

    def _grouped(
        self,
    ) -> tuple[np.ndarray, np.ndarray, dict[int, slice | np.ndarray], dict[int, int]]:
        """Offsets and lengths of the kept data records; the positions of the records of each
        (version, kind) pair present among them, in file order, and of its first record."""
        rows_of: dict[int, slice | np.ndarray] = {}
        first: dict[int, int] = {}
        groups = self.chunks[0][3] if len(self.chunks) == 1 else None
        if groups is not None:  # the usual case: one chunk, grouped by `_by_key`
            offs, lens = self.chunks[0][0], self.chunks[0][1]
            for pv, found in groups.items():
                rows_of[pv] = found
                first[pv] = 0 if isinstance(found, slice) else int(found[0])
            return offs, lens, rows_of, first
        pairs = [_pairs(c[0].size, c[2], c[3]) for c in self.chunks]
        if len(self.chunks) == 1:
            offs, lens, pair = self.chunks[0][0], self.chunks[0][1], pairs[0]
        elif self.chunks:
            offs = np.concatenate([c[0] for c in self.chunks])
            lens = np.concatenate([c[1] for c in self.chunks])
            pair = np.concatenate(pairs)
        else:
            offs = lens = pair = np.zeros(0, dtype=np.int64)
        present = np.flatnonzero(np.bincount(pair)) if pair.size else _EMPTY
        if present.size == 1:
            rows_of[int(present[0])], first[int(present[0])] = slice(None), 0
        elif present.size <= _FEW:  # a handful of formats; no sort
            for pv in present.tolist():
                rows_of[pv] = found = np.flatnonzero(pair == pv)
                first[pv] = int(found[0])
        else:
            order = np.argsort(pair, kind="stable")
            ranked = pair[order]
            lo = np.searchsorted(ranked, present, side="left").tolist()
            hi = np.searchsorted(ranked, present, side="right").tolist()
            for pv, a, b in zip(present.tolist(), lo, hi, strict=True):
                rows_of[pv] = order[a:b]
                first[pv] = int(order[a])
        return offs, lens, rows_of, first

    def _finish(self) -> LogFile:
        streams: list[Stream] = []
        offs, lens, rows_of, first = self._grouped()
        # Streams in order of their first record; (version, kind) pairs map onto them.
        key_of: dict[tuple[int, str, str, tuple[str, ...]], int] = {}
        stream_keys: list[tuple[int, str, tuple[str, ...], int]] = []
        members: list[list[int]] = []
        for pv in sorted(rows_of, key=first.__getitem__):
            vid, kind = pv // 2, ("array" if pv % 2 else "block")
            spec = self.versions[vid].spec
            assert spec is not None
            columns = self._columns(vid, kind)
            key = (self.versions[vid].index, kind, spec.text, columns)
            if key not in key_of:
                key_of[key] = len(stream_keys)
                stream_keys.append((self.versions[vid].index, kind, columns, vid))
                members.append([])
            members[key_of[key]].append(pv)
        numbers: dict[int, int] = {}
        for (index, kind, columns, vid), pvs in zip(stream_keys, members, strict=True):
            rows: slice | np.ndarray = rows_of[pvs[0]]
            if len(pvs) > 1:  # one layout under several versions (e.g. a repeated comment)
                rows = np.sort(np.concatenate([rows_of[pv] for pv in pvs]))
            numbers[index] = numbers.get(index, 0) + 1
            spec = self.versions[vid].spec
            assert spec is not None
            at = self.versions[vid].offset
            if kind == "block":
                streams.append(self._block(index, spec, columns, numbers[index], at, offs[rows]))
            else:
                streams.append(
                    self._array(index, spec, columns, numbers[index], at, offs[rows], lens[rows])
                )
        # Formats that were defined but never used still show up, with no records.
        used = {s.index for s in streams}
        for index in range(1, 256):
            vid = int(self.current[index])
            if index in used or vid < 0:
                continue
            spec = self.versions[vid].spec
            if spec is None:
                continue
            empty = np.zeros(0, dtype=np.int64)
            columns = self._columns(vid, "block")
            streams.append(self._block(index, spec, columns, 1, self.versions[vid].offset, empty))
        streams.sort(key=lambda s: (s.index, s.number))
        if not self.markers or self.markers[-1].kind != "end":
            self.warnings.append(f"{self.path}: not closed cleanly (no End Data at the end)")
        return LogFile(
            path=self.path,
            size_bytes=self.n,
            streams=streams,
            markers=self.markers,
            damage=self.damage,
            truncated_bytes=self.truncated,
            record_count=self.record_count,
            warnings=self.warnings,
        )

    def _times(self, offs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if offs.size == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.float64)
        t = _items(self.arr, 4, _TIME_V)[offs].view(_TIME)  # void items gather fastest
        return _split_times(t["s"], t["ns"])

    def _block(
        self,
        index: int,
        spec: FormatSpec,
        columns: tuple[str, ...],
        number: int,
        def_off: int,
        offs: np.ndarray,
    ) -> Stream:
        fields = [(c, d) for c, d in zip(columns, spec.field_dtypes, strict=True)]
        dtype = np.dtype([("time_s", "<f8"), *fields])  # packed: 8 bytes, then the record's
        if not offs.size:
            out = np.empty(0, dtype=dtype)
            time_ns = np.zeros(0, np.int64)
        else:
            # One gather of every record's TIME and fields, which already have the layout of a
            # row (TIME is 8 bytes, like time_s); then TIME is replaced by time_s in place.
            out = _items(self.arr, 4, np.dtype(f"V{dtype.itemsize}"))[offs].view(dtype)
            # TIME copied out of the rows first: one pass over them instead of one per operand.
            raw = np.ndarray(out.shape, dtype=_TIME_V, buffer=out, strides=out.strides)
            t = raw.copy().view(_TIME)
            time_ns = _split_times(t["s"], t["ns"], out["time_s"])[0]
        return Stream(index, "block", spec, columns, number, def_off, time_ns, offs, _data=out)

    def _array(
        self,
        index: int,
        spec: FormatSpec,
        columns: tuple[str, ...],
        number: int,
        def_off: int,
        offs: np.ndarray,
        lens: np.ndarray,
    ) -> Stream:
        time_ns, time_s = self._times(offs)
        lens = lens.astype(np.int64)
        values = _gather_elements(self.arr, offs + TIMED_SIZE, lens).view(spec.field_dtypes[0])
        return Stream(
            index, "array", spec, columns, number, def_off, time_ns, offs,
            lengths=lens, values=values, time_s=time_s,
        )


def _items(arr: np.ndarray, offset: int, dtype: np.dtype) -> np.ndarray:
    """The items of `dtype` starting at every byte of `arr` from `offset` on (an unaligned view):
    indexed by record offsets, they gather a field or a whole row of every record at once, as
    one block copy per record."""
    count = max(0, arr.size - offset - dtype.itemsize + 1)
    return np.ndarray((count,), dtype=dtype, buffer=arr, offset=offset if count else 0,
                      strides=(1,))


def _headers(arr: np.ndarray, offs: np.ndarray) -> np.ndarray:
    """The 4-byte header of every record at `offs`, as uint32: type | index << 8 | length << 16."""
    return _items(arr, 0, _HEADER)[offs].view("<u4")


def _between(ctrl: np.ndarray, end: int) -> tuple[int, int] | None:
    """(a, b) when the positions of [0, end) not in `ctrl` (increasing, all below end) are the
    run [a, b), else None."""
    k = ctrl.size
    if not k:
        return 0, end
    lead = int(np.count_nonzero(ctrl == np.arange(k)))  # ctrl[j] - j never decreases
    rest = k - lead
    if rest and int(ctrl[lead]) != end - rest:
        return None
    return lead, end - rest


def _by_key(
    words: np.ndarray, codes: np.ndarray, need16: np.ndarray, pair16: np.ndarray,
    valid: list[int],
) -> dict[int, np.ndarray | slice] | None:
    """The positions of the records of each (version, kind) pair, by the keys a valid record
    can have (see `_Parser._keyed`): a Data Block's whole header is known, a Byte Array's type
    and index. None when some record has none of them (it is corrupt) or the keys are too many
    for a pass each."""
    if len(valid) > _FEW:
        return None
    groups: dict[int, np.ndarray | slice] = {}
    total = 0
    for k16 in valid:
        need = int(need16[k16])
        same = words == (k16 | need << 16) if need >= 0 else codes == k16
        if len(valid) == 1:  # every record has the key, or some record is corrupt
            return {int(pair16[k16]): slice(None)} if same.all() else None
        found = np.flatnonzero(same)
        if not found.size:
            continue
        total += found.size
        pv = int(pair16[k16])
        if pv in groups:  # a Byte Array under both type codes
            found = np.sort(np.concatenate([groups[pv], found]))
        groups[pv] = found
    return groups if total == words.size else None


def _pairs(
    count: int, pairs: np.ndarray | None, groups: dict[int, np.ndarray | slice] | None
) -> np.ndarray:
    """The pair of each of the `count` records of a chunk (see `_Parser.chunks`)."""
    if pairs is not None or groups is None:
        return pairs if pairs is not None else np.zeros(count, dtype=np.int64)
    out = np.empty(count, dtype=np.int64)
    for pv, rows in groups.items():
        out[rows] = pv
    return out


def _gather_elements(arr: np.ndarray, starts: np.ndarray, lens: np.ndarray) -> np.ndarray:
    """The bytes arr[starts[i] : starts[i] + lens[i]] of every record, one after the other.

    Raw bytes of one device come in a few lengths: the records of each common length are
    copied as whole rows (one block copy per record, gathered and scattered as void items);
    the rest as the pieces of their lengths' binary digits (a record of 2^k + 2^j bytes is a
    piece of 2^k bytes then one of 2^j), at most 16 block copies per record.
    """
    total = int(lens.sum())
    if not total:
        return np.zeros(0, dtype=np.uint8)
    counts = np.bincount(lens)
    width = int(counts.argmax())
    if counts[width] == lens.size:  # one length: the rows are the output
        return _items(arr, 0, np.dtype(f"V{width}"))[starts].view(np.uint8).reshape(-1)
    out = np.empty(total, dtype=np.uint8)
    before = np.cumsum(lens) - lens
    rest = lens > 0
    for width in np.argsort(counts)[::-1][:_ROW_GROUPS].tolist():
        if width == 0 or counts[width] * 20 < lens.size:
            break
        group = lens == width
        slots = _items(out, 0, np.dtype(f"V{width}"))
        slots[before[group]] = _items(arr, 0, np.dtype(f"V{width}"))[starts[group]]
        rest &= ~group
    if rest.any():
        r_starts, r_lens, r_before = starts[rest], lens[rest], before[rest]
        for k in range(int(r_lens.max()).bit_length() - 1, -1, -1):
            has = np.flatnonzero((r_lens & (1 << k)) != 0)
            if not has.size:
                continue
            done = r_lens[has] >> (k + 1) << (k + 1)  # the bytes of the higher digits
            slots = _items(out, 0, np.dtype(f"V{1 << k}"))
            slots[r_before[has] + done] = _items(arr, 0, np.dtype(f"V{1 << k}"))[r_starts[has] + done]
    return out


def _split_times(
    sec: np.ndarray, nsec: np.ndarray, out: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Exact int64 ns and float64 seconds (seconds + nanoseconds / 1e9, into `out` if given) of
    TIME fields."""
    time_ns = np.multiply(sec, _NS, dtype=np.int64)
    time_ns += nsec
    frac = np.divide(nsec, 1e9, dtype=np.float64)
    # int32 and uint32 are exact in float64: the same sums as in int64 first
    time_s = np.add(frac, sec, out=frac if out is None else out)
    return time_ns, time_s


def read_log_bytes(data: bytes, *, name: str = "<bytes>", salvage: bool = False) -> LogFile:
    """Read a binary log held in memory; `name` is used in messages."""
    return _Parser(bytes(data), name, salvage).run()


def read_log(path: str | os.PathLike[str], *, salvage: bool = False) -> LogFile:
    """Read a binary log file.

    Raises LogFormatError (with the file name and byte offset) on corruption unless `salvage`;
    a cut-short last record is dropped with a warning either way.
    """
    p = Path(path)
    return read_log_bytes(p.read_bytes(), name=str(p), salvage=salvage)
