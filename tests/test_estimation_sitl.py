"""Offline SITL evaluation: JSBSim truth, simulated devices, real decoders, the estimator as the
thread runs it, and VQF / Madgwick on the same samples (a short, one-seed version of
bench/estimation_sitl_bench.py)."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from companion.core.state import ImuSample, VehicleState
from companion.core.sync import MessageQueue
from companion.estimation.imu_filters import run_filter
from companion.estimation.thread import EstimatorThread
from companion.evaluation.sitl import FlightSpec, SitlRecording, record_flight
from companion.evaluation.sitl_estimator import (
    EskfAsThread,
    EskfOptions,
    EskfRun,
    imu_series,
    run_eskf,
)
from companion.evaluation.sitl_scoring import filter_errors, outage_growth, steady_turn_mask
from companion.vehicle import VEHICLE
from companion.watchdog.thread import RuntimeContext

WARMUP_S = 30.0
BENCH = Path(__file__).resolve().parents[1] / "bench" / "estimation_sitl_bench.py"

SIMPLE_SENSORS = {"imu_profile": "simple", "gps_profile": "simple", "turbulence": "none"}
"""The original sensor model and calm air, which these accuracy figures were set against."""


def rms_deg(x: np.ndarray) -> float:
    return math.degrees(float(np.sqrt(np.mean(np.square(x)))))


@pytest.fixture(scope="module")
def turns() -> SitlRecording:
    """90 s of the turns scenario (8 s level, 20 s at 30 deg bank, 8 s level, 20 s at -30)."""
    # estimator accuracy under the realistic profile: see issue #15 bench
    return record_flight(FlightSpec(aircraft="c172p", scenario="turns", seed=7, duration_s=90.0,
                                    **SIMPLE_SENSORS))


def test_recording_has_every_sample_and_fix(turns: SitlRecording) -> None:
    assert turns.trim_method
    assert all(s is not None for s in turns.imu), "the IMU decoder lost a frame"
    # 10 Hz fixes from 0.1 s, each handed off 50 ms late (the last one is still on its way)
    assert len(turns.gps) == 899 and len(turns.gps_error_ned_m) == 900
    fix_ticks = sorted(turns.gps)
    assert fix_ticks[0] == 14 and np.all(np.diff(fix_ticks) == 10)
    first = turns.gps[fix_ticks[0]]
    assert first.latency_s == 0.0 and first.hdop == pytest.approx(0.9)
    assert len(turns.horizon) == 900
    # the GPS error is realistic: about a metre, not zero and not tens of metres
    gps_h = np.linalg.norm(turns.gps_error_ned_m[:, :2], axis=1)
    assert 0.3 < float(np.sqrt(np.mean(gps_h**2))) < 3.0
    # the pilot really flew steady 30 deg turns
    turn = steady_turn_mask(turns)
    assert 0.25 < turn.mean() < 0.6
    assert 25.0 < math.degrees(float(np.abs(turns.euler_true_rad[turn, 0]).mean())) < 35.0


@pytest.fixture(scope="module")
def turns_run(turns: SitlRecording) -> EskfRun:
    return run_eskf(turns)


def test_project_estimator_beats_imu_only_filters_in_turns(
    turns: SitlRecording, turns_run: EskfRun
) -> None:
    scored = turns.t_s >= WARMUP_S
    turn = steady_turn_mask(turns) & scored
    assert turn.sum() > 2000
    run = turns_run
    ours = filter_errors(turns, run.quat, run=run)
    vqf = filter_errors(turns, run_filter("vqf", imu_series(turns))[0], zup=True)
    madgwick = filter_errors(turns, run_filter("madgwick", imu_series(turns))[0], zup=True)

    ours_turn = rms_deg(ours.inclination_rad[turn])
    vqf_turn = rms_deg(vqf.inclination_rad[turn])
    madgwick_turn = rms_deg(madgwick.inclination_rad[turn])
    # IMU-only filters take the turn's specific force for gravity: they slide towards wings
    # level, so their error approaches the 30 deg bank
    assert vqf_turn > 15.0 and madgwick_turn > 15.0
    assert ours_turn < 0.05 * min(vqf_turn, madgwick_turn)
    # Absolute bounds. Measured on this flight with seeds 1 to 13 (the test flies seed 7):
    # inclination RMS 0.13-0.28 deg (seed 7: 0.26), in the turns 0.14-0.28 (0.28), worst
    # sample 0.38-0.99 deg (0.43), heading RMS 0.18-0.59 deg (0.35), velocity RMS 0.07-0.12 m/s
    # (0.07), horizontal position RMS 0.44-1.72 m (0.78). Each bound is about 1.4x the worst
    # seed: another platform's floating point or a harmless retune may move seed 7 within the
    # seeds' spread, while an estimator that got half again worse fails.
    assert rms_deg(ours.inclination_rad[scored]) < 0.4
    assert ours_turn < 0.4
    assert math.degrees(float(np.max(ours.inclination_rad[scored]))) < 1.4
    assert ours.heading_rad is not None and ours.vel_m_s is not None and ours.hpos_m is not None
    assert rms_deg(ours.heading_rad[scored]) < 0.8
    assert float(np.sqrt(np.mean(ours.vel_m_s[scored] ** 2))) < 0.17
    assert float(np.sqrt(np.mean(ours.hpos_m[scored] ** 2))) < 2.4
    # numerically healthy all the way
    assert run.start_tick == 99  # one second of IMU averaging, a fix already there
    assert run.exceptions == 0 and run.non_finite == 0 and ours.non_finite == 0
    assert run.pd_checks > 8000 and run.pd_failures == 0
    assert run.faults == 0, run.fault_reasons
    assert run.gps_accepted > 850
    step = run.step_us[np.isfinite(run.step_us)]
    assert step.size == turns.ticks - 100 and float(np.median(step)) > 0.0
    # NEES is computed on every 10th sample once running, with finite values
    assert run.nees.size > 800 and np.isfinite(run.nees).all()


def test_a_receiver_without_vertical_velocity_leaves_the_vertical_channel_sound(
    turns: SitlRecording, turns_run: EskfRun
) -> None:
    """NMEA without PASHR,POS has no vertical velocity: it must not be fused as 0 m/s (that
    cost 0.36 m/s of vertical velocity error and, on the j3cub, GPS resets)."""
    assert all(fix.vd_m_s is None for fix in turns.gps.values())
    scored = turns.t_s >= WARMUP_S
    true_vd = turns.vel_true_m_s[scored, 2]
    assert float(np.sqrt(np.mean(true_vd**2))) > 0.2  # the aircraft does move vertically
    vd_err = turns_run.vel_m_s[scored, 2] - true_vd
    assert float(np.sqrt(np.mean(vd_err**2))) < 0.1


class _WatchedQueue(MessageQueue[ImuSample]):
    """The IMU stream, telling the test when the thread's initial phase has emptied it."""

    def __init__(self) -> None:
        super().__init__(512, drop_oldest=True)
        self.drained = threading.Event()

    def drain(self) -> list[ImuSample]:
        out = super().drain()
        self.drained.set()
        return out


