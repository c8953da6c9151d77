"""The autopilot link's parameters (``AP_*``): the rates it asks for, its clock map, which
autopilot it follows and how it commands one. Apart from the link so that the thread's module
holds what it does, and this one what a user can set."""

from __future__ import annotations

from companion.core.params import ParamSpec, int_param

__all__ = ["link_params"]


def link_params(prefix: str) -> list[ParamSpec]:
    """The link's parameters under `prefix` (the row's, ``AP``)."""
    def hz(suffix: str, default: int, what: str) -> ParamSpec:
        return int_param(f"{prefix}_{suffix}", default, 0, 400, "Hz",
                         f"Rate asked of the autopilot for {what} (SET_MESSAGE_INTERVAL); "
                         "0 asks nothing and takes what the autopilot already sends.")
    return [
        hz("IMU_HZ", 50, "its IMU (HIGHRES_IMU or RAW_IMU)"),
        hz("GPS_HZ", 5, "GPS_RAW_INT"),
        hz("ATT_HZ", 25, "ATTITUDE, its own attitude estimate"),
        hz("POS_HZ", 10, "GLOBAL_POSITION_INT, its own position estimate"),
        hz("RC_HZ", 10, "RC_CHANNELS and SERVO_OUTPUT_RAW"),
        hz("TIME_HZ", 1, "SYSTEM_TIME"),
        int_param(f"{prefix}_SYNC_MS", 1000, 100, 60_000, "ms",
                  "Period of the TIMESYNC round trips that map the autopilot's clock."),
        int_param(f"{prefix}_SYSID", 0, 0, 255, "",
                  "System id of the autopilot to follow; 0: the first one heard."),
        int_param(f"{prefix}_CMD_HZ", 25, 1, 100, "Hz",
                  "Most attitude targets a second sent to the autopilot in GUIDED "
                  "(SET_ATTITUDE_TARGET from the control law; ArduPlane holds each a few seconds)."),
        int_param(f"{prefix}_PX4_PRE", 1, 0, 1, "",
                  "PX4 only. 1: while the control law is on (CTL_MODE not 0) and PX4 is "
                  "not in OFFBOARD, stream its disengaged attitude (wings level, present "
                  "heading) so that the pilot or ground can switch to OFFBOARD, which PX4 "
                  "refuses without a setpoint stream; PX4 ignores them in other modes. "
                  "0: send only in OFFBOARD (the switch is then refused)."),
        int_param(f"{prefix}_DSTREAM", 1, 0, 1, "",
                  "1: when an ArduPilot refuses SET_MESSAGE_INTERVAL, ask with "
                  "REQUEST_DATA_STREAM instead, which sets that port's SRn_* stream rates "
                  "until the autopilot reboots (never saved; a NOTICE says so). 0: never."),
    ]
