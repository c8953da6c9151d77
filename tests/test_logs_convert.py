"""Converter and ``companion logs`` tools: the vectors' CSVs, round trips of random formats and
values (binary -> reader -> CSV, checked against the values and the C library), the CLI."""

from __future__ import annotations

import ctypes
import ctypes.util
import json
import math
import struct
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd
import pytest
from conftest import data_file
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from companion.logs import cli
from companion.logs.convert import convert_file, format_time, render_block_lines
from companion.logs.formats import parse_format
from companion.logs.reader import read_log, read_log_bytes
from companion.logs.records import (
    BEGIN,
    END,
    DataPacker,
    encode_array,
    encode_comment,
    encode_definition,
    encode_marker,
)

VECTORS = data_file("vectors", "log-example.bin").parent
T0 = 1_700_000_000 * 10**9
_LIBC_NAME = ctypes.util.find_library("c")
LIBC = ctypes.CDLL(_LIBC_NAME) if _LIBC_NAME else None


def data_lines(path: Path) -> list[bytes]:
    return [ln for ln in path.read_bytes().split(b"\n") if ln and not ln.startswith(b"%")]


def test_vectors_convert_to_identical_data_lines(tmp_path: Path) -> None:
    out = convert_file(VECTORS / "log-example.bin", tmp_path)
    assert [p.name for p in out] == [f"log-example_fmt{i}.csv" for i in range(1, 6)]
    for p in out:
        assert data_lines(p) == data_lines(VECTORS / p.name), p.name


def test_csv_layout_markers_and_matlab_loading(tmp_path: Path) -> None:
    (p1,) = [
        p
        for p in convert_file(VECTORS / "log-example.bin", tmp_path)
        if p.name.endswith("fmt1.csv")
    ]
    lines = p1.read_text().splitlines()
    assert lines[0].startswith("%") and "% columns: time_s,t_ms,p,q,r,temp_c100,status" in lines
    markers = [ln for ln in lines if ln.startswith("% begin") or ln.startswith("% end")]
    assert markers == [
        "% begin data 1700000000.000000000",
        "% end data 1700000000.327848196",
        "% begin data 1700000000.327848197",
        "% end data 1700000000.633900131",
    ]
    # The second Begin comes after the 6th record of this format.
    body = [
        ln
        for ln in lines
        if not ln.startswith("% source")
        and not ln.startswith("% columns")
        and not ln.startswith("% format")
    ]
    assert body[7] == "% end data 1700000000.327848196"
    table = np.loadtxt(p1, comments="%", delimiter=",")
    assert table.shape == (15, 7)


def test_time_is_exact_with_nine_decimals() -> None:
    assert format_time(1700000000_000000001) == "1700000000.000000001"
    assert format_time(0) == "0.000000000"
    assert format_time(-500_000_000) == "-0.500000000"
    assert format_time(-1_000_000_001) == "-1.000000001"
    spec = parse_format("%d")
    lines = render_block_lines(
        spec, np.array([-1, 5], dtype=np.int64), [np.array([1, 2], dtype=np.int32)]
    )
    assert lines == ["-0.000000001,1\n", "0.000000005,2\n"]


def test_trailing_newline_in_a_format_is_not_doubled() -> None:
    spec = parse_format("%d\n")
    assert render_block_lines(spec, np.array([0]), [np.array([3], dtype=np.int32)]) == [
        "0.000000000,3\n"
    ]


# -- round trip of random formats and values ----------------------------------------------------

TABLE = [
    "%c", "%hhd", "%hhi", "%hhu", "%hhx", "%hhX", "%hho", "%hd", "%hi", "%hu", "%hx", "%hX", "%ho",
    "%d", "%i", "%ld", "%li", "%u", "%x", "%X", "%o", "%lu", "%lx", "%lX", "%lld", "%lli",
    "%llu", "%llx", "%llX", "%f", "%e", "%g", "%E", "%G", "%lf", "%le", "%lg",
]  # fmt: skip


@st.composite
def formats(draw: st.DrawFn) -> str:
    convs = draw(st.lists(st.sampled_from(TABLE), min_size=1, max_size=6))
    out = []
    for c in convs:
        flags = draw(st.lists(st.sampled_from("-+ #0"), max_size=3).map("".join))
        width = draw(st.one_of(st.just(""), st.integers(1, 12).map(str)))
        prec = draw(st.one_of(st.just(""), st.integers(0, 9).map(lambda p: f".{p}")))
        out.append("%" + flags + width + prec + c[1:])
    sep = draw(st.sampled_from([",", ", ", ";", ",%%,"]))
    return sep.join(out)


