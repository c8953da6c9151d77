"""Reader: the contract's vectors, several formats and Begin/End pairs, redefinition, every kind
of damage with and without salvage, truncated tails, and fuzzing (only LogFormatError may
come out, in bounded time)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from conftest import data_file
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from companion.logs.formats import parse_format
from companion.logs.framing import framed_length
from companion.logs.reader import read_log, read_log_bytes
from companion.logs.records import (
    ARRAY,
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

VECTORS = data_file("vectors", "log-example.bin").parent
T0 = 1_700_000_000 * 10**9


class Builder:
    """A log assembled record by record with the library's encoders; remembers offsets."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.offsets: list[int] = []
        self.size = 0

    def _add(self, rec: bytes) -> int:
        self.offsets.append(self.size)
        self.parts.append(rec)
        self.size += len(rec)
        return self.offsets[-1]

    def begin(self, t: int) -> int:
        return self._add(encode_marker(BEGIN, t))

    def end(self, t: int) -> int:
        return self._add(encode_marker(END, t))

    def define(self, index: int, fmt: str, names: str | None = None) -> int:
        if names is not None:
            self._add(encode_comment(index, names))
        return self._add(encode_definition(index, fmt))

    def data(self, index: int, fmt: str, t: int, *values: float) -> int:
        return self._add(DataPacker(index, parse_format(fmt)).pack(t, values))

    def array(self, index: int, payload: bytes, t: int, *, alt: bool = False) -> int:
        rec = bytearray(encode_array(index, payload, t))
        if alt:
            rec[0] = ARRAY_ALT
        return self._add(bytes(rec))

    def bytes(self) -> bytes:
        return b"".join(self.parts)


def sample_log() -> tuple[Builder, list[int]]:
    """Three formats, two Begin/End pairs, arrays; returns the builder and the data offsets."""
    b = Builder()
    data_offs = []
    b.begin(T0)
    b.define(1, "%d,%f", "n,x")
    b.define(2, "%hhu,%lld", "a,b")
    b.define(3, "%hhu", "px")
    for k in range(10):
        data_offs.append(b.data(1, "%d,%f", T0 + 10 + k, k, k * 0.5))
        data_offs.append(b.data(2, "%hhu,%lld", T0 + 20 + k, k, -(k**5)))
    b.array(3, bytes(range(4)), T0 + 40)
    b.end(T0 + 50)
    b.begin(T0 + 60)
    for k in range(10, 15):
        data_offs.append(b.data(1, "%d,%f", T0 + 70 + k, k, k * 0.5))
    b.array(3, bytes([9, 8]), T0 + 90, alt=True)
    b.end(T0 + 100)
    return b, data_offs


# -- the vectors --------------------------------------------------------------------------------


def test_vector_values_and_structure() -> None:
    lf = read_log(VECTORS / "log-example.bin")
    assert lf.closed_cleanly and not lf.damage and lf.truncated_bytes == 0
    assert lf.indexes == [1, 2, 3, 4, 5]
    assert [(m.kind, m.time_ns) for m in lf.markers] == [
        ("begin", 1700000000000000000),
        ("end", 1700000000327848196),
        ("begin", 1700000000327848197),
        ("end", 1700000000633900131),
    ]
    assert len(lf.begin_end_pairs()) == 2
    d1 = lf.data(1)
    assert d1.dtype.names == ("time_s", "t_ms", "p", "q", "r", "temp_c100", "status")
    assert d1.dtype["t_ms"] == np.dtype("<i4") and d1.dtype["p"] == np.dtype("<f4")
    assert d1.dtype["temp_c100"] == np.dtype("<i2") and d1.dtype["status"] == np.dtype("<u2")
    assert len(d1) == 15
    assert d1["t_ms"][0] == 24224963 and d1["temp_c100"][0] == -18084 and d1["status"][0] == 43401
    assert f"{d1['p'][0]:f}" == "544.809875"
    assert lf.time_ns(1)[0] == 1700000000053569706
    assert d1["time_s"][0] == pytest.approx(1700000000.053569706, abs=1e-6)
    d3 = lf.data(3)
    assert d3["a"][0] == -3120705304108787542 and d3["b"][0] == 3710517852100179178
    assert d3.dtype["b"] == np.dtype("<u8")
    d2 = lf.data(2)
    assert (
        d2.dtype["lat"] == np.dtype("<f8")
        and d2["sats_signed"][2] == -56
        and d2["flags"][0] == 3724181412
    )
    # Byte arrays, one written as 0xDA and one as 0xBA.
    (s5,) = lf.streams_of(5)
    assert s5.kind == "array"
    assert [a.tolist() for a in s5.arrays()] == [
        [16, 145, 95, 196, 253, 184, 248, 186, 80, 33],
        [137, 100, 93, 225, 238, 167, 3],
    ]
    raw = (VECTORS / "log-example.bin").read_bytes()
    assert {raw[int(o)] for o in s5.offsets} == {ARRAY, ARRAY_ALT}
    frame = lf.to_pandas(1)
    assert list(frame.columns) == list(d1.dtype.names)
    assert len(frame) == 15


