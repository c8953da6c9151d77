"""Flight archives: the ustar view of a flight directory (read back by tarfile and GNU tar, any
range, fixed at the snapshot) and its unpacking by ``companion logs convert|info|export|report``."""

from __future__ import annotations

import io
import json
import os
import random
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np
import pytest

from companion.logs import cli
from companion.logs.archive import (
    ArchiveError,
    FlightArchive,
    is_archive,
    unpack,
    unpack_flight,
)
from companion.logs.reader import read_log
from companion.report import generate_report
from companion.report.cli import main as report_main

SIM_TIMEOUT_S = 120
STAMP = "20240501T102233Z"
T_FILES = 1_714_558_953  # 2024-05-01T10:22:33Z


def _write(path: Path, data: bytes, mtime_s: int = T_FILES) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    os.utime(path, (mtime_s, mtime_s))
    return path


@pytest.fixture
def flight(tmp_path: Path) -> Path:
    """A small flight: logs of awkward sizes, a sub-directory, an empty file and what an
    archive leaves out (a hidden temporary, a symbolic link)."""
    rng = random.Random(7)
    d = tmp_path / "flights" / STAMP
    _write(d / "imu.bin", rng.randbytes(1000))
    _write(d / "gps.bin", rng.randbytes(512))
    _write(d / "servo.bin", b"")
    _write(d / "run.json", json.dumps({"started_utc": "2024-05-01T10:22:34+00:00"}).encode())
    _write(d / "report" / "figs" / "roll.png", rng.randbytes(3000), T_FILES + 60)
    _write(d / ".run.json.123.tmp", b"half written")
    (d / "link.bin").symlink_to(d / "imu.bin")
    for sub in (d / "report" / "figs", d / "report", d):
        os.utime(sub, (T_FILES + 70, T_FILES + 70))
    return d


def _tar(data: bytes) -> tarfile.TarFile:
    return tarfile.open(fileobj=io.BytesIO(data), mode="r:")


EXPECTED_NAMES = [
    f"{STAMP}", f"{STAMP}/gps.bin", f"{STAMP}/imu.bin", f"{STAMP}/report",
    f"{STAMP}/report/figs", f"{STAMP}/report/figs/roll.png", f"{STAMP}/run.json",
    f"{STAMP}/servo.bin",
]


# ----------------------------------------------------------------------------- the archive
def test_archive_reads_back_with_tarfile_byte_exact(flight: Path) -> None:
    a = FlightArchive.snapshot(flight)
    data = a.read(0, a.size)
    assert len(data) == a.size and a.size % 512 == 0 and data[-1024:] == bytes(1024)
    assert a.name == STAMP and a.mtime_s == T_FILES + 70 and a.first_mtime_s == T_FILES
    with _tar(data) as tf:
        members = tf.getmembers()
        assert [m.name for m in members] == EXPECTED_NAMES
        for m in members:
            assert (m.uid, m.gid, m.uname, m.gname) == (0, 0, "", "")
            assert m.mtime == int((flight.parent / m.name).stat().st_mtime)
            if m.isdir():
                assert m.mode == 0o755
                continue
            assert m.isfile() and m.mode == 0o644
            f = tf.extractfile(m)
            assert f is not None
            assert f.read() == (flight.parent / m.name).read_bytes(), m.name


def test_gnu_tar_lists_and_extracts(flight: Path, tmp_path: Path) -> None:
    tar = shutil.which("tar")
    if tar is None:
        pytest.skip("no tar program on this machine")
    path = FlightArchive.snapshot(flight).write_to(tmp_path / "flight.tar")
    listed = subprocess.run([tar, "-tvf", str(path)], capture_output=True, text=True, check=True)
    assert listed.stderr == ""
    assert [line.split()[-1].rstrip("/") for line in listed.stdout.splitlines()] == EXPECTED_NAMES
    out = tmp_path / "gnu"
    out.mkdir()
    done = subprocess.run([tar, "-xf", str(path), "-C", str(out)], capture_output=True, text=True)
    assert done.returncode == 0 and done.stderr == ""
    for name in EXPECTED_NAMES:
        if (flight.parent / name).is_file():
            assert (out / name).read_bytes() == (flight.parent / name).read_bytes(), name
    assert not (out / STAMP / "link.bin").exists() and not (out / STAMP / ".run.json.123.tmp").exists()


def test_archive_is_deterministic(flight: Path, tmp_path: Path) -> None:
    first = FlightArchive.snapshot(flight)
    copy = tmp_path / "elsewhere" / STAMP
    shutil.copytree(flight, copy, symlinks=True)  # copy2: same contents and mtimes
    for sub in (copy / "report" / "figs", copy / "report", copy):
        os.utime(sub, (T_FILES + 70, T_FILES + 70))
    again = FlightArchive.snapshot(copy)
    assert again.size == first.size
    assert again.read(0, again.size) == first.read(0, first.size)


