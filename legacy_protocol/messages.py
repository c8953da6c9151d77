"""What the legacy UDP protocol's datagrams carry: type codes, enumerations and every body layout.

The protocol, byte by byte, is documented in docs/legacy-protocol.md. Each body layout is
declared exactly once, as a frozen dataclass whose field annotations carry the wire format
(``Annotated[int, U32]``); :mod:`legacy_protocol.codec` derives the packing and unpacking from
these declarations, so the two directions cannot drift apart. This module is the contract's
vocabulary (what a datagram means); the codec is how it becomes bytes.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar

__all__ = [
    "COMMAND_TYPES",
    "DEFAULT_COMMAND_PORT",
    "DEFAULT_MONITOR_PORT",
    "MESSAGE_TYPES",
    "NS_PER_S",
    "PAYLOAD_CLASSES",
    "UNCHANGED",
    "AckResult",
    "Command",
    "CommandAck",
    "Control",
    "Estimator",
    "GpsFix",
    "Gps",
    "HorizonAttitude",
    "Imu",
    "ManagerStatus",
    "Message",
    "MsgType",
    "Payload",
    "RestartThread",
    "Servo",
    "ServoFlag",
    "SetManagerParams",
    "SetThreadParams",
    "Stop",
    "StopReason",
    "ThreadFlag",
    "ThreadId",
    "ThreadStatus",
    "WireField",
]

DEFAULT_MONITOR_PORT = 5501
"""UDP port the aircraft sends messages to (monitors listen here)."""

DEFAULT_COMMAND_PORT = 5500
"""UDP port the aircraft listens on for commands."""

UNCHANGED = 0xFFFFFFFF
"""Parameter value in SET_* commands meaning 'keep the current setting'."""

NS_PER_S = 1_000_000_000
"""Nanoseconds per second: the wire splits times into seconds and nanoseconds."""


class MsgType(enum.IntEnum):
    """Type byte of every datagram; messages are < 0x80, commands >= 0x80."""

    THREAD_STATUS = 0x01
    MANAGER_STATUS = 0x02
    COMMAND_ACK = 0x03
    IMU = 0x10
    GPS = 0x11
    SERVO = 0x12
    ESTIMATOR = 0x13
    CONTROL = 0x14
    SET_THREAD_PARAMS = 0x81
    SET_MANAGER_PARAMS = 0x82
    STOP = 0x83
    HORIZON_ATTITUDE = 0x84
    RESTART_THREAD = 0x85


class ThreadId(enum.IntEnum):
    """Ids of the standard managed threads; further threads take the next free ids."""

    IMU = 1
    GPS = 2
    SERVO = 3
    ESTIMATOR = 4
    CONTROL = 5


class ThreadFlag(enum.IntFlag):
    """THREAD_STATUS.flags bits, in the order the thesis's four LEDs show them."""

    INITIALISED = 0x01
    RUNNING = 0x02
    IN_PERIODIC = 0x04
    ALIVE = 0x08


class ServoFlag(enum.IntFlag):
    """SERVO.flags bits."""

    AUTOMATIC = 0x01
    FAILSAFE = 0x02


class AckResult(enum.IntEnum):
    """COMMAND_ACK.result values."""

    ACCEPTED = 0
    BAD_VALUE = 1
    UNKNOWN_THREAD = 2
    NOT_ALLOWED = 3


class GpsFix(enum.IntEnum):
    """GPS.fix_type values."""

    NONE = 0
    GPS = 1
    DGPS = 2
    RTK = 3


class StopReason(enum.IntEnum):
    """STOP.reason values; only the operator reason is defined by the contract."""

    OPERATOR = 0


@dataclass(frozen=True)
class WireField:
    """Wire format of one dataclass field: a struct code, repeated ``count`` times.

    ``count > 1`` makes the field a tuple of that many values.  ``pad_after`` zero bytes follow the
    field on the wire (reserved space in the contract); they are written as zero and ignored when
    read, so a future sender may use them without breaking this decoder.
    """

    code: str
    count: int = 1
    pad_after: int = 0