def values_for(fmt: str) -> st.SearchStrategy[list[int | float]]:
    spec = parse_format(fmt)
    parts = []
    for c in spec.conversions:
        if c.dtype.kind == "f":
            width: Literal[32, 64] = 32 if c.dtype.itemsize == 4 else 64
            parts.append(st.floats(width=width, allow_nan=True, allow_infinity=True))
        else:
            info = np.iinfo(c.dtype)
            parts.append(st.integers(int(info.min), int(info.max)))
    return st.tuples(*parts).map(list)


def c_printf(fmt: str, spec_values: list[tuple[str, str, int | float]]) -> bytes:
    assert LIBC is not None
    args: list[object] = []
    for length, conv, value in spec_values:
        if conv in "feEgGF":
            args.append(ctypes.c_double(float(value)))
        elif length == "ll":
            args.append(ctypes.c_ulonglong(int(value) & (2**64 - 1)))
        elif length == "l":
            args.append(ctypes.c_long(int(value)))
        else:
            args.append(ctypes.c_int(int(value)))
    buf = ctypes.create_string_buffer(8192)
    n = LIBC.snprintf(buf, 8192, fmt.encode(), *args)
    return buf.raw[:n]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_round_trip_random_formats(data: st.DataObject) -> None:
    fmt = data.draw(formats())
    spec = parse_format(fmt)
    rows = data.draw(st.lists(values_for(fmt), min_size=1, max_size=8))
    packer = DataPacker(3, spec)
    parts = [encode_marker(BEGIN, T0), encode_definition(3, fmt)]
    times = [T0 + 17 * k for k in range(len(rows))]
    parts += [packer.pack(t, r) for t, r in zip(times, rows, strict=True)]
    parts.append(encode_marker(END, T0 + 10**9))
    lf = read_log_bytes(b"".join(parts))
    arr = lf.data(3)
    assert lf.time_ns(3).tolist() == times
    # Field by field, bit for bit (NaN payloads included).
    for k, row in enumerate(rows):
        expected = struct.pack(spec.struct_format, *row)
        got = b"".join(arr[name][k].tobytes() for name in (arr.dtype.names or ())[1:])
        assert got == expected
    # Text: each line equals C's printf of the stored values, and Python's % where it is exact.
    (stream,) = lf.streams_of(3)
    lines = render_block_lines(spec, stream.time_ns, [arr[n] for n in stream.columns])
    for k, line in enumerate(lines):
        stored = struct.unpack(spec.struct_format, struct.pack(spec.struct_format, *rows[k]))
        head, _, body = line.partition(",")
        assert head == format_time(times[k])
        assert body.endswith("\n")
        body_bytes = body[:-1].encode("latin-1")
        if LIBC is not None:
            args = [(c.length, c.conv, v) for c, v in zip(spec.conversions, stored, strict=True)]
            assert body_bytes == c_printf(fmt, args)
        pys = [c.python_spec for c in spec.conversions]
        finite = all(not isinstance(v, float) or math.isfinite(v) for v in stored)
        if (
            all(p is not None for p in pys)
            and finite
            and not any(c.conv == "c" for c in spec.conversions)
        ):
            py_fmt = spec.literals[0].replace("%", "%%") + "".join(
                str(p) + lit.replace("%", "%%")
                for p, lit in zip(pys, spec.literals[1:], strict=True)
            )
            assert body[:-1] == py_fmt % tuple(stored)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.binary(min_size=0, max_size=40), min_size=1, max_size=6),
    st.sampled_from(["%hhu", "%hhd", "%c", "%02hhX", "%-4hho", "%#hhx"]),
)
def test_round_trip_byte_arrays(payloads: list[bytes], fmt: str) -> None:
    parts = [encode_comment(9, "sample"), encode_definition(9, fmt)]
    parts += [encode_array(9, p, T0 + k) for k, p in enumerate(payloads)]
    lf = read_log_bytes(b"".join(parts))
    (s,) = lf.streams_of(9)
    dtype = parse_format(fmt).conversions[0].dtype
    assert [a.tobytes() for a in s.arrays()] == payloads
    assert s.value_field == "sample"
    assert all(a.dtype == dtype for a in s.arrays())


# -- the CLI ------------------------------------------------------------------------------------


def _damaged(tmp_path: Path) -> Path:
    raw = bytearray((VECTORS / "log-example.bin").read_bytes())
    lf = read_log(VECTORS / "log-example.bin")
    victim = int(lf.streams_of(2)[0].offsets[3])
    raw[victim] = 0x42
    path = tmp_path / "damaged.bin"
    path.write_bytes(bytes(raw))
    return path