def test_replica_matches_the_estimator_thread_sample_by_sample(turns: SitlRecording) -> None:
    """EskfAsThread must stay the thread: same initial phase, GPS and horizon handling."""
    ticks = 2500
    short = SitlRecording(**{**vars(turns), "t_s": turns.t_s[:ticks]})
    run = run_eskf(short, EskfOptions(horizon=True))
    init = run.start_tick
    assert init == 99 and run.horizon_used > 200

    queue = _WatchedQueue()
    thread = EstimatorThread(task=VEHICLE["estimator"].task)
    thread.ctx = RuntimeContext(state=VehicleState(imu_stream=queue), home_lla=turns.home_lla)
    thread.ctx.params.declare_all(thread.param_specs())
    init_fix = turns.gps[max(k for k in turns.gps if k <= init)]
    thread.ctx.state.gps.write(init_fix)
    result: list[bool] = []
    worker = threading.Thread(target=lambda: result.append(thread.prologue()), daemon=True)
    worker.start()
    try:
        assert queue.drained.wait(10.0), "the initial phase never started"
        for k in range(init + 1):
            sample = turns.imu[k]
            assert sample is not None
            queue.put(sample)
    finally:
        worker.join(10.0)
    assert not worker.is_alive() and result == [True]

    state = thread.ctx.state
    for k in range(init + 1, ticks):
        sample = turns.imu[k]
        assert sample is not None
        queue.put(sample)
        if k in turns.gps:
            state.gps.write(turns.gps[k])
        if k in turns.horizon:
            state.horizon.write(turns.horizon[k])
        assert thread.step() == 1
        out = state.estimator.read()
        assert out is not None
        np.testing.assert_allclose(out.quat_wxyz, run.quat[k], rtol=0, atol=1e-12,
                                   err_msg=f"attitude differs at tick {k}")
        np.testing.assert_allclose(out.pos_ned_m, run.pos_m[k], rtol=0, atol=1e-9,
                                   err_msg=f"position differs at tick {k}")
        np.testing.assert_allclose(out.vel_ned_m_s, run.vel_m_s[k], rtol=0, atol=1e-9,
                                   err_msg=f"velocity differs at tick {k}")
    assert thread.horizon_used == run.horizon_used
    assert thread.gps_accepted == run.gps_accepted


