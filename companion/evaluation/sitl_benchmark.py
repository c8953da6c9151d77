"""One SITL benchmark job: fly a flight, run every estimator variant and reference, score them.

:func:`evaluate` returns a :class:`RunResult` compact enough to pass between processes (the
benchmarks run many in parallel). Separate from the pieces it strings together.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.estimation.imu_filters import run_filter
from companion.estimation.quat import FloatArray
from companion.evaluation.sitl import (
    GPS_EVERY,
    BoolArray,
    FlightSpec,
    record_flight,
)
from companion.evaluation.sitl_estimator import (
    GYRO_MATRIX_EVERY,
    EskfOptions,
    EskfRun,
    imu_series,
    run_eskf,
)
from companion.evaluation.sitl_scoring import (
    FilterErrors,
    OutageGrowth,
    filter_errors,
    outage_growth,
    steady_turn_mask,
)

log = logging.getLogger(__name__)

IMU_ONLY_FILTERS = ("attitude", "vqf", "madgwick")
"""IMU-only references: the project's `estimate_attitude`, VQF 6-D and Madgwick, all defaults."""


@dataclass
class RunResult:
    """Everything a benchmark needs from one recording, compact enough to pass between processes.

    Error series are float32 (the pooled statistics do not need more) and keyed by filter name:
    ``vqf`` and ``madgwick`` for the IMU-only references, the :func:`evaluate` variant names for
    the project's estimator.
    """

    spec: FlightSpec
    trim_method: str
    t_s: NDArray[np.float32]
    bank_rad: NDArray[np.float32]
    steady_turn: BoolArray
    gps_error_h_m: NDArray[np.float32]
    """(M, 2): validity time (s) and horizontal error (m) of every GPS fix, the floor under any
    GPS/INS position error (the simulated receiver's error wanders like a real one's)."""
    errors: dict[str, FilterErrors]
    eskf: dict[str, EskfRun]
    outage: dict[str, OutageGrowth]
    elapsed_s: float
    camera: dict[str, Any] | None = None
    """The camera's figures when the horizon fixes came from the detector."""
    gyro_matrix_true: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))
    """The simulated gyro's matrix error in the estimator's axes
    (:attr:`SitlRecording.gyro_matrix_trimmed`)."""


def _compact(run: EskfRun) -> EskfRun:
    """Drop the per-tick state arrays (errors keep what matters) before pickling."""
    empty = np.zeros((0, 3))
    return EskfRun(
        quat=np.zeros((0, 4)), pos_m=empty, vel_m_s=empty, gyro_bias_rad_s=empty,
        accel_bias_m_s2=empty, step_us=run.step_us, filter_us=run.filter_us,
        step_cpu_us=run.step_cpu_us, update_tick=run.update_tick,
        nees_t_s=run.nees_t_s, nees=run.nees, nees_blocks=run.nees_blocks,
        start_tick=run.start_tick, faults=run.faults, fault_reasons=run.fault_reasons,
        pd_checks=run.pd_checks, pd_failures=run.pd_failures, non_finite=run.non_finite,
        exceptions=run.exceptions, gps_accepted=run.gps_accepted, gps_rejected=run.gps_rejected,
        horizon_used=run.horizon_used, moving_start=run.moving_start,
        gyro_matrix=run.gyro_matrix[::GYRO_MATRIX_EVERY].copy(), learnt=run.learnt)


def _f32(errors: FilterErrors) -> FilterErrors:
    def c(x: FloatArray | None) -> FloatArray | None:
        return None if x is None else x.astype(np.float32)  # type: ignore[return-value]

    return FilterErrors(c(errors.inclination_rad), c(errors.heading_rad),  # type: ignore[arg-type]
                        c(errors.vel_m_s), c(errors.hpos_m), errors.non_finite)


def evaluate(
    spec: FlightSpec,
    variants: Mapping[str, EskfOptions] | None = None,
    imu_only: Sequence[str] = IMU_ONLY_FILTERS,
    compact: bool = True,
) -> RunResult:
    """Fly ``spec`` once and score every estimator variant and IMU-only reference on it.

    ``variants`` maps a name to :class:`EskfOptions` (default: ``{"eskf": EskfOptions()}``);
    a variant with a GPS outage also gets its :class:`OutageGrowth`. ``compact`` drops the
    per-tick estimates and keeps the error series (what a multi-process benchmark sends back).
    """
    t0 = time.perf_counter()
    chosen = dict(variants) if variants is not None else {"eskf": EskfOptions()}
    unknown = sorted(set(imu_only) - set(IMU_ONLY_FILTERS))
    if unknown:
        raise ValueError(f"evaluate: unknown IMU-only filter(s) {unknown}; "
                         f"use {', '.join(IMU_ONLY_FILTERS)}")
    rec = record_flight(spec)
    errors: dict[str, FilterErrors] = {}
    runs: dict[str, EskfRun] = {}
    outage: dict[str, OutageGrowth] = {}
    for name, opts in chosen.items():
        run = run_eskf(rec, opts)
        err = filter_errors(rec, run.quat, run=run)
        if opts.gps_outage_s is not None:
            outage[name] = outage_growth(rec, err, opts.gps_outage_s)
        errors[name] = _f32(err) if compact else err
        runs[name] = _compact(run) if compact else run
    if imu_only:
        series = imu_series(rec)
        for name in IMU_ONLY_FILTERS:
            if name in imu_only:
                quat, frame = run_filter(name, series)
                err = filter_errors(rec, quat, zup=frame == "enu")
                errors[name] = _f32(err) if compact else err
    gps_h = np.linalg.norm(rec.gps_error_ned_m[:, :2], axis=1)
    return RunResult(
        spec=spec,
        trim_method=rec.trim_method,
        t_s=rec.t_s.astype(np.float32),
        bank_rad=rec.euler_true_rad[:, 0].astype(np.float32),
        steady_turn=steady_turn_mask(rec),
        gps_error_h_m=np.concatenate((rec.t_s[GPS_EVERY - 1::GPS_EVERY][:len(gps_h)][:, None],
                                      gps_h[:, None]), axis=1).astype(np.float32),
        errors=errors,
        eskf=runs,
        outage=outage,
        elapsed_s=time.perf_counter() - t0,
        camera=rec.camera,
        gyro_matrix_true=rec.gyro_matrix_trimmed,
    )
