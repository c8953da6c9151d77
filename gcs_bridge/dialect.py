"""The MAVLink dialect the bridge speaks, plus what pymavlink 2.4.50 leaves out of it.

The bridge speaks MAVLink 2 with the `common` message set only: every ground station knows it,
and a vehicle that claims no vendor dialect is not asked vendor questions. pymavlink's generated
`common` module lacks PROTOCOL_VERSION (id 300), which QGroundControl asks for to decide whether
to switch to MAVLink 2, so it is defined here from the message definition.
"""

from __future__ import annotations

import enum
import struct
from typing import Any

from pymavlink.dialects.v20 import common as mavlink
from pymavlink.dialects.v20.common import MAVLink_message as Message

#: A received message: its fields depend on its type, so it is typed loosely.
RxMessage = Any

__all__ = [
    "COMPONENT_ID",
    "Identity",
    "Message",
    "RxMessage",
    "MSG_ID_PROTOCOL_VERSION",
    "ProtocolVersionMessage",
    "crc_extra_of",
    "mavlink",
    "message_name",
    "message_id",
]

#: Component id of the bridge: MAVSDK only discovers an autopilot from a component-1 HEARTBEAT.
COMPONENT_ID = mavlink.MAV_COMP_ID_AUTOPILOT1

MSG_ID_PROTOCOL_VERSION = 300
_PROTOCOL_VERSION_CRC_EXTRA = 217


class Identity(enum.Enum):
    """Which autopilot a link's HEARTBEAT claims, which fixes how clients encode integers.

    GENERIC (the default) is the honest answer: QGroundControl loads its generic plugin (no
    setup pages, no missing-parameter or firmware-version dialogs) and, like MAVSDK, sends
    integers bytewise. MAVProxy reads integers bytewise only from a PX4 and as a plain float
    otherwise, so a MAVProxy link says `identity=px4`; ARDUPILOT makes every client use the C
    cast (exact only up to 2**24). Chosen per link (see docs/ground-stations.md); the bridge
    never invents another firmware's parameters or version to go with a claim.
    """

    GENERIC = "generic"
    PX4 = "px4"
    ARDUPILOT = "ardupilot"

    @property
    def autopilot(self) -> int:
        if self is Identity.PX4:
            return int(mavlink.MAV_AUTOPILOT_PX4)
        if self is Identity.ARDUPILOT:
            return int(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
        return int(mavlink.MAV_AUTOPILOT_GENERIC)

    @property
    def bytewise(self) -> bool:
        """Whether integer parameters travel bytewise (else by C cast) under this claim."""
        return self is not Identity.ARDUPILOT

    @classmethod
    def parse(cls, text: str) -> Identity:
        """An identity from its name; ValueError names the choices."""
        try:
            return cls(text.strip().lower())
        except ValueError:
            raise ValueError(f"identity {text!r}: use generic, px4 or ardupilot") from None


class ProtocolVersionMessage(mavlink.MAVLink_message):
    """PROTOCOL_VERSION (id 300), absent from pymavlink 2.4.50's common dialect."""

    id = MSG_ID_PROTOCOL_VERSION
    msgname = "PROTOCOL_VERSION"
    fieldnames = ["version", "min_version", "max_version", "spec_version_hash",
                  "library_version_hash"]
    ordered_fieldnames = list(fieldnames)
    fieldtypes = ["uint16_t", "uint16_t", "uint16_t", "uint8_t", "uint8_t"]
    orders = [0, 1, 2, 3, 4]
    lengths = [1, 1, 1, 8, 8]
    array_lengths = [0, 0, 0, 8, 8]
    crc_extra = _PROTOCOL_VERSION_CRC_EXTRA
    unpacker = struct.Struct("<HHH8s8s")

    def __init__(self, version: int, min_version: int, max_version: int,
                 spec_version_hash: bytes = b"", library_version_hash: bytes = b"") -> None:
        mavlink.MAVLink_message.__init__(self, self.id, self.msgname)
        self._fieldnames = list(self.fieldnames)
        self.version = version
        self.min_version = min_version
        self.max_version = max_version
        self.spec_version_hash = spec_version_hash[:8].ljust(8, b"\0")
        self.library_version_hash = library_version_hash[:8].ljust(8, b"\0")

    def pack(self, mav: mavlink.MAVLink, force_mavlink1: bool = False) -> bytes:
        payload = self.unpacker.pack(self.version, self.min_version, self.max_version,
                                     self.spec_version_hash, self.library_version_hash)
        return self._pack(mav, self.crc_extra, payload, force_mavlink1=force_mavlink1)


def crc_extra_of(msg_id: int) -> int | None:
    """CRC_EXTRA of a message id, or None when the dialect does not know it."""
    if msg_id == MSG_ID_PROTOCOL_VERSION:
        return _PROTOCOL_VERSION_CRC_EXTRA
    cls = mavlink.mavlink_map.get(msg_id)
    return None if cls is None else int(cls.crc_extra)


def message_name(msg_id: int) -> str:
    if msg_id == MSG_ID_PROTOCOL_VERSION:
        return "PROTOCOL_VERSION"
    cls = mavlink.mavlink_map.get(msg_id)
    return str(cls.msgname) if cls is not None else f"UNKNOWN_{msg_id}"


_ID_BY_NAME = {str(cls.msgname): int(mid) for mid, cls in mavlink.mavlink_map.items()}
_ID_BY_NAME["PROTOCOL_VERSION"] = MSG_ID_PROTOCOL_VERSION


def message_id(name: str) -> int | None:
    """Message id of a MAVLink message name (upper case), or None when unknown."""
    return _ID_BY_NAME.get(name.upper())
