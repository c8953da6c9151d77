"""Scoring IMU-only filters on the real recordings: inclination error against the truth.

Every filter of :mod:`companion.estimation.imu_filters` runs on the same resampled samples
(`imu_series`) and is scored against the same truth and alignment
(:mod:`companion.evaluation.realdata` loads, resamples and aligns); PX4's log is scored as
agreement with its EKF2. Separate from the data's preparation, which knows the recordings,
while this knows only what a score is.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.estimation.imu_filters import ImuSeries, run_filter
from companion.estimation.quat import (
    FloatArray,
    quat_to_rotmat,
)
from companion.evaluation.realdata import (
    LEIRIA_DIR,
    PX4_ULOG,
    RESAMPLE_RATE_HZ,
    ROBOT_UP_BASE,
    TRUTH_LAG_S,
    Alignment,
    ImuRecording,
    angle_between_rad,
    consistent_from_s,
    fit_alignment,
    interpolate_quat,
    list_leiria,
    load_leiria,
    load_leiria_xsens,
    load_px4_ulog,
    resample_uniform,
    true_up_sensor,
    truth_wxyz,
    up_sensor_from_quat,
    wahba,
)


def imu_series(rec: ImuRecording) -> ImuSeries:
    """A recording as the filters take it: its median period, and its own time stamps for
    ``ours_timed``."""
    return ImuSeries(rec.gyro_rad_s, rec.accel_m_s2, float(np.median(np.diff(rec.t_s))),
                     t_s=rec.t_s)


@dataclass(frozen=True)
class Score:
    """Inclination error statistics of one filter on one recording, degrees."""

    rmse_deg: float
    mean_deg: float
    p95_deg: float
    max_deg: float

    @classmethod
    def of(cls, err_rad: FloatArray) -> Score:
        e = np.degrees(err_rad)
        return cls(float(np.sqrt(np.mean(e**2))), float(np.mean(e)),
                   float(np.percentile(e, 95)), float(np.max(e)))


def inclination_errors_rad(
    rec: ImuRecording, align: Alignment, q_wxyz: FloatArray, frame: str, skip_s: float = 0.0
) -> FloatArray:
    """Per-sample inclination error of one filter's output on ``rec`` (after ``skip_s``)."""
    err = angle_between_rad(up_sensor_from_quat(q_wxyz, frame), true_up_sensor(rec, align))
    return err[rec.t_s - rec.t_s[0] >= skip_s]  # type: ignore[no-any-return]


def score_recording(
    raw: ImuRecording,
    filters: Sequence[str] = ("ours", "vqf"),
    rate_hz: float = RESAMPLE_RATE_HZ,
    with_timed: bool = False,
    skip_s: float = 0.0,
) -> dict[str, Score]:
    """Every named filter on the same resampled samples, one alignment, one truth.

    ``with_timed`` adds ``"ours_timed"``: our filter on the raw irregular samples and their
    time stamps, scored against the same alignment. Scoring starts at
    :func:`consistent_from_s` (or ``skip_s`` if later); every filter runs from the first sample.
    """
    align = fit_alignment(raw)
    skip_s = max(skip_s, consistent_from_s(raw, align))
    uni = resample_uniform(raw, rate_hz)
    out: dict[str, Score] = {}
    for name in filters:
        q, frame = run_filter(name, imu_series(uni))
        out[name] = Score.of(inclination_errors_rad(uni, align, q, frame, skip_s))
    if with_timed:
        q, frame = run_filter("ours_timed", imu_series(raw))
        out["ours_timed"] = Score.of(inclination_errors_rad(raw, align, q, frame, skip_s))
    return out


def score_xsens(speed: str, path: int, root: Path = LEIRIA_DIR) -> Score | None:
    """The XSENS unit's own orientation against the truth; alignment fitted on its output.

    The XSENS file carries no raw samples, so its mounting is fitted to its own output: the
    rotation that best maps its vertical onto the truth's (Wahba on the up vectors, with the
    robot base's vertical and the acquisition's lag as for the IMUs). This favours the XSENS
    figures slightly. The first :data:`XSENS_SKIP_S` are left out (the robot's start-up).
    """
    rec = load_leiria_xsens(speed, path, root)
    if rec is None or rec.reference_wxyz is None:
        return None
    truth = interpolate_quat(rec.t_s, truth_wxyz(rec), rec.t_s + TRUTH_LAG_S)
    # XSENS quaternions rotate sensor vectors into its z-up navigation frame
    up_est = up_sensor_from_quat(rec.reference_wxyz, "enu")
    up_tool = np.einsum("nji,j->ni", quat_to_rotmat(truth), ROBOT_UP_BASE)
    scored = rec.t_s - rec.t_s[0] >= XSENS_SKIP_S
    weight = scored.astype(float)
    for _ in range(5):
        mount = wahba(up_tool, up_est, weight)
        resid = angle_between_rad(up_est @ mount.T, up_tool)
        weight = (scored & (resid <= max(3.0 * float(np.median(resid[scored])),
                                         math.radians(2.0)))).astype(float)
    err = angle_between_rad(up_est, up_tool @ mount)
    return Score.of(err[scored])


XSENS_SKIP_S = 2.5
"""The robot's start-up glitches end within 2.4 s in every raw-IMU recording."""


@dataclass(frozen=True)
class SequenceResult:
    """One recording's scores, per filter, and whether it was held out of the tuning."""

    name: str
    held_out: bool
    scores: dict[str, Score]


def score_leiria(
    names: Sequence[str] | None = None,
    filters: Sequence[str] = ("ours", "vqf"),
    with_timed: bool = False,
    root: Path = LEIRIA_DIR,
) -> list[SequenceResult]:
    """:func:`score_recording` on every named recording of the subset (all by default)."""
    out = []
    for name in list_leiria(root) if names is None else names:
        raw = load_leiria(name, root)
        scores = score_recording(raw, filters, with_timed=with_timed, skip_s=raw.score_from_s)
        out.append(SequenceResult(name, raw.held_out, scores))
    return out


def mean_rmse_deg(results: Sequence[SequenceResult], filter_name: str) -> float:
    """Mean over recordings of the per-recording inclination RMSE (the headline figure)."""
    return float(np.mean([r.scores[filter_name].rmse_deg for r in results]))


PX4_SKIP_S = 5.0
"""PX4's EKF2 was converged when the log starts, the filters start from nothing: the first
seconds are left out of the agreement figures."""


def score_px4(
    filters: Sequence[str] = ("ours", "vqf"), path: Path = PX4_ULOG, with_timed: bool = False
) -> dict[str, Score]:
    """Inclination *agreement* of each filter with PX4's EKF2 on the same flight (not accuracy).

    The body frame is the flight controller's, so no mounting is fitted; every filter gets the
    log resampled onto its median sample period (:func:`resample_uniform`), ``ours_timed`` the
    samples as logged with their time stamps.
    """
    raw = load_px4_ulog(path)
    rate = 1.0 / float(np.median(np.diff(raw.t_s)))
    uni = resample_uniform(raw, rate)
    out: dict[str, Score] = {}
    runs: list[tuple[str, ImuRecording]] = [(n, uni) for n in filters]
    if with_timed:
        runs.append(("ours_timed", raw))
    for name, rec in runs:
        assert rec.reference_wxyz is not None
        q, frame = run_filter(name, imu_series(rec))
        err = angle_between_rad(up_sensor_from_quat(q, frame),
                                up_sensor_from_quat(rec.reference_wxyz, "ned"))
        out[name] = Score.of(err[rec.t_s - rec.t_s[0] >= PX4_SKIP_S])
    return out
