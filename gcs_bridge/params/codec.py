"""Parameter values on the wire: the 4 bytes of PARAM_VALUE / PARAM_SET, kept as bytes.

MAVLink carries every parameter in a float field. Integers go either *bytewise* (the int's
bytes copied into the field: exact for every int32) or by *C cast* (the int converted to a
float: exact only up to 2**24). Which one a client uses depends on the autopilot the HEARTBEAT
claims (see `Identity`). A bytewise int whose bit pattern is a signalling NaN would be changed
by any trip through a Python float, so values here never become floats on the way: the raw 4
bytes are read from and written into the frame directly.
"""

from __future__ import annotations

import math
import struct

from companion.core.params import ParamSpec, ParamType
from gcs_bridge.dialect import mavlink

T_UINT8 = mavlink.MAV_PARAM_TYPE_UINT8
T_INT8 = mavlink.MAV_PARAM_TYPE_INT8
T_UINT16 = mavlink.MAV_PARAM_TYPE_UINT16
T_INT16 = mavlink.MAV_PARAM_TYPE_INT16
T_UINT32 = mavlink.MAV_PARAM_TYPE_UINT32
T_INT32 = mavlink.MAV_PARAM_TYPE_INT32
T_REAL32 = mavlink.MAV_PARAM_TYPE_REAL32

_INT_FORMATS = {
    T_UINT8: "<B", T_INT8: "<b", T_UINT16: "<H", T_INT16: "<h", T_UINT32: "<I", T_INT32: "<i",
}
_INT_RANGES = {
    T_UINT8: (0, 0xFF), T_INT8: (-0x80, 0x7F), T_UINT16: (0, 0xFFFF), T_INT16: (-0x8000, 0x7FFF),
    T_UINT32: (0, 0xFFFFFFFF), T_INT32: (-0x80000000, 0x7FFFFFFF),
}
_TYPE_NAMES = {
    T_UINT8: "uint8", T_INT8: "int8", T_UINT16: "uint16", T_INT16: "int16", T_UINT32: "uint32",
    T_INT32: "int32", mavlink.MAV_PARAM_TYPE_UINT64: "uint64", mavlink.MAV_PARAM_TYPE_INT64: "int64",
    T_REAL32: "real32", mavlink.MAV_PARAM_TYPE_REAL64: "real64",
}


class WireValueError(ValueError):
    """A PARAM_SET value that cannot be a parameter value; `reason` fits a STATUSTEXT."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def type_name(mav_type: int) -> str:
    return _TYPE_NAMES.get(mav_type, f"type {mav_type}")


def encode(spec: ParamSpec, value: int | float, *, bytewise: bool) -> bytes:
    """The 4 wire bytes for a registry value of `spec`'s type."""
    if spec.ptype is ParamType.FLOAT32:
        return struct.pack("<f", float(value))
    if bytewise:
        return struct.pack("<i", int(value))
    return struct.pack("<f", float(int(value)))


def decode(raw: bytes, mav_type: int, *, bytewise: bool) -> int | float:
    """A value from the 4 wire bytes and the sender's declared type.

    Integer types are read bytewise or through the float, as the identity dictates; REAL32 is
    a float either way (and may still be an integral value for an int32 parameter, which the
    registry then accepts). 64-bit types cannot travel in 4 bytes. Strict: a bytewise integer
    whose unused bytes are neither zero nor its sign's extension, a cast integer that is not
    finite, integral and within its type, and a NaN or infinite REAL32 are refused, so garbage
    never becomes a legal value.
    """
    if len(raw) != 4:
        raise WireValueError(f"value field has {len(raw)} bytes, expected 4")
    name = type_name(mav_type)
    if mav_type == T_REAL32:
        f = float(struct.unpack("<f", raw)[0])
        if not math.isfinite(f):
            raise WireValueError(f"value {f!r} (real32) is not a finite number")
        return f
    if mav_type in _INT_FORMATS:
        fmt = _INT_FORMATS[mav_type]
        size = struct.calcsize(fmt)
        if bytewise:
            value = int(struct.unpack(fmt, raw[:size])[0])
            # the bytes the type does not use are zero, or the sign's extension: anything else
            # is not a value of that type (a float's bits, NaN's 00 00 c0 7f among them)
            unused = raw[size:]
            fills = (b"\x00", b"\xff") if fmt.islower() and value < 0 else (b"\x00",)
            if all(unused != fill * len(unused) for fill in fills):
                raise WireValueError(f"wrong type: bytes {raw.hex(' ')} are not a {name} "
                                     f"(its unused bytes are {unused.hex(' ')})")
            return value
        f = float(struct.unpack("<f", raw)[0])
        if not math.isfinite(f) or f != int(f):
            raise WireValueError(f"wrong type: {f!r} sent as {name} is not an integer")
        lo, hi = _INT_RANGES[mav_type]
        if not lo <= f <= hi:
            raise WireValueError(f"wrong type: {f:.0f} does not fit a {name}")
        return int(f)
    raise WireValueError(f"wrong type: {name} is not supported (int32 or real32)")


def type_matches(spec: ParamSpec, mav_type: int) -> bool:
    """Whether a client's declared type is acceptable for `spec` (ints of any width for int32)."""
    if spec.ptype is ParamType.FLOAT32:
        return mav_type == T_REAL32
    return mav_type in _INT_FORMATS or mav_type == T_REAL32


def frame_payload(frame: bytes | bytearray, min_len: int) -> bytes:
    """A MAVLink 1/2 frame's payload, re-padded to `min_len` (MAVLink 2 trims trailing zeros).

    pymavlink 2.4.50's `get_payload()` is 4 bytes off for MAVLink 2, hence this.
    """
    if frame and frame[0] == 0xFD:
        header = 10
    else:
        header = 6
    length = frame[1] if len(frame) > 1 else 0
    payload = bytes(frame[header:header + length])
    return payload.ljust(min_len, b"\0")


def raw_value_of(msg: mavlink.MAVLink_message) -> bytes:
    """The untouched 4 value bytes of a received PARAM_SET or PARAM_VALUE."""
    return frame_payload(msg.get_msgbuf(), 4)[:4]


class ParamValueMessage(mavlink.MAVLink_param_value_message):
    """PARAM_VALUE whose value field is packed from raw bytes, never through a float."""

    def __init__(self, param_id: bytes, raw: bytes, param_type: int, param_count: int,
                 param_index: int) -> None:
        shown = struct.unpack("<f", raw)[0]
        super().__init__(param_id, shown, param_type, param_count, param_index)
        self.raw_value = raw

    def pack(self, mav: mavlink.MAVLink, force_mavlink1: bool = False) -> bytes:
        payload = struct.pack("<4sHH16sB", self.raw_value, self.param_count, self.param_index,
                              self._param_id_raw, self.param_type)
        return self._pack(mav, self.crc_extra, payload, force_mavlink1=force_mavlink1)


def param_value_message(spec: ParamSpec, value: int | float, index: int, count: int,
                        *, bytewise: bool) -> ParamValueMessage:
    return ParamValueMessage(spec.name.encode("ascii"), encode(spec, value, bytewise=bytewise),
                             spec.ptype.mav_type, count, index)
