"""How wrong an estimate of a SITL recording was: errors against the truth, tick by tick.

Inclination (heading-free, so comparable across filters whatever their earth frame), heading,
velocity and horizontal position errors, the steady-turn ticks, and the growth of the errors
over a GPS outage. Separate from the runs: any estimate of a recording is scored the same way.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from companion.estimation.quat import (
    FloatArray,
    heading_error_rad,
    inclination_error_rad,
    quat_to_rotmat,
)
from companion.evaluation.sitl import (
    IMU_RATE_HZ,
    BoolArray,
    SitlRecording,
)
from companion.evaluation.sitl_estimator import EskfRun

log = logging.getLogger(__name__)

STEADY_TURN_BANK_RAD = math.radians(20.0)
STEADY_TURN_HOLD_S = 2.0


def inclination_error_zup_rad(q_zup: FloatArray, q_true_ned: FloatArray) -> FloatArray:
    """Tilt error of a z-up-frame estimate against the NED truth (heading-free)."""
    up_est = quat_to_rotmat(q_zup)[..., 2, :]
    down_true = quat_to_rotmat(q_true_ned)[..., 2, :]
    cos_a = np.sum(-up_est * down_true, axis=-1)
    sin_a = np.linalg.norm(np.cross(-up_est, down_true), axis=-1)
    return np.arctan2(sin_a, cos_a)




@dataclass
class FilterErrors:
    """Per-tick errors of one filter against the truth (NaN where it had no estimate)."""

    inclination_rad: FloatArray
    heading_rad: FloatArray | None = None
    vel_m_s: FloatArray | None = None
    """Norm of the 3-D velocity error."""
    hpos_m: FloatArray | None = None
    """Norm of the horizontal position error."""
    non_finite: int = 0


def filter_errors(rec: SitlRecording, quat: FloatArray, *, zup: bool = False,
                  run: EskfRun | None = None) -> FilterErrors:
    """Errors of an estimate against the recording's truth; ``run`` adds heading/vel/pos."""
    finite = np.isfinite(quat).all(axis=1)
    incl = np.full(rec.ticks, np.nan)
    if zup:
        incl[finite] = inclination_error_zup_rad(quat[finite], rec.quat_true[finite])
        started = np.ones(rec.ticks, dtype=bool)
    else:
        incl[finite] = inclination_error_rad(quat[finite], rec.quat_true[finite])
        started = np.arange(rec.ticks) >= (run.start_tick if run is not None and
                                          run.start_tick >= 0 else rec.ticks)
    non_finite = int(np.count_nonzero(started & ~finite))
    if run is None:
        return FilterErrors(incl, non_finite=non_finite)
    heading = np.full(rec.ticks, np.nan)
    heading[finite] = heading_error_rad(quat[finite], rec.quat_true[finite])
    vel = np.linalg.norm(run.vel_m_s - rec.vel_true_m_s, axis=1)
    hpos = np.linalg.norm(run.pos_m[:, :2] - rec.pos_true_m[:, :2], axis=1)
    return FilterErrors(incl, heading, vel, hpos, non_finite)


def steady_turn_mask(rec: SitlRecording, bank_rad: float = STEADY_TURN_BANK_RAD,
                     hold_s: float = STEADY_TURN_HOLD_S) -> BoolArray:
    """Ticks where the true bank has stayed beyond ``bank_rad`` for the last ``hold_s``."""
    banked = np.abs(rec.euler_true_rad[:, 0]) > bank_rad
    window = max(1, int(round(hold_s * IMU_RATE_HZ)))
    unbanked = np.concatenate(([0], np.cumsum(~banked)))
    k = np.arange(rec.ticks)
    lo = np.maximum(k + 1 - window, 0)
    held = (unbanked[k + 1] - unbanked[lo]) == 0
    return banked & held & (k + 1 >= window)


@dataclass(frozen=True)
class OutageGrowth:
    """How far the estimate drifted during a GPS outage (errors at its end and worst within)."""

    before_incl_deg: float
    end_incl_deg: float
    max_incl_deg: float
    before_heading_deg: float
    end_heading_deg: float
    before_vel_m_s: float
    end_vel_m_s: float
    before_hpos_m: float
    end_hpos_m: float
    max_hpos_m: float
    recovered_hpos_m: float
    """Horizontal position error 10 s after the outage ended."""


def outage_growth(rec: SitlRecording, err: FilterErrors, window_s: tuple[float, float],
                  before_s: float = 5.0) -> OutageGrowth:
    """Errors just before (mean over ``before_s``), at the end of and within an outage."""
    if err.heading_rad is None or err.vel_m_s is None or err.hpos_m is None:
        raise ValueError("outage_growth needs the errors of a navigation filter (run=...)")
    t = rec.t_s
    t0, t1 = window_s
    before = (t >= t0 - before_s) & (t < t0)
    inside = (t >= t0) & (t < t1)
    if not before.any() or not inside.any():
        raise ValueError(f"outage window {window_s} is not inside the recording (0..{t[-1]:.1f} s)")
    end = int(np.nonzero(inside)[0][-1])
    after = min(int(np.searchsorted(t, t1 + 10.0)), len(t) - 1)
    deg = math.degrees

    def mean(x: FloatArray) -> float:
        return float(np.nanmean(np.abs(x[before])))

    return OutageGrowth(
        before_incl_deg=deg(mean(err.inclination_rad)),
        end_incl_deg=deg(float(err.inclination_rad[end])),
        max_incl_deg=deg(float(np.nanmax(err.inclination_rad[inside]))),
        before_heading_deg=deg(mean(err.heading_rad)),
        end_heading_deg=deg(abs(float(err.heading_rad[end]))),
        before_vel_m_s=mean(err.vel_m_s),
        end_vel_m_s=float(err.vel_m_s[end]),
        before_hpos_m=mean(err.hpos_m),
        end_hpos_m=float(err.hpos_m[end]),
        max_hpos_m=float(np.nanmax(err.hpos_m[inside])),
        recovered_hpos_m=float(err.hpos_m[after]),
    )
