"""The log tools at the speed of the disk: `logs info` on a flight directory and its bad inputs,
what the commands import at start (no matplotlib for a command that draws nothing), and the
reader's fast record walk against the reference walk on a large log (same offsets, same arrays,
same damage, with and without salvage). Timing is measured by bench/reader_bench.py, not here."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.logs import cli
from companion.logs.formats import parse_format
from companion.logs.framing import _scan
from companion.logs.reader import _Parser, read_log_bytes
from companion.logs.records import (
    BEGIN,
    END,
    DataPacker,
    encode_array,
    encode_comment,
    encode_definition,
    encode_marker,
)
from companion.logs.streams import LogFormatError

REPO = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000 * 10**9
FAST = "%hhu,%hhu,%.6f,%.6f,%.6f,%.5f,%.5f,%.5f"  # the IMU's fast format
SLOW = "%.7f,%.7f,%.7f,%.6f,%.6f,%.6f,%.2f,%hu"
WIDE = ",".join(["%.6f"] * 15 + ["%.9lf", "%.9lf", "%.3f", "%.3f", "%.3lf"])


def make_log(records: int, seed: int = 1, *, adversarial: bool = False,
             raw_len: int | None = None) -> bytes:
    """A long log like the IMU's: a fast format, raw bytes as Byte Arrays of varying length, a
    slow format every 100 records, a redefinition and a restart half way. `adversarial` fills
    the Byte Arrays with bytes that look like record headers (false starts for the fast walk);
    `raw_len` gives them all that length (long runs of one pattern of record sizes)."""
    rng = np.random.default_rng(seed)
    fast = DataPacker(1, parse_format(FAST))
    slow = DataPacker(2, parse_format(SLOW))
    wide = DataPacker(1, parse_format(WIDE))
    parts = [encode_comment(1, "counter,status,p,q,r,ax,ay,az"), encode_definition(1, FAST),
             encode_definition(2, SLOW), encode_definition(3, "%02hhX"), encode_marker(BEGIN, T0)]
    lure = bytes([0xDB, 0x01, 0x1E, 0x00, 0xBA, 0x03, 0x04, 0x00, 0xBD, 0x00, 0x00, 0x00])
    t = T0
    for k in range(records):
        t += 10_000_000
        if k == records // 2:  # a restart and a new layout for index 1
            parts += [encode_marker(END, t), encode_marker(BEGIN, t), encode_definition(1, WIDE)]
        if k < records // 2:
            parts.append(fast.pack(t, (k % 256, 0, *rng.normal(0, 1, 6).tolist())))
        else:
            parts.append(wide.pack(t, rng.normal(0, 1, 20).tolist()))
        n = int(rng.integers(0, 40)) if raw_len is None else raw_len
        payload = (lure * 4)[:n] if adversarial else rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        parts.append(encode_array(3, payload, t))
        if k % 100 == 99:
            parts.append(slow.pack(t, (*rng.normal(0, 1, 7).tolist(), k % 65536)))
    parts.append(encode_marker(END, t))
    return b"".join(parts)


def _same(buf: bytes, salvage: bool) -> None:
    """The reader with the fast walk and with the reference walk only: identical results."""
    def read(fast: bool) -> object:
        try:
            return _Parser(buf, "log.bin", salvage, fast=fast).run()
        except LogFormatError as exc:
            return (exc.offset, exc.kind, str(exc))

    a, b = read(True), read(False)
    if not hasattr(a, "streams"):
        assert a == b
        return
    assert hasattr(b, "streams")
    assert (a.record_count, a.truncated_bytes, a.warnings) == (b.record_count, b.truncated_bytes,
                                                                b.warnings)
    assert a.markers == b.markers and a.damage == b.damage
    assert len(a.streams) == len(b.streams)
    for x, y in zip(a.streams, b.streams, strict=True):
        assert (x.index, x.kind, x.columns, x.number, x.format) == (y.index, y.kind, y.columns,
                                                                     y.number, y.format)
        assert np.array_equal(x.offsets, y.offsets) and np.array_equal(x.time_ns, y.time_ns)
        assert x.data.dtype == y.data.dtype and x.data.tobytes() == y.data.tobytes()


@pytest.mark.parametrize(("adversarial", "raw_len"), [(False, None), (True, None), (False, 24),
                                                      (True, 24)])
def test_fast_walk_finds_the_records_of_the_reference_walk(adversarial: bool,
                                                           raw_len: int | None) -> None:
    buf = make_log(20_000, adversarial=adversarial, raw_len=raw_len)
    assert len(buf) > 1_000_000
    fast = _scan(buf, 0, len(buf))
    slow = _scan(buf, 0, len(buf), fast=False)
    assert np.array_equal(fast[0], slow[0]) and fast[1:] == slow[1:] == (len(buf), "eof")
    _same(buf, salvage=False)
    lf = read_log_bytes(buf)
    assert [s.n_records for s in lf.streams] == [10_000, 10_000, 200, 20_000]


@pytest.mark.parametrize("raw_len", [None, 24])
def test_fast_walk_agrees_on_cut_and_damaged_logs(raw_len: int | None) -> None:
    buf = make_log(8_000, seed=2, raw_len=raw_len)
    offs = _scan(buf, 0, len(buf), fast=False)[0]
    rng = np.random.default_rng(3)
    for cut in (len(buf) - 1, len(buf) - 7, int(offs[-3]) + 2, len(buf) // 2 + 1):
        _same(buf[:cut], salvage=False)
    for k in range(12):
        damaged = bytearray(buf)
        for where in rng.choice(offs[10:], size=1 + k % 3, replace=False):
            damaged[int(where) + int(rng.integers(0, 4))] = int(rng.integers(0, 256))
        if k % 4 == 3:  # a zero-filled hole, as an interrupted copy leaves
            at = int(rng.integers(0, len(buf) - 5000))
            damaged[at : at + 4096] = bytes(4096)
        _same(bytes(damaged), salvage=False)
        _same(bytes(damaged), salvage=True)


def test_long_table_of_byte_arrays_is_built_on_demand() -> None:
    lf = read_log_bytes(make_log(300))
    arrays = lf.streams_of(3)[0]
    assert arrays._data is None  # the element values are decoded, the long table is not yet
    values = arrays.values
    assert values is not None and arrays.lengths is not None
    assert np.array_equal(arrays.data["value"], values)
    assert np.array_equal(np.concatenate(arrays.arrays()), values)
    head = arrays.head(10)
    assert head.n_records == 10 and head.data.size == int(arrays.lengths[:10].sum())


# ------------------------------------------------------------------------- logs info DIR
def _flight(tmp_path: Path) -> Path:
    d = tmp_path / "flight"
    d.mkdir()
    (d / "imu.bin").write_bytes(make_log(500))
    (d / "gps.bin").write_bytes(make_log(50, seed=4))
    (d / "run.json").write_text("{}")
    return d


def test_info_of_a_flight_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = _flight(tmp_path)
    assert cli.main(["info", str(d)]) == 0
    out = capsys.readouterr().out
    assert out.count("file:") == 2 and "gps.bin" in out and "imu.bin" in out
    size = sum(p.stat().st_size for p in d.glob("*.bin"))
    records = (2 * 500 + 5 + 9) + (2 * 50 + 9)
    assert out.strip().splitlines()[-1] == (
        f"total: 2 log(s), {size} bytes ({size / 1e6:.1f} MB), {records} records")
    assert cli.main(["info", str(d), "--json"]) == 0
    infos = json.loads(capsys.readouterr().out)
    assert [Path(i["file"]).name for i in infos] == ["gps.bin", "imu.bin"]


def test_info_bad_inputs_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli.main(["info", str(empty)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(empty) in err and "no .bin" in err
    assert cli.main(["info", str(tmp_path / "missing")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(tmp_path / "missing") in err
    d = _flight(tmp_path)
    buf = bytearray((d / "gps.bin").read_bytes())
    offs = _scan(bytes(buf), 0, len(buf), fast=False)[0]
    buf[int(offs[40])] = 0x77
    (d / "gps.bin").write_bytes(bytes(buf))
    assert cli.main(["info", str(d)]) == 0  # the default: the damage is skipped and reported
    captured = capsys.readouterr()
    assert f"byte offset {int(offs[40])}" in captured.err and "gps.bin" in captured.out
    assert cli.main(["info", str(d), "--strict"]) == 1
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and str(d / "gps.bin") in lines[0]
    assert f"byte offset {int(offs[40])}" in lines[0]
    assert "imu.bin" in captured.out and "1 log(s) unreadable" in captured.out
    assert "Traceback" not in captured.err


# ------------------------------------------------------------------------- start-up imports
_PROBE = """
import sys
from companion.cli import main
rc = main(sys.argv[1:])
heavy = sorted(m for m in ("matplotlib", "pandas", "pyarrow", "duckdb", "rerun") if m in sys.modules)
print("HEAVY=" + ",".join(heavy))
sys.exit(rc)
"""


@pytest.mark.parametrize("command", [["logs", "info", "FILE"], ["logs", "info", "DIR"],
                                     ["params", "show"], ["--help"]])
def test_commands_that_draw_nothing_import_no_plotting(tmp_path: Path,
                                                      command: list[str]) -> None:
    d = _flight(tmp_path)
    argv = [str(d / "imu.bin") if a == "FILE" else str(d) if a == "DIR" else a for a in command]
    done = subprocess.run([sys.executable, "-c", _PROBE, *argv], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    if command == ["--help"]:  # argparse exits before the probe prints: check the parser alone
        done = subprocess.run(
            [sys.executable, "-c", "import sys\nfrom companion.cli import build_parser\n"
             "build_parser()\nprint('HEAVY=' + ','.join(m for m in ('matplotlib', 'pandas', "
             "'pyarrow', 'duckdb', 'rerun') if m in sys.modules))"],
            cwd=tmp_path, capture_output=True, text=True, timeout=120, check=False)
    assert "HEAVY=\n" in done.stdout, done.stdout[-500:]
