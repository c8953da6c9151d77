"""An autopilot's MAVLink messages as the runtime's samples: SI units, the runtime's clock.

The only place an autopilot's scaling is undone. ArduPilot sends RAW_IMU and SCALED_IMU(2/3)
already scaled (milli-g and milli-rad/s, with the sensor's own temperature in centi-degrees);
PX4's RAW_IMU carries raw sensor counts whose scale it does not send, so on PX4 only
HIGHRES_IMU (SI floats) and SCALED_IMU* are used. MAVLink's body frame is forward-right-down,
as the runtime's, and an accelerometer's reading is the specific force (about -9.8 m/s^2 on z at
rest), as `ImuSample` carries it.

An autopilot's IMU has no frame counter of fixed period, so its samples say so
(`counter_period_s = 0`) and the estimator integrates over the differences of their times.

Each converter takes the message and the runtime time at which it was measured (mapped from the
message's own stamp by `ClockSync`) and returns a frozen sample, or None when the message says
it has nothing (a GPS without a fix still gives a `GpsFix` with `fix = 0`; a HIGHRES_IMU whose
`fields_updated` lacks the gyro or accelerometer gives None).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from companion.core.fastinit import fast_frozen
from companion.core.state import GpsFix, ImuSample, ServoState
from companion.drivers.servo_protocol import CH_THROTTLE, us_to_throttle

__all__ = ["AutopilotEstimate", "BatterySample", "Firmware", "euler_from_quat",
           "quat_from_euler_wxyz", "IMU_MESSAGES", "TruthSample", "gps_fix",
           "imu_sample", "message_time_ns", "servo_state", "truth_sample"]

G_M_S2 = 9.80665
"""ArduPilot's GRAVITY_MSS: RAW_IMU's milli-g are of this g."""
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12


class Firmware:
    """What the HEARTBEAT's `autopilot` field says, as a word for logs and people."""

    ARDUPILOT = "ardupilot"
    PX4 = "px4"
    OTHER = "other"

    @staticmethod
    def of(autopilot: int) -> str:
        if autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
            return Firmware.ARDUPILOT
        if autopilot == MAV_AUTOPILOT_PX4:
            return Firmware.PX4
        return Firmware.OTHER


IMU_MESSAGES = ("HIGHRES_IMU", "RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3")
"""In order of preference: the first that arrives at all is the one the IMU slot gets, so two
instances never interleave in the estimator's stream."""

_HIGHRES_GYRO_ACC = 0b111111  # fields_updated: xacc..zacc, xgyro..zgyro


def message_time_ns(msg: Any) -> int | None:
    """The autopilot's own time stamp of `msg` in ns since its boot, or None (no stamp, or a
    GPS time of week / UNIX time that is not the boot clock)."""
    boot_ms = getattr(msg, "time_boot_ms", None)
    if boot_ms is not None:
        return int(boot_ms) * 1_000_000
    usec = getattr(msg, "time_usec", None)
    # a time_usec may be either clock (MAVLink allows both): below 10^14 us (three years of
    # uptime) it is the boot clock (ArduPilot's GPS_RAW_INT: the fix's own time), above it UNIX
    # time, which `AutopilotLink` maps through SYSTEM_TIME
    if usec is not None and 0 < usec < 10**14:
        return int(usec) * 1000
    return None


def imu_sample(msg: Any, firmware: str, t_ns: int, counter: int) -> ImuSample | None:
    """The IMU message `msg` as a sample, or None when it cannot be one on this firmware."""
    kind = msg.get_type()
    if kind == "HIGHRES_IMU":
        if msg.fields_updated & _HIGHRES_GYRO_ACC != _HIGHRES_GYRO_ACC:
            return None
        return ImuSample(t_ns, counter & 0xFF, (msg.xgyro, msg.ygyro, msg.zgyro),
                         (msg.xacc, msg.yacc, msg.zacc), counter_period_s=0.0)
    if kind == "RAW_IMU" and firmware == Firmware.PX4:
        return None  # raw counts: PX4 does not send their scale
    if kind in IMU_MESSAGES:
        acc = G_M_S2 / 1000.0
        return ImuSample(t_ns, counter & 0xFF,
                         (msg.xgyro / 1000.0, msg.ygyro / 1000.0, msg.zgyro / 1000.0),
                         (msg.xacc * acc, msg.yacc * acc, msg.zacc * acc), counter_period_s=0.0)
    return None


def imu_temperature_c(msg: Any) -> float | None:
    """The IMU's temperature in a RAW/SCALED_IMU (centi-degrees, 0 = not sent) or HIGHRES_IMU."""
    if msg.get_type() == "HIGHRES_IMU":
        return float(msg.temperature)
    temp = getattr(msg, "temperature", 0)
    return temp / 100.0 if temp else None


# GPS_FIX_TYPE -> GpsFix.fix (0 none, 1 GPS, 2 DGPS, 3 RTK); a 2-D fix is no position the
# estimator can use, so it is no fix here
_FIX = {0: 0, 1: 0, 2: 0, 3: 1, 4: 2, 5: 3, 6: 3, 7: 1, 8: 1}