def test_random_ranges_are_slices_of_the_whole(flight: Path) -> None:
    a = FlightArchive.snapshot(flight)
    whole = a.read(0, a.size)
    rng = random.Random(1)
    for _ in range(400):
        offset = rng.randrange(0, a.size + 600)
        n = rng.choice([0, 1, 89, 90, 511, 512, 513, rng.randrange(0, a.size + 100)])
        assert a.read(offset, n) == whole[offset:offset + n], (offset, n)
    with pytest.raises(ValueError):
        a.read(-1, 10)


def test_growth_after_the_snapshot_is_not_part_of_it(flight: Path) -> None:
    a = FlightArchive.snapshot(flight)
    before = a.read(0, a.size)
    with open(flight / "imu.bin", "ab") as f:
        f.write(b"appended while recording" * 100)
    with open(flight / "servo.bin", "ab") as f:
        f.write(b"first records")
    _write(flight / "summary.json", b"{}")  # a new file: not in the old snapshot either
    assert a.read(0, a.size) == before
    b = FlightArchive.snapshot(flight)
    assert b.size > a.size
    with _tar(b.read(0, b.size)) as tf:
        m = tf.getmember(f"{STAMP}/imu.bin")
        assert m.size == 1000 + 2400
        assert f"{STAMP}/summary.json" in tf.getnames()


def test_a_file_that_shrank_vanished_or_changed_is_named(flight: Path) -> None:
    a = FlightArchive.snapshot(flight)
    imu = next(m for m in a.members if m.name.endswith("imu.bin"))
    gps = next(m for m in a.members if m.name.endswith("gps.bin"))
    whole = a.read(0, a.size)
    with open(flight / "imu.bin", "r+b") as f:
        f.truncate(600)
    with pytest.raises(ArchiveError, match=r"imu\.bin: shrank from 1000 to 600 bytes"):
        a.read(imu.data_offset + 500, 200)
    with pytest.raises(ArchiveError, match=r"imu\.bin: shrank"):  # shrank: maybe rewritten
        a.read(imu.data_offset, 10)
    # only the pieces a range covers are read: the rest of the archive still reads
    assert a.read(imu.header_offset, 512) == whole[imu.header_offset:imu.data_offset]
    assert a.read(gps.header_offset, 1024) == whole[gps.header_offset:gps.header_offset + 1024]

    (flight / "gps.bin").unlink()
    with pytest.raises(ArchiveError, match=r"gps\.bin: vanished"):
        a.read(gps.data_offset, 1)

    roll = flight / "report" / "figs" / "roll.png"
    tmp = roll.with_name("new.png")
    tmp.write_bytes(bytes(3000))
    os.replace(tmp, roll)  # same size, another file
    member = next(m for m in a.members if m.name.endswith("roll.png"))
    with pytest.raises(ArchiveError, match=r"roll\.png: was replaced"):
        a.read(member.data_offset, 10)

    run = flight / "run.json"
    text = run.read_bytes()
    run.write_bytes(text.upper())  # rewritten in place, same size
    os.utime(run, (T_FILES + 5, T_FILES + 5))
    member = next(m for m in a.members if m.name.endswith("run.json"))
    with pytest.raises(ArchiveError, match=r"run\.json: was rewritten"):
        a.read(member.data_offset, 10)


def test_long_names_use_the_prefix_field_or_are_refused(tmp_path: Path) -> None:
    d = tmp_path / STAMP
    deep = d / ("a" * 60) / ("b" * 60) / ("c" * 40 + ".csv")  # 181 bytes with the flight name
    _write(deep, b"x,y\n1,2\n")
    a = FlightArchive.snapshot(d)
    with _tar(a.read(0, a.size)) as tf:
        name = str(deep.relative_to(tmp_path))
        assert name in tf.getnames()
        f = tf.extractfile(name)
        assert f is not None and f.read() == b"x,y\n1,2\n"
    _write(d / ("z" * 120 + ".bin"), b"one component too long")
    with pytest.raises(ArchiveError, match="z{120}.bin: the name is .* bytes"):
        FlightArchive.snapshot(d)
    with pytest.raises(ArchiveError, match="not a flight directory"):
        FlightArchive.snapshot(deep)


# ----------------------------------------------------------------------------- unpacking
def _download(flight: Path, path: Path) -> Path:
    """What a ground station saves: the archive under a name of its own."""
    return FlightArchive.snapshot(flight).write_to(path)


