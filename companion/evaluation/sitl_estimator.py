"""The project's estimator on a SITL recording, fed as the estimator thread feeds it.

:class:`EskfAsThread` is :class:`~companion.estimation.fusion.EstimatorCore` with the thread's
parameter defaults, and :func:`run_eskf` drives its one cycle tick by tick with the recording's
samples, fixes, temperature and (optionally) horizon and heading fixes, timing each step;
``tests/test_estimation_sitl.py`` checks it against the real thread sample by sample.
:func:`imu_series` hands the same samples to the IMU-only references
(:mod:`companion.estimation.imu_filters`). Separate from the recording (what was flown) and
from the scoring (how wrong it was).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from companion.estimation.calibration import GyroCalibration, calibration_from_row
from companion.estimation.fusion import EstimatorCore, HeadingFix
from companion.estimation.imu_filters import ImuSeries
from companion.estimation.params import estimator_param_defaults
from companion.estimation.quat import (
    FloatArray,
    quat_conjugate,
    quat_from_euler,
    quat_multiply,
    quat_to_rotvec,
)
from companion.evaluation.sitl import (
    IMU_DT_S,
    BoolArray,
    SitlRecording,
)
from companion.vehicle import VEHICLE

log = logging.getLogger(__name__)

ESTIMATOR_PARAM_PREFIX = VEHICLE["estimator"].task.param_prefix
"""The vehicle's estimator parameters' prefix (``EST``)."""
TEMPERATURE_EVERY = 100
"""IMU ticks between temperature readings (the IMU's slow block comes once a second)."""
NEES_EVERY = 10
"""IMU ticks between NEES samples (10 Hz is plenty for a slowly varying statistic)."""




class EskfAsThread(EstimatorCore):
    """:class:`EstimatorCore`, the code the estimator thread runs, with the thread's defaults.

    ``params`` overrides thread parameters by suffix (unknown names are refused);
    ``eskf_kwargs`` are added to the keyword arguments given to :class:`Eskf` (a tuning
    experiment, not a thread feature). :meth:`cycle` is one thread cycle.
    """

    def __init__(
        self,
        home_lla: tuple[float, float, float] | None,
        *,
        params: Mapping[str, float] | None = None,
        eskf_kwargs: Mapping[str, float] | None = None,
    ) -> None:
        defaults = estimator_param_defaults(ESTIMATOR_PARAM_PREFIX)
        given = dict(params or {})
        unknown = sorted(set(given) - set(defaults))
        if unknown:
            raise ValueError(
                f"EskfAsThread: unknown estimator parameter(s) {unknown}; known: {sorted(defaults)}"
            )
        super().__init__({**defaults, **given}, home_lla, eskf_kwargs=eskf_kwargs)


@dataclass(frozen=True)
class EskfOptions:
    """One way of running the project's estimator on a recording."""

    horizon: bool = False
    """Deliver the recording's horizon fixes to the estimator."""
    gps_outage_s: tuple[float, float] | None = None
    """GPS fixes handed off within [start, end) seconds are withheld (the receiver lost them)."""
    params: Mapping[str, float] = field(default_factory=dict)
    eskf_kwargs: Mapping[str, float] = field(default_factory=dict)
    check_pd_every: int = 1
    """IMU ticks between explicit Cholesky checks of the covariance (1: every sample)."""
    heading_std_rad: float = 0.0
    """With each GPS fix, also fuse a heading fix of the airframe: the true heading plus this
    much white noise (0: none). Stands for a heading sensor the simulated aircraft does not
    carry (a dual-antenna receiver, a calibrated magnetometer): what one would buy."""
    heading_bias_rad: float = 0.0
    """A constant error of those heading fixes (a magnetometer's declination or interference
    error, a dual-antenna baseline's mounting error), told to nobody."""
    measure_cpu: bool = False
    """Also take the thread CPU time of every step (``step_cpu_us``); the clock read costs
    tens of microseconds here, so only the timing study asks for it."""


@dataclass
class EskfRun:
    """Per-tick output of one estimator run (NaN before the filter started)."""

    quat: FloatArray
    pos_m: FloatArray
    vel_m_s: FloatArray
    gyro_bias_rad_s: FloatArray
    accel_bias_m_s2: FloatArray
    step_us: NDArray[np.float32]
    """Wall time of each cycle: predict, any updates and the state snapshot the thread
    publishes (NaN before the start)."""
    filter_us: NDArray[np.float32]
    """The same without the snapshot: the filter's own predict and updates."""
    step_cpu_us: NDArray[np.float32]
    """CPU time of this thread for the same work as ``step_us`` (NaN unless measured): on a
    shared machine the wall time also counts the time the scheduler gave to other processes."""
    update_tick: BoolArray
    """Ticks in which a GPS fix was fused (or tried)."""
    nees_t_s: FloatArray
    nees: FloatArray
    """Normalised estimation error squared over all 15 error states, every NEES_EVERY ticks."""
    nees_blocks: FloatArray
    """NEES of each 3-state block alone (position, velocity, attitude, gyro bias, accel bias)."""
    start_tick: int
    faults: int
    fault_reasons: list[str]
    pd_checks: int
    pd_failures: int
    non_finite: int
    """Ticks with a non-finite state value (should stay 0)."""
    exceptions: int
    """Exceptions out of the filter: each would have cost the thread a restart (should stay 0)."""
    gps_accepted: int
    gps_rejected: int
    horizon_used: int
    moving_start: bool
    gyro_matrix: FloatArray = field(default_factory=lambda: np.zeros((0, 9)))
    """The estimated gyro matrix error ``M`` (row-major) per tick, NaN before the start; once
    a second (every ``GYRO_MATRIX_EVERY`` ticks) after :func:`evaluate` compacts the run."""
    learnt: GyroCalibration | None = None
    """What the filter had learnt of the gyro at the end (None if it never ran): what
    ``companion estimation calibration`` would hand to the next flight."""


HEADING_SEED_OFFSET = 7919
"""The heading fixes' noise has its own stream, seeded from the flight's seed plus this."""
GYRO_MATRIX_EVERY = 100
"""Ticks between the gyro-matrix estimates a compacted run keeps (1 s at 100 Hz)."""


def _no_clock() -> int:
    return 0


def _pd(p: FloatArray, yaw_aligned: bool) -> bool:
    sub = p if yaw_aligned else np.delete(np.delete(p, 8, axis=0), 8, axis=1)
    try:
        np.linalg.cholesky(sub)
    except np.linalg.LinAlgError:
        return False
    return True


def _error_state(rec: SitlRecording, k: int, st_q: FloatArray, pos: FloatArray, vel: FloatArray,
                 bg: FloatArray, ba: FloatArray) -> FloatArray:
    """True minus estimated error state in the ESKF's convention (q_true = exp(dtheta) * q)."""
    dq = quat_multiply(rec.quat_true[k], quat_conjugate(st_q))
    return np.concatenate((rec.pos_true_m[k] - pos, rec.vel_true_m_s[k] - vel,
                           quat_to_rotvec(dq), rec.gyro_bias_true_rad_s[k] - bg,
                           rec.accel_bias_true_m_s2[k] - ba))


def run_eskf(rec: SitlRecording, options: EskfOptions | None = None) -> EskfRun:
    """Run the project's estimator over a recording, as the estimator thread would."""
    opts = options or EskfOptions()
    # the trims the flight's level calibration set, unless the options name their own
    est = EskfAsThread(rec.home_lla, params={**rec.level_trim, **opts.params},
                       eskf_kwargs=opts.eskf_kwargs)
    n = rec.ticks
    quat = np.full((n, 4), np.nan)
    pos = np.full((n, 3), np.nan)
    vel = np.full((n, 3), np.nan)
    bg = np.full((n, 3), np.nan)
    ba = np.full((n, 3), np.nan)
    gm = np.full((n, 9), np.nan)
    step_us = np.full(n, np.nan, dtype=np.float32)
    filter_us = np.full(n, np.nan, dtype=np.float32)
    step_cpu_us = np.full(n, np.nan, dtype=np.float32)
    update_tick = np.zeros(n, dtype=bool)
    nees_t: list[float] = []
    nees: list[float] = []
    blocks: list[FloatArray] = []
    start = -1
    pd_checks = pd_failures = non_finite = exceptions = 0
    outage = opts.gps_outage_s
    every = max(1, int(opts.check_pd_every))
    perf = time.perf_counter_ns
    cpu = time.thread_time_ns if opts.measure_cpu else _no_clock
    heading_rng = np.random.default_rng(rec.spec.seed + HEADING_SEED_OFFSET)
    for k in range(n):
        sample = rec.imu[k]
        fix = rec.gps.get(k)
        t = float(rec.t_s[k])
        if fix is not None and outage is not None and outage[0] <= t < outage[1]:
            fix = None
        hzn = rec.horizon.get(k) if opts.horizon else None
        samples = [sample] if sample is not None else []
        c0 = cpu()
        t0 = perf()
        try:
            temperature_c = None
            if k % TEMPERATURE_EVERY == 0 and len(rec.imu_temperature_c) > k:
                # the slow block's temperature, once a second at its 0.01 C resolution
                temperature_c = round(float(rec.imu_temperature_c[k]), 2)
            heading = None
            if opts.heading_std_rad > 0.0 and fix is not None and est.filter is not None:
                heading = HeadingFix(
                    float(rec.euler_true_rad[k, 2]) + opts.heading_bias_rad
                    + opts.heading_std_rad * float(heading_rng.standard_normal()),
                    opts.heading_std_rad)
            running = est.cycle(samples, fix, hzn, temperature_c=temperature_c, heading=heading)
            t1 = perf()
            f = est.filter
            st = f.state() if f is not None and running else None
        except Exception:  # the thread would crash and be restarted: count, never hide
            log.exception("estimator raised at t=%.2f s", t)
            exceptions += 1
            continue
        t2 = perf()
        c2 = cpu()
        if st is None or f is None:
            continue
        if start < 0:
            start = k
        else:
            step_us[k] = (t2 - t0) / 1e3
            filter_us[k] = (t1 - t0) / 1e3
            if opts.measure_cpu:
                step_cpu_us[k] = (c2 - c0) / 1e3
        update_tick[k] = fix is not None
        quat[k], pos[k], vel[k] = st.quaternion, st.pos_ned_m, st.vel_ned_m_s
        bg[k], ba[k] = st.gyro_bias_rad_s, st.accel_bias_m_s2
        gm[k] = st.gyro_matrix.reshape(-1)
        if not (np.isfinite(quat[k]).all() and np.isfinite(pos[k]).all()
                and np.isfinite(vel[k]).all()):
            non_finite += 1
        if k % every == 0 or fix is not None:
            pd_checks += 1
            # the 15 navigation states (marginal): the GPS delay has no truth to score here
            p = f.covariance[:15, :15]
            if not (np.isfinite(p).all() and _pd(p, st.yaw_aligned)):
                pd_failures += 1
                continue
            if k % NEES_EVERY == 0 and st.yaw_aligned:
                e = _error_state(rec, k, st.quaternion, st.pos_ned_m, st.vel_ned_m_s,
                                 st.gyro_bias_rad_s, st.accel_bias_m_s2)
                nees_t.append(t)
                nees.append(float(e @ np.linalg.solve(p, e)))
                blocks.append(np.array([
                    float(e[i:i + 3] @ np.linalg.solve(p[i:i + 3, i:i + 3], e[i:i + 3]))
                    for i in range(0, 15, 3)]))
    f = est.filter
    return EskfRun(
        quat=quat, pos_m=pos, vel_m_s=vel, gyro_bias_rad_s=bg, accel_bias_m_s2=ba,
        step_us=step_us, filter_us=filter_us,
        step_cpu_us=step_cpu_us, update_tick=update_tick,
        nees_t_s=np.array(nees_t), nees=np.array(nees),
        nees_blocks=np.array(blocks).reshape(-1, 5),
        start_tick=start,
        faults=f.faults if f is not None else 0,
        fault_reasons=[fl.reason for fl in f.fault_log] if f is not None else [],
        pd_checks=pd_checks, pd_failures=pd_failures, non_finite=non_finite,
        exceptions=exceptions, gps_accepted=est.gps_accepted, gps_rejected=est.gps_rejected,
        horizon_used=est.horizon_used, moving_start=est.moving_start, gyro_matrix=gm,
        learnt=(calibration_from_row([v for part in f.gyro_calibration() for v in part],
                                     float(rec.t_s[-1] - rec.t_s[max(start, 0)]))
                if f is not None and start >= 0 else None),
    )




def first_level_quat_zup(accel: FloatArray) -> FloatArray:
    """A z-up-frame quaternion that makes the first specific force read as 'up'."""
    a = accel[0] / np.linalg.norm(accel[0])
    roll = math.atan2(-a[1], -a[2])
    pitch = math.atan2(a[0], math.hypot(a[1], a[2]))
    q_ned = quat_from_euler(roll, pitch, 0.0)
    # body -> NED, then NED -> (north, west, up): a half turn about north
    return np.asarray(quat_multiply((0.0, 1.0, 0.0, 0.0), q_ned))



def imu_series(rec: SitlRecording) -> ImuSeries:
    """The decoded samples as the IMU-only filters take them (`run_filter`): at the IMU's
    rate, Madgwick started level with its yaw at zero."""
    gyro, accel = rec.imu_arrays()
    return ImuSeries(gyro, accel, IMU_DT_S, start_zup=first_level_quat_zup(accel))
