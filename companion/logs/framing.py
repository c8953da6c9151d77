"""Framing of binary flight logs: where each record starts, found without reading what it means.

A log is a chain of records: each header gives the size of its record (a fixed part per record
type plus the length field), so the offset of the next record follows from the header alone.
This module follows that chain and nothing else; what a record means (which definition applies,
whether its length fits its format) is the reader's (`companion.logs.reader`), and recovering
from damage is `companion.logs.resync`'s. It is separate because it is the hot loop of every
read and of the writer's repair of a file cut short by a crash (`framed_length`), and because
its three walks must agree with each other byte for byte: they are kept side by side.

How it stays fast: the chain is followed without a Python step per record. A run of one
repeating pattern of record headers (one Data Block format, or a few interleaved) is predicted
from its first records and every predicted header is checked at once through strided views
(`_verify_run`); elsewhere walkers started every few kilobytes follow the chain in lockstep,
one numpy step per record, and hand over where one lands on the next one's start
(`_walk_fast`); what neither proves (damage, the end of the file) is walked record by record
(`_scan_py`, the reference the others are tested against). The walks hand over the headers
they read, so no later pass reads them again.

How it stays safe: every loop advances through the file and every allocation is proportional
to the file size.
"""

from __future__ import annotations

from array import array

import numpy as np

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
)

__all__ = ["KNOWN_LUT", "NO_OFFSETS", "frame", "framed_length", "items"]

_UNKNOWN = 1 << 62  # size of an unknown record type in the boundary pass: always "past the end"
_SIZES = [_UNKNOWN] * 256
for _t in (BEGIN, END, DATA, ARRAY, ARRAY_ALT):
    _SIZES[_t] = TIMED_SIZE
for _t in (COMMENT, DEFINITION):
    _SIZES[_t] = HEADER_SIZE
KNOWN_LUT = np.zeros(256, dtype=bool)
KNOWN_LUT[list(KNOWN_TYPES)] = True
_SIZES_NP = np.minimum(np.array(_SIZES, dtype=np.int64), 1 << 40)  # no overflow in sums
NO_OFFSETS = np.zeros(0, dtype=np.int64)
_NO_WORDS = np.zeros(0, dtype="<u4")
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
# Items gathered at record offsets (`items`): a header, its type and index bytes.
_HEADER = np.dtype("V4")
_KEY = np.dtype("V2")


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
    offs, _, off, reason = frame(buf, start, stop, fast=fast)
    return offs, off, reason


def frame(
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
    header_at = items(arr, 0, _HEADER)  # the 4 header bytes at every offset, in one gather
    last = header_at.size - 1
    pos = starts
    steps = [pos]
    words: list[np.ndarray] = []
    for k in range(_SEGMENT // 4 + 1):
        # A walker past the end (or on an unknown type) reads garbage (the last header), but
        # it has passed its stop, and what it reads there is never used.
        word = header_at[np.minimum(pos, last)].view("<u4")
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
    words.append(header_at[np.minimum(pos, last)].view("<u4"))
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
            seen = lut.take(items(arr, 0, _KEY)[cand].view("<u2"))
            seg, cand = seg[seen], cand[seen]
            if seg.size:
                head = np.ones(seg.size, dtype=bool)  # the first candidate of its segment
                np.not_equal(seg[1:], seg[:-1], out=head[1:])
                seg, cand = seg[head], cand[head]
        ok = np.ones(cand.size, dtype=bool)
        sizes, high, known = _SIZES_NP, _HIGH, KNOWN_LUT
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
    return np.frombuffer(offs, dtype=np.int64) if len(offs) else NO_OFFSETS


def _join(pieces: list[np.ndarray], empty: np.ndarray = NO_OFFSETS) -> np.ndarray:
    pieces = [x for x in pieces if x.size]
    if not pieces:
        return empty
    return pieces[0] if len(pieces) == 1 else np.concatenate(pieces)


def framed_length(buf: bytes) -> int:
    """Length of the longest prefix of `buf` made of whole records (framing only)."""
    _, off, reason = _scan(buf, 0, len(buf))
    return len(buf) if reason == "eof" else off


def items(arr: np.ndarray, offset: int, dtype: np.dtype) -> np.ndarray:
    """The items of `dtype` starting at every byte of `arr` from `offset` on (an unaligned view):
    indexed by record offsets, they gather a field or a whole row of every record at once, as
    one block copy per record."""
    count = max(0, arr.size - offset - dtype.itemsize + 1)
    return np.ndarray((count,), dtype=dtype, buffer=arr, offset=offset if count else 0,
                      strides=(1,))


def _headers(arr: np.ndarray, offs: np.ndarray) -> np.ndarray:
    """The 4-byte header of every record at `offs`, as uint32: type | index << 8 | length << 16."""
    return items(arr, 0, _HEADER)[offs].view("<u4")
