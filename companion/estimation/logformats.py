"""The estimator's log records (``estimator.bin``): format numbers, columns and encodings.

Separate from the thread that writes them, so the readers (the calibration command's
`calibration_from_log`, reports) use the same definitions without loading the thread, and the
calibration module does not import the thread that imports the filter that imports it.
"""

from __future__ import annotations

from typing import Any

__all__ = ["CAL_COLUMNS", "CAL_EVERY", "FMT_CAL", "FMT_GPS", "FMT_STATE", "GPS_COLUMNS",
           "STATE_COLUMNS", "define_estimator_logs"]

FMT_STATE = 1
FMT_GPS = 2
FMT_CAL = 3
CAL_EVERY = 10
"""GPS fusions between two calibration records (once a second with a 10 Hz receiver)."""
STATE_COLUMNS = ["roll_rad", "pitch_rad", "yaw_rad", "north_m", "east_m", "down_m",
                 "vn_m_s", "ve_m_s", "vd_m_s", "gbx_rad_s", "gby_rad_s", "gbz_rad_s",
                 "bax_m_s2", "bay_m_s2", "baz_m_s2", "std_n_m", "std_e_m", "std_d_m",
                 "std_vn_m_s", "std_ve_m_s", "std_vd_m_s", "std_roll_rad", "std_pitch_rad",
                 "std_yaw_rad", "faults", "aligned"]
GPS_COLUMNS = ["in_n_m", "in_e_m", "in_d_m", "in_vn_m_s", "in_ve_m_s", "in_vd_m_s", "nis",
               "accepted", "latency_s", "gps_lag_s", "gps_lag_std_s", "gyro_scale_x",
               "gyro_scale_y", "gyro_scale_z", "gyro_temp_x", "gyro_temp_y", "gyro_temp_z"]
"""Per fused fix: innovations, NIS, verdict, the whole latency applied, and the receiver delay
the filter estimates within it (with its 1-sigma), the gyro scale-factor errors it estimates
(the diagonal of ``EST_GS_STD``'s matrix; fractions, 0 when not estimated) and the gyro
bias's temperature coefficient it estimates (rad/s per degree C, 0 without ``EST_GB_TEMP``)."""
CAL_COLUMNS = ([f"gm_{r}{c}" for r in "xyz" for c in "xyz"]
               + [f"gm_std_{r}{c}" for r in "xyz" for c in "xyz"]
               + ["gt_x", "gt_y", "gt_z", "gt_std_x", "gt_std_y", "gt_std_z"])
"""What the filter has learnt of the gyro (`Eskf.gyro_calibration`): its matrix error and
temperature coefficient with their 1-sigma, so ``companion estimation calibration`` can hand
them to the next flight (companion.estimation.calibration)."""


def define_estimator_logs(tlog: Any) -> None:
    """Define the three record formats on the thread's log writer."""
    tlog.define(FMT_STATE, ",".join(["%.6f"] * 3 + ["%.3f"] * 6 + ["%.6f"] * 6
                                    + ["%.4f"] * 9) + ",%u,%hhu", STATE_COLUMNS)
    tlog.define(FMT_GPS, ",".join(["%.3f"] * 6) + ",%.3f,%hhu,%.3f,%.4f,%.4f,%.5f,%.5f,%.5f"
                + ",%.7f,%.7f,%.7f", GPS_COLUMNS)
    tlog.define(FMT_CAL, ",".join(["%.6f"] * 18 + ["%.8f"] * 6), CAL_COLUMNS)
