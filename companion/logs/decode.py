"""Decoding the records of one stream of a binary flight log into numpy arrays.

Given the offsets of a stream's records (found and validated by `companion.logs.reader`), this
builds the `Stream`: a Data Block format's rows come out of the file bytes with one gather of
whole records (TIME and fields already have the layout of a row, TIME becoming ``time_s`` in
place), a Byte Array format's elements with one block copy per record of its common lengths
(the others in pieces of power-of-two sizes). It is separate from the reader because it is
the per-format part of a read, the one that knows the two record layouts, and it needs
nothing of the reader's state but the file bytes.
"""

from __future__ import annotations

import numpy as np

from companion.logs.formats import FormatSpec
from companion.logs.framing import items
from companion.logs.records import NS_PER_S, TIMED_SIZE
from companion.logs.streams import Stream

__all__ = ["array_stream", "block_stream"]

_TIME_V = np.dtype("V8")  # a TIME, gathered as one void item
_TIME = np.dtype([("s", "<i4"), ("ns", "<u4")])
_ROW_GROUPS = 4  # Byte Array lengths copied as whole rows (the most common ones)


def _times(arr: np.ndarray, offs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact int64 ns and float64 seconds of the TIME of every record at `offs`."""
    if offs.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.float64)
    t = items(arr, 4, _TIME_V)[offs].view(_TIME)  # void items gather fastest
    return _split_times(t["s"], t["ns"])


def block_stream(
    arr: np.ndarray,
    index: int,
    spec: FormatSpec,
    columns: tuple[str, ...],
    number: int,
    def_off: int,
    offs: np.ndarray,
) -> Stream:
    """The stream of the Data Blocks at `offs` (records of one format) in the file bytes `arr`:
    one row per record."""
    fields = [(c, d) for c, d in zip(columns, spec.field_dtypes, strict=True)]
    dtype = np.dtype([("time_s", "<f8"), *fields])  # packed: 8 bytes, then the record's
    if not offs.size:
        out = np.empty(0, dtype=dtype)
        time_ns = np.zeros(0, np.int64)
    else:
        # One gather of every record's TIME and fields, which already have the layout of a
        # row (TIME is 8 bytes, like time_s); then TIME is replaced by time_s in place.
        out = items(arr, 4, np.dtype(f"V{dtype.itemsize}"))[offs].view(dtype)
        # TIME copied out of the rows first: one pass over them instead of one per operand.
        raw = np.ndarray(out.shape, dtype=_TIME_V, buffer=out, strides=out.strides)
        t = raw.copy().view(_TIME)
        time_ns = _split_times(t["s"], t["ns"], out["time_s"])[0]
    return Stream(index, "block", spec, columns, number, def_off, time_ns, offs, _data=out)


def array_stream(
    arr: np.ndarray,
    index: int,
    spec: FormatSpec,
    columns: tuple[str, ...],
    number: int,
    def_off: int,
    offs: np.ndarray,
    lens: np.ndarray,
) -> Stream:
    """The stream of the Byte Arrays at `offs` (of `lens` elements each) in the file bytes
    `arr`: every element, in file order."""
    time_ns, time_s = _times(arr, offs)
    lens = lens.astype(np.int64)
    values = _gather_elements(arr, offs + TIMED_SIZE, lens).view(spec.field_dtypes[0])
    return Stream(
        index, "array", spec, columns, number, def_off, time_ns, offs,
        lengths=lens, values=values, time_s=time_s,
    )


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
        return items(arr, 0, np.dtype(f"V{width}"))[starts].view(np.uint8).reshape(-1)
    out = np.empty(total, dtype=np.uint8)
    before = np.cumsum(lens) - lens
    rest = lens > 0
    for width in np.argsort(counts)[::-1][:_ROW_GROUPS].tolist():
        if width == 0 or counts[width] * 20 < lens.size:
            break
        group = lens == width
        slots = items(out, 0, np.dtype(f"V{width}"))
        slots[before[group]] = items(arr, 0, np.dtype(f"V{width}"))[starts[group]]
        rest &= ~group
    if rest.any():
        r_starts, r_lens, r_before = starts[rest], lens[rest], before[rest]
        for k in range(int(r_lens.max()).bit_length() - 1, -1, -1):
            has = np.flatnonzero((r_lens & (1 << k)) != 0)
            if not has.size:
                continue
            done = r_lens[has] >> (k + 1) << (k + 1)  # the bytes of the higher digits
            slots = items(out, 0, np.dtype(f"V{1 << k}"))
            slots[r_before[has] + done] = items(arr, 0, np.dtype(f"V{1 << k}"))[r_starts[has] + done]
    return out


def _split_times(
    sec: np.ndarray, nsec: np.ndarray, out: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Exact int64 ns and float64 seconds (seconds + nanoseconds / 1e9, into `out` if given) of
    TIME fields."""
    time_ns = np.multiply(sec, NS_PER_S, dtype=np.int64)
    time_ns += nsec
    frac = np.divide(nsec, 1e9, dtype=np.float64)
    # int32 and uint32 are exact in float64: the same sums as in int64 first
    time_s = np.add(frac, sec, out=frac if out is None else out)
    return time_ns, time_s
