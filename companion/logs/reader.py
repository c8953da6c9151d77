"""Reader of binary flight logs: whole file in, one numpy structured array per format out.

How it stays fast: record boundaries are a chain (each header gives the size of its record),
followed without a Python step per record. A run of one repeating pattern of record sizes (one
Data Block format, or a few interleaved) is predicted from its first records and every
predicted header is checked at once (`_verify_run`); elsewhere walkers started every few
kilobytes follow the chain in lockstep, one numpy step per record, and hand over where one
lands on the next one's start (`_walk_fast`); what neither proves (damage, the end of the
file) is walked record by record (`_scan_py`, the reference the others are tested against).
Everything else (which definition applies to each record, validation, field extraction) is
done with numpy over all records at once: each Data Block format's rows come out of the file
bytes with one gather of whole records (TIME and fields already have the layout of a row, TIME
becoming ``time_s`` in place), each Byte Array format's elements with one block copy per
record of its common lengths.

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
_DATA_LUT = np.zeros(256, dtype=bool)  # Data Block, Byte Array, Data Array
_DATA_LUT[[DATA, ARRAY, ARRAY_ALT]] = True
_SIZES_NP = np.minimum(np.array(_SIZES, dtype=np.int64), 1 << 40)  # no overflow in sums
_EMPTY = np.zeros(0, dtype=np.int64)
# The fast walk (`_walk_fast`): stretches shorter than _FAST_MIN bytes are walked in Python;
# a stretch starts at _FAST_CHUNK bytes and doubles while it is proved whole; one walker per
# _SEGMENT bytes starts at the first of the segment's first _PROBE bytes from which
# _PROBE_STEPS headers chain onto known types; a failed hand-over is followed in Python for at
# most _RESYNC bytes; past what the fast walk proves, _SLOW_WINDOW bytes are walked in Python.
_FAST_MIN = 1 << 15
_FAST_CHUNK = 1 << 18
_FAST_CHUNK_MAX = 1 << 22
_SEGMENT = 4096
_PROBE = 128
_PROBE_STEPS = 3
_PROBE_ROUNDS = 8
_HIGH = np.arange(256, dtype=np.int64) << 8  # the high byte of a length, shifted
_RESYNC = 4 * _SEGMENT
# Runs (`_verify_run`): the period (at most _RUN_PERIOD records) is learnt from the records of
# the first _RUN_LEARN bytes; a run shorter than _RUN_MIN records hands over to the walkers.
_RUN_PERIOD = 12
_RUN_LEARN = 4096
_RUN_MIN = 512
_SLOW_WINDOW = 1 << 14
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
    `_walk_fast`, which returns only offsets it has proved to be on the chain; whatever it
    leaves (damage, the end of the file, a stretch it could not prove) is walked by `_scan_py`
    a window at a time, so both give the same offsets and the same stop (tested).
    """
    n = len(buf)
    limit = min(stop, n - 3)
    if not fast or limit - start < _FAST_MIN:
        offs, off, reason = _scan_py(buf, start, stop)
        return np.frombuffer(offs, dtype=np.int64) if len(offs) else _EMPTY, off, reason
    arr = np.frombuffer(buf, dtype=np.uint8)
    parts: list[np.ndarray] = []
    pos = start
    chunk = _FAST_CHUNK
    while True:
        if limit - pos >= _FAST_MIN:
            end = min(limit, pos + chunk)
            while True:  # runs of a repeating pattern first, verified whole
                nodes, pos = _verify_run(buf, arr, pos, end)
                parts.append(nodes)
                if nodes.size < _RUN_MIN or pos >= end:
                    break
            whole = pos >= end
            if not whole:
                nodes, pos, whole = _walk_fast(buf, arr, pos, end)
                parts.append(nodes)
            if whole:  # proved up to `end`: go on with a longer stretch
                chunk = min(2 * chunk, _FAST_CHUNK_MAX)
                if pos < limit:
                    continue
            else:
                chunk = _FAST_CHUNK
        # The reference walk: the end of the range, or past what the fast walk could not prove.
        offs, pos, reason = _scan_py(buf, pos, min(stop, pos + _SLOW_WINDOW))
        if len(offs):
            parts.append(np.frombuffer(offs, dtype=np.int64))
        if reason != "window" or pos >= stop:
            out = np.concatenate(parts) if parts else _EMPTY
            return out, pos, reason