def gps_fix(msg: Any, t_ns: int) -> GpsFix:
    """GPS_RAW_INT or GPS2_RAW as a fix. Unknown values (UINT16_MAX, zero accuracies) are None;
    velocity north/east comes from ground speed and course, down is not sent."""
    fix = _FIX.get(int(msg.fix_type), 0)
    eph = None if msg.eph == 0xFFFF else msg.eph / 100.0
    epv = None if msg.epv == 0xFFFF else msg.epv / 100.0
    speed = None if msg.vel == 0xFFFF else msg.vel / 100.0
    course = None if msg.cog == 0xFFFF else msg.cog / 100.0
    vn = ve = None
    if speed is not None and course is not None:
        vn = speed * math.cos(math.radians(course))
        ve = speed * math.sin(math.radians(course))
    h_acc = getattr(msg, "h_acc", 0)
    v_acc = getattr(msg, "v_acc", 0)
    usec = int(getattr(msg, "time_usec", 0))
    utc = (usec / 1e6) % 86400.0 if usec > 10**15 else None  # UNIX time, not boot time
    sats = None if msg.satellites_visible == 255 else int(msg.satellites_visible)
    has_position = fix > 0 or (msg.lat != 0 or msg.lon != 0)
    return GpsFix(
        t_ns=t_ns, utc_s=utc,
        lat_deg=msg.lat / 1e7 if has_position else None,
        lon_deg=msg.lon / 1e7 if has_position else None,
        alt_m=msg.alt / 1000.0 if has_position else None,
        fix=fix, sats=sats, hdop=eph, vdop=epv, speed_m_s=speed, course_deg=course,
        vn_m_s=vn, ve_m_s=ve, vd_m_s=None,
        alt_std_m=v_acc / 1000.0 if v_acc else None,
        h_std_m=h_acc / 1000.0 if h_acc else None)


def servo_state(rc: Any | None, outputs: Any | None, t_ns: int, seq: int, guided: bool,
                throttle_channel: int = CH_THROTTLE) -> ServoState:
    """RC_CHANNELS (the pilot's sticks, us) and SERVO_OUTPUT_RAW (what the autopilot drives,
    us) as one exchange; `guided`: the autopilot is in the mode the companion flies in (what
    the control law engages on, as the thesis aircraft's mode switch). `pilot_throttle` is the
    throttle the aircraft flies at when the law engages: the autopilot's throttle output."""
    pilot = tuple(int(getattr(rc, f"chan{i}_raw", 0)) for i in range(1, 9)) if rc else (0,) * 8
    computer = (tuple(int(getattr(outputs, f"servo{i}_raw", 0)) for i in range(1, 9))
                if outputs else (0,) * 8)
    # the throttle the aircraft flies at: the autopilot's own output (in AUTO the pilot's stick
    # may sit at idle while the autopilot flies), else the pilot's stick
    throttle_us = computer[throttle_channel] or pilot[throttle_channel]
    throttle = us_to_throttle(throttle_us) if throttle_us else 0.0
    failsafe = rc is None or getattr(rc, "rssi", 255) == 0
    return ServoState(t_ns, seq & 0xFF, pilot, computer, guided, guided, failsafe, 0, 0,
                      pilot_auto_switch=guided, pilot_throttle=throttle)


@fast_frozen
@dataclass(frozen=True)
class AutopilotEstimate:
    """The autopilot's own estimate (ATTITUDE and GLOBAL_POSITION_INT), beside ours."""

    t_ns: int
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rollspeed_rad_s: float
    pitchspeed_rad_s: float
    yawspeed_rad_s: float
    lat_deg: float | None = None
    lon_deg: float | None = None
    alt_m: float | None = None
    vn_m_s: float | None = None
    ve_m_s: float | None = None
    vd_m_s: float | None = None
    ekf_flags: int = 0


@fast_frozen
@dataclass(frozen=True)
class BatterySample:
    """One BATTERY_STATUS: the pack's voltage, current and charge (None where not sent)."""

    t_ns: int
    battery_id: int
    voltage_v: float | None
    current_a: float | None
    remaining_pct: int | None


@fast_frozen
@dataclass(frozen=True)
class TruthSample:
    """A SITL's SIMSTATE: the simulator's true attitude, body rates, specific force and
    position (no velocity, no altitude: the message carries none)."""

    t_ns: int
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rates_rad_s: tuple[float, float, float]
    accel_m_s2: tuple[float, float, float]
    lat_deg: float
    lon_deg: float


def truth_sample(msg: Any, t_ns: int) -> TruthSample | None:
    """SIMSTATE (ArduPilot's SITL) as truth; None before the simulator has a position."""
    if msg.lat == 0 and msg.lng == 0:
        return None
    return TruthSample(t_ns, msg.roll, msg.pitch, msg.yaw, (msg.xgyro, msg.ygyro, msg.zgyro),
                       (msg.xacc, msg.yacc, msg.zacc), msg.lat / 1e7, msg.lng / 1e7)


def euler_from_quat(w: float, x: float, y: float, z: float) -> tuple[float, float, float]:
    """MAVLink's quaternion (w, x, y, z) as ZYX Euler angles (rad)."""
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def quat_from_euler_wxyz(roll: float, pitch: float, yaw: float) -> list[float]:
    """ZYX Euler angles (rad) as MAVLink's quaternion (w, x, y, z)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return [cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy]
