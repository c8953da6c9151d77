"""Codec for the thesis's legacy UDP ground/aircraft protocol.

The protocol, byte by byte, is documented in docs/legacy-protocol.md.  Every datagram is a 16-byte header followed by a
fixed-size, little-endian, packed body chosen by the header's type byte.  Each body layout is
declared exactly once, as a frozen dataclass whose field annotations carry the wire format
(``Annotated[int, U32]``); the packing and unpacking code is derived from that declaration so the
two directions cannot drift apart.

Decoding never raises: a datagram from the network is untrusted, so problems come back as a
:class:`DecodeError` value naming the reason and the byte offset.  Encoding raises ``ValueError``
because a bad value there is a bug in the caller, not bad input from the network.

Size: the declarations of all 13 datagram layouts are most of it, and they belong in one
place next to the code derived from them.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import struct
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar

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
    "GpsFix",
    "Gps",
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
    "WireField",
    "as_dict",
    "decode",
    "encode",
    "layout_of",
    "payload_class",
    "wire_fields",
]

HEADER_SIZE = 16
"""Bytes of the common header that starts every datagram."""

DEFAULT_MONITOR_PORT = 5501
"""UDP port the aircraft sends messages to (monitors listen here)."""

DEFAULT_COMMAND_PORT = 5500
"""UDP port the aircraft listens on for commands."""

UNCHANGED = 0xFFFFFFFF
"""Parameter value in SET_* commands meaning 'keep the current setting'."""

_NS_PER_S = 1_000_000_000
_HEADER = struct.Struct("<BBHIiI")


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
        return self.frame_tv_sec * _NS_PER_S + self.frame_tv_nsec


@dataclass(frozen=True)
class RestartThread:
    """Ask the manager to restart one thread."""

    TYPE: ClassVar[MsgType] = MsgType.RESTART_THREAD
    thread_id: Annotated[int, _u8_pad(3)]


Message = ThreadStatus | ManagerStatus | CommandAck | Imu | Gps | Servo | Estimator | Control
Command = SetThreadParams | SetManagerParams | Stop | HorizonAttitude | RestartThread
Payload = Message | Command

# ---------------------------------------------------------------------------------------------
# Layout machinery: derived from the declarations above, never written by hand per type.


@dataclass(frozen=True)
class _Layout:
    cls: type[Any]
    type_code: MsgType
    size: int
    body: struct.Struct
    fields: tuple[tuple[str, WireField], ...]


def _fields_of(cls: type[Any]) -> tuple[tuple[str, WireField], ...]:
    hints = typing.get_type_hints(cls, include_extras=True)
    out: list[tuple[str, WireField]] = []
    for f in dataclasses.fields(cls):
        wire = [m for m in getattr(hints[f.name], "__metadata__", ()) if isinstance(m, WireField)]
        if len(wire) != 1:
            raise TypeError(f"{cls.__name__}.{f.name} needs exactly one WireField annotation")
        out.append((f.name, wire[0]))
    return tuple(out)


def _build_layout(cls: type[Any]) -> _Layout:
    fields = _fields_of(cls)
    fmt = "<" + "".join(
        f"{w.count if w.count > 1 else ''}{w.code}{f'{w.pad_after}x' if w.pad_after else ''}"
        for _, w in fields
    )
    body = struct.Struct(fmt)
    return _Layout(cls, cls.TYPE, HEADER_SIZE + body.size, body, fields)


_PAYLOAD_CLASSES: tuple[type[Any], ...] = (
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
_LAYOUTS: dict[int, _Layout] = {cls.TYPE: _build_layout(cls) for cls in _PAYLOAD_CLASSES}
_BY_CLASS: dict[type[Any], _Layout] = {lay.cls: lay for lay in _LAYOUTS.values()}

MESSAGE_TYPES: frozenset[MsgType] = frozenset(t for t in MsgType if t < 0x80)
"""Types sent by the aircraft."""

COMMAND_TYPES: frozenset[MsgType] = frozenset(t for t in MsgType if t >= 0x80)
"""Types sent by the ground."""


def layout_of(type_code: int) -> tuple[str, int]:
    """Name and fixed total datagram size of a type, so callers can size buffers or report."""
    lay = _LAYOUTS[type_code]
    return lay.type_code.name, lay.size


def payload_class(type_code: int) -> type[Any]:
    """Dataclass that carries a type's body (KeyError for an unknown type)."""
    return _LAYOUTS[type_code].cls


def wire_fields(cls: type[Any]) -> tuple[tuple[str, WireField], ...]:
    """(field name, wire format) pairs of a payload class, in wire order."""
    return _BY_CLASS[cls].fields


# ---------------------------------------------------------------------------------------------
# Public encode / decode.


@dataclass(frozen=True)
class Header:
    """The 16-byte header common to every datagram."""

    type_code: int
    vehicle_id: int
    size: int
    seq: int
    tv_sec: int
    tv_nsec: int

    @property
    def t_ns(self) -> int:
        """Send time as integer nanoseconds since the epoch."""
        return self.tv_sec * _NS_PER_S + self.tv_nsec


@dataclass(frozen=True)
class Decoded:
    """A well-formed datagram: its header and its typed body."""

    header: Header
    payload: Payload

    @property
    def name(self) -> str:
        """Contract name of the datagram type, e.g. ``"THREAD_STATUS"``."""
        return MsgType(self.header.type_code).name


@dataclass(frozen=True)
class DecodeError:
    """Why a datagram was rejected and the byte offset where the problem was found."""

    reason: str
    offset: int

    def __str__(self) -> str:
        return f"{self.reason} (at byte {self.offset})"