def test_unpack_next_to_the_download_and_reuse(flight: Path, tmp_path: Path) -> None:
    saved = _download(flight, tmp_path / "log_0_2024-5-1-10-22-33.bin")
    assert is_archive(saved)
    assert not is_archive(flight / "imu.bin") and not is_archive(flight)
    assert not is_archive(tmp_path / "missing.bin")
    got = unpack_flight(saved)
    assert got == tmp_path / "log_0_2024-5-1-10-22-33.bin.flight" / STAMP
    for name in EXPECTED_NAMES:
        src = flight.parent / name
        if src.is_file():
            assert (got.parent / name).read_bytes() == src.read_bytes(), name
    assert [p.name for p in got.parent.iterdir()] == [STAMP]  # no temporary left behind
    (got / "imu_fmt1.csv").write_text("converted later\n")  # outputs of the tools may be added
    assert unpack(saved) == unpack(saved)
    assert unpack(saved).reused
    (got / "imu.bin").write_bytes(b"edited")
    with pytest.raises(ArchiveError, match="exists and differs from the archive"):
        unpack(saved)
    other = unpack_flight(saved, tmp_path / "chosen")
    assert other == tmp_path / "chosen" / STAMP and (other / "imu.bin").stat().st_size == 1000


def _cut(data: bytes, n: int) -> bytes:
    return data[:n]


def _zero(data: bytes, start: int, n: int) -> bytes:
    return data[:start] + bytes(n) + data[start + n:]


def _flip(data: bytes, at: int) -> bytes:
    return data[:at] + bytes([data[at] ^ 0xFF]) + data[at + 1:]


def test_truncated_or_corrupt_archives_give_the_file_and_offset(flight: Path,
                                                                tmp_path: Path) -> None:
    a = FlightArchive.snapshot(flight)
    data = a.read(0, a.size)
    imu = next(m for m in a.members if m.name.endswith("imu.bin"))
    last = a.members[-1]
    end = a.size - 1024
    cases = [
        # (damaged bytes, offset in the message, words in the message)
        (_cut(data, imu.data_offset + 300), imu.data_offset + 300, "truncated: member"),
        (_cut(data, imu.header_offset + 200), imu.header_offset, "truncated tar header"),
        (_cut(data, end), end, "end-of-archive marker is missing"),
        (_cut(data, end + 100), end + 100, "end-of-archive marker is missing"),
        (_zero(data, imu.header_offset, 512), imu.data_offset, "has a hole"),  # QGC's gaps
        (_flip(data, last.header_offset + 3), last.header_offset, "bad checksum"),
        (_flip(data, 3), 0, "not a readable tar archive"),
    ]
    for k, (damaged, offset, words) in enumerate(cases):
        path = tmp_path / f"bad{k}.bin"
        path.write_bytes(damaged)
        with pytest.raises(ArchiveError) as err:
            unpack(path)
        assert str(err.value).startswith(f"{path}: byte offset {offset}: "), (k, str(err.value))
        assert words in str(err.value), (k, str(err.value))
        assert not (tmp_path / f"bad{k}.bin.flight" / STAMP).exists()


def _tar_with(tmp_path: Path, name: str, *members: tarfile.TarInfo) -> Path:
    path = tmp_path / name
    with tarfile.open(path, "w", format=tarfile.USTAR_FORMAT) as tf:
        for m in members:
            tf.addfile(m, io.BytesIO(b"x" * m.size) if m.isfile() else None)
    return path


def _info(name: str, kind: bytes = tarfile.REGTYPE, size: int = 1) -> tarfile.TarInfo:
    m = tarfile.TarInfo(name)
    m.type = kind
    m.size = size if kind == tarfile.REGTYPE else 0
    if kind == tarfile.SYMTYPE:
        m.linkname = "/etc/passwd"
    return m


@pytest.mark.parametrize(("members", "words"), [
    ([_info("f/../../evil.bin")], "leads outside"),
    ([_info("/abs/evil.bin")], "is absolute"),
    ([_info("f/ok.bin"), _info("f/link", tarfile.SYMTYPE)], "not a file or a directory"),
    ([_info("f/a.bin"), _info("g/b.bin")], "holds one flight directory, this one 2: f, g"),
    ([_info("loose.bin")], "not inside a flight directory"),
])
def test_unsafe_or_foreign_archives_are_refused(tmp_path: Path, members: list[tarfile.TarInfo],
                                                words: str) -> None:
    path = _tar_with(tmp_path, "download.bin", *members)
    with pytest.raises(ArchiveError, match=words):
        unpack(path, tmp_path / "out")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    assert not (tmp_path.parent / "evil.bin").exists()


