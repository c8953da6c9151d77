"""The reader's fast paths against its careful ones, where the fast walk against the reference
walk (test_logs_cli_speed.py) does not reach: records checked through the table of 16-bit keys
(`_KEYED_MIN` data records or more in one stretch) give what the per-record check gives, with
damage, salvage, redefinitions, both Byte Array codes and many formats; the headers the fast
walks hand over are the bytes at their offsets; the Byte Array gather (whole rows, binary
pieces) gives every record's bytes."""

from __future__ import annotations

from unittest import mock

import numpy as np
import pytest

from companion.logs import framing, reader
from companion.logs.decode import _gather_elements
from companion.logs.formats import parse_format
from companion.logs.framing import _headers, frame
from companion.logs.reader import _Parser
from companion.logs.records import (
    ARRAY_ALT,
    BEGIN,
    END,
    DataPacker,
    encode_array,
    encode_comment,
    encode_definition,
    encode_marker,
)
from companion.logs.streams import LogFormatError

T0 = 1_700_000_000 * 10**9
ANY = mock.ANY
FAST = "%hhu,%hhu,%.6f,%.6f,%.6f,%.5f,%.5f,%.5f"
SLOW = "%.7f,%.7f,%.7f,%hu"
WIDE = ",".join(["%.6f"] * 12)


def make_log(records: int, *, seed: int = 1, redefine: bool = False, alt: bool = False,
             formats: int = 3) -> tuple[bytes, list[int]]:
    """A log like the IMU's (a fast format, raw bytes as Byte Arrays of a few lengths, a slow
    format every 50 records) and the offsets of its records. `redefine`: index 1 changes layout
    half way; `alt`: some Byte Arrays use the 0xDA code; `formats`: more indexes defined
    (extra ones get a record now and then)."""
    rng = np.random.default_rng(seed)
    fast = DataPacker(1, parse_format(FAST))
    slow = DataPacker(2, parse_format(SLOW))
    wide = DataPacker(1, parse_format(WIDE))
    extra = [DataPacker(k, parse_format("%d,%hu")) for k in range(4, formats + 1)]
    parts = [encode_comment(1, "counter,status,p,q,r,ax,ay,az"), encode_definition(1, FAST),
             encode_definition(2, SLOW), encode_comment(3, "raw"), encode_definition(3, "%02hhX")]
    parts += [encode_definition(p.index, "%d,%hu") for p in extra]
    parts.append(encode_marker(BEGIN, T0))
    t = T0
    for k in range(records):
        t += 10_000_000
        if redefine and k == records // 2:
            parts.append(encode_definition(1, WIDE))
        packer = wide if redefine and k >= records // 2 else fast
        n_values = 12 if packer is wide else 8
        parts.append(packer.pack(t, (k % 256, 0, *rng.normal(0, 1, n_values - 2).tolist())))
        n = int(rng.choice([20, 20, 20, 40, 7, 0, 300]))
        raw = encode_array(3, rng.integers(0, 256, n, dtype=np.uint8).tobytes(), t)
        if alt and k % 7 == 3:
            raw = bytes([ARRAY_ALT]) + raw[1:]
        parts.append(raw)
        if k % 50 == 49:
            parts.append(slow.pack(t, (*rng.normal(0, 1, 3).tolist(), k % 65536)))
        if extra and k % 97 == 5:
            parts.append(extra[k % len(extra)].pack(t, (k, k % 65536)))
    parts.append(encode_marker(END, t))
    offsets = np.cumsum([0] + [len(p) for p in parts[:-1]]).tolist()
    return b"".join(parts), offsets


def read(buf: bytes, salvage: bool) -> object:
    """Everything a read gives, comparable with ==."""
    try:
        lf = _Parser(buf, "log.bin", salvage).run()
    except LogFormatError as exc:
        return (exc.offset, exc.kind, str(exc))
    out: list[object] = [lf.record_count, lf.truncated_bytes, lf.warnings, lf.markers, lf.damage]
    for s in lf.streams:
        out.append((s.index, s.kind, s.columns, s.number, s.format, s.definition_offset,
                    s.offsets.tolist(), s.time_ns.tolist(), str(s.data.dtype), s.data.tobytes()))
        if s.kind == "array":
            assert s.lengths is not None and s.values is not None and s.time_s is not None
            out.append((s.lengths.tolist(), s.values.tobytes(), s.time_s.tobytes()))
    return out


