"""What every part of the bridge shares: the runtime, the vehicle's ids, time, parameters.

`BridgeCore` is read by the receive and send threads of every link; it holds no per-link
state and nothing in it changes after construction except through the runtime's own
thread-safe objects (parameter registry, slots, manager).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

from companion.core.params import ParamSpec, float_param, int_param
from companion.watchdog import RuntimeContext, ThreadManager
from gcs_bridge.dialect import COMPONENT_ID

UINT16_MAX = 0xFFFF
INT16_MAX = 0x7FFF

#: Thread ids of the runtime's data sources (the legacy protocol's contract).
THREAD_IMU, THREAD_GPS, THREAD_SERVO, THREAD_ESTIMATOR, THREAD_CONTROL = 1, 2, 3, 4, 5

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


def clamp_int(value: float | int | None, lo: int, hi: int, missing: int) -> int:
    """An integer field value: `missing` for None/NaN, else rounded and clamped to [lo, hi]."""
    if value is None:
        return missing
    v = float(value)
    if math.isnan(v):
        return missing
    if math.isinf(v):
        return hi if v > 0 else lo
    return max(lo, min(hi, int(round(v))))


def nan_if_none(value: float | None) -> float:
    return float("nan") if value is None else float(value)


@dataclass
class BridgeCore:
    ctx: RuntimeContext
    manager: ThreadManager
    compid: int = COMPONENT_ID
    boot_real_ns: int = 0
    boot_mono_ns: int = 0
    _cpu: tuple[float, float] = field(default=(0.0, 0.0))

    def __post_init__(self) -> None:
        self.boot_real_ns = self.ctx.clock.realtime_ns()
        self.boot_mono_ns = self.ctx.clock.monotonic_ns()
        self._cpu = (time.process_time(), time.monotonic())

    @property
    def sysid(self) -> int:
        return int(self.ctx.vehicle_id)

    def now_real_ns(self) -> int:
        return self.ctx.clock.realtime_ns()

    def time_boot_ms(self, real_ns: int | None = None) -> int:
        """Milliseconds since the bridge started (MAVLink's "boot"), wrapped to uint32."""
        t = self.now_real_ns() if real_ns is None else real_ns
        return max(0, (t - self.boot_real_ns) // 1_000_000) & 0xFFFFFFFF

    def time_usec(self, real_ns: int | None = None) -> int:
        """Unix time in microseconds (MAVLink accepts epoch time in time_usec fields)."""
        t = self.now_real_ns() if real_ns is None else real_ns
        return max(0, t // 1000)

    def thread_message_ms(self, thread_id: int) -> int | None:
        """The message period of a runtime thread, None when the thread does not exist."""
        t = self.manager.find(thread_id)
        if t is None:
            return None
        try:
            return int(t.message_ms)
        except Exception:  # a thread whose parameters are not declared yet
            return None

    def cpu_load_permille(self) -> int:
        """Process CPU use since the last call, in tenths of a percent of one core."""
        cpu, wall = time.process_time(), time.monotonic()
        cpu0, wall0 = self._cpu
        self._cpu = (cpu, wall)
        if wall - wall0 <= 0:
            return 0
        return clamp_int(1000.0 * (cpu - cpu0) / (wall - wall0), 0, 1000, 0)
