"""`companion estimation replay DIR... --table out.csv`, where output goes, partial replays, and
the IMU-only filter from the registry (VQF by default).

Everything runs the real command in a subprocess on real files: the PX4 sample, DataFlash logs
written from a simulated flight by test_estimation_replay's writer, and a junk file.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_estimation_replay import SAMPLE_ULG, Rows, flight_rows, write_dataflash

from companion.estimation.imu_filters import DEFAULT_FILTER, ImuSeries, run_filter, to_ned
from companion.estimation.quat import quat_from_euler, quat_to_euler
from companion.estimation.replay.runner import ReplayOptions, replay
from companion.estimation.replay.sources import read_flight_log
from companion.evaluation.sitl import FlightSpec, SitlRecording, record_flight

REPO = Path(__file__).resolve().parents[1]


def _cli(*args: str, cwd: Path, timeout_s: float = 180.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion", "estimation", "replay", *args],
                          capture_output=True, text=True, timeout=timeout_s, cwd=cwd,
                          env={**os.environ, "PYTHONPATH": str(REPO)})


@pytest.fixture(scope="module")
def flight() -> SitlRecording:
    return record_flight(FlightSpec(duration_s=20, level_calibration=False))


def test_vqf_is_the_default_and_turned_to_ned() -> None:
    assert DEFAULT_FILTER == "vqf"
    # level and still, then rolled 20 deg: FRD samples, as the logs hold them
    n = 1200
    roll = np.where(np.arange(n) < 200, 0.0, np.radians(20.0))
    g = 9.80665
    accel = np.column_stack([np.zeros(n), -g * np.sin(roll), -g * np.cos(roll)])
    series = ImuSeries(np.zeros((n, 3)), accel, 0.01)
    q, frame = run_filter("vqf", series)
    e = quat_to_euler(to_ned(q, frame))
    assert frame == "enu"
    assert abs(np.degrees(e[150, 0])) < 0.5 and abs(np.degrees(e[150, 1])) < 0.5
    ours = quat_to_euler(run_filter("ours", series)[0])
    # both say the roll once they have converged on the tilted samples
    assert np.degrees(e[-1, 0]) == pytest.approx(20.0, abs=1.0)
    assert np.degrees(ours[-1, 0]) == pytest.approx(20.0, abs=1.0)
    q_ned = quat_from_euler(0.1, -0.2, 0.3)
    assert np.allclose(to_ned(q_ned, "ned"), q_ned)


def test_replay_runs_the_filter_asked_for() -> None:
    fl = read_flight_log(SAMPLE_ULG)
    default = replay(fl)
    assert default.estimator == "attitude" and default.imu_filter == "vqf"
    ours = replay(fl, ReplayOptions(imu_filter="ours"))
    assert ours.imu_filter == "ours_timed"  # a log's samples have time stamps
    inc = {r.imu_filter: r.comparisons[0].metrics["inclination_deg"]["rmse"]
           for r in (default, ours)}
    assert inc["vqf"] < 0.5 and inc["ours_timed"] < 0.5, inc
    assert inc["vqf"] != inc["ours_timed"]
    # the time alignment is stated: nearest sample, within its tolerance
    m = default.comparisons[0].metrics
    assert 0.0 <= m["median_time_offset_ms"] <= m["match_tolerance_ms"]
    with pytest.raises(ValueError, match="unknown IMU-only filter 'kalman'"):
        replay(fl, ReplayOptions(imu_filter="kalman"))


def test_batch_over_directories_writes_one_row_per_log(flight: SitlRecording,
                                                       tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    (logs / "day2").mkdir(parents=True)
    write_dataflash(logs / "1.BIN", flight_rows(flight))
    write_dataflash(logs / "day2" / "1.bin", flight_rows(flight, gps=False))
    (logs / "day2" / "junk.bin").write_bytes(b"\x00junk" * 50)
    (logs / "notes.txt").write_text("not a log")
    work = tmp_path / "work"
    work.mkdir()
    proc = _cli(str(logs), str(SAMPLE_ULG), "--table", "t.csv", "--no-plot", cwd=work)
    assert proc.returncode == 2, proc.stderr  # the junk file, on its own line
    assert "Traceback" not in proc.stderr
    assert [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")] == [
        ln for ln in proc.stderr.splitlines() if "junk.bin" in ln]
    rows = list(csv.DictReader((work / "t.csv").open()))
    assert [Path(r["source"]).name for r in rows] == ["1.BIN", "1.bin", "junk.bin", "sample.ulg"]
    by = {r["source"]: r for r in rows}
    first, nogps, junk, px4 = (by[str(p)] for p in (
        logs / "1.BIN", logs / "day2" / "1.bin", logs / "day2" / "junk.bin", SAMPLE_ULG))
    assert first["estimator"] == "eskf" and float(first["ATT_incl_rmse_deg"]) < 3.0
    assert first["status"] == "ok" and float(first["duration_s"]) == pytest.approx(20, abs=0.1)
    assert nogps["estimator"] == "attitude" and nogps["imu_filter"] == "vqf"
    assert "no GPS" in nogps["estimator_reason"]
    assert junk["status"] == "error" and "junk.bin" in junk["notes"]
    assert px4["references"] == "vehicle_attitude"
    assert float(px4["vehicle_attitude_incl_rmse_deg"]) < 0.5
    assert px4["ATT_incl_rmse_deg"] == ""
    # every log in its own directory under the current one, none beside the inputs
    made = sorted(p.name for p in work.iterdir() if p.is_dir())
    assert made == ["1-replay", "1-replay-2", "sample-replay"]
    assert not any(p.name.endswith("-replay") for p in logs.rglob("*"))
    assert not (SAMPLE_ULG.parent / "sample-replay").exists()


def test_a_log_without_imu_or_gps_is_a_partial_replay(flight: SitlRecording,
                                                      tmp_path: Path) -> None:
    full = flight_rows(flight)
    no_imu = write_dataflash(tmp_path / "noimu.bin", Rows([], full.gps, full.att))
    proc = _cli(str(no_imu), "-o", "out", "--json", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["estimator"] == "none" and summary["estimate"]["samples"] == 0
    assert any("no IMU messages" in n for n in summary["notes"])
    assert summary["timelines"]["gps"]["samples_used"] == len(full.gps)
    assert (tmp_path / "out" / "noimu-replay" / "summary.json").is_file()
    no_gps = write_dataflash(tmp_path / "nogps.bin", Rows(full.imu, [], full.att))
    proc = _cli(str(no_gps), "-o", "out", "--no-plot", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "IMU-only vqf" in proc.stdout and "the log has no GPS messages" in proc.stdout


def test_bad_options_are_one_line(tmp_path: Path) -> None:
    for args in (["--imu-filter", "kalman"], ["--param", "EST_NOPE=1"]):
        proc = _cli(str(SAMPLE_ULG), *args, cwd=tmp_path, timeout_s=60.0)
        assert proc.returncode == 2
        assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr
    proc = _cli(str(tmp_path), cwd=tmp_path, timeout_s=60.0)
    assert proc.returncode == 2 and "no logs" in proc.stderr