def test_several_formats_and_pairs_round_trip() -> None:
    b, _ = sample_log()
    lf = read_log_bytes(b.bytes())
    assert lf.closed_cleanly
    assert [(p[0].time_ns, p[1].time_ns) for p in lf.begin_end_pairs() if p[0] and p[1]] == [
        (T0, T0 + 50),
        (T0 + 60, T0 + 100),
    ]
    d1 = lf.data(1)
    assert d1["n"].tolist() == list(range(15))
    assert d1["x"].tolist() == [k * 0.5 for k in range(15)]
    assert lf.time_ns(1).tolist() == [T0 + 10 + k for k in range(10)] + [
        T0 + 70 + k for k in range(10, 15)
    ]
    assert lf.data(2)["b"].tolist() == [-(k**5) for k in range(10)]
    long = lf.data(3)
    assert long.dtype.names == ("time_s", "record", "element", "px")
    assert long["px"].tolist() == [0, 1, 2, 3, 9, 8]
    assert long["record"].tolist() == [0, 0, 0, 0, 1, 1]
    assert long["element"].tolist() == [0, 1, 2, 3, 0, 1]
    assert lf.record_count == len(b.offsets)


def test_da_is_read_exactly_like_ba() -> None:
    def build(alt: bool) -> bytes:
        b = Builder()
        b.define(7, "%hhd")
        b.array(7, bytes([0, 255, 128, 5]), T0, alt=alt)
        return b.bytes()

    a, c = read_log_bytes(build(False)), read_log_bytes(build(True))
    assert a.data(7).tolist() == c.data(7).tolist()
    assert a.data(7)["value"].tolist() == [0, -1, -128, 5]


def test_columns_default_and_mismatched_comment() -> None:
    b = Builder()
    b.define(1, "%d,%d")
    b.define(2, "%d,%d,%d", "a,b")  # one name short: c1.. instead
    b.define(3, "%d,%d", "time_s,time_s")
    b.data(1, "%d,%d", T0, 1, 2)
    b.data(2, "%d,%d,%d", T0, 1, 2, 3)
    b.data(3, "%d,%d", T0, 1, 2)
    lf = read_log_bytes(b.bytes())
    assert lf.data(1).dtype.names == ("time_s", "c1", "c2")
    assert lf.data(2).dtype.names == ("time_s", "c1", "c2", "c3")
    assert lf.data(3).dtype.names == ("time_s", "time_s_2", "time_s_3")
    assert any("names 2 columns for 3 fields" in w for w in lf.warnings)


def test_defined_but_unused_format_is_listed_empty() -> None:
    b = Builder()
    b.define(4, "%u", "z")
    lf = read_log_bytes(b.bytes())
    (s,) = lf.streams_of(4)
    assert s.n_records == 0 and s.data.dtype.names == ("time_s", "z")


def test_redefinition_after_begin_starts_a_new_stream() -> None:
    b = Builder()
    b.begin(T0)
    b.define(1, "%d", "n")
    b.data(1, "%d", T0 + 1, 5)
    b.end(T0 + 2)
    b.begin(T0 + 3)
    b.define(1, "%f,%f", "x,y")
    redef = b.offsets[-1]
    b.data(1, "%f,%f", T0 + 4, 1.5, 2.5)
    b.end(T0 + 5)
    b.begin(T0 + 6)
    b.define(1, "%d", "n")  # back to the first layout: same stream as before
    b.data(1, "%d", T0 + 7, 6)
    b.end(T0 + 8)
    lf = read_log_bytes(b.bytes())
    s1, s2 = lf.streams_of(1)
    assert (s1.format, s1.number, s1.data["n"].tolist()) == ("%d", 1, [5, 6])
    assert (s2.format, s2.number, s2.data["x"].tolist()) == ("%f,%f", 2, [1.5])
    assert s2.definition_offset == redef
    with pytest.raises(ValueError, match="changes layout"):
        lf.data(1)
    frame = lf.to_pandas(1)
    assert (
        frame["n"].tolist()[0] == 5
        and np.isnan(frame["n"].tolist()[1])
        and frame["n"].tolist()[2] == 6
    )
    assert frame["x"].tolist()[1] == 1.5


