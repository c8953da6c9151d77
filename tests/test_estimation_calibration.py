"""The gyro calibration one flight learns, carried to the next flight of the same part
(companion.estimation.calibration, `Eskf.set_gyro_calibration`,
`companion estimation calibration`)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.core.config import Config
from companion.core.params import parse_param_file
from companion.estimation.calibration import (
    MIN_GS_STD,
    CalibrationLogError,
    GyroCalibration,
    learnt_from_log,
    next_flight_params,
)
from companion.estimation.eskf import Eskf
from companion.evaluation.sitl import FlightSpec, record_flight
from companion.evaluation.sitl_estimator import EskfOptions, run_eskf
from companion.evaluation.sitl_scoring import filter_errors
from companion.logs import read_log
from companion.sim.lockstep import run_lockstep
from companion.sim.runner import SimOptions

G = 9.80665


def _turn_yaw(f: Eskf, rate_rad_s: float, seconds: float, scale: float) -> float:
    """Yaw after a turn about z read by a gyro whose z sensitivity is ``1 + scale``."""
    f.initialise((0.0, 0.0, -G), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), yaw_rad=0.0)
    for _ in range(int(seconds * 100)):
        f.predict((0.0, 0.0, (1.0 + scale) * rate_rad_s), (0.0, 0.0, -G), 0.01)
    return f.state().yaw_rad


def test_a_known_gyro_matrix_is_applied_and_a_bad_one_refused() -> None:
    """With the matrix given (and not estimated) a 5 % scale error leaves no heading error
    over a quarter turn; without it the heading is 4.5 deg off."""
    truth = math.radians(90.0)
    plain = _turn_yaw(Eskf(), truth / 10.0, 10.0, 0.05)
    assert math.degrees(abs(plain - truth)) == pytest.approx(4.5, abs=0.1)
    f = Eskf()
    m = np.zeros((3, 3))
    m[2, 2] = 0.05
    assert f.set_gyro_calibration(m, (0.0, 0.0, 2e-4))
    calibrated = _turn_yaw(f, truth / 10.0, 10.0, 0.05)
    assert math.degrees(abs(calibrated - truth)) < 0.01
    matrix, matrix_std, temp, temp_std = f.gyro_calibration()
    assert matrix[8] == pytest.approx(0.05) and temp == [0.0, 0.0, 2e-4]
    assert matrix_std == [0.0] * 9 and temp_std == [0.0] * 3  # neither is estimated here
    for bad_m, bad_k in ((np.zeros((2, 2)), (0.0, 0.0, 0.0)), (np.full((3, 3), 0.2), (0, 0, 0)),
                         (np.zeros((3, 3)), (0.0, math.nan, 0.0)),
                         (np.zeros((3, 3)), (0.0, 0.0, 0.5)), ("x", (0.0, 0.0, 0.0))):
        before = f.rejected_inputs
        assert not f.set_gyro_calibration(bad_m, bad_k)  # type: ignore[arg-type]
        assert f.rejected_inputs == before + 1
    assert f.gyro_calibration()[0][8] == pytest.approx(0.05)  # unchanged by the refusals


def test_an_estimated_matrix_starts_from_the_calibration_with_its_prior() -> None:
    f = Eskf(gyro_matrix_std=0.004, gyro_bias_temp_rad_s_per_c=3e-4)
    m = np.full((3, 3), 0.01)
    assert f.set_gyro_calibration(m, (1e-4, -1e-4, 5e-4))
    f.initialise((0.0, 0.0, -G), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), yaw_rad=0.0)
    matrix, matrix_std, temp, temp_std = f.gyro_calibration()
    assert matrix == pytest.approx([0.01] * 9) and temp == pytest.approx([1e-4, -1e-4, 5e-4])
    assert matrix_std == pytest.approx([0.004] * 9) and temp_std == pytest.approx([3e-4] * 3)
    # a prior change in flight restarts the estimate from the calibration, not from zero
    assert f.set_gyro_matrix_std(0.006)
    assert f.gyro_calibration()[0] == pytest.approx([0.01] * 9)
    assert f.set_gyro_bias_temp(1e-3)
    assert f.gyro_calibration()[2] == pytest.approx([1e-4, -1e-4, 5e-4])


def test_next_flight_priors_narrow_to_what_was_learnt_within_floor_and_default() -> None:
    cal = GyroCalibration(tuple(0.001 * i for i in range(9)), (0.008,) * 8 + (0.01,),
                          (1e-4, 2e-4, 3e-4), (5e-4, 5e-4, 6e-4), 120.0)
    out = next_flight_params(cal, {"GS_STD": 0.015, "GB_TEMP": 1.5e-3})
    assert out["EST_GM_XX"] == 0.0 and out["EST_GM_ZZ"] == pytest.approx(0.008)
    assert out["EST_GT_Z"] == pytest.approx(3e-4)
    assert out["EST_GS_STD"] == pytest.approx(0.006)  # 0.6 x the largest learnt 1-sigma
    assert out["EST_GB_TEMP"] == pytest.approx(3.6e-4)
    tight = GyroCalibration((0.0,) * 9, (1e-4,) * 9, (0.0,) * 3, (1e-6,) * 3)
    floor = next_flight_params(tight, {"GS_STD": 0.015, "GB_TEMP": 1.5e-3})
    assert floor["EST_GS_STD"] == MIN_GS_STD and floor["EST_GB_TEMP"] == pytest.approx(2e-4)
    loose = GyroCalibration((0.0,) * 9, (0.1,) * 9, (0.0,) * 3, (0.01,) * 3)
    capped = next_flight_params(loose, {"GS_STD": 0.015, "GB_TEMP": 1.5e-3})
    assert capped["EST_GS_STD"] == 0.015 and capped["EST_GB_TEMP"] == 1.5e-3
    # a term the learning flight did not estimate keeps the next flight's default prior
    off = next_flight_params(GyroCalibration((0.0,) * 9, (0.0,) * 9, (0.0,) * 3, (0.0,) * 3),
                             {"GS_STD": 0.015, "GB_TEMP": 1.5e-3})
    assert "EST_GS_STD" not in off and "EST_GB_TEMP" not in off


def _fly(tmp: Path, duration_s: float, params: str = "", **sim: int) -> Path:
    cfg = Config()
    cfg.logs.dir = str(tmp / "flights")
    cfg.params.file = str(tmp / "params.parm")
    if params:
        tmp.mkdir(parents=True, exist_ok=True)
        (tmp / "params.parm").write_text(params)
    opts = SimOptions(scenario="turns", imu_profile="consumer", **{"seed": 4, **sim})
    summary = run_lockstep(cfg, opts, duration_s, handle_signals=False)
    return Path(summary["flight_dir"])


def test_a_flight_learns_a_calibration_the_cli_hands_to_the_next_flight(tmp_path: Path) -> None:
    """The real path: a lockstep flight's estimator logs what it learnt, the CLI writes a
    parameter file from its last record, and the next flight's estimator starts from it."""
    first = _fly(tmp_path / "a", 75.0)
    cal = learnt_from_log(first)
    assert cal.flight_s >= 60.0 and max(map(abs, cal.matrix)) > 1e-4  # it learnt something
    assert 0.0 < max(cal.matrix_std) < 0.015  # narrower than the prior it started from
    out = tmp_path / "next.parm"
    proc = subprocess.run([sys.executable, "-m", "companion", "estimation", "calibration",
                           str(first), "-o", str(out)], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    rows = {name: value for _n, name, _raw, value, problem in parse_param_file(out)
            if problem is None}
    assert rows["EST_GM_ZZ"] == pytest.approx(cal.matrix[8], abs=1e-6)
    assert set(rows) >= {"EST_GM_XY", "EST_GT_Z", "EST_GS_STD", "EST_GB_TEMP"}
    second = _fly(tmp_path / "b", 5.0, out.read_text(), seed=5, imu_seed=4)  # same part
    start = read_log(second / "estimator.bin").data(3)[0]
    assert start["gm_zz"] == pytest.approx(cal.matrix[8], abs=2e-6)
    assert start["gt_x"] == pytest.approx(cal.temp_rad_s_per_c[0], abs=1e-7)
    assert start["gm_std_xx"] == pytest.approx(rows["EST_GS_STD"], rel=0.05)


def test_logs_without_a_calibration_are_refused_by_name(tmp_path: Path) -> None:
    short = _fly(tmp_path, 20.0)
    for path, words in ((short, "records cover"), (short / "gps.bin", "no calibration records"),
                        (tmp_path / "nothing.bin", "no such file")):
        with pytest.raises(CalibrationLogError, match=words) as err:
            learnt_from_log(path)
        assert str(path.name) in str(err.value)
    (tmp_path / "junk.bin").write_bytes(b"\x00garbage" * 50)
    proc = subprocess.run([sys.executable, "-m", "companion", "estimation", "calibration",
                           str(tmp_path / "junk.bin")], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 2 and "junk.bin" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_the_next_flight_of_the_same_part_is_better_for_what_the_first_learnt() -> None:
    """The part whose first opposite turn gives the tuning flights' largest tilt error
    (seed 6): flown once, then again on another day (other pilot jitter, air and GPS), with
    and without the calibration the first flight learnt."""
    spec = FlightSpec(aircraft="j3cub", seed=6, duration_s=120.0, gps_latency_s=0.15)
    first = run_eskf(record_flight(spec), EskfOptions(check_pd_every=1000))
    assert first.learnt is not None
    params = {k.removeprefix("EST_"): v for k, v in
              next_flight_params(first.learnt, {"GS_STD": 0.015, "GB_TEMP": 1.5e-3}).items()}
    again = record_flight(FlightSpec(aircraft="j3cub", seed=14, imu_part_seed=6,
                                     duration_s=120.0, gps_latency_s=0.15))
    scored = again.t_s >= 30.0
    figures = {}
    for name, opts in (("cold", EskfOptions(check_pd_every=1000)),
                       ("learnt", EskfOptions(params=params, check_pd_every=1000))):
        run = run_eskf(again, opts)
        assert run.faults == 0 and run.exceptions == 0
        incl = np.degrees(filter_errors(again, run.quat, run=run).inclination_rad[scored])
        figures[name] = (float(np.sqrt(np.mean(incl**2))), float(incl.max()))
    assert figures["learnt"][0] < 0.9 * figures["cold"][0]
    assert figures["learnt"][1] < 0.8 * figures["cold"][1]


def test_a_part_switched_on_again_keeps_its_errors_but_not_its_turn_on_bias() -> None:
    first = record_flight(FlightSpec(seed=6, duration_s=2.0))
    again = record_flight(FlightSpec(seed=14, imu_part_seed=6, duration_s=2.0))
    other = record_flight(FlightSpec(seed=14, duration_s=2.0))
    assert np.array_equal(first.imu_gyro_matrix, again.imu_gyro_matrix)
    assert np.array_equal(first.imu_misalignment_rad, again.imu_misalignment_rad)
    assert not np.array_equal(first.imu_gyro_matrix, other.imu_gyro_matrix)
    # a new power-on: its own turn-on bias, not the first flight's
    assert np.abs(first.gyro_bias_true_rad_s[0] - again.gyro_bias_true_rad_s[0]).max() > 1e-4