def test_gps_outage_in_a_turn_grows_the_error_and_gps_return_recovers_it() -> None:
    # estimator accuracy under the realistic profile: see issue #15 bench
    rec = record_flight(FlightSpec(aircraft="c172p", scenario="auto", seed=3, duration_s=70.0,
                                   **SIMPLE_SENSORS))
    window = (35.0, 55.0)
    inside = (rec.t_s >= window[0]) & (rec.t_s < window[1])
    assert np.all(np.abs(np.degrees(rec.euler_true_rad[inside, 0])) > 20.0), "not in a turn"
    scored = rec.t_s >= 20.0
    incl_rms = {}
    for name, hzn in (("gps only", False), ("horizon", True)):
        opts = EskfOptions(gps_outage_s=window, horizon=hzn)
        run = run_eskf(rec, opts)
        assert run.faults == 0 and run.pd_failures == 0 and run.non_finite == 0
        err = filter_errors(rec, run.quat, run=run)
        g = outage_growth(rec, err, window)
        assert g.end_hpos_m > 2.0 * g.before_hpos_m  # dead reckoning drifts...
        assert g.recovered_hpos_m < 1.5  # ...and the first fixes after the gap pull it back
        assert g.max_incl_deg < 2.0
        incl_rms[name] = rms_deg(err.inclination_rad[scored])
        if hzn:
            assert run.horizon_used > 0.95 * sum(1 for k in rec.horizon if k > run.start_tick)
    # an absolute tilt measurement at 10 Hz beats what GPS alone tells about the tilt
    assert incl_rms["horizon"] < incl_rms["gps only"]
    with pytest.raises(ValueError, match="not inside the recording"):
        outage_growth(rec, err, (100.0, 160.0))


def test_bad_options_are_refused_with_the_field_named() -> None:
    with pytest.raises(ValueError, match="aircraft.*b747"):
        FlightSpec(aircraft="b747")
    with pytest.raises(ValueError, match="scenario"):
        FlightSpec(scenario="barrel")
    with pytest.raises(ValueError, match="duration_s"):
        FlightSpec(duration_s=0.0)
    with pytest.raises(ValueError, match="wind_ned_m_s"):
        FlightSpec(wind_ned_m_s=(0.0, math.nan, 0.0))
    with pytest.raises(ValueError, match="horizon_quality"):
        FlightSpec(horizon_quality=0.0)
    with pytest.raises(ValueError, match="NOPE"):
        EskfAsThread(None, params={"NOPE": 1.0})