U8 = WireField("B")
U16 = WireField("H")
U32 = WireField("I")
I32 = WireField("i")
F32 = WireField("f")
F64 = WireField("d")


def _u8_pad(pad: int) -> WireField:
    """A uint8 followed by ``pad`` reserved zero bytes."""
    return WireField("B", pad_after=pad)


# ---------------------------------------------------------------------------------------------
# Message bodies, aircraft to ground.  Field order is the contract's table order.


@dataclass(frozen=True)
class ThreadStatus:
    """One managed thread's execution state, sent in rotation by the thread manager."""

    TYPE: ClassVar[MsgType] = MsgType.THREAD_STATUS
    thread_id: Annotated[int, U8]
    flags: Annotated[int, U8]
    restarts: Annotated[int, U16]
    mean_step_us: Annotated[int, U32]
    watchdog_period_ms: Annotated[int, U32]
    message_period_ms: Annotated[int, U32]
    name: Annotated[str, WireField("16s")]

    def has(self, flag: ThreadFlag) -> bool:
        """True if every bit of ``flag`` is set, so callers need not mask by hand."""
        return (self.flags & flag) == flag


@dataclass(frozen=True)
class ManagerStatus:
    """Global watchdog settings and uptime of the on-board application."""

    TYPE: ClassVar[MsgType] = MsgType.MANAGER_STATUS
    elapsed_ms: Annotated[int, U32]
    execution_time_s: Annotated[int, U32]
    status_period_ms: Annotated[int, U32]
    granularity_ms: Annotated[int, U32]
    thread_count: Annotated[int, _u8_pad(3)]


@dataclass(frozen=True)
class CommandAck:
    """The aircraft's answer to one command, matched by the command's sequence number."""

    TYPE: ClassVar[MsgType] = MsgType.COMMAND_ACK
    command_type: Annotated[int, U8]
    result: Annotated[int, _u8_pad(2)]
    command_seq: Annotated[int, U32]


@dataclass(frozen=True)
class Imu:
    """Latest IMU sample: body rates, specific force, sensor temperature."""

    TYPE: ClassVar[MsgType] = MsgType.IMU
    p_rad_s: Annotated[float, F32]
    q_rad_s: Annotated[float, F32]
    r_rad_s: Annotated[float, F32]
    ax_m_s2: Annotated[float, F32]
    ay_m_s2: Annotated[float, F32]
    az_m_s2: Annotated[float, F32]
    temperature_c: Annotated[float, F32]
    frame_count: Annotated[int, U32]


@dataclass(frozen=True)
class Gps:
    """Latest GPS solution with its accuracy indicators."""

    TYPE: ClassVar[MsgType] = MsgType.GPS
    lat_deg: Annotated[float, F64]
    lon_deg: Annotated[float, F64]
    alt_m: Annotated[float, F32]
    v_north_m_s: Annotated[float, F32]
    v_east_m_s: Annotated[float, F32]
    v_down_m_s: Annotated[float, F32]
    pdop: Annotated[float, F32]
    hdop: Annotated[float, F32]
    vdop: Annotated[float, F32]
    tdop: Annotated[float, F32]
    latency_ms: Annotated[float, F32]
    alt_std_m: Annotated[float, F32]
    fix_type: Annotated[int, U8]
    satellites: Annotated[int, _u8_pad(2)]


@dataclass(frozen=True)
class Servo:
    """Pilot and computer servo commands, battery levels and mode flags."""

    TYPE: ClassVar[MsgType] = MsgType.SERVO
    pilot_us: Annotated[tuple[int, ...], WireField("H", count=8)]
    computer_us: Annotated[tuple[int, ...], WireField("H", count=8)]
    avionics_battery_raw: Annotated[int, U8]
    servo_battery_raw: Annotated[int, U8]
    flags: Annotated[int, _u8_pad(1)]