def damaged(buf: bytes, offsets: list[int]) -> list[bytes]:
    """The log with one record made corrupt in each of the ways the check looks for."""
    cases = []
    data = [p for p in offsets if buf[p] in (0xDB, 0xBA, 0xDA)]
    block = next(p for p in data[4000:] if buf[p] == 0xDB and buf[p + 1] == 1)
    array = next(p for p in data[4000:] if buf[p] in (0xBA, 0xDA))
    for where, value in ((block + 1, 77),  # an undefined index
                         (block + 1, 3),  # a Data Block of a 1-byte format
                         (array + 1, 1),  # a Byte Array of a multi-field format
                         (array + 1, 0),  # index 0
                         (array, 0xDA)):  # the other Byte Array code: valid
        bad = bytearray(buf)
        bad[where] = value
        cases.append(bytes(bad))
    return cases


@pytest.mark.parametrize(("redefine", "alt", "formats"), [(False, False, 3), (True, False, 3),
                                                          (False, True, 3), (False, False, 20)])
def test_keyed_check_agrees_with_the_per_record_check(monkeypatch: pytest.MonkeyPatch,
                                                      redefine: bool, alt: bool,
                                                      formats: int) -> None:
    buf, offsets = make_log(12_000, redefine=redefine, alt=alt, formats=formats)
    assert len(buf) > 4 * framing._FAST_MIN
    inputs = [buf, *damaged(buf, offsets)]
    keyed = [read(b, salvage) for b in inputs for salvage in (False, True)]
    monkeypatch.setattr(reader, "_KEYED_MIN", 1 << 62)  # every stretch checked record by record
    careful = [read(b, salvage) for b in inputs for salvage in (False, True)]
    assert keyed == careful
    assert isinstance(keyed[0], list)  # the clean log reads
    kinds = {r[1] for r in keyed if isinstance(r, tuple)}
    assert {"undefined_index", "length_mismatch"} <= kinds


def test_keyed_check_of_a_single_format_log(monkeypatch: pytest.MonkeyPatch) -> None:
    packer = DataPacker(1, parse_format(FAST))
    parts = [encode_definition(1, FAST), encode_marker(BEGIN, T0)]
    parts += [packer.pack(T0 + k, (k % 256, 0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0))
              for k in range(10_000)]
    buf = b"".join([*parts, encode_marker(END, T0 + 10_000)])
    at = len(parts[0]) + len(parts[1]) + 7_000 * len(parts[2])  # a Data Block's start
    inputs = [buf]
    for where, value in ((at + 1, 9), (at + 1, 0), (at, 0xBA)):
        bad = bytearray(buf)
        bad[where] = value
        inputs.append(bytes(bad))
    keyed = [read(b, salvage) for b in inputs for salvage in (False, True)]
    monkeypatch.setattr(reader, "_KEYED_MIN", 1 << 62)
    assert keyed == [read(b, salvage) for b in inputs for salvage in (False, True)]
    assert keyed[2::2] == [(at, kind, ANY) for kind in ("undefined_index", "undefined_index",
                                                      "length_mismatch")]  # strict reads


@pytest.mark.parametrize("raw", [None, 24])
def test_headers_handed_over_by_the_fast_walks_are_the_file_bytes(raw: int | None) -> None:
    buf, _ = make_log(20_000, seed=5, alt=True)
    if raw is not None:  # one pattern of record sizes: long verified runs, now and then broken
        packer = DataPacker(1, parse_format(FAST))
        parts = [encode_definition(1, FAST), encode_definition(3, "%hhu")]
        for k in range(20_000):
            parts += [packer.pack(T0 + k, (k % 256, 0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0)),
                      encode_array(3, bytes(raw + (k % 997 == 0)), T0 + k)]
        buf = b"".join(parts)
    arr = np.frombuffer(buf, dtype=np.uint8)
    for fast in (True, False):
        offs, words, stop, reason = frame(buf, 0, len(buf), fast=fast)
        assert (stop, reason) == (len(buf), "eof")
        assert words.dtype == np.dtype("<u4") and words.shape == offs.shape
        assert np.array_equal(words, _headers(arr, offs))
        assert np.array_equal(words & 0xFF, arr[offs])


def test_byte_array_gather_gives_every_record() -> None:
    rng = np.random.default_rng(7)
    arr = rng.integers(0, 256, 100_000, dtype=np.uint8)
    for lengths in ([0, 0, 0], [16] * 50, [20] * 900 + [40] * 60 + [7, 300, 0, 1, 65_535 // 2],
                    rng.integers(0, 600, 500).tolist(), [3, 0, 5] * 40):
        lens = np.array(lengths, dtype=np.int64)
        starts = rng.integers(0, arr.size - int(lens.max(initial=0)), lens.size)
        got = _gather_elements(arr, starts, lens)
        want = b"".join(arr[s : s + n].tobytes() for s, n in zip(starts, lens, strict=True))
        assert got.dtype == np.uint8 and got.tobytes() == want
