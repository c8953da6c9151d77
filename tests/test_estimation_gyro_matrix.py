"""The filter estimates the gyro's scale-factor and cross-axis error (`EST_GS_STD`).

A consumer MEMS gyro's sensitivity is good to a few per cent per axis, and each axis also sees
a per cent or two of the others: in a turn that is a rate error of some 0.1 deg/s which comes
and goes with the turn, too fast for the bias states and too slow for the accelerometer to
correct. The filter carries the 3x3 error ``M`` (the part reads ``(I + M) w + b``) as nine
states. Checked: with the states off the gyro is taken as exact and ``M`` never moves; the
parameter turns them on and off in flight; bad values are refused; and on a SITL flight of the
realistic consumer part the estimate moves toward the simulator's true matrix and the
inclination error falls.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.estimation.eskf import Eskf
from companion.estimation.eskf_state import IDX_GYRO_MATRIX, N_STATES
from companion.estimation.fusion import EstimatorCore
from companion.estimation.params import estimator_param_defaults
from companion.evaluation.sitl import FlightSpec, record_flight
from companion.evaluation.sitl_estimator import ESTIMATOR_PARAM_PREFIX, EskfOptions, run_eskf
from companion.evaluation.sitl_scoring import filter_errors

G = 9.80665


def started(**kwargs: float) -> Eskf:
    f = Eskf(cov_period_s=0.01, **kwargs)
    assert f.initialise((0.0, 0.0, -G), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (20.0, 0.0, 0.0),
                        yaw_rad=0.0)
    return f


def turn(f: Eskf, seconds: float, rate_rad_s: float = 0.2) -> None:
    """Yaw at a constant rate with GPS fixes that agree with a straight line: the filter sees
    innovations, so every coupled state would move."""
    for k in range(int(seconds * 100)):
        f.predict((0.0, 0.0, rate_rad_s), (0.0, 0.0, -G), 0.01)
        if k % 10 == 9:
            t = (k + 1) * 0.01
            f.update_gps((20.0 * t, 0.0, 0.0), (20.0, 0.0, 0.0), 2.0, 0.3)


def test_off_means_the_gyro_is_exact_and_the_states_stay_uncoupled() -> None:
    f = started()  # gyro_matrix_std 0: the default of the bare filter
    turn(f, 5.0)
    assert np.array_equal(f.gyro_matrix_estimate, np.zeros((3, 3)))
    assert np.array_equal(f.state().gyro_matrix, np.zeros((3, 3)))
    p = f.covariance
    block = p[IDX_GYRO_MATRIX, :]
    others = np.delete(block, np.arange(IDX_GYRO_MATRIX.start, IDX_GYRO_MATRIX.stop), axis=1)
    assert np.array_equal(others, np.zeros_like(others))
    assert p.shape == (N_STATES, N_STATES)


def test_on_the_states_couple_to_the_attitude_in_a_turn_and_learn() -> None:
    f = started(gyro_matrix_std=0.01)
    p0 = f.covariance[IDX_GYRO_MATRIX, IDX_GYRO_MATRIX].copy()
    np.testing.assert_allclose(np.diagonal(p0), 1e-4)
    turn(f, 10.0)
    p = f.covariance
    # a yaw rate read into roll or pitch tilts the attitude, which gravity shows the GPS
    # velocity: the elements multiplying w_z in the x and y rows learn. The yaw scale (a
    # heading error) needs a horizontal acceleration to show, and w_x, w_y are zero here: those
    # stay at the prior (plus the random walk)
    var = np.diagonal(p[IDX_GYRO_MATRIX, IDX_GYRO_MATRIX]).reshape(3, 3)
    assert (var[0:2, 2] < 0.98e-4).all(), var
    assert var[2, 2] == pytest.approx(1e-4, rel=1e-3)
    np.testing.assert_allclose(var[:, :2], 1e-4, rtol=1e-3)
    assert np.linalg.eigvalsh(p).min() > 0.0
    assert np.isfinite(f.gyro_matrix_estimate).all()
    assert np.abs(f.gyro_matrix_estimate).max() <= f.max_gyro_matrix


def test_the_parameter_turns_the_states_on_and_off_in_flight() -> None:
    params = estimator_param_defaults(ESTIMATOR_PARAM_PREFIX)
    assert params["GS_STD"] > 0.0  # on by default in the thread
    core = EstimatorCore(params, None)
    f = core.new_filter(moving=False)
    assert f.gyro_matrix_std == params["GS_STD"]
    core.filter = f
    core.update_params({"GS_STD": 0.0})
    assert f.gyro_matrix_std == 0.0
    var = np.diagonal(f.covariance)[IDX_GYRO_MATRIX]
    assert (var < 1e-10).all()
    core.update_params({"GS_STD": 0.02})
    np.testing.assert_allclose(np.diagonal(f.covariance)[IDX_GYRO_MATRIX], 4e-4)


@pytest.mark.parametrize("bad", [-0.01, math.nan, math.inf])
def test_bad_priors_are_refused(bad: float) -> None:
    f = started(gyro_matrix_std=0.01)
    before = f.covariance
    rejected = f.rejected_inputs
    assert f.set_gyro_matrix_std(bad) is False
    assert f.rejected_inputs == rejected + 1
    assert np.array_equal(f.covariance, before)
    with pytest.raises(ValueError, match="gyro_matrix_std"):
        Eskf(gyro_matrix_std=bad)


def test_sitl_estimate_moves_toward_the_parts_true_matrix_and_helps_the_attitude() -> None:
    # seed 101 draws a part with a large matrix error (1.1 % RMS over the nine elements, in
    # the axes the level trims give). Flight by flight the states do not always help: with
    # the level-calibrated installation seed 8 (1.1 %) gains nothing; over the 32 tuning
    # flights of seeds 9-16 they take the inclination RMSE from 0.47 to 0.41 deg.
    rec = record_flight(FlightSpec(aircraft="c172p", seed=101, duration_s=150.0))
    truth = rec.gyro_matrix_trimmed.reshape(-1)  # in the axes the level trims give
    scored = rec.t_s >= 30.0
    incl = {}
    runs = {}
    for gs in (0.0, 0.01):
        run = run_eskf(rec, EskfOptions(params={"GS_STD": gs}))
        assert run.faults == 0 and run.pd_failures == 0 and run.non_finite == 0
        err = filter_errors(rec, run.quat, run=run)
        incl[gs] = math.degrees(float(np.sqrt(np.mean(err.inclination_rad[scored] ** 2))))
        runs[gs] = run
    final = runs[0.01].gyro_matrix[-1]
    rms_before = float(np.sqrt(np.mean(truth**2)))  # the estimate starts at zero
    rms_after = float(np.sqrt(np.mean((final - truth) ** 2)))
    assert rms_before > 0.006
    assert rms_after < 0.75 * rms_before, (rms_before, rms_after)
    assert np.array_equal(runs[0.0].gyro_matrix[-1], np.zeros(9))
    assert incl[0.01] < 0.9 * incl[0.0], incl
