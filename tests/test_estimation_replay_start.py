"""The replay's GPS/INS filter starts on logs as they come from real vehicles, or says why not.

Issue #40: on a real ArduCopter 3.1 log the ESKF never started although every GPS record had a
3-D fix: those logs date a GPS record by the receiver's time of week (TimeMS) and keep the boot
time in ``T``. The logs here are written from a simulated flight (`record_flight`) by the
DataFlash writer of test_estimation_replay, in the older message layouts where needed, and then
edited the way real logs are: a late first fix, a hand launch, a long IMU gap, a hovering
vehicle whose GPS course gives no heading, no IMU at all.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from test_estimation_replay import (
    DF_MESSAGES,
    Rows,
    df_fmt,
    df_msg,
    flight_rows,
    truth_errors_deg,
    write_dataflash,
)

from companion.estimation.replay.runner import ReplayOptions, replay
from companion.estimation.replay.sources import read_flight_log
from companion.estimation.replay.start import why_no_fix
from companion.evaluation.sitl import FlightSpec, SitlRecording, record_flight

OLD_SPECS = {  # ArduCopter 3.1's layouts: TimeMS everywhere, GPS time of week + boot time T
    "IMU": (1, "Iffffff", "TimeMS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ"),
    "GPS": (2, "BIHBcLLeeEefI", "Status,TimeMS,Week,NSats,HDop,Lat,Lng,RelAlt,Alt,Spd,GCrs,VZ,T"),
    "ATT": (3, "IccccCC", "TimeMS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw"),
}
GPS_WEEK_MS0 = 403_369_800  # a time of week, as in the log: days after boot


@pytest.fixture(scope="module")
def flight() -> SitlRecording:
    return record_flight(FlightSpec(duration_s=40, level_calibration=False))


def write_old_dataflash(path: Path, rows: Rows) -> Path:
    """`rows` in ArduCopter 3.1's layout (ms clocks; GPS TimeMS is the GPS time of week)."""
    out = [df_fmt("FMT")] + [df_fmt(n, OLD_SPECS[n]) for n in OLD_SPECS]
    events: list[tuple[int, bytes]] = []
    for t, v in rows.imu:
        events.append((t, df_msg("IMU", t // 1000, *v, spec=OLD_SPECS["IMU"])))
    for t, v in rows.gps:
        status, _gms, _gwk, sats, hdop, lat, lon, alt, spd, crs, vz = v[:11]
        events.append((t, df_msg("GPS", status, GPS_WEEK_MS0 + t // 1000, 1817, sats, hdop,
                                 lat, lon, 0.0, alt, spd, crs, vz, t // 1000,
                                 spec=OLD_SPECS["GPS"])))
    for t, (r, p, y) in rows.att:
        events.append((t, df_msg("ATT", t // 1000, r, r, p, p, y % 360.0, y % 360.0,
                                 spec=OLD_SPECS["ATT"])))
    events.sort(key=lambda e: e[0])
    path.write_bytes(b"".join(out + [e[1] for e in events]))
    assert set(DF_MESSAGES) >= set(OLD_SPECS)
    return path


def test_old_dataflash_gps_is_dated_by_its_boot_time(flight: SitlRecording,
                                                     tmp_path: Path) -> None:
    path = write_old_dataflash(tmp_path / "ac31.bin", flight_rows(flight))
    fl = read_flight_log(path)
    assert fl.gps is not None
    # the GPS records on the IMU's clock (their T), not days later (their TimeMS)
    assert abs(int(fl.gps.t_us[0]) - int(fl.imu.t_us[0])) < 2_000_000
    res = replay(fl)
    assert res.estimator == "eskf", res.notes
    assert res.start.started_at_s is not None and res.start.started_at_s < 3.0
    err = truth_errors_deg(res, flight)
    assert err["incl"] < 3.0, err  # ms time stamps: a little worse than the thread (1.8)


def test_clocks_that_do_not_match_are_named_with_times() -> None:
    imu = np.arange(0, 60_000_000, 10_000, dtype=np.int64)
    gps_t = imu[::20] + GPS_WEEK_MS0 * 1000
    why = why_no_fix(imu, gps_t, gps_t.tolist(), len(gps_t), 0)
    assert "outside the IMU's samples (0.0 s to 60.0 s)" in why
    assert f"{GPS_WEEK_MS0 / 1000:.1f} s" in why
    assert why_no_fix(imu, None, [], 0, 0) == "the log has no GPS messages"
    assert "none of its 3 GPS messages" in why_no_fix(imu, imu[:3], [], 0, 0)
    assert why_no_fix(imu, imu[::20], imu[::20].tolist(), 3000, 0) == ""


def test_a_late_first_fix_starts_from_the_samples_before_it(flight: SitlRecording,
                                                            tmp_path: Path) -> None:
    rows = flight_rows(flight)
    rows.gps = [r for r in rows.gps if r[0] >= 15_000_000]  # the receiver finds a fix late
    res = replay(read_flight_log(write_dataflash(tmp_path / "late.bin", rows)))
    assert res.estimator == "eskf"
    first = rows.gps[0][0] / 1e6
    assert res.start.first_fix_s == pytest.approx(first, abs=0.02)
    # fed from INIT_S (1 s) before the fix: the level it starts from is the one at the fix
    assert res.start.fed_from_s == pytest.approx(first - 1.0, abs=0.02)
    assert res.start.started_at_s == pytest.approx(first, abs=0.05)
    err = truth_errors_deg(res, flight, from_s=first + 5.0)
    assert err["incl"] < 4.0, err


def test_a_hand_launch_is_retried_until_the_start_is_usable(flight: SitlRecording,
                                                            tmp_path: Path) -> None:
    rows = flight_rows(flight)
    # the first 4 s after the first fix: the thrower's arm, 2 g and more
    t_fix = rows.gps[0][0]
    rows.imu = [(t, (*v[:3], *(2.2 * np.asarray(v[3:6])))) if t < t_fix + 4_000_000 else (t, v)
                for t, v in rows.imu]
    res = replay(read_flight_log(write_dataflash(tmp_path / "throw.bin", rows)))
    assert res.estimator == "eskf", res.notes
    assert len(res.start.refusals) >= 2
    assert all(g > 1.5 * 9.8 for _, g in res.start.refusals)
    assert res.start.started_at_s is not None and res.start.started_at_s > 4.0
    assert any("refused" in n for n in res.notes)
    summary_refusals = res.start.as_dict()["refusals"]
    assert summary_refusals[0]["accel_norm_m_s2"] > 15.0


def test_a_start_that_never_comes_says_why_with_times(flight: SitlRecording,
                                                      tmp_path: Path) -> None:
    rows = flight_rows(flight)
    rows.imu = [(t, (*v[:3], *(3.0 * np.asarray(v[3:6])))) for t, v in rows.imu]
    res = replay(read_flight_log(write_dataflash(tmp_path / "never.bin", rows)))
    assert res.estimator == "attitude" and res.imu_filter == "vqf"
    assert res.start.reason.startswith("every start was refused")
    assert "m/s^2" in res.start.reason and " s to " in res.start.reason
    assert res.estimator_reason == f"ESKF did not start: {res.start.reason}"


def test_a_long_imu_gap_restarts_the_filter(flight: SitlRecording, tmp_path: Path) -> None:
    rows = flight_rows(flight)
    rows.imu = [r for r in rows.imu if not 12e6 <= r[0] < 20e6]  # 8 s without IMU
    res = replay(read_flight_log(write_dataflash(tmp_path / "gap.bin", rows)))
    assert res.estimator == "eskf"
    assert len(res.start.restarts) == 1
    at, length = res.start.restarts[0]
    assert at == pytest.approx(12.0, abs=0.05) and length == pytest.approx(8.0, abs=0.05)
    assert any("started again after 1 IMU gap" in n for n in res.notes)
    err = truth_errors_deg(res, flight, from_s=26.0)
    assert err["incl"] < 4.0, err


def test_heading_from_the_logs_own_attitude(flight: SitlRecording, tmp_path: Path) -> None:
    rows = flight_rows(flight)
    # a receiver that reports no ground speed (a hover, for the filter): no course to align on
    rows.gps = [(t, (*v[:8], 0.0, 0.0, *v[10:])) for t, v in rows.gps]
    path = write_dataflash(tmp_path / "hover.bin", rows)
    own = replay(read_flight_log(path), ReplayOptions(heading_from="gps"))
    assert own.estimator == "eskf" and not own.estimate.aligned.any()
    assert own.start.heading_from == "gps"
    res = replay(read_flight_log(path), ReplayOptions(heading_from="ref"))
    assert res.start.heading_from == "ATT" and res.estimate.aligned.all()
    # the default: the log's attitude, since the first fix is too slow for a course...
    auto = replay(read_flight_log(path))
    assert auto.start.heading_from == "ATT" and auto.estimate.aligned.all()
    assert any("heading started from ATT's yaw" in n for n in auto.notes)
    # ...but the GPS course, as in flight, when the vehicle already flies at the first fix
    flying = replay(read_flight_log(write_dataflash(tmp_path / "fly.bin", flight_rows(flight))))
    assert flying.start.heading_from == "gps" and flying.start.heading_start_deg is None
    k = int(round(res.start.started_at_s * 100))  # type: ignore[operator]
    true_yaw = math.degrees(flight.euler_true_rad[min(k, flight.ticks - 1), 2])
    assert res.start.heading_start_deg is not None
    assert abs((res.start.heading_start_deg - true_yaw + 180) % 360 - 180) < 2.0
    assert res.comparisons[0].metrics["yaw_samples_compared"] > 3000
    bad = replay(read_flight_log(path), ReplayOptions(heading_from="XKF1"))
    assert bad.start.heading_from == "gps"
    assert any("no such reference (ATT)" in n for n in bad.notes)
