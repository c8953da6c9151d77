"""The MAVLink dialect the bridge speaks, plus what pymavlink 2.4.50 leaves out of it.

The bridge speaks MAVLink 2 with the `common` message set only: every ground station knows it,
and a vehicle that claims no vendor dialect is not asked vendor questions. pymavlink's generated
`common` module lacks PROTOCOL_VERSION (id 300), which QGroundControl asks for to decide whether
to switch to MAVLink 2, so it is defined here from the message definition.
"""

from __future__ import annotations

import enum
import logging
import math
import struct
from collections.abc import Sequence
from typing import Any, ClassVar

from pymavlink.dialects.v20 import common as mavlink
from pymavlink.dialects.v20.common import MAVLink_message as Message
from pymavlink.generator.mavcrc import x25crc

log = logging.getLogger(__name__)

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
    "AvailableModesMessage",
    "COMP_METADATA_TYPE_GENERAL",
    "COMP_METADATA_TYPE_PARAMETER",
    "ComponentMetadataMessage",
    "CurrentModeMessage",
    "DefinedMessage",
    "EXTRA_MESSAGES",
    "Field",
    "MAV_MODE_PROPERTY_ADVANCED",
    "MAV_MODE_PROPERTY_NOT_USER_SELECTABLE",
    "MSG_ID_AVAILABLE_MODES",
    "MSG_ID_COMPONENT_METADATA",
    "MSG_ID_CURRENT_MODE",
    "compute_crc_extra",
    "register_extra_messages",
    "wire_order",
    "UINT16_MAX",
    "INT16_MAX",
    "clamp_int",
    "nan_if_none",
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
    extra = EXTRA_MESSAGES.get(msg_id)  # known even if never registered with pymavlink
    if extra is not None:
        return int(extra.crc_extra)
    cls = mavlink.mavlink_map.get(msg_id)
    return None if cls is None else int(cls.crc_extra)


def message_name(msg_id: int) -> str:
    if msg_id == MSG_ID_PROTOCOL_VERSION:
        return "PROTOCOL_VERSION"
    extra = EXTRA_MESSAGES.get(msg_id)
    if extra is not None:
        return extra.msgname
    cls = mavlink.mavlink_map.get(msg_id)
    return str(cls.msgname) if cls is not None else f"UNKNOWN_{msg_id}"


_ID_BY_NAME = {str(cls.msgname): int(mid) for mid, cls in mavlink.mavlink_map.items()}
_ID_BY_NAME["PROTOCOL_VERSION"] = MSG_ID_PROTOCOL_VERSION


def message_id(name: str) -> int | None:
    """Message id of a MAVLink message name (upper case), or None when unknown."""
    return _ID_BY_NAME.get(name.upper())



# ------------------------------------------------------------------------------ field values
UINT16_MAX = 0xFFFF
INT16_MAX = 0x7FFF


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

# ----------------------------------------------------------- messages newer than pymavlink 2.4.50
# COMPONENT_METADATA (QGroundControl and MAVSDK ask for it to find the parameter metadata),
# AVAILABLE_MODES (QGroundControl enumerates the flight modes with it) and CURRENT_MODE
# (QGroundControl and MAVSDK's events plugin read the intended mode from it) are in common.xml
# but not in pymavlink 2.4.50. They are defined here from their XML field lists, and their
# CRC_EXTRA is computed from those lists the way mavgen does, so a typo in a field shows up as
# a CRC mismatch against the reference values in the tests rather than as silently dropped
# frames. COMPONENT_INFORMATION (395) is left out on purpose: it is deprecated, QGroundControl
# only falls back to it when COMPONENT_METADATA fails, and its layout changed twice (CRC_EXTRA
# 163, 231, then 0), so a client built against another layout would drop it anyway.

#: COMP_METADATA_TYPE values (common.xml; pymavlink 2.4.50 has no such enum).
COMP_METADATA_TYPE_GENERAL = 0
COMP_METADATA_TYPE_PARAMETER = 1

#: MAV_MODE_PROPERTY bits (common.xml; absent from pymavlink 2.4.50).
MAV_MODE_PROPERTY_ADVANCED = 1
MAV_MODE_PROPERTY_NOT_USER_SELECTABLE = 2

MSG_ID_COMPONENT_METADATA = 397
MSG_ID_AVAILABLE_MODES = 435
MSG_ID_CURRENT_MODE = 436

#: A field as the XML declares it: (base type, name, array length or 0). "char[100]" is
#: ("char", "uri", 100); the "uint8_t_mavlink_version" pseudo-type is plain "uint8_t".
Field = tuple[str, str, int]