# ----------------------------------------------------------------------------- the tools
@pytest.fixture(scope="module")
def sim_flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3 s SITL flight flown by the real `companion sim` (5x faster than real time)."""
    work = tmp_path_factory.mktemp("sim")
    cmd = [sys.executable, "-m", "companion", "sim", "--duration", "3", "--fast", "--mavlink",
           "none", "--no-legacy", "--log-dir", str(work / "flights"), "--params-file",
           str(work / "p.parm")]
    done = subprocess.run(cmd, cwd=work, capture_output=True, text=True, timeout=SIM_TIMEOUT_S)
    assert done.returncode == 0, done.stderr[-2000:]
    (flight,) = sorted((work / "flights").iterdir())
    return flight


def _data_lines(path: Path) -> list[bytes]:
    return [ln for ln in path.read_bytes().split(b"\n") if ln and not ln.startswith(b"%")]


def test_convert_info_export_take_a_downloaded_archive(
        sim_flight: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    saved = _download(sim_flight, tmp_path / "log_0_2026-1-1-0-0-0.bin")
    logs = sorted(p.name for p in sim_flight.glob("*.bin"))
    assert len(logs) >= 5

    assert cli.main(["convert", str(saved)]) == 0
    out = capsys.readouterr()
    unpacked = tmp_path / (saved.name + ".flight") / sim_flight.name
    assert f"{saved}: flight archive unpacked into {unpacked}" in out.err
    csvs = [Path(p) for p in out.out.split()]
    assert csvs and all(p.parent == unpacked for p in csvs)
    assert {p.name.split("_fmt")[0] for p in csvs} == {n[:-4] for n in logs}
    reference = tmp_path / "reference"
    assert cli.main(["convert", str(sim_flight), "-o", str(reference)]) == 0
    capsys.readouterr()
    for p in csvs:
        assert _data_lines(p) == _data_lines(reference / p.name), p.name

    assert cli.main(["info", str(saved), "--json"]) == 0
    out = capsys.readouterr()
    assert f"flight archive already unpacked in {unpacked}" in out.err
    infos = json.loads(out.out)
    assert [Path(i["file"]).name for i in infos] == logs
    for info in infos:
        assert info["records"] == read_log(sim_flight / Path(info["file"]).name).record_count

    assert cli.main(["info", str(saved)]) == 0
    assert capsys.readouterr().out.count("file:  ") == len(logs)

    assert cli.main(["export", str(saved), "--to", "npz", "-o", str(tmp_path / "npz")]) == 0
    capsys.readouterr()
    with np.load(tmp_path / "npz" / "imu.npz") as z:
        direct = read_log(sim_flight / "imu.bin")
        assert np.array_equal(z["fmt1"], direct.streams_of(1)[0].data)

    # a directory of downloads: the archives among its *.bin are unpacked too
    downloads = tmp_path / "downloads"
    downloads.mkdir()
    shutil.copy(saved, downloads / "log_1_2026-1-1-0-0-0.bin")
    assert cli.main(["convert", str(downloads), "-o", str(tmp_path / "csv2")]) == 0
    assert len(capsys.readouterr().out.split()) == len(csvs)


@pytest.fixture(scope="module")
def direct_report(sim_flight: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The report of the flight directory itself (made here, outside the tests' leak check:
    matplotlib keeps its font files open once loaded)."""
    out = tmp_path_factory.mktemp("direct")
    generate_report(sim_flight, out, measure_csv=False)
    return out


def test_report_takes_a_downloaded_archive(sim_flight: Path, direct_report: Path,
                                           tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    saved = _download(sim_flight, tmp_path / "log_0_2026-1-1-0-0-0.ulg")
    out = tmp_path / "report"
    assert report_main(["report", str(saved), "-o", str(out), "--no-csv-size"]) == 0
    printed = capsys.readouterr()
    assert "flight archive unpacked into" in printed.err
    assert (out / "report.html").is_file()
    figures = [Path(p) for p in printed.out.split() if p.endswith(".png")]
    assert figures
    for p in figures:  # the unpacked flight is the flight: same figures, byte for byte
        assert p.read_bytes() == (direct_report / p.name).read_bytes(), p.name


def test_tools_report_a_damaged_archive_without_a_traceback(
        sim_flight: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    whole = FlightArchive.snapshot(sim_flight)
    bad = tmp_path / "log_0_cut.bin"
    bad.write_bytes(whole.read(0, whole.size // 2))
    for run in (lambda: cli.main(["convert", str(bad)]),
                lambda: cli.main(["info", str(bad)]),
                lambda: cli.main(["export", str(bad), "--to", "npz"]),
                lambda: report_main(["report", str(bad)])):
        assert run() == 1
        err = capsys.readouterr().err
        assert err.startswith(f"error: {bad}: byte offset ") and "truncated" in err, err
        assert "Traceback" not in err
    assert not (tmp_path / "log_0_cut.bin.flight" / sim_flight.name).exists()