def test_bench_smoke(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = importlib.util.spec_from_file_location("estimation_sitl_bench", BENCH)
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = bench  # its dataclasses look their module up
    try:
        spec.loader.exec_module(bench)
    finally:
        del sys.modules[spec.name]
    out = tmp_path / "figures.json"
    code = bench.main(["--aircraft", "c172p", "--wind-m-s", "0", "--seeds", "1",
                       "--duration-s", "45", "--outage-seeds", "0", "--long-s", "0",
                       "--timing-s", "5", "--workers", "1", "--json", str(out)])
    assert code == 0
    figures = json.loads(out.read_text())
    acc = figures["accuracy"]["c172p, still air"]
    assert set(acc) == {"eskf", "attitude", "vqf", "madgwick", "gps fix"}
    assert 0.0 < acc["attitude"]["incl_rmse_deg"] < 90.0
    assert acc["eskf"]["incl_rmse_deg"] < acc["vqf"]["incl_rmse_deg"]
    assert acc["eskf"]["pd_failures"] == 0
    assert figures["timing"]["eskf"]["step_median_us"] > 0.0
    text = capsys.readouterr().out
    assert "### Accuracy" in text and "### Targets" in text
    with pytest.raises(SystemExit):
        bench.main(["--param", "NOPE=1"])


def test_a_heading_reference_takes_out_the_tilt_error_of_turns_if_it_is_unbiased() -> None:
    """In the realistic world the tilt error of steady turns is mostly the heading error seen
    through the centripetal acceleration: an unbiased heading fix takes most of it out, a
    biased one puts more in (docs/estimation.md; bench/estimation_budget_bench.py)."""
    rec = record_flight(FlightSpec(aircraft="c172p", scenario="turns", seed=101, duration_s=90.0,
                                   wind_ned_m_s=(0.0, 8.0, 0.0)))
    scored = rec.t_s >= WARMUP_S

    def incl_rms_deg(**aiding: float) -> float:
        run = run_eskf(rec, EskfOptions(check_pd_every=1000, **aiding))
        assert run.faults == 0 and run.exceptions == 0 and run.non_finite == 0
        return rms_deg(filter_errors(rec, run.quat, run=run).inclination_rad[scored])

    alone = incl_rms_deg()
    aided = incl_rms_deg(heading_std_rad=math.radians(1.0))
    biased = incl_rms_deg(heading_std_rad=math.radians(1.0), heading_bias_rad=math.radians(2.0))
    assert aided < 0.8 * alone, (alone, aided)
    assert biased > 1.5 * alone, (alone, biased)


def test_a_dual_antenna_receiver_through_the_decoder_meets_the_turn_accuracy() -> None:
    """The same flight with the dual-antenna profile: its HDT goes through the NMEA decoder
    and the estimator core; HDG_USE 0 gives back the single-antenna flight exactly."""
    spec = FlightSpec(aircraft="c172p", scenario="turns", seed=101, duration_s=90.0,
                      wind_ned_m_s=(0.0, 8.0, 0.0))
    single = record_flight(spec)
    dual = record_flight(dataclasses.replace(spec, gps_profile="dual-antenna"))
    assert all(fix.heading_deg is not None for fix in dual.gps.values() if fix.fix > 0)
    assert all(fix.heading_deg is None for fix in single.gps.values())
    scored = single.t_s >= WARMUP_S

    def incl(rec: SitlRecording, **params: float) -> tuple[np.ndarray, EskfRun]:
        run = run_eskf(rec, EskfOptions(check_pd_every=1000, params=params))
        assert run.faults == 0 and run.exceptions == 0 and run.non_finite == 0
        return filter_errors(rec, run.quat, run=run).inclination_rad[scored], run

    single_err, _ = incl(single)
    dual_err, _ = incl(dual)
    blind_err, _ = incl(dual, HDG_USE=0)
    assert np.array_equal(blind_err, single_err, equal_nan=True)
    assert rms_deg(dual_err) < 0.8 * rms_deg(single_err), (rms_deg(single_err), rms_deg(dual_err))
    assert rms_deg(dual_err) < 0.5 and math.degrees(float(dual_err.max())) < 2.0
    # antennas across the wings (first left): the receiver reads 90 deg more, HDG_OFS takes it off
    across = dataclasses.replace(dual, gps={
        k: dataclasses.replace(fix, heading_deg=(fix.heading_deg + 90.0) % 360.0)
        if fix.heading_deg is not None else fix for k, fix in dual.gps.items()})
    across_err, _ = incl(across, HDG_OFS=math.pi / 2)
    assert np.allclose(across_err, dual_err, atol=1e-4, equal_nan=True)