#: MAVLink base type -> (struct code, size in bytes).
_BASE_TYPES: dict[str, tuple[str, int]] = {
    "char": ("s", 1), "uint8_t": ("B", 1), "int8_t": ("b", 1),
    "uint16_t": ("H", 2), "int16_t": ("h", 2),
    "uint32_t": ("I", 4), "int32_t": ("i", 4), "float": ("f", 4),
    "uint64_t": ("Q", 8), "int64_t": ("q", 8), "double": ("d", 8),
}


def wire_order(fields: Sequence[Field]) -> list[Field]:
    """The order fields travel in: largest base type first, ties in declaration order (a stable
    sort, as mavgen does, so every field is naturally aligned on the wire)."""
    return sorted(fields, key=lambda f: -_BASE_TYPES[f[0]][1])


def compute_crc_extra(name: str, fields: Sequence[Field]) -> int:
    """CRC_EXTRA of a message from its name and its base fields (extensions excluded).

    mavgen's recipe: X.25 CRC over "NAME ", then for each field in wire order "type " and
    "name " and, for an array, one byte holding its length; the two CRC bytes XORed.
    """
    crc = x25crc((name + " ").encode("ascii"))
    for ftype, fname, length in wire_order(fields):
        crc.accumulate_str(ftype + " ")
        crc.accumulate_str(fname + " ")
        if length:
            crc.accumulate([length])
    return (crc.crc & 0xFF) ^ (crc.crc >> 8)


class DefinedMessage(mavlink.MAVLink_message):
    """A message built from its XML field list, packable and decodable like a generated one.

    Subclasses set `id`, `msgname` and `definition`; everything pymavlink's encoder, decoder
    and tools read (field names, wire order, struct layout, CRC_EXTRA) is derived from that
    list. A char array is kept both as text (the attribute, cut at the first NUL, as pymavlink
    does) and as the raw bytes that are packed; any value decodes without raising.
    """

    id: ClassVar[int]
    msgname: ClassVar[str]
    definition: ClassVar[tuple[Field, ...]]
    fieldnames: ClassVar[list[str]]
    ordered_fieldnames: ClassVar[list[str]]
    fieldtypes: ClassVar[list[str]]
    fielddisplays_by_name: ClassVar[dict[str, str]] = {}
    fieldenums_by_name: ClassVar[dict[str, str]] = {}
    fieldunits_by_name: ClassVar[dict[str, str]] = {}
    orders: ClassVar[list[int]]
    lengths: ClassVar[list[int]]
    array_lengths: ClassVar[list[int]]
    crc_extra: ClassVar[int]
    unpacker: ClassVar[struct.Struct]
    native_format: ClassVar[bytearray]
    instance_field: ClassVar[str | None] = None
    instance_offset: ClassVar[int] = -1

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        fields = cls.definition
        wire = wire_order(fields)
        cls.fieldnames = [f[1] for f in fields]
        cls.ordered_fieldnames = [f[1] for f in wire]
        cls.fieldtypes = [f[0] for f in fields]
        cls.orders = [cls.ordered_fieldnames.index(f[1]) for f in fields]
        # struct items per wire field: a char array is one "Ns" item, a numeric array N items
        cls.lengths = [f[2] if f[2] and f[0] != "char" else 1 for f in wire]
        cls.array_lengths = [f[2] for f in wire]
        cls.unpacker = struct.Struct("<" + "".join(
            f"{f[2] or ''}{_BASE_TYPES[f[0]][0]}" for f in wire))
        cls.native_format = bytearray(
            ("<" + "".join("c" if f[0] == "char" else _BASE_TYPES[f[0]][0] for f in wire))
            .encode("ascii"))
        cls.crc_extra = compute_crc_extra(cls.msgname, fields)

    def _set_fields(self, values: dict[str, Any]) -> None:
        mavlink.MAVLink_message.__init__(self, self.id, self.msgname)
        self._fieldnames = list(self.fieldnames)
        self._instance_field = self.instance_field
        self._instance_offset = self.instance_offset
        for ftype, name, length in self.definition:
            value = values[name]
            if ftype == "char":
                raw = value if isinstance(value, bytes | bytearray) else str(value).encode()
                setattr(self, "_" + name + "_raw", bytes(raw))
                setattr(self, name, bytes(raw).split(b"\0", 1)[0].decode("ascii", "replace"))
            elif length:
                setattr(self, name, list(value))
            else:
                setattr(self, name, value)

    def pack(self, mav: mavlink.MAVLink, force_mavlink1: bool = False) -> bytes:
        items: list[Any] = []
        for ftype, name, length in wire_order(self.definition):
            if ftype == "char":
                items.append(getattr(self, "_" + name + "_raw"))
            elif length:
                items.extend((list(getattr(self, name)) + [0] * length)[:length])
            else:
                items.append(getattr(self, name))
        return self._pack(mav, self.crc_extra, self.unpacker.pack(*items),
                          force_mavlink1=force_mavlink1)