def _flatten(lay: _Layout, msg: object) -> Iterator[Any]:
    for name, wire in lay.fields:
        value = getattr(msg, name)
        if wire.count > 1:
            if not isinstance(value, (tuple, list)) or len(value) != wire.count:
                raise ValueError(
                    f"{lay.type_code.name}.{name}: expected {wire.count} values, got {value!r}"
                )
            yield from value
        elif wire.code.endswith("s"):
            yield _encode_text(lay, name, wire, value)
        else:
            yield value


def _encode_text(lay: _Layout, name: str, wire: WireField, value: object) -> bytes:
    if not isinstance(value, str):
        raise ValueError(f"{lay.type_code.name}.{name}: expected str, got {value!r}")
    try:
        raw = value.encode("latin-1")  # C chars on the wire: one byte per character
    except UnicodeEncodeError as exc:
        raise ValueError(f"{lay.type_code.name}.{name}: {exc.reason} at {exc.start}") from None
    limit = int(wire.code[:-1])
    if len(raw) > limit:
        raise ValueError(f"{lay.type_code.name}.{name}: {len(raw)} bytes, at most {limit} fit")
    return raw


def _explain_pack_error(lay: _Layout, msg: object, exc: Exception) -> ValueError:
    """Re-pack field by field so the error names the offending field, not just the struct."""
    for name, wire in lay.fields:
        value = getattr(msg, name)
        values = value if wire.count > 1 else (value,)
        if wire.code.endswith("s"):
            continue
        for v in values:
            try:
                struct.pack("<" + wire.code, v)
            except (struct.error, OverflowError, TypeError) as field_exc:
                return ValueError(f"{lay.type_code.name}.{name}={v!r}: {field_exc}")
    return ValueError(f"{lay.type_code.name}: {exc}")


def encode(msg: Payload, *, vehicle_id: int, seq: int, t_ns: int) -> bytes:
    """Build one datagram.

    ``seq`` is reduced modulo 2**32 so a sender may keep a plain counter; ``t_ns`` is the send time
    in integer nanoseconds since the epoch (split into the header's seconds and nanoseconds).
    Raises ``ValueError`` naming the field when a value does not fit its wire type.
    """
    lay = _BY_CLASS.get(type(msg))
    if lay is None:
        raise ValueError(f"not a legacy protocol payload: {type(msg).__name__}")
    if not 1 <= vehicle_id <= 255:
        raise ValueError(f"vehicle_id {vehicle_id} outside 1..255")
    tv_sec, tv_nsec = divmod(int(t_ns), _NS_PER_S)
    if not -(2**31) <= tv_sec < 2**31:
        raise ValueError(f"t_ns {t_ns} does not fit the header's int32 seconds")
    values = list(_flatten(lay, msg))
    try:
        body = lay.body.pack(*values)
    except (struct.error, OverflowError, TypeError) as exc:
        raise _explain_pack_error(lay, msg, exc) from None
    header = _HEADER.pack(lay.type_code, vehicle_id, lay.size, seq % 2**32, tv_sec, tv_nsec)
    return header + body


def _build(lay: _Layout, values: tuple[Any, ...]) -> Any:
    kwargs: dict[str, Any] = {}
    i = 0
    for name, wire in lay.fields:
        if wire.count > 1:
            kwargs[name] = tuple(values[i : i + wire.count])
            i += wire.count
        else:
            v = values[i]
            if isinstance(v, bytes):
                v = v.split(b"\0", 1)[0].decode("latin-1")  # C chars: 1 byte, 1 char
            kwargs[name] = v
            i += 1
    return lay.cls(**kwargs)


def decode(datagram: bytes | bytearray | memoryview) -> Decoded | DecodeError:
    """Parse one datagram; malformed input comes back as a :class:`DecodeError`, never raised.

    The checks are strict because the contract's sizes are fixed: the type must be known, and
    both the header's size field and the datagram's real length must equal that type's size.
    Reserved (zero) bytes are not checked, so a later sender may reuse them.
    """
    data = bytes(datagram)
    n = len(data)
    if n == 0:
        return DecodeError("empty datagram", 0)
    lay = _LAYOUTS.get(data[0])
    if lay is None:
        return DecodeError(f"unknown type 0x{data[0]:02x}", 0)
    name = lay.type_code.name
    if n != lay.size:
        kind = "short" if n < lay.size else "long"
        return DecodeError(f"{kind} datagram: {n} bytes, {name} is {lay.size}", min(n, lay.size))
    type_code, vehicle_id, size_field, seq, tv_sec, tv_nsec = _HEADER.unpack_from(data, 0)
    if size_field != lay.size:
        return DecodeError(f"size field says {size_field}, {name} is {lay.size}", 2)
    if vehicle_id == 0:
        return DecodeError("vehicle id 0 (must be 1..255)", 1)
    if tv_nsec >= _NS_PER_S:
        return DecodeError(f"header tv_nsec {tv_nsec} is not below 1e9", 12)
    payload = _build(lay, lay.body.unpack_from(data, HEADER_SIZE))
    header = Header(type_code, vehicle_id, size_field, seq, tv_sec, tv_nsec)
    return Decoded(header, payload)


def as_dict(payload: Payload) -> dict[str, Any]:
    """Plain field dict for JSON output; non-finite floats become None, which JSON can carry."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(payload):
        v = getattr(payload, f.name)
        if isinstance(v, float) and not math.isfinite(v):
            v = None
        elif isinstance(v, tuple):
            v = list(v)
        out[f.name] = v
    return out
