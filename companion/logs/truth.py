"""The truth log (``truth.bin``): what a simulator knows of the aircraft, for scoring estimates.

One layout whoever writes it: the JSBSim world (every column) or an autopilot's SITL through
its SIMSTATE (attitude, rates, specific force and position; NaN where the message carries
nothing), so the accuracy tools read either the same way.
"""

from __future__ import annotations

from typing import Any

__all__ = ["FMT_SURFACES", "FMT_TRUTH", "TRUTH_COLUMNS", "TRUTH_FORMAT", "define_truth_log"]

FMT_TRUTH = 1
FMT_SURFACES = 2
TRUTH_COLUMNS = ["roll_rad", "pitch_rad", "yaw_rad", "north_m", "east_m", "down_m",
                 "vn_m_s", "ve_m_s", "vd_m_s", "p_rad_s", "q_rad_s", "r_rad_s",
                 "ax_m_s2", "ay_m_s2", "az_m_s2", "lat_deg", "lon_deg", "alt_m",
                 "airspeed_m_s", "sim_time_s"]
TRUTH_FORMAT = ",".join(["%.6f"] * 15 + ["%.9lf", "%.9lf", "%.3f", "%.3f", "%.3lf"])


def define_truth_log(tlog: Any) -> None:
    """Format 1, the truth itself (format 2, the surfaces, is the JSBSim world's own)."""
    tlog.define(FMT_TRUTH, TRUTH_FORMAT, TRUTH_COLUMNS)
