"""Whom a frame is for, read from its bytes: each message's target_system/target_component offsets.

The router (`gcs_bridge.router`) forwards frames as bytes and must not decode them: it reads the
two target bytes where the message's wire layout puts them. The table is computed once from
pymavlink's ardupilotmega dialect (a superset of `common`): a message's payload is its fields in
`ordered_fieldnames` order, packed as its `unpacker` format says, so a field's offset is the size
of the fields before it. MAVLink 2 drops the payload's trailing zero bytes, and a MAVLink 1
frame has no extension fields: an offset past the payload reads 0 (broadcast), as a decoder
would fill it. A message without a target_system field (HEARTBEAT, ATTITUDE...) is a broadcast;
so is one the dialect does not know (it is forwarded everywhere it may go).
"""

from __future__ import annotations

import re
import struct
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as apm

__all__ = ["COMMAND_OFFSETS", "TARGETS", "field_offsets", "payload_u16", "target_of"]

STX_V2 = 0xFD
_TOKEN = re.compile(r"(\d*)([a-zA-Z?])")


def field_offsets(cls: Any) -> dict[str, int]:
    """Byte offset of each field of message class `cls` in its payload (wire order)."""
    fmt = cls.unpacker.format
    tokens = _TOKEN.findall(fmt.lstrip("<"))
    names = cls.ordered_fieldnames
    if len(tokens) != len(names):
        raise ValueError(f"{cls.msgname}: format {fmt!r} does not match fields {names}")
    offsets: dict[str, int] = {}
    offset = 0
    for name, (count, code) in zip(names, tokens, strict=True):
        offsets[name] = offset
        offset += struct.calcsize(f"<{count}{code}")
    return offsets


def _targets() -> dict[int, tuple[int, int | None]]:
    table: dict[int, tuple[int, int | None]] = {}
    for msg_id, cls in apm.mavlink_map.items():
        offsets = field_offsets(cls)
        if "target_system" in offsets:
            table[msg_id] = (offsets["target_system"], offsets.get("target_component"))
    return table


TARGETS: dict[int, tuple[int, int | None]] = _targets()
"""msg id -> (target_system offset, target_component offset or None: the whole system)."""

COMMAND_OFFSETS: dict[int, int] = {
    msg_id: field_offsets(apm.mavlink_map[msg_id])["command"]
    for msg_id in (apm.MAVLINK_MSG_ID_COMMAND_LONG, apm.MAVLINK_MSG_ID_COMMAND_INT)}
"""Where COMMAND_LONG and COMMAND_INT carry their command (uint16), for the signing policy."""


def _payload_byte(data: bytes, offset: int) -> int:
    header = 10 if data[0] == STX_V2 else 6
    return data[header + offset] if offset < data[1] else 0


def payload_u16(data: bytes, offset: int) -> int:
    """The little-endian uint16 at `offset` of a frame's payload (0 past its end)."""
    return _payload_byte(data, offset) | _payload_byte(data, offset + 1) << 8


def target_of(data: bytes, msg_id: int) -> tuple[int, int] | None:
    """(target system, target component) of a whole frame; None for a message without a
    target (a broadcast by nature). Component 0 stands for "every component"."""
    entry = TARGETS.get(msg_id)
    if entry is None:
        return None
    sys_at, comp_at = entry
    return (_payload_byte(data, sys_at), 0 if comp_at is None else _payload_byte(data, comp_at))
