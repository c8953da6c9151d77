"""Flight report beside a flight controller: our estimate against the autopilot's, the link's
clock map and the GUIDED targets, on a flight written with the project's log writer and the
producers' own format definitions, with known values.

The flight (20 s): truth at 100 Hz rolls at a constant rate, holds its pitch and turns through
+-180 deg of yaw; our estimate (50 Hz, aligned from 2 s) is the truth plus (0.01, -0.02, 0.03) rad;
the autopilot's (25 Hz, 1 s to 19 s) is the truth plus (-0.01, 0, -0.03) rad. Every signal is
linear between records, so interpolation is exact and the report's numbers are known.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from companion.core.config import DeviceConfig
from companion.core.mathutil import wrap_pi
from companion.estimation.logformats import FMT_STATE, STATE_COLUMNS, define_estimator_logs
from companion.logs import LogService
from companion.logs.truth import FMT_TRUTH, TRUTH_COLUMNS, define_truth_log
from companion.report import FIGURES, generate_report, load_flight
from companion.report import report as report_module
from companion.report import summary as summary_module
from companion.report.autopilot import summarise_autopilot
from companion.report.autopilot_figures import AUTOPILOT_FIGURES, fig_autopilot_targets
from companion.report.figures import MissingData, Products
from companion.report.headers import PRODUCERS
from gcs_bridge.autopilot.link import FMT_COMMAND, FMT_ESTIMATE, FMT_TSYNC

T0_NS = 1_700_000_000 * 10**9
OURS_ERR = np.array([0.01, -0.02, 0.03])
AP_ERR = np.array([-0.01, 0.0, -0.03])
ALIGNED_S = 2.0
TARGETS_S = (10.0, 15.0)
ROLL_SP, PITCH_SP, THRUST = 0.3, 0.05, 0.6
AUTOPILOT_NAMES = {f.name for f in AUTOPILOT_FIGURES}


def truth_at(t: float) -> np.ndarray:
    return np.array([-0.3 + 0.03 * t, 0.05, float(wrap_pi(3.0 + 0.02 * t))])


def _ns(t: float) -> int:
    return T0_NS + round(t * 1e9)


def write_flight(d: Path, *, guided: bool = True) -> Path:
    with LogService(d, flush_period_ms=10, clock_ns=lambda: T0_NS) as svc:
        est, truth, ap = svc.open("estimator"), svc.open("truth"), svc.open("autopilot")
        define_estimator_logs(est)
        define_truth_log(truth)
        link = PRODUCERS["autopilot"].build(DeviceConfig(port="tcp:127.0.0.1:5760"))
        link.define_logs(ap)  # the link's own definitions (nothing is opened)
        for lg in (est, truth, ap):
            lg.begin()
        for k in range(2001):
            t = k * 0.01
            row = dict.fromkeys(TRUTH_COLUMNS, 0.0)
            row.update(zip(("roll_rad", "pitch_rad", "yaw_rad"), truth_at(t), strict=True))
            row.update(lat_deg=47.0, lon_deg=8.0, alt_m=500.0, sim_time_s=t)
            assert truth.log(FMT_TRUTH, *row.values(), t_ns=_ns(t))
        for k in range(1000):
            t = 0.007 + k * 0.02
            aligned = t >= ALIGNED_S
            att = wrap_pi(truth_at(t) + (OURS_ERR if aligned else 0.5))
            state = dict.fromkeys(STATE_COLUMNS, 0.0)
            state.update(zip(("roll_rad", "pitch_rad", "yaw_rad"), att, strict=True))
            state.update(faults=0, aligned=int(aligned))
            assert est.log(FMT_STATE, *state.values(), t_ns=_ns(t))
        for k in range(450):
            t = 1.013 + k * 0.04
            att = wrap_pi(truth_at(t) + AP_ERR)
            assert ap.log(FMT_ESTIMATE, *att, 0.0, 0.0, 0.0, 47.0, 8.0, 500.0, 0.0, 0.0, 0.0, 0,
                          t_ns=_ns(t))
        for k in range(20):  # a round trip a second; the map restarts once, at 15.5 s
            t = 0.5 + k
            offset_ms = 1.7e12 + 0.003 * t + (5.0 if k >= 15 else 0.0)  # 3 ppm
            latency = 1.0 + 0.1 * k
            assert ap.log(FMT_TSYNC, offset_ms, 3.0, latency, 2 * latency + 0.5, int(k > 0),
                          int(k >= 15), t_ns=_ns(t))
        if guided:
            for k in range(51):
                t = TARGETS_S[0] + k * 0.1
                assert ap.log(FMT_COMMAND, ROLL_SP, PITCH_SP, truth_at(t)[2], THRUST, 1,
                              t_ns=_ns(t))
        for lg in (est, truth, ap):
            lg.end()
    return d


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_flight(tmp_path_factory.mktemp("beside") / "f1")


@pytest.fixture(scope="module")
def result(flight: Path, tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    return generate_report(flight, tmp_path_factory.mktemp("out"), measure_csv=False,
                           keep_figures=True)


def _deg(v: np.ndarray) -> tuple[float, ...]:
    return tuple(math.degrees(abs(float(x))) for x in v)


def test_summary_numbers_are_what_the_data_says(result) -> None:  # type: ignore[no-untyped-def]
    a = result.summary.autopilot
    assert a is not None and a.attitude is not None
    att = a.attitude
    # our aligned samples (from 2.007 s) inside the autopilot's span (1.013 s to 18.973 s)
    assert att.n == 849
    assert att.t_s[0] == pytest.approx(2.007) and att.t_s[-1] == pytest.approx(18.967)
    assert att.rms_diff_deg == pytest.approx(_deg(OURS_ERR - AP_ERR), abs=1e-3)
    assert att.ours_rmse_deg == pytest.approx(_deg(OURS_ERR), abs=1e-3)
    assert att.autopilot_rmse_deg == pytest.approx(_deg(AP_ERR), abs=1e-3)
    sync = a.sync
    assert sync is not None and sync.n == 20 and sync.reset_count == 1
    assert sync.reset_times_s == pytest.approx([15.5])
    assert sync.offset_change_ms[:15] == pytest.approx(0.003 * np.arange(15), abs=1e-3)
    assert sync.offset_change_ms[15] == pytest.approx(5.0 + 0.003 * 15, abs=1e-3)
    assert sync.latency_median_ms == pytest.approx(1.95, abs=1e-5)
    assert not sync.synced[0] and sync.synced[1:].all()
    sent = a.targets
    assert sent is not None and sent.n == 51 and sent.span_s == pytest.approx(5.0)
    t = sent.t_s
    ours_roll = -0.3 + 0.03 * t + OURS_ERR[0]
    expected_roll = math.degrees(math.sqrt(float(np.mean((ours_roll - ROLL_SP) ** 2))))
    ours = sent.rms_from_target_deg(sent.ours_rad)
    assert ours == pytest.approx((expected_roll, math.degrees(0.02), math.degrees(0.03)), abs=1e-3)
    assert sent.rms_from_target_deg(sent.autopilot_rad)[1:] == pytest.approx((0.0, 1.71887), abs=1e-3)


def test_the_page_shows_the_comparison(result) -> None:  # type: ignore[no-untyped-def]
    html = result.html.read_text(encoding="utf-8")
    for row in (
        "<th>attitude, ours - autopilot (RMS)</th><td>roll 1.15, pitch 1.15, yaw 3.44 deg "
        "(849 samples, 17.0 s)</td>",
        "<th>attitude RMSE against truth, ours</th><td>roll 0.57, pitch 1.15, yaw 1.72 deg</td>",
        "<th>attitude RMSE against truth, autopilot</th><td>roll 0.57, pitch 0.00, yaw 1.72 deg</td>",
        "<th>autopilot clock map</th><td>20 round trips, drift 3.00 ppm (last), latency 1.95 ms "
        "(median), 1 restart</td>",
        "<th>attitude targets sent in GUIDED</th><td>51 over 5.0 s</td>",
    ):
        assert row in html, row
    for spec in AUTOPILOT_FIGURES:
        assert f"<h2 id={spec.name}>" in html
    assert not any("autopilot" in m for m in result.missing), result.missing


def test_figures_hold_the_data(result) -> None:  # type: ignore[no-untyped-def]
    drawn = {p.stem for p in result.figures}
    assert AUTOPILOT_NAMES <= drawn
    att = result.figure_objects["autopilot_attitude"].axes
    assert [ax.get_ylabel() for ax in att] == ["roll (deg)", "pitch (deg)", "yaw (deg)",
                                               "ours - autopilot (deg)"]
    assert {str(ln.get_label()) for ln in att[0].get_lines()} == {"ours", "autopilot", "truth"}
    assert att[0].get_title() == "roll RMSE against truth: ours 0.57 deg, autopilot 0.57 deg"
    diff = {str(ln.get_label()): np.asarray(ln.get_ydata()) for ln in att[3].get_lines()}
    assert set(diff) == {"roll (rms 1.15 deg)", "pitch (rms 1.15 deg)", "yaw (rms 3.44 deg)"}
    assert diff["yaw (rms 3.44 deg)"] == pytest.approx(np.full(849, math.degrees(0.06)), abs=1e-3)
    clock = result.figure_objects["autopilot_clock"].axes
    assert clock[0].get_ylabel() == "offset change (ms)" and "20 round trips, 1 restart" in \
        clock[0].get_title()
    assert clock[2].get_title() == "link latency: median 1.95 ms, round trip median 4.40 ms"
    tgt = result.figure_objects["autopilot_targets"].axes
    assert tgt[3].get_title() == "51 attitude targets sent in GUIDED over 5.0 s"
    target_line = next(ln for ln in tgt[0].get_lines() if ln.get_label() == "target")
    assert np.asarray(target_line.get_ydata()) == pytest.approx(np.full(51, math.degrees(ROLL_SP)))


def test_no_guided_no_targets_figure(tmp_path: Path) -> None:
    fd = load_flight(write_flight(tmp_path / "f2", guided=False))
    with pytest.raises(MissingData, match="autopilot.bin format 5 has no records"):
        fig_autopilot_targets(Products(fd))


def test_a_flight_without_autopilot_bin_has_the_report_it_always_had(
        flight: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    d = tmp_path / "f3"
    shutil.copytree(flight, d)
    (d / "autopilot.bin").unlink()
    now = generate_report(d, tmp_path / "now", measure_csv=False)
    assert now.summary.autopilot is None
    assert {p.stem for p in now.figures}.isdisjoint(AUTOPILOT_NAMES)
    assert len(now.figures) + len(now.missing) == len(FIGURES)
    html = now.html.read_text(encoding="utf-8")
    assert "autopilot" not in html
    # the same report with the autopilot's additions taken out: byte for byte
    monkeypatch.setattr(report_module, "figures_for", lambda fd: FIGURES)
    monkeypatch.setattr(summary_module, "summarise_autopilot", lambda fd: None)
    before = generate_report(d, tmp_path / "before", measure_csv=False)
    assert before.html.read_bytes() == now.html.read_bytes()
    assert [p.read_bytes() for p in before.figures] == [p.read_bytes() for p in now.figures]


def test_what_cannot_be_compared_is_said(tmp_path: Path) -> None:
    d = write_flight(tmp_path / "f4", guided=False)
    (d / "estimator.bin").unlink()
    a = summarise_autopilot(load_flight(d))
    assert a is not None and a.attitude is None and a.targets is None and a.sync is not None
    assert a.attitude_missing == "estimator.bin is missing (on-board state estimate)"