def test_identical_redefinition_continues_the_stream() -> None:
    b = Builder()
    for k in range(3):
        b.begin(T0 + 10 * k)
        b.define(2, "%hu", "v")
        b.data(2, "%hu", T0 + 10 * k + 1, k)
        b.end(T0 + 10 * k + 2)
    lf = read_log_bytes(b.bytes())
    assert len(lf.streams_of(2)) == 1
    assert lf.data(2)["v"].tolist() == [0, 1, 2]


def test_nsec_out_of_range_is_not_corruption() -> None:
    b = Builder()
    b.define(1, "%d")
    off = b.data(1, "%d", T0, 1)
    raw = bytearray(b.bytes())
    raw[off + 8 : off + 12] = (1_500_000_000).to_bytes(4, "little")
    lf = read_log_bytes(bytes(raw))
    assert lf.time_ns(1)[0] == (T0 // 10**9) * 10**9 + 1_500_000_000


# -- damage ---------------------------------------------------------------------------------------


def _patched(raw: bytes, offset: int, new: bytes) -> bytes:
    return raw[:offset] + new + raw[offset + len(new) :]


def _corruptions() -> list[tuple[str, str, bytes, int, int]]:
    """(name, kind, damaged file, offset of the damage, bytes salvage skips)."""
    b, data_offs = sample_log()
    raw = b.bytes()
    victim = data_offs[5]  # a record of index 2: 12 + 9 bytes
    size = 12 + 9
    cases = [
        ("unknown type", "unknown_type", _patched(raw, victim, b"\x42"), victim, size),
        ("undefined index", "undefined_index", _patched(raw, victim + 1, b"\x09"), victim, size),
        (
            "length mismatch",
            "length_mismatch",
            _patched(raw, victim + 2, b"\x0a\x00"),
            victim,
            size,
        ),
    ]
    # A Format Comment whose length runs past the end of the file, records after it.
    bc = Builder()
    bc.define(1, "%d")
    bc.data(1, "%d", T0, 1)
    comment = bc._add(encode_comment(9, "spare,names"))
    for k in range(5):
        bc.data(1, "%d", T0 + k, k)
    rawc = bc.bytes()
    cases.append(
        (
            "past eof",
            "past_eof",
            _patched(rawc, comment + 2, b"\xff\xff"),
            comment,
            4 + len("spare,names"),
        )
    )
    # A definition that is not a format string: the data of its index then fail too in strict mode.
    bd = Builder()
    bd.define(1, "%d")
    bad = bd._add(b"\xfd\x02\x02\x00%s")
    bd.data(1, "%d", T0, 3)
    cases.append(("bad definition", "bad_definition", bd.bytes(), bad, 6))
    # A Begin Data with a non-zero length.
    cases.append(("marker length", "length_mismatch", _patched(raw, 2, b"\x04\x00"), 0, 12))
    return cases


CORRUPTIONS = _corruptions()


@pytest.mark.parametrize(
    ("name", "kind", "raw", "offset", "skipped"), CORRUPTIONS, ids=[c[0] for c in CORRUPTIONS]
)
def test_corruption_stops_with_the_byte_offset(
    name: str, kind: str, raw: bytes, offset: int, skipped: int, tmp_path: Path
) -> None:
    path = tmp_path / "damaged.bin"
    path.write_bytes(raw)
    with pytest.raises(LogFormatError) as err:
        read_log(path, strict=True)
    assert err.value.offset == offset
    assert err.value.kind == kind
    assert str(path) in str(err.value) and f"byte offset {offset}" in str(err.value)


@pytest.mark.parametrize(
    ("name", "kind", "raw", "offset", "skipped"), CORRUPTIONS, ids=[c[0] for c in CORRUPTIONS]
)
def test_salvage_skips_to_the_next_plausible_record(
    name: str, kind: str, raw: bytes, offset: int, skipped: int
) -> None:
    lf = read_log_bytes(raw, salvage=True)
    assert [(d.offset, d.kind, d.skipped_bytes) for d in lf.damage] == [(offset, kind, skipped)]
    by_default = read_log_bytes(raw)  # skipping damage is the default, `salvage` a no-op alias
    assert [(d.offset, d.skipped_bytes) for d in by_default.damage] == [(offset, skipped)]
    assert lf.skipped_bytes == skipped and lf.skipped_records == 1
    if name in ("unknown type", "undefined index", "length mismatch"):
        good = read_log_bytes(sample_log()[0].bytes())
        assert lf.data(1).tolist() == good.data(1).tolist()
        assert lf.data(2)["a"].tolist() == [k for k in range(10) if k != 2]
        assert lf.data(3).tolist() == good.data(3).tolist()
    if name == "past eof":
        assert lf.data(1)["c1"].tolist() == [1, 0, 1, 2, 3, 4]
    if name == "bad definition":
        assert lf.data(1)["c1"].tolist() == [3]
    if name == "marker length":
        assert [m.offset for m in lf.markers][0] != 0


def test_salvage_of_several_damaged_regions() -> None:
    b, data_offs = sample_log()
    raw = bytearray(b.bytes())
    for off in data_offs[2:20:4]:
        raw[off] = 0x00
    lf = read_log_bytes(bytes(raw), salvage=True)
    assert [d.offset for d in lf.damage] == data_offs[2:20:4]
    assert len(lf.data(1)) + len(lf.data(2)) == len(data_offs) - len(data_offs[2:20:4])


def test_truncated_tail_at_every_cut_point() -> None:
    b, _ = sample_log()
    b.data(1, "%d,%f", T0 + 200, 99, 9.5)
    raw = b.bytes()
    last = b.offsets[-1]
    for cut in range(last + 1, len(raw)):
        lf = read_log_bytes(raw[:cut])
        assert lf.truncated_bytes == cut - last
        assert len(lf.data(1)) == 15, cut
        assert not lf.closed_cleanly
        assert any("cut short" in w for w in lf.warnings)
    assert len(read_log_bytes(raw).data(1)) == 16


def test_truncated_variable_length_tail() -> None:
    b = Builder()
    b.define(3, "%hhu", "px")
    b.array(3, bytes(range(200)), T0)
    raw = b.bytes()
    for cut in (len(raw) - 1, len(raw) - 150, b.offsets[-1] + 5):
        lf = read_log_bytes(raw[:cut])
        assert lf.truncated_bytes == cut - b.offsets[-1]
        assert lf.streams_of(3)[0].n_records == 0


def test_framed_length() -> None:
    b, _ = sample_log()
    raw = b.bytes()
    assert framed_length(raw) == len(raw)
    assert framed_length(raw[:-3]) == b.offsets[-1]
    assert framed_length(b"") == 0


def test_empty_and_tiny_inputs() -> None:
    lf = read_log_bytes(b"")
    assert lf.streams == [] and not lf.closed_cleanly
    assert read_log_bytes(b"\xbd").truncated_bytes == 1
    with pytest.raises(LogFormatError):
        read_log_bytes(b"\x01", strict=True)
    assert read_log_bytes(b"\x01").damage  # the default: skipped and reported


# -- fuzzing ------------------------------------------------------------------------------------

_BUDGET_S = 5.0


def _read_safely(raw: bytes) -> None:
    start = time.monotonic()
    try:
        read_log_bytes(raw, strict=True)
    except LogFormatError as exc:
        assert 0 <= exc.offset <= len(raw)
    lf = read_log_bytes(raw, salvage=True)  # salvage never raises
    for s in lf.streams:
        assert s.n_records <= len(raw) // 12
    assert time.monotonic() - start < _BUDGET_S


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=3000))
def test_fuzz_random_bytes(raw: bytes) -> None:
    _read_safely(raw)


