"""IMU-only attitude filters by name: ours, VQF and Madgwick, for every evaluation.

One registry (shaped like ``horizon.detector``'s) that the SITL evaluation and the real-data
evaluation both run their comparisons through, so a filter is wired once: adding one is one
function and one table row. The third-party filters (``vqf``, ``ahrs``) are imported when first
run, not when the registry is, so neither the flight nor a tool that never runs them pays for
them.

Every filter gets the same samples (`ImuSeries`) and returns its attitudes with their frame:
``"ned"`` (the project's convention, body to NED) or ``"enu"`` (a z-up earth frame with an
arbitrary heading, in which only the inclination means anything).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from companion.estimation.quat import FloatArray

__all__ = ["ALIASES", "DEFAULT_FILTER", "FILTERS", "FilterRun", "ImuSeries", "filter_names",
           "level_start_zup", "resolve", "run_filter", "to_ned"]


@dataclass(frozen=True)
class ImuSeries:
    """The samples a filter runs on."""

    gyro_rad_s: FloatArray
    """(N, 3) body rates, rad/s."""
    accel_m_s2: FloatArray
    """(N, 3) specific force, m/s^2."""
    dt_s: float
    """The sample period a fixed-rate filter takes (the series' rate is ``1 / dt_s``)."""
    t_s: FloatArray | None = None
    """The samples' own time stamps, for a filter that follows them (``ours_timed``)."""
    start_zup: FloatArray | None = None
    """Where a z-up filter that needs a start (Madgwick) starts; None: `level_start_zup` of
    the first accelerometer sample."""


FilterRun = Callable[[ImuSeries], tuple[FloatArray, str]]
"""A filter run: samples in, (N, 4) attitudes (w, x, y, z) and their frame out."""


def level_start_zup(accel_m_s2: FloatArray) -> FloatArray:
    """The z-up quaternion that levels a sample: the smallest rotation of the body's measured
    up onto (0, 0, 1)."""
    a0 = accel_m_s2 / np.linalg.norm(accel_m_s2)
    axis = np.cross(a0, (0.0, 0.0, 1.0))
    ang = math.atan2(float(np.linalg.norm(axis)), float(a0[2]))
    n = float(np.linalg.norm(axis))
    return (np.array((1.0, 0.0, 0.0, 0.0)) if n < 1e-9
            else np.concatenate(([math.cos(ang / 2)], math.sin(ang / 2) * axis / n)))


def run_ours(imu: ImuSeries) -> tuple[FloatArray, str]:
    """The project's filter (`estimate_attitude`), defaults, at the series' fixed rate."""
    from companion.estimation.attitude import estimate_attitude

    return estimate_attitude(imu.gyro_rad_s, imu.accel_m_s2, 1.0 / imu.dt_s), "ned"


def run_ours_timed(imu: ImuSeries) -> tuple[FloatArray, str]:
    """The project's filter, defaults, on the samples' own time stamps (per-sample dt)."""
    from companion.estimation.attitude import estimate_attitude

    if imu.t_s is None:
        raise ValueError("ours_timed needs the samples' time stamps (ImuSeries.t_s)")
    return estimate_attitude(imu.gyro_rad_s, imu.accel_m_s2, 1.0 / imu.dt_s, t_s=imu.t_s), "ned"


def run_vqf(imu: ImuSeries) -> tuple[FloatArray, str]:
    """VQF 6-D (the ``vqf`` package, default parameters) with its fixed sample period."""
    from vqf import VQF

    filt = VQF(imu.dt_s)
    out = filt.updateBatch(np.ascontiguousarray(imu.gyro_rad_s),
                           np.ascontiguousarray(imu.accel_m_s2))
    return np.asarray(out["quat6D"], dtype=float), "enu"


def run_madgwick(imu: ImuSeries) -> tuple[FloatArray, str]:
    """Madgwick (``ahrs``), IMU only, default gain, started level (`ImuSeries.start_zup`)."""
    from ahrs.filters import Madgwick

    filt = Madgwick(frequency=1.0 / imu.dt_s)
    q = imu.start_zup if imu.start_zup is not None else level_start_zup(imu.accel_m_s2[0])
    n = len(imu.gyro_rad_s)
    out = np.empty((n, 4))
    for k in range(n):
        q = filt.updateIMU(q, imu.gyro_rad_s[k], imu.accel_m_s2[k])
        out[k] = q
    return out, "enu"


FILTERS: dict[str, FilterRun] = {
    "ours": run_ours,
    "ours_timed": run_ours_timed,
    "vqf": run_vqf,
    "madgwick": run_madgwick,
}
ALIASES: dict[str, str] = {"attitude": "ours"}
"""The SITL evaluation's name for ours (its figures are keyed by it)."""

DEFAULT_FILTER = "vqf"
"""The IMU-only filter every IMU-only use runs unless told otherwise (the replay's fallback when
a log has no usable GPS): VQF, because on the real recordings with truth it is as good as ours
or better (docs/estimation.md, "Which IMU-only filter"), and it is a maintained library rather
than code of ours to keep tuned. Ours stays selectable by name."""


def resolve(name: str) -> str:
    """The registered name behind ``name`` (an alias or a name); ValueError when unknown."""
    real = ALIASES.get(name, name)
    if real not in FILTERS:
        raise ValueError(
            f"unknown IMU-only filter {name!r}; choose from {', '.join(filter_names())}")
    return real


_X_PI = np.array((0.0, 1.0, 0.0, 0.0))
"""Half a turn about x: takes a z-up earth frame (x east-ish, y north-ish) to a z-down one."""


def to_ned(q_wxyz: FloatArray, frame: str) -> FloatArray:
    """Attitudes of either frame as body-to-NED quaternions (heading still arbitrary for a
    z-up filter: only roll, pitch and heading changes mean anything).

    A z-up filter fed FRD samples aligns the body's measured up (-z body, level and still)
    with its earth +z, so turning its earth frame half a turn about x makes it z-down (NED
    with some heading) without touching the body side.
    """
    from companion.estimation.quat import quat_multiply

    q = np.asarray(q_wxyz, dtype=float)
    if frame == "ned":
        return q
    if frame != "enu":
        raise ValueError(f"frame must be 'ned' or 'enu', got {frame!r}")
    out = quat_multiply(np.broadcast_to(_X_PI, q.shape), q)
    return np.asarray(out, dtype=float)


def filter_names() -> list[str]:
    """Registered names followed by their aliases, for help texts and argument choices."""
    return [*FILTERS, *ALIASES]


def run_filter(name: str, imu: ImuSeries) -> tuple[FloatArray, str]:
    """Run the filter ``name`` (a name from :data:`FILTERS` or an alias) on ``imu``."""
    return FILTERS[resolve(name)](imu)
