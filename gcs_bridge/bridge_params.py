"""The bridge's own parameters (MAV_*): battery scaling, default stream rates, pacing.

Declared in the runtime's registry by `MavlinkBridge`; read where they act (status for the
batteries, streams for the rates, the link for download pacing and parameter bursts). Separate
from `runtime_view` because these are settings a user changes, not the runtime's handles.
"""

from __future__ import annotations

from companion.core.params import ParamSpec, float_param, int_param

BRIDGE_PARAMS: list[ParamSpec] = [
    float_param("MAV_B1_V_FULL", 8.4, 0.1, 100.0, "V",
                "Avionics battery voltage when the servo board reads 100 (full). The board's raw "
                "unit is unknown (thesis ch. 6), so voltage = raw / 100 x this."),
    float_param("MAV_B2_V_FULL", 5.6, 0.1, 100.0, "V",
                "Servo battery voltage when the servo board reads 100 (full)."),
    int_param("MAV_B_RAW_EMPTY", 80, 0, 99, "",
              "Raw battery reading taken as 0 % remaining (100 is full)."),
    int_param("MAV_B_LOW_PCT", 20, 0, 100, "%",
              "Below this remaining charge a battery is reported low and unhealthy."),
    int_param("MAV_PARAM_BURST", 20, 1, 500, "",
              "Parameters sent per sender cycle while answering a full parameter list."),
    *[float_param(name, hz, 0.0, 200.0, "Hz",
                  f"Default rate of {what} on every MAVLink link; 0 = off. A link's own "
                  "setting (e.g. `?ATTITUDE=10`) or SET_MESSAGE_INTERVAL overrides it for that "
                  "link; on a serial radio the schedule is fitted to MAV_RADIO_PCT of the line.")
      for name, hz, what in [
          ("MAV_ATT_HZ", 20.0, "ATTITUDE and ATTITUDE_QUATERNION (the HUD's attitude)"),
          ("MAV_POS_HZ", 5.0, "GLOBAL_POSITION_INT and LOCAL_POSITION_NED (the map)"),
          ("MAV_HUD_HZ", 5.0, "VFR_HUD"),
          ("MAV_GPS_HZ", 2.0, "GPS_RAW_INT"),
          ("MAV_STAT_HZ", 2.0, "SYS_STATUS, EXTENDED_SYS_STATE and BATTERY_STATUS"),
          ("MAV_IMU_HZ", 10.0, "HIGHRES_IMU"),
          ("MAV_RC_HZ", 4.0, "RC_CHANNELS and SERVO_OUTPUT_RAW"),
      ]],
    int_param("MAV_BULK_KB_S", 400, 1, 100_000, "kB/s",
              "Byte rate of log downloads and MAVLink FTP replies on a network link (1 kB = "
              "1000 bytes), so a download never crowds out telemetry; on a serial radio they "
              "get what the telemetry schedule leaves of the line instead."),
    int_param("MAV_RADIO_PCT", 50, 5, 90, "%",
              "Share of a serial link's byte rate (baud / 10) the default telemetry schedule "
              "may use; faster streams are slowed until it fits, and the rest of the line is "
              "left to answers, parameter lists and log downloads. Network links are not "
              "limited."),
]