def _verify_run(buf: bytes, arr: np.ndarray, start: int, end: int) -> tuple[np.ndarray, int]:
    """The longest stretch from `start` (a record start) that repeats the sizes of its first
    records, as far as it is proved: offsets and the offset after the last one.

    Most logs are long runs of one pattern of record sizes (one Data Block size, or a fast and a
    slow format interleaved), so the offsets of the whole stretch are predicted from the period
    and every predicted record's header is checked at once: a record whose header gives the
    next predicted offset proves it, from `start` on, up to the first that does not.
    """
    n = arr.size
    head, stop, _ = _scan_py(buf, start, min(end, start + _RUN_LEARN))
    if len(head) < 2 * _RUN_PERIOD:
        return _as_offsets(head), stop
    first = np.frombuffer(head, dtype=np.int64)
    sizes = np.diff(first)
    period = 0
    for p in range(1, _RUN_PERIOD + 1):
        if np.array_equal(sizes[p:], sizes[:-p]):
            period = p
            break
    if not period:
        return first[:-1], int(first[-1])
    cum = np.concatenate(([0], np.cumsum(sizes[:period])))
    span = int(cum[-1])
    lo, hi = arr[2:], arr[3:]  # the length bytes, as arrays indexed by record offset
    proved: list[np.ndarray] = []
    pos = start
    periods = _RUN_MIN  # predicted at once: grows while the run holds
    while pos < end:
        # offsets and sizes of `periods` periods from pos (the pattern does not depend on pos)
        base = (np.arange(periods, dtype=np.int64)[:, None] * span + cum[:-1]).reshape(-1)
        want = np.tile(sizes[:period], periods)
        m = int(np.searchsorted(base, end - pos))
        offs = base[:m] + pos
        got = _SIZES_NP[arr.take(offs)] + lo.take(offs) + _HIGH[hi.take(offs)]
        bad = np.flatnonzero(got != want[:m])
        upto = int(bad[0]) + 1 if bad.size else m  # offs[:upto] are on the chain
        last = int(offs[upto - 1] + got[upto - 1])
        if last > n:  # the last one does not fit or is unknown: not proved
            proved.append(offs[: upto - 1])
            return _join(proved), int(offs[upto - 1])
        proved.append(offs[:upto])
        pos = last
        if bad.size:
            break
        periods = min(periods * 4, (end - pos) // span + 1)
    return _join(proved), pos


def _walk_fast(buf: bytes, arr: np.ndarray, start: int, end: int) -> tuple[np.ndarray, int, bool]:
    """The record chain from `start` (a record start) over [start, end), in numpy.

    The stretch is cut into segments of `_SEGMENT` bytes. In each segment (but the first) a
    walker starts at the first offset of its first `_PROBE` bytes from which `_PROBE_STEPS`
    headers in a row chain onto known record types, and all walkers follow their chains in
    lockstep, one record per numpy step, past the next walker's start. A walker that lands
    exactly on the next one's start hands over to it: since the first walker starts on the
    chain, every walker reached by an unbroken series of hand-overs is on it too. Where a
    hand-over fails (a walker started inside a record, a record spans segments, damage) the
    chain is followed record by record from where the last good walker stopped until it meets
    a walker's start again (`_resync`).

    Returns the offsets proved (records that fit, starting before `end`), the offset after the
    last of them (a record start, or the end of a record that reaches past `end`), and whether
    the whole stretch was proved. `end` must be at most len(buf) - 3.
    """
    n = arr.size
    k_seg = max(1, (end - start) // _SEGMENT)
    starts = np.array([start], dtype=np.int64)
    if k_seg > 1:
        found = _walker_starts(arr, start + _SEGMENT, k_seg - 1)
        starts = np.concatenate((starts, found[found >= 0]))
    stops = np.append(starts[1:], end)
    sizes, high = _SIZES_NP, _HIGH
    lo, hi = arr[2:], arr[3:]  # the length bytes, as arrays indexed by record offset
    pos = starts
    steps = [pos]
    for k in range(_SEGMENT // 4 + 1):
        # take(mode="clip"): a walker past the end (or on an unknown type) reads garbage, but
        # it has passed its stop, and what it reads there is never used.
        pos = pos + sizes[arr.take(pos, mode="clip")] + lo.take(pos, mode="clip") + high[
            hi.take(pos, mode="clip")
        ]
        steps.append(pos)
        if k % 4 == 3:
            behind = int(np.count_nonzero(pos < stops))
            # the last few stragglers (a segment without a walker of its own) are resynced
            if not behind or (behind * 256 < pos.size and k >= _SEGMENT // 64):
                break
    paths = np.stack(steps)  # (step, walker): walker k's offsets down column k
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
        return paths.T[inside.T], int(after[-1]), True
    walked = paths.T
    pieces: list[np.ndarray] = []
    k = 0
    while True:
        j_at = int(np.searchsorted(bad, k))
        j = int(bad[j_at]) if j_at < bad.size else starts.size
        if j > k:
            pieces.append(walked[k:j][inside.T[k:j]])
        if j == starts.size:
            return _join(pieces), int(after[-1]), True
        # Walker j is on the chain but did not hand over: follow the chain from there.
        row = walked[j][inside[:, j]]
        if after[j] > n:  # its last record does not fit or has an unknown type: not proved
            pieces.append(row[:-1])
            return _join(pieces), int(row[-1]), False
        pieces.append(row)
        p = int(after[j]) if after[j] >= 0 else int(walked[j][count[j] - 1])
        if after[j] < 0:  # cut by the step bound: go on from its last offset
            pieces[-1] = row[:-1]
        nodes, p, k = _resync(buf, p, starts, j + 1, end)
        pieces.append(nodes)
        if k < 0:
            return _join(pieces), p, p >= end


def _walker_starts(arr: np.ndarray, first: int, count: int) -> np.ndarray:
    """Per segment (`count` of `_SEGMENT` bytes from `first`), the first offset of its first
    `_PROBE` bytes from which `_PROBE_STEPS` headers chain onto known types; -1 where none."""
    n = arr.size
    grid = arr[first : first + count * _SEGMENT].reshape(count, _SEGMENT)[:, :_PROBE]
    # Walkers start on Data Blocks and Byte Arrays (nearly every record; compares are cheap).
    mask = (grid == DATA) | (grid == ARRAY) | (grid == ARRAY_ALT)
    found = np.full(count, -1, dtype=np.int64)
    pending = np.arange(count)
    sizes, high, known = _SIZES_NP, _HIGH, _KNOWN_LUT
    for _ in range(_PROBE_ROUNDS):
        col = (mask if pending.size == count else mask[pending]).argmax(axis=1)
        has = mask[pending, col]
        q = pending * _SEGMENT + col + first
        cand = q
        ok = has & known[arr[q]]
        for _ in range(_PROBE_STEPS):
            q = q + sizes[arr.take(q, mode="clip")] + arr.take(q + 2, mode="clip") + high[
                arr.take(q + 3, mode="clip")
            ]
            ok &= (q == n) | ((q < n) & known[arr.take(q, mode="clip")])
        found[pending[ok]] = cand[ok]
        retry = has & ~ok
        mask[pending[retry], col[retry]] = False
        pending = pending[retry]
        if not pending.size:
            break
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


def _join(pieces: list[np.ndarray]) -> np.ndarray:
    pieces = [x for x in pieces if x.size]
    if not pieces:
        return _EMPTY
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
        self.chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
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
            found, stop_off, reason = _scan(self.buf, pos, stop, fast=self.fast)
            err = self._commit(found)
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

    def _commit(self, offs: np.ndarray) -> tuple[int, str, str] | None:
        """Validate and keep framed records up to the first corrupt one (returned)."""
        if offs.size == 0:
            return None
        arr = self.arr
        types = arr.take(offs)
        idx = arr.take(offs + 1)
        lens = arr.take(offs + 2) + _HIGH[arr.take(offs + 3)]
        is_data = _DATA_LUT[types]
        ctrl = np.flatnonzero(~is_data)
        start_current = self.current.copy()
        n_versions0 = len(self.versions)
        n_markers0 = len(self.markers)
        err_pos = offs.size
        err: tuple[str, str] | None = None
        ev_pos: list[int] = []
        for p in ctrl.tolist():
            before = len(self.versions)
            err = self._control(int(offs[p]))
            if err is not None:
                err_pos = p
                break
            if len(self.versions) > before:
                ev_pos.append(p)
        # Which version is in force for each data record: the last event of its index before it.
        data_pos = np.flatnonzero(is_data[:err_pos])
        # The data records are usually one contiguous run (controls at the start and the end):
        # then slices (views) stand for the gathers by data_pos.
        run = data_pos.size and int(data_pos[-1]) - int(data_pos[0]) + 1 == data_pos.size
        dsel = slice(int(data_pos[0]), int(data_pos[-1]) + 1) if run else data_pos
        d_idx = idx[dsel]
        if ev_pos and data_pos.size and ev_pos[-1] < data_pos[0]:
            vid = self.current[d_idx]  # every definition before every data record: one gather
        else:
            vid = start_current[d_idx]
        if ev_pos and data_pos.size and ev_pos[-1] >= data_pos[0]:
            ev_p = np.asarray(ev_pos, dtype=np.int64)
            ev_vid = np.arange(n_versions0, len(self.versions), dtype=np.int64)
            ev_idx = idx[ev_p].astype(np.int64)
            span = offs.size + 1
            ev_key = ev_idx * span + ev_p
            order = np.argsort(ev_key, kind="stable")
            ev_key, ev_vid, ev_idx = ev_key[order], ev_vid[order], ev_idx[order]
            j = np.searchsorted(ev_key, d_idx.astype(np.int64) * span + data_pos, side="right") - 1
            jc = np.clip(j, 0, None)
            hit = (j >= 0) & (ev_idx[jc] == d_idx)
            vid = np.where(hit, ev_vid[jc], vid)
        # One lookup per record: the length its (version, kind) requires; -1 any (a Byte Array
        # of a 1-byte format), -2 none (a Byte Array of another format), -3 no definition.
        sizes = self._vsize
        known_size = sizes >= 0
        lut = np.full(2 * sizes.size + 2, -3, dtype=np.int64)
        lut[2::2] = np.where(known_size, sizes, -3)
        lut[3::2] = np.where(known_size, np.where(self._vbytes, -1, -2), -3)
        d_types = types[dsel]
        is_block = d_types == DATA
        need = lut[vid * 2 + 2 + ~is_block]
        bad = (need != lens[dsel]) & (need != -1)
        if bad.any():
            k = int(np.argmax(bad))
            p = int(data_pos[k])
            index = int(idx[p])
            name = TYPE_NAMES[int(types[p])]
            vspec = self.versions[int(vid[k])].spec if vid[k] >= 0 else None
            text = vspec.text if vspec is not None else ""
            if need[k] == -3:
                err = "undefined_index", f"{name} for format index {index}, which has no definition"
            elif is_block[k]:
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
        if err_pos < offs.size:
            self._rollback(int(offs[err_pos]), start_current, n_versions0, n_markers0)
        if run and err_pos == offs.size:  # all kept, contiguous: views
            self.chunks.append((offs[dsel], types[dsel], lens[dsel], vid))
        else:
            keep = data_pos < err_pos
            if keep.any():
                kp = data_pos[keep]
                self.chunks.append((offs[kp], types[kp], lens[kp], vid[keep]))
        self.record_count += err_pos
        if err is not None:
            return int(offs[err_pos]), err[0], err[1]
        return None

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

    def _finish(self) -> LogFile:
        streams: list[Stream] = []
        if len(self.chunks) == 1:
            offs, types, lens, vids = self.chunks[0]
        elif self.chunks:
            offs = np.concatenate([c[0] for c in self.chunks])
            types = np.concatenate([c[1] for c in self.chunks])
            lens = np.concatenate([c[2] for c in self.chunks])
            vids = np.concatenate([c[3] for c in self.chunks])
        else:
            offs = types = lens = vids = np.zeros(0, dtype=np.int64)
        is_block = types == DATA
        # Streams in order of their first record; (version, kind) pairs map onto them.
        key_of: dict[tuple[int, str, str, tuple[str, ...]], int] = {}
        stream_keys: list[tuple[int, str, tuple[str, ...], int]] = []
        pair = vids * 2 + (~is_block).astype(np.int64)
        counts = np.bincount(pair) if pair.size else np.zeros(0, dtype=np.int64)
        present = np.flatnonzero(counts)
        few = present.size <= _FEW
        if few:  # the usual case: a handful of formats; no sort over all records
            first = np.array([int(np.argmax(pair == pv)) for pv in present.tolist()], dtype=np.int64)
        else:
            present, first = np.unique(pair, return_index=True)
        stream_of_pair: dict[int, int] = {}
        for pv in present[np.argsort(first, kind="stable")].tolist():
            vid, kind = pv // 2, ("array" if pv % 2 else "block")
            spec = self.versions[vid].spec
            assert spec is not None
            columns = self._columns(vid, kind)
            key = (self.versions[vid].index, kind, spec.text, columns)
            if key not in key_of:
                key_of[key] = len(stream_keys)
                stream_keys.append((self.versions[vid].index, kind, columns, vid))
            stream_of_pair[pv] = key_of[key]
        lut = np.zeros(counts.size, dtype=np.int64)
        for pv, sv in stream_of_pair.items():
            lut[pv] = sv
        sid = lut[pair]
        groups: list[slice | np.ndarray]
        if len(stream_keys) == 1:
            groups = [slice(None)]
        elif len(stream_keys) <= _FEW:
            groups = [np.flatnonzero(sid == k) for k in range(len(stream_keys))]
        else:
            order = np.argsort(sid, kind="stable")
            bounds = np.searchsorted(sid[order], np.arange(len(stream_keys) + 1))
            groups = [order[bounds[k] : bounds[k + 1]] for k in range(len(stream_keys))]
        numbers: dict[int, int] = {}
        for s, (index, kind, columns, vid) in enumerate(stream_keys):
            rows = groups[s]
            numbers[index] = numbers.get(index, 0) + 1
            spec = self.versions[vid].spec
            assert spec is not None
            builder = self._block if kind == "block" else self._array
            streams.append(
                builder(
                    index,
                    spec,
                    columns,
                    numbers[index],
                    self.versions[vid].offset,
                    offs[rows],
                    lens[rows],
                )
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
            streams.append(
                self._block(index, spec, columns, 1, self.versions[vid].offset, empty, empty)
            )
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
        win = _rows(self.arr, offs + 4, 8)
        t = win.view(np.dtype([("s", "<i4"), ("ns", "<u4")])).reshape(-1)
        return _split_times(t["s"], t["ns"])

    def _block(
        self,
        index: int,
        spec: FormatSpec,
        columns: tuple[str, ...],
        number: int,
        def_off: int,
        offs: np.ndarray,
        lens: np.ndarray,
    ) -> Stream:
        fields = [(c, d) for c, d in zip(columns, spec.field_dtypes, strict=True)]
        dtype = np.dtype([("time_s", "<f8"), *fields])  # packed: 8 bytes, then the record's
        if not offs.size:
            out = np.empty(0, dtype=dtype)
            time_ns = np.zeros(0, np.int64)
        else:
            # One gather of every record's TIME and fields, which already have the layout of a
            # row (TIME is 8 bytes, like time_s); then TIME is replaced by time_s in place.
            rows = _rows(self.arr, offs + 4, 8 + spec.size)
            raw = rows.view(
                np.dtype({"names": ["s", "ns"], "formats": ["<i4", "<u4"], "itemsize": 8 + spec.size})
            ).reshape(-1)
            time_ns, time_s = _split_times(raw["s"], raw["ns"])
            out = rows.view(dtype).reshape(-1)
            out["time_s"] = time_s
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
            lengths=lens.copy(), values=values, time_s=time_s,
        )


def _rows(arr: np.ndarray, starts: np.ndarray, width: int) -> np.ndarray:
    """arr[start : start + width] for every start, as the rows of a (len(starts), width) array.

    Gathered as one `width`-byte void item per row (an unaligned view of the buffer), which
    numpy copies as a block: several times faster than rows of a sliding-window view."""
    items = np.ndarray((arr.size - width + 1,), dtype=f"V{width}", buffer=arr, strides=(1,))
    return items[starts].view(np.uint8).reshape(starts.size, width)


def _gather_elements(arr: np.ndarray, starts: np.ndarray, lens: np.ndarray) -> np.ndarray:
    """The bytes arr[starts[i] : starts[i] + lens[i]] of every record, one after the other.

    Raw bytes of one device come in a few lengths: the records of each common length are
    copied as whole rows (one block copy per record, gathered and scattered as void items);
    the rest element by element.
    """
    total = int(lens.sum())
    out = np.empty(total, dtype=np.uint8)
    if not total:
        return out
    before = np.cumsum(lens) - lens
    rest = lens > 0
    counts = np.bincount(lens)
    for width in np.argsort(counts)[::-1][:_ROW_GROUPS].tolist():
        if width == 0 or counts[width] * 20 < lens.size:
            break
        group = lens == width
        rows = np.ndarray((arr.size - width + 1,), dtype=f"V{width}", buffer=arr, strides=(1,))
        slots = np.ndarray((total - width + 1,), dtype=f"V{width}", buffer=out, strides=(1,))
        slots[before[group]] = rows[starts[group]]
        rest &= ~group
    if rest.any():
        r_starts, r_lens, r_before = starts[rest], lens[rest], before[rest]
        r_first = np.cumsum(r_lens) - r_lens
        step = np.arange(int(r_lens.sum())) - np.repeat(r_first, r_lens)
        out[np.repeat(r_before, r_lens) + step] = arr[np.repeat(r_starts, r_lens) + step]
    return out


def _split_times(sec: np.ndarray, nsec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact int64 ns and float64 seconds of TIME fields."""
    s64 = sec.astype(np.int64)
    ns64 = nsec.astype(np.int64)
    return s64 * _NS + ns64, s64.astype(np.float64) + ns64.astype(np.float64) / 1e9


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
