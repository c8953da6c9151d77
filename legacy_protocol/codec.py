"""Codec for the thesis's legacy UDP ground/aircraft protocol: the header, encode and decode.

The protocol, byte by byte, is documented in docs/legacy-protocol.md.  Every datagram is a 16-byte
header followed by a fixed-size, little-endian, packed body chosen by the header's type byte.  The
bodies are declared in :mod:`legacy_protocol.messages`; the packing and unpacking code here is
derived from those declarations, so the two directions cannot drift apart.

Decoding never raises: a datagram from the network is untrusted, so problems come back as a
:class:`DecodeError` value naming the reason and the byte offset.  Encoding raises ``ValueError``
because a bad value there is a bug in the caller, not bad input from the network.
"""

from __future__ import annotations

import dataclasses
import math
import struct
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from legacy_protocol.messages import NS_PER_S, PAYLOAD_CLASSES, MsgType, Payload, WireField

__all__ = [
    "HEADER_SIZE",
    "DecodeError",
    "Decoded",
    "Header",
    "as_dict",
    "decode",
    "encode",
    "layout_of",
    "payload_class",
    "wire_fields",
]

HEADER_SIZE = 16
"""Bytes of the common header that starts every datagram."""

_HEADER = struct.Struct("<BBHIiI")

# ---------------------------------------------------------------------------------------------
# Layout machinery: derived from the declarations in messages, never written by hand per type.


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


_LAYOUTS: dict[int, _Layout] = {cls.TYPE: _build_layout(cls) for cls in PAYLOAD_CLASSES}
_BY_CLASS: dict[type[Any], _Layout] = {lay.cls: lay for lay in _LAYOUTS.values()}


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
        return self.tv_sec * NS_PER_S + self.tv_nsec


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
    tv_sec, tv_nsec = divmod(int(t_ns), NS_PER_S)
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
    if tv_nsec >= NS_PER_S:
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
