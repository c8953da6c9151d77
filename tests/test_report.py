"""Flight report: figures from a real SITL flight, checked on the figure objects and the files."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from companion.report import FIGURES, generate_report, load_flight
from companion.report.analysis import counter_gaps, period_stats
from companion.report.cli import main as report_main
from companion.report.figures import Products, fig_batteries
from companion.report.headers import definition_records

ALL_FIGURES = {f.name for f in FIGURES}
SIM_TIMEOUT_S = 150


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 20 s SITL flight flown by the real `companion sim` (5x faster than real time)."""
    work = tmp_path_factory.mktemp("sim")
    cmd = [sys.executable, "-m", "companion", "sim", "--duration", "20", "--fast", "--mavlink", "none",
           "--no-legacy", "--log-dir", str(work / "flights"), "--params-file", str(work / "p.parm")]
    done = subprocess.run(cmd, cwd=work, capture_output=True, text=True, timeout=SIM_TIMEOUT_S)
    assert done.returncode == 0, done.stderr[-2000:]
    dirs = sorted((work / "flights").iterdir())
    assert len(dirs) == 1, dirs
    return dirs[0]


@pytest.fixture(scope="module")
def report(flight: Path, tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    return generate_report(flight, tmp_path_factory.mktemp("report"), keep_figures=True)


def _records(flight: Path, name: str) -> int:
    data = load_flight(flight).block(name, 1)
    return 0 if data is None else int(data.size)


def _has_data(ax) -> bool:  # type: ignore[no-untyped-def]
    lines = [ln for ln in ax.get_lines() if np.size(ln.get_xdata()) > 0]
    return bool(lines or ax.patches or ax.collections)


def _line(ax, label_start: str):  # type: ignore[no-untyped-def]
    found = [ln for ln in ax.get_lines() if str(ln.get_label()).startswith(label_start)]
    assert found, f"no line {label_start!r} in {[ln.get_label() for ln in ax.get_lines()]}"
    return found[0]


def test_every_figure_is_drawn_as_a_valid_image(report) -> None:  # type: ignore[no-untyped-def]
    assert not report.missing, report.missing
    assert {p.stem for p in report.figures} == ALL_FIGURES
    assert set(report.figure_objects) == ALL_FIGURES
    for path in report.figures:
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        img = imread(path)
        assert img.ndim == 3 and img.shape[0] > 150 and img.shape[1] > 600, (path, img.shape)
        assert float(img[..., :3].std()) > 0.01, f"{path} is blank"
    for name, fig in report.figure_objects.items():
        assert fig.axes, name
        for ax in fig.axes:
            if ax.get_ylabel() or ax.get_title():  # twin axes share the data check of their host
                assert _has_data(ax), f"{name}: axes {ax.get_title()!r} has no data"


def test_gps_figures_have_the_expected_axes_and_data(report, flight: Path) -> None:  # type: ignore[no-untyped-def]
    n_gps = _records(flight, "gps")
    fix = report.figure_objects["gps_fix"].axes
    assert fix[0].get_ylabel() == "fix" and fix[1].get_ylabel() == "satellites"
    assert np.size(_line(fix[0], "fix type").get_xdata()) == n_gps
    assert "100.0 % of" in fix[0].get_title()
    track = report.figure_objects["gps_track"].axes
    assert (track[0].get_xlabel(), track[0].get_ylabel()) == ("east (m)", "north (m)")
    north = np.asarray(_line(track[0], "GPS").get_ydata())
    assert north.size == n_gps and np.ptp(north) > 300.0  # 20 s at cruise speed
    quality = report.figure_objects["gps_quality"].axes
    drawn = {str(ln.get_label()) for ln in quality[0].get_lines()}
    assert {"HDOP", "PDOP", "VDOP"} <= drawn  # NMEA GSA gives these three
    gps = load_flight(flight).block("gps", 1)
    assert gps is not None
    for dop in {"HDOP", "PDOP", "VDOP", "TDOP"} - drawn:  # left out only when never reported
        assert np.isnan(gps[dop.lower()]).all()
    assert quality[1].get_ylabel() == "latency (ms)" and quality[2].get_ylabel() == "std dev (m)"


def test_sample_periods_match_the_device_rates(report, flight: Path) -> None:  # type: ignore[no-untyped-def]
    axes = report.figure_objects["periods"].axes
    assert len(axes) == 6
    titles = [ax.get_title() for ax in axes[::2]]
    assert [t.split(":")[0] for t in titles] == ["imu", "gps", "servo"]
    assert all("mean" in t and "p99" in t and "max" in t for t in titles)
    fd = load_flight(flight)
    imu_data, gps_data = fd.block("imu", 1), fd.block("gps", 1)
    assert imu_data is not None and gps_data is not None
    imu = period_stats(fd.rel_s(imu_data["time_s"]))
    gps = period_stats(fd.rel_s(gps_data["time_s"]))
    assert imu is not None and gps is not None
    assert imu.mean_ms == pytest.approx(10.0, abs=1.0)
    assert gps.mean_ms == pytest.approx(100.0, abs=5.0)
    assert imu.max_ms >= imu.p99_ms >= imu.mean_ms
    assert np.size(_line(axes[0], "period").get_ydata()) == imu.n


def test_roll_rate_batteries_position_attitude(report) -> None:  # type: ignore[no-untyped-def]
    roll = report.figure_objects["roll_rate_aileron"].axes
    assert roll[0].get_ylabel() == "roll rate (deg/s)"
    twin = [ax for ax in roll if ax.get_ylabel() == "aileron command (-1..1)"]
    assert twin and np.size(_line(twin[0], "pilot aileron").get_ydata()) > 500
    batt = report.figure_objects["batteries"].axes
    for ax in batt:
        level = np.asarray(ax.get_lines()[0].get_ydata())
        assert 50 < level.mean() < 120  # the board reports ~100 when full
    pos = report.figure_objects["position_error"].axes
    assert {str(ln.get_label()) for ln in pos[0].get_lines()} == {"GPS", "truth", "estimate"}
    gps_err = np.asarray(_line(pos[2], "GPS - truth").get_ydata())
    assert np.nanmedian(gps_err) < 15.0  # a few metres of GPS noise, not a frame mix-up
    assert _line(pos[2], "estimate - truth") is not None
    att = report.figure_objects["attitude"].axes
    assert len(att) == 4 and att[0].get_ylabel() == "roll (deg)"
    assert {str(ln.get_label()) for ln in att[0].get_lines()} == {"estimate", "truth"}
    health = report.figure_objects["thread_health"].axes
    labels = [t.get_text() for t in health[0].get_yticklabels()]
    assert {"imu", "gps", "servo", "estimator", "truth"} <= {lb.split("\n")[0] for lb in labels}


def test_html_is_one_self_contained_page(report) -> None:  # type: ignore[no-untyped-def]
    html = report.html.read_text(encoding="utf-8")
    assert html.count("data:image/png;base64,") == len(ALL_FIGURES)
    assert "<script" not in html and "http://" not in html and "https://" not in html
    for text in ("duration", "restarts", "log size (binary)", "same logs as CSV", "imu.bin"):
        assert text in html
    s = report.summary
    assert s.duration_s == pytest.approx(20.0, abs=2.0)
    assert s.csv_bytes is not None and s.csv_bytes > s.binary_bytes > 0
    assert s.restarts == 0
    assert {t.name for t in s.threads} >= {"imu", "gps", "servo"}


def test_report_is_reproducible(flight: Path, report, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    again = generate_report(flight, tmp_path / "again", measure_csv=False)
    first = {p.name: p.read_bytes() for p in report.figures}
    second = {p.name: p.read_bytes() for p in again.figures}
    assert first == second


def _copy(flight: Path, dest: Path) -> Path:
    shutil.copytree(flight, dest)
    shutil.rmtree(dest / "report", ignore_errors=True)
    return dest


def test_missing_and_truncated_logs_give_a_partial_report(flight: Path, tmp_path: Path) -> None:
    d = _copy(flight, tmp_path / "partial")
    (d / "gps.bin").unlink()
    imu = d / "imu.bin"
    data = imu.read_bytes()
    imu.write_bytes(data[: len(data) // 2 + 5])  # cut mid-flight, inside a record
    result = generate_report(d, tmp_path / "out", measure_csv=False)
    drawn = {p.stem for p in result.figures}
    assert {"gps_fix", "gps_track", "gps_quality"}.isdisjoint(drawn)
    assert {"periods", "roll_rate_aileron", "batteries", "thread_health"} <= drawn
    assert any("gps.bin is missing" in m for m in result.missing)
    assert any(p.startswith("imu.bin:") and "cut short" in p for p in result.problems)
    assert any(p.startswith("imu.bin:") and "not closed cleanly" in p for p in result.problems)
    html = result.html.read_text(encoding="utf-8")
    assert "Missing or damaged" in html and "gps.bin is missing" in html
    periods = load_flight(d).block("imu", 1)
    assert periods is not None and 0 < periods.size < _records(flight, "imu")


def test_damaged_bytes_are_skipped_and_reported(flight: Path, tmp_path: Path) -> None:
    d = _copy(flight, tmp_path / "damaged")
    servo = d / "servo.bin"
    data = bytearray(servo.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 300] = b"\xee" * 300
    servo.write_bytes(bytes(data))
    fd = load_flight(d)
    assert fig_batteries(Products(fd)).axes  # still drawn from the records around the damage
    damage = [p for p in fd.problems if p.startswith("servo.bin: byte offset")]
    assert damage and "bytes skipped" in damage[0]
    offset = int(damage[0].split("byte offset ")[1].split(":")[0])
    assert middle - 100 <= offset <= middle + 300


def test_lost_format_definitions_are_restored(flight: Path, tmp_path: Path) -> None:
    d = _copy(flight, tmp_path / "headless")
    servo = d / "servo.bin"
    raw = servo.read_bytes()
    head = definition_records(raw[:2000])
    assert raw.startswith(head)  # the writer puts them first (when it wrote them at all)
    servo.write_bytes(raw[len(head):])
    fd = load_flight(d)
    assert fig_batteries(Products(fd)).axes
    assert any("servo.bin" in p and "current definitions" in p for p in fd.problems)
    assert _records(d, "servo") == _records(flight, "servo") > 500


def test_empty_directory_and_bad_run_json(tmp_path: Path) -> None:
    d = tmp_path / "empty"
    d.mkdir()
    (d / "run.json").write_text('{"software": [1, 2,\n')
    result = generate_report(d, tmp_path / "out")
    assert result.figures == [] and len(result.missing) == len(ALL_FIGURES)
    assert any(p.startswith("run.json: line 2") for p in result.problems)
    assert result.html.is_file()
    (d / "imu.bin").write_bytes(b"\x00" * 64)  # not a log at all
    result = generate_report(d, tmp_path / "out", measure_csv=False)
    assert any(p.startswith("imu.bin: byte offset 0") for p in result.problems)


def test_cli_report(flight: Path, report: object, tmp_path: Path,
                    capsys: pytest.CaptureFixture[str]) -> None:
    # `report` (module scope) draws first: matplotlib keeps each font it has drawn with open
    # for the life of the process, which the leak check would otherwise blame on this test
    # when it runs alone
    out = tmp_path / "cli"
    assert report_main(["report", str(flight), "-o", str(out), "--no-csv-size"]) == 0
    printed = capsys.readouterr().out.split()
    assert str(out / "report.html") in printed and len(printed) == len(ALL_FIGURES) + 1
    assert report_main(["report", str(tmp_path / "nowhere")]) == 1
    assert "not a flight directory" in capsys.readouterr().err


def test_period_and_counter_helpers() -> None:
    s = period_stats(np.array([0.0, 0.01, 0.02, 0.05]), 10.0)
    assert s is not None
    assert s.n == 3 and s.max_ms == pytest.approx(30.0) and s.mean_ms == pytest.approx(50.0 / 3)
    assert period_stats(np.array([1.0])) is None
    assert counter_gaps(np.array([97, 98, 99, 0, 1, 3, 4]), 100) == 1
    assert counter_gaps(np.array([5, 5, 6]), 100) == 0