class ComponentMetadataMessage(DefinedMessage):
    """COMPONENT_METADATA (id 397): where the general metadata file is, and its CRC32."""

    id = MSG_ID_COMPONENT_METADATA
    msgname = "COMPONENT_METADATA"
    definition = (("uint32_t", "time_boot_ms", 0), ("uint32_t", "file_crc", 0),
                  ("char", "uri", 100))
    time_boot_ms: int
    file_crc: int
    uri: str

    def __init__(self, time_boot_ms: int, file_crc: int, uri: str | bytes) -> None:
        self._set_fields({"time_boot_ms": time_boot_ms, "file_crc": file_crc, "uri": uri})


class AvailableModesMessage(DefinedMessage):
    """AVAILABLE_MODES (id 435): one flight mode of `number_modes` (`mode_index` from 1)."""

    id = MSG_ID_AVAILABLE_MODES
    msgname = "AVAILABLE_MODES"
    definition = (("uint8_t", "number_modes", 0), ("uint8_t", "mode_index", 0),
                  ("uint8_t", "standard_mode", 0), ("uint32_t", "custom_mode", 0),
                  ("uint32_t", "properties", 0), ("char", "mode_name", 35))
    fieldenums_by_name = {"standard_mode": "MAV_STANDARD_MODE",
                          "properties": "MAV_MODE_PROPERTY"}
    number_modes: int
    mode_index: int
    standard_mode: int
    custom_mode: int
    properties: int
    mode_name: str

    def __init__(self, number_modes: int, mode_index: int, standard_mode: int,
                 custom_mode: int, properties: int, mode_name: str | bytes) -> None:
        self._set_fields({"number_modes": number_modes, "mode_index": mode_index,
                          "standard_mode": standard_mode, "custom_mode": custom_mode,
                          "properties": properties, "mode_name": mode_name})


class CurrentModeMessage(DefinedMessage):
    """CURRENT_MODE (id 436): the mode now, and the one last commanded (0: unknown)."""

    id = MSG_ID_CURRENT_MODE
    msgname = "CURRENT_MODE"
    definition = (("uint8_t", "standard_mode", 0), ("uint32_t", "custom_mode", 0),
                  ("uint32_t", "intended_custom_mode", 0))
    fieldenums_by_name = {"standard_mode": "MAV_STANDARD_MODE"}
    standard_mode: int
    custom_mode: int
    intended_custom_mode: int

    def __init__(self, standard_mode: int, custom_mode: int,
                 intended_custom_mode: int = 0) -> None:
        self._set_fields({"standard_mode": standard_mode, "custom_mode": custom_mode,
                          "intended_custom_mode": intended_custom_mode})


#: The messages this module adds to pymavlink's common dialect, by id.
EXTRA_MESSAGES: dict[int, type[DefinedMessage]] = {
    cls.id: cls for cls in (ComponentMetadataMessage, AvailableModesMessage, CurrentModeMessage)
}


def register_extra_messages() -> None:
    """Make every pymavlink parser of the common dialect decode the messages defined here.

    pymavlink looks a received id up in the module-wide `mavlink_map`, so this teaches every
    parser in the process at once: the bridge's (which then see a stray COMPONENT_METADATA
    from another component as what it is, and ignore it like any message they do not
    handle) and a test's or tool's. That is safe because these classes decode any payload
    without raising (pymavlink zero-pads a short one), exactly like generated ones. A class
    that pymavlink itself defines one day is left in place. Idempotent; done on import.
    """
    for msg_id, cls in EXTRA_MESSAGES.items():
        existing = mavlink.mavlink_map.setdefault(msg_id, cls)
        if existing is not cls and existing.msgname != cls.msgname:
            log.warning("message id %d is %s in pymavlink, not %s", msg_id,
                        existing.msgname, cls.msgname)
            continue
        _ID_BY_NAME.setdefault(str(existing.msgname), msg_id)


register_extra_messages()