_SAMPLE = sample_log()[0].bytes()
_VECTOR = (VECTORS / "log-example.bin").read_bytes()


@st.composite
def mutated(draw: st.DrawFn) -> bytes:
    raw = bytearray(draw(st.sampled_from([_VECTOR, _SAMPLE])))
    for _ in range(draw(st.integers(1, 8))):
        op = draw(st.sampled_from(["flip", "set", "cut", "insert", "delete"]))
        pos = draw(st.integers(0, max(0, len(raw) - 1)))
        if op == "flip" and raw:
            raw[pos] ^= 1 << draw(st.integers(0, 7))
        elif op == "set" and raw:
            raw[pos] = draw(st.sampled_from([0x00, 0xFF, 0xBD, 0xED, 0xFC, 0xFD, 0xDB, 0xBA, 0xDA]))
        elif op == "cut":
            del raw[pos:]
        elif op == "insert":
            raw[pos:pos] = draw(st.binary(min_size=1, max_size=20))
        elif op == "delete":
            del raw[pos : pos + draw(st.integers(1, 20))]
    return bytes(raw)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mutated())
def test_fuzz_mutated_valid_files(raw: bytes) -> None:
    _read_safely(raw)


def test_adversarial_inputs_are_bounded() -> None:
    # Many candidate record starts that are never plausible, and many tiny records.
    for raw in (
        b"\xdb" * 200_000,
        b"\xfc\x01\x00\x00" * 50_000,
        b"\xbd\x00\x00\x00" + b"\x00" * 100_000,
    ):
        start = time.monotonic()
        read_log_bytes(raw, salvage=True)
        assert time.monotonic() - start < 10.0