def test_cli_convert_directory_and_output_dir(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tmp_path / "in"
    src.mkdir()
    (src / "a.bin").write_bytes((VECTORS / "log-example.bin").read_bytes())
    (src / "b.uavlog").write_bytes((VECTORS / "log-example.bin").read_bytes())
    (src / "notes.txt").write_text("ignored")
    assert cli.main(["convert", str(src), "-o", str(tmp_path / "out")]) == 0
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == sorted(
        [f"a_fmt{i}.csv" for i in range(1, 6)] + [f"b_fmt{i}.csv" for i in range(1, 6)]
    )
    captured = capsys.readouterr()
    assert "a_fmt1.csv" in captured.out and captured.err == ""  # no progress when not a TTY


def test_cli_convert_default_dir_is_next_to_input(tmp_path: Path) -> None:
    path = tmp_path / "x.bin"
    path.write_bytes((VECTORS / "log-example.bin").read_bytes())
    assert cli.main(["convert", str(path)]) == 0
    assert data_lines(tmp_path / "x_fmt3.csv") == data_lines(VECTORS / "log-example_fmt3.csv")


def test_cli_damaged_file_is_read_and_strict_fails(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _damaged(tmp_path)
    assert cli.main(["convert", str(path), "-o", str(tmp_path / "s"), "--strict"]) == 1
    err = capsys.readouterr().err
    assert (
        "byte offset" in err
        and "damaged.bin" in err
        and "--strict" in err
        and "Traceback" not in err
    )
    for extra in ([], ["--salvage"]):  # the default; --salvage is accepted and the same
        assert cli.main(["convert", str(path), "-o", str(tmp_path / "o"), *extra]) == 0
        err = capsys.readouterr().err
        assert "skipped" in err and "byte offset" in err
        assert len(data_lines(tmp_path / "o" / "damaged_fmt2.csv")) == 16


def test_cli_missing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["info", str(tmp_path / "nope.bin")]) == 1
    assert "cannot read" in capsys.readouterr().err


def test_cli_progress_on_a_terminal(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("sys.stderr.isatty", lambda: True, raising=False)
    path = tmp_path / "x.bin"
    path.write_bytes((VECTORS / "log-example.bin").read_bytes())
    assert cli.main(["convert", str(path)]) == 0
    assert "100.0%" in capsys.readouterr().err


def test_cli_info(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["info", str(VECTORS / "log-example.bin")]) == 0
    out = capsys.readouterr().out
    assert (
        "closed cleanly:  yes" in out
        and "begin/end pairs: 2" in out
        and "'%8.3f,%02X,%lu,%ld'" in out
    )
    assert cli.main(["info", str(VECTORS / "log-example.bin"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert [f["records"] for f in info["formats"]] == [15, 17, 15, 13, 2]
    assert info["start"] == "1700000000.000000000" and info["end"] == "1700000000.633900131"
    assert info["damage"] == [] and info["closed_cleanly"] is True
    path = _damaged(tmp_path)
    assert cli.main(["info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["damage"][0]["kind"] == "unknown_type"


def test_cli_export_npz_and_parquet(tmp_path: Path) -> None:
    src = VECTORS / "log-example.bin"
    assert cli.main(["export", str(src), "--to", "npz", "-o", str(tmp_path / "x.npz")]) == 0
    with np.load(tmp_path / "x.npz") as z:
        assert z["fmt1"]["t_ms"][0] == 24224963
        assert z["fmt1_time_ns"][0] == 1700000000053569706
        assert z["fmt5"]["value"].tolist()[:3] == [16, 145, 95]
        assert z["markers"]["kind"].tolist() == ["begin", "end", "begin", "end"]
    assert cli.main(["export", str(src), "--to", "parquet", "-o", str(tmp_path / "pq")]) == 0
    frame = pd.read_parquet(tmp_path / "pq" / "log-example_fmt3.parquet")
    assert list(frame.columns) == ["time_s", "time_ns", "a", "b", "c", "d", "e", "f"]
    assert frame["b"].iloc[1] == 17054435391394920820


def test_add_commands_registers_the_log_actions() -> None:
    import argparse

    parser = argparse.ArgumentParser(prog="companion")
    logs = parser.add_subparsers().add_parser("logs")
    cli.add_commands(logs.add_subparsers(required=True))
    args = parser.parse_args(["logs", "info", "x.bin", "--json"])
    assert args.func is cli.cmd_info and args.json
    args = parser.parse_args(["logs", "convert", "a.bin", "b", "-o", "out", "--strict"])
    assert args.func is cli.cmd_convert and args.paths == ["a.bin", "b"] and args.strict
    args = parser.parse_args(["logs", "export", "a.bin", "--to", "npz"])
    assert args.func is cli.cmd_export and args.to == "npz"
    with pytest.raises(SystemExit):
        parser.parse_args(["logs", "export", "a.bin", "--to", "xls"])