@dataclass(frozen=True)
class Estimator:
    """Attitude, local position and velocity estimate plus gyro biases."""

    TYPE: ClassVar[MsgType] = MsgType.ESTIMATOR
    roll_rad: Annotated[float, F32]
    pitch_rad: Annotated[float, F32]
    yaw_rad: Annotated[float, F32]
    north_m: Annotated[float, F32]
    east_m: Annotated[float, F32]
    down_m: Annotated[float, F32]
    v_north_m_s: Annotated[float, F32]
    v_east_m_s: Annotated[float, F32]
    v_down_m_s: Annotated[float, F32]
    gyro_bias_x_rad_s: Annotated[float, F32]
    gyro_bias_y_rad_s: Annotated[float, F32]
    gyro_bias_z_rad_s: Annotated[float, F32]


@dataclass(frozen=True)
class Control:
    """Normalised control-surface and throttle outputs of the control thread."""

    TYPE: ClassVar[MsgType] = MsgType.CONTROL
    aileron: Annotated[float, F32]
    elevator: Annotated[float, F32]
    rudder: Annotated[float, F32]
    throttle: Annotated[float, F32]
    enabled: Annotated[int, _u8_pad(3)]


# ---------------------------------------------------------------------------------------------
# Command bodies, ground to aircraft.


@dataclass(frozen=True)
class SetThreadParams:
    """Change one thread's watchdog and message periods (UNCHANGED keeps a value)."""

    TYPE: ClassVar[MsgType] = MsgType.SET_THREAD_PARAMS
    thread_id: Annotated[int, _u8_pad(3)]
    watchdog_period_ms: Annotated[int, U32] = UNCHANGED
    message_period_ms: Annotated[int, U32] = UNCHANGED


@dataclass(frozen=True)
class SetManagerParams:
    """Change the manager's execution time, status period and watchdog granularity."""

    TYPE: ClassVar[MsgType] = MsgType.SET_MANAGER_PARAMS
    execution_time_s: Annotated[int, U32] = UNCHANGED
    status_period_ms: Annotated[int, U32] = UNCHANGED
    granularity_ms: Annotated[int, U32] = UNCHANGED


@dataclass(frozen=True)
class Stop:
    """Ask the on-board application to stop every thread cleanly and exit."""

    TYPE: ClassVar[MsgType] = MsgType.STOP
    reason: Annotated[int, U32] = 0  # StopReason.OPERATOR; a plain int keeps JSON output plain


@dataclass(frozen=True)
class HorizonAttitude:
    """Attitude measured on the ground by horizon detection, stamped with its video frame time."""

    TYPE: ClassVar[MsgType] = MsgType.HORIZON_ATTITUDE
    roll_rad: Annotated[float, F32]
    pitch_rad: Annotated[float, F32]
    quality: Annotated[float, F32]
    frame_tv_sec: Annotated[int, I32]
    frame_tv_nsec: Annotated[int, U32]

    @property
    def frame_t_ns(self) -> int:
        """Frame time as integer nanoseconds since the epoch."""
        return self.frame_tv_sec * NS_PER_S + self.frame_tv_nsec


@dataclass(frozen=True)
class RestartThread:
    """Ask the manager to restart one thread."""

    TYPE: ClassVar[MsgType] = MsgType.RESTART_THREAD
    thread_id: Annotated[int, _u8_pad(3)]


Message = ThreadStatus | ManagerStatus | CommandAck | Imu | Gps | Servo | Estimator | Control
Command = SetThreadParams | SetManagerParams | Stop | HorizonAttitude | RestartThread
Payload = Message | Command

PAYLOAD_CLASSES: tuple[type[Any], ...] = (
    ThreadStatus,
    ManagerStatus,
    CommandAck,
    Imu,
    Gps,
    Servo,
    Estimator,
    Control,
    SetThreadParams,
    SetManagerParams,
    Stop,
    HorizonAttitude,
    RestartThread,
)

MESSAGE_TYPES: frozenset[MsgType] = frozenset(t for t in MsgType if t < 0x80)
"""Types sent by the aircraft."""

COMMAND_TYPES: frozenset[MsgType] = frozenset(t for t in MsgType if t >= 0x80)
"""Types sent by the ground."""
