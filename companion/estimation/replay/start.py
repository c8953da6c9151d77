"""Starting the GPS/INS filter on a replayed log, and saying exactly why when it cannot.

The flight's initial phase (`EstimatorCore.initial_phase`) averages `INIT_S` of IMU samples to
level the attitude and waits for a GPS fix. On the aircraft the IMU and the GPS start together;
a log does not: its first fix may come minutes after its first IMU sample, and the vehicle may
be flying, vibrating on its motors or being thrown by then. So a replay

* feeds the core from `INIT_S` before the first usable fix, so the accelerometer average it
  levels with ends at the fix whose position and velocity start the navigation state (the
  samples before are not lost to the comparison: there is no estimate to compare before a fix);
* starts again from the next `INIT_S` window when the core refuses a start (the accelerometer's
  mean is not about 1 g, as in a hand launch or a hard manoeuvre), as often as it takes, and
  lists every refusal with its time;
* can take the starting heading from the log's own attitude (`heading_from`) when the GPS
  course cannot give one (a copter that never flies 5 m/s). The default is the flight's: the
  heading waits for the GPS course, so the yaw compared afterwards is our own.

`StartReport` says which of these happened, with times in seconds from the first IMU sample.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

GRAVITY_M_S2 = 9.80665


@dataclass
class StartReport:
    """How the ESKF started on a replay, or why it did not (times: s from the first IMU
    sample)."""

    imu_span_s: tuple[float, float] | None = None
    gps_span_s: tuple[float, float] | None = None
    first_fix_s: float | None = None
    fed_from_s: float | None = None
    started_at_s: float | None = None
    refusals: list[tuple[float, float]] = field(default_factory=list)  # (at s, |accel| m/s^2)
    restarts: list[tuple[float, float]] = field(default_factory=list)  # (gap at s, length s)
    heading_from: str = "gps"
    heading_start_deg: float | None = None
    reason: str = ""  # empty when it started

    def as_dict(self) -> dict[str, Any]:
        def r(x: float | None) -> float | None:
            return None if x is None else round(x, 3)

        return {
            "imu_span_s": None if self.imu_span_s is None else [r(x) for x in self.imu_span_s],
            "gps_span_s": None if self.gps_span_s is None else [r(x) for x in self.gps_span_s],
            "first_fix_s": r(self.first_fix_s), "fed_from_s": r(self.fed_from_s),
            "started_at_s": r(self.started_at_s),
            "refusals": [{"at_s": r(a), "accel_norm_m_s2": round(g, 3)}
                         for a, g in self.refusals[:20]],
            "refusal_count": len(self.refusals),
            "restarts_after_gaps": [{"gap_at_s": r(a), "gap_s": r(g)}
                                    for a, g in self.restarts[:20]],
            "heading_from": self.heading_from,
            "heading_start_deg": r(self.heading_start_deg), "reason": self.reason or None}


def why_no_fix(imu_t_us: IntArray, gps_t_us: IntArray | None, fix_t_us: list[int],
               offered: int, t0_us: int) -> str:
    """Why there is no fix to start from, with the times that show it (empty: there is one
    inside the IMU's span)."""
    def s(t: float) -> str:
        return f"{(t - t0_us) / 1e6:.1f} s"

    if gps_t_us is None or not len(gps_t_us):
        return "the log has no GPS messages"
    if not offered:
        return (f"none of its {len(gps_t_us)} GPS messages ({s(gps_t_us[0])} to "
                f"{s(gps_t_us[-1])}) has a 3-D fix with a position")
    inside = [t for t in fix_t_us if imu_t_us[0] <= t <= imu_t_us[-1]]
    if not inside:
        return (f"its {offered} GPS fixes ({s(fix_t_us[0])} to {s(fix_t_us[-1])}) all lie "
                f"outside the IMU's samples ({s(imu_t_us[0])} to {s(imu_t_us[-1])}): the "
                "two clocks do not match")
    return ""


def first_fed_index(t_us: IntArray, first_fix_us: int, init_s: float) -> int:
    """The first IMU sample the core gets: `init_s` before the first fix (or the first)."""
    return int(np.searchsorted(t_us, first_fix_us - int(init_s * 1e6), side="left"))


def heading_lookup(ref_t_us: IntArray, yaw_rad: FloatArray
                   ) -> Callable[[int], float | None]:
    """The reference's yaw nearest a time (ns), None when none is within 0.5 s."""
    def at(t_ns: int) -> float | None:
        if not len(ref_t_us):
            return None
        t = t_ns // 1000
        j = int(np.clip(np.searchsorted(ref_t_us, t), 0, len(ref_t_us) - 1))
        if j > 0 and abs(ref_t_us[j - 1] - t) < abs(ref_t_us[j] - t):
            j -= 1
        if abs(int(ref_t_us[j]) - t) > 500_000 or not math.isfinite(float(yaw_rad[j])):
            return None
        return float(yaw_rad[j])

    return at


def refused_accel_norm(accel: FloatArray, t_us: IntArray, end_us: int, init_s: float) -> float:
    """The mean specific force's norm over the `init_s` before `end_us` (what a refused start
    averaged)."""
    lo = int(np.searchsorted(t_us, end_us - int(init_s * 1e6), side="left"))
    hi = int(np.searchsorted(t_us, end_us, side="right"))
    if hi <= lo:
        return math.nan
    return float(np.linalg.norm(accel[lo:hi].mean(axis=0)))
