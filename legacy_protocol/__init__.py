"""The thesis's legacy UDP ground/aircraft protocol: codec, monitor link and ground monitor.

The message declarations (:mod:`legacy_protocol.messages`) and the codec
(:mod:`legacy_protocol.codec`) are what the on-board network adapter and any ground tool share;
the monitor modules are ground-only and import Textual lazily, so importing this package stays
cheap on the aircraft.
"""

from __future__ import annotations

from legacy_protocol.codec import HEADER_SIZE, Decoded, DecodeError, Header, decode, encode
from legacy_protocol.messages import (
    COMMAND_TYPES,
    DEFAULT_COMMAND_PORT,
    DEFAULT_MONITOR_PORT,
    MESSAGE_TYPES,
    UNCHANGED,
    AckResult,
    Command,
    CommandAck,
    Control,
    Estimator,
    Gps,
    GpsFix,
    HorizonAttitude,
    Imu,
    ManagerStatus,
    Message,
    MsgType,
    Payload,
    RestartThread,
    Servo,
    ServoFlag,
    SetManagerParams,
    SetThreadParams,
    Stop,
    StopReason,
    ThreadFlag,
    ThreadId,
    ThreadStatus,
)

__all__ = [
    "COMMAND_TYPES",
    "DEFAULT_COMMAND_PORT",
    "DEFAULT_MONITOR_PORT",
    "HEADER_SIZE",
    "MESSAGE_TYPES",
    "UNCHANGED",
    "AckResult",
    "Command",
    "CommandAck",
    "Control",
    "DecodeError",
    "Decoded",
    "Estimator",
    "Gps",
    "GpsFix",
    "Header",
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
    "decode",
    "encode",
]
