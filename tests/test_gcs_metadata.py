"""Component metadata (COMPONENT_METADATA and its two JSON files) and the messages the bridge
adds to pymavlink 2.4.50's common dialect, without sockets.

References that do not come from the code under test: pymavlink's own generator (mavparse)
and the message definitions pymavlink ships, pymavlink's generated `development` dialect
(which has AVAILABLE_MODES and CURRENT_MODE), the CRC_EXTRA values of the C headers generated
from mavlink/mavlink's common.xml, and a bit-by-bit CRC32.
"""

from __future__ import annotations

import json
import re
import struct
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import development
from pymavlink.generator import mavparse
from pymavlink.generator.mavcrc import x25crc

from companion.core.config import Config
from companion.core.params import ParamSpec, ParamType, float_param, format_value, int_param
from companion.runtime import declared_registry
from gcs_bridge import dialect
from gcs_bridge.dialect import (
    EXTRA_MESSAGES,
    MSG_ID_PROTOCOL_VERSION,
    AvailableModesMessage,
    ComponentMetadataMessage,
    CurrentModeMessage,
    compute_crc_extra,
    crc_extra_of,
    mavlink,
    message_id,
    message_name,
)
from gcs_bridge.services import metadata
from gcs_bridge.services.ftp_wire import mavlink_crc32
from gcs_bridge.services.metadata import (
    GENERAL_PATH,
    PARAMETERS_PATH,
    ComponentMetadata,
    normalize_path,
    split_description,
)

PYMAVLINK_XML = Path(mavlink.__file__).resolve().parent

# The definitions as mavlink/mavlink's message_definitions/v1.0/common.xml has them.
NEW_MESSAGES_XML = """<?xml version="1.0"?>
<mavlink>
  <version>3</version>
  <messages>
    <message id="397" name="COMPONENT_METADATA">
      <description>Component metadata message.</description>
      <field type="uint32_t" name="time_boot_ms" units="ms">Timestamp.</field>
      <field type="uint32_t" name="file_crc">CRC32 of the general metadata file.</field>
      <field type="char[100]" name="uri">MAVLink FTP URI for the general metadata file.</field>
    </message>
    <message id="435" name="AVAILABLE_MODES">
      <description>Information about a flight mode.</description>
      <field type="uint8_t" name="number_modes">Number of modes.</field>
      <field type="uint8_t" name="mode_index">Mode index, from 1.</field>
      <field type="uint8_t" name="standard_mode" enum="MAV_STANDARD_MODE">Standard mode.</field>
      <field type="uint32_t" name="custom_mode">Custom mode.</field>
      <field type="uint32_t" name="properties" enum="MAV_MODE_PROPERTY">Properties.</field>
      <field type="char[35]" name="mode_name">Name of custom mode.</field>
    </message>
    <message id="436" name="CURRENT_MODE">
      <description>Get the current mode.</description>
      <field type="uint8_t" name="standard_mode" enum="MAV_STANDARD_MODE">Standard mode.</field>
      <field type="uint32_t" name="custom_mode">Custom mode.</field>
      <field type="uint32_t" name="intended_custom_mode" invalid="0">Intended mode.</field>
    </message>
  </messages>
</mavlink>
"""
# MAVLINK_MSG_ID_<NAME>_CRC in the C headers generated from the same common.xml.
C_HEADER_CRC_EXTRA = {"COMPONENT_METADATA": 182, "AVAILABLE_MODES": 134, "CURRENT_MODE": 193}

# Keys of component_metadata/general.schema.json and parameter.schema.json (mavlink/mavlink),
# both "additionalProperties": false.
GENERAL_KEYS = {"version", "vendorName", "modelName", "firmwareVersion", "hardwareVersion",
                "metadataTypes"}
GENERAL_REQUIRED = {"version", "metadataTypes"}
METADATA_TYPE_KEYS = {"type", "uri", "fileCrc", "uriFallback", "fileCrcFallback",
                      "translationUri", "translationUriFallback"}
METADATA_TYPE_REQUIRED = {"type", "uri"}
PARAMETER_FILE_KEYS = {"version", "translation", "parameters"}
PARAMETER_KEYS = {"name", "type", "shortDesc", "longDesc", "units", "default", "decimalPlaces",
                  "min", "max", "increment", "rebootRequired", "group", "category", "volatile",
                  "values", "bitmask", "readOnly"}
PARAMETER_NAME_RE = re.compile(r"^[\.\-a-zA-Z0-9_\{\}]{1,16}$")


def parse(frame: bytes) -> Any:
    """What a fresh pymavlink parser of the common dialect makes of one frame."""
    return mavlink.MAVLink(None, 0, 0).parse_char(frame)


def frame_of(msg_id: int, payload: bytes, crc_extra: int) -> bytes:
    """A MAVLink 2 frame built by hand (any payload, correct checksum)."""
    header = bytes([0xFD, len(payload), 0, 0, 0, 1, 1,
                    msg_id & 0xFF, (msg_id >> 8) & 0xFF, msg_id >> 16])
    crc = x25crc(header[1:] + payload)
    crc.accumulate(bytes([crc_extra]))
    return header + payload + struct.pack("<H", crc.crc)


# ------------------------------------------------------------------------------- dialect
def test_crc_extra_recipe_matches_mavgen_for_every_shipped_message() -> None:
    checked = 0
    for xml in ("minimal.xml", "standard.xml", "common.xml", "development.xml"):
        for m in mavparse.MAVXML(str(PYMAVLINK_XML / xml), mavparse.PROTOCOL_2_0).message:
            base = m.fields if m.extensions_start is None else m.fields[:m.extensions_start]
            fields = [(f.type, f.name, f.array_length) for f in base]
            assert compute_crc_extra(m.name, fields) == m.crc_extra, m.name
            checked += 1
    assert checked > 200
    heartbeat = [("uint8_t", "type", 0), ("uint8_t", "autopilot", 0), ("uint8_t", "base_mode", 0),
                 ("uint32_t", "custom_mode", 0), ("uint8_t", "system_status", 0),
                 ("uint8_t", "mavlink_version", 0)]
    assert compute_crc_extra("HEARTBEAT", heartbeat) == 50
    protocol_version = [("uint16_t", "version", 0), ("uint16_t", "min_version", 0),
                        ("uint16_t", "max_version", 0), ("uint8_t", "spec_version_hash", 8),
                        ("uint8_t", "library_version_hash", 8)]
    assert compute_crc_extra("PROTOCOL_VERSION", protocol_version) == 217
    assert crc_extra_of(MSG_ID_PROTOCOL_VERSION) == 217


def test_new_messages_match_their_definitions(tmp_path: Path) -> None:
    xml = tmp_path / "new.xml"
    xml.write_text(NEW_MESSAGES_XML, encoding="utf-8")
    reference = {m.name: m for m in mavparse.MAVXML(str(xml), mavparse.PROTOCOL_2_0).message}
    assert {cls.msgname for cls in EXTRA_MESSAGES.values()} == set(reference)
    for msg_id, cls in EXTRA_MESSAGES.items():
        ref = reference[cls.msgname]
        assert (msg_id, cls.id) == (ref.id, ref.id)
        assert cls.crc_extra == ref.crc_extra == C_HEADER_CRC_EXTRA[cls.msgname]
        assert cls.fieldnames == ref.fieldnames
        assert cls.ordered_fieldnames == ref.ordered_fieldnames
        assert cls.unpacker.size == ref.wire_length
        assert crc_extra_of(msg_id) == cls.crc_extra
        assert message_name(msg_id) == cls.msgname
        assert message_id(cls.msgname.lower()) == msg_id


@pytest.mark.parametrize("ours, theirs, args", [
    (AvailableModesMessage, development.MAVLink_available_modes_message,
     (4, 2, 0, 0x10203, 2, b"ATTITUDE HOLD")),
    (CurrentModeMessage, development.MAVLink_current_mode_message, (0, 0x10203, 7)),
])
def test_modes_messages_interoperate_with_pymavlink_generated_ones(
        ours: type[dialect.DefinedMessage], theirs: Any, args: tuple[Any, ...]) -> None:
    assert (ours.crc_extra, ours.unpacker.format) == (theirs.crc_extra, theirs.unpacker.format)
    assert (ours.orders, ours.lengths) == (theirs.orders, theirs.lengths)
    assert ours.array_lengths == theirs.array_lengths
    mine = ours(*args).pack(mavlink.MAVLink(None, 1, 1))
    decoded = development.MAVLink(None, 0, 0).parse_char(mine)
    back = parse(theirs(*args).pack(development.MAVLink(None, 1, 1)))
    assert isinstance(back, ours)
    for name in ours.fieldnames:
        assert getattr(decoded, name) == getattr(back, name), name


def test_component_metadata_message_round_trip_and_registration() -> None:
    msg = ComponentMetadataMessage(123_456, 0xFEDCBA98, "mftp://[;comp=1]@meta/general.json")
    frame = msg.pack(mavlink.MAVLink(None, 7, 1))
    assert frame[7] | frame[8] << 8 | frame[9] << 16 == 397
    assert frame[1] < 108  # MAVLink 2 trims the URI's trailing zeros; the decoder pads them
    got = parse(frame)
    assert got.get_type() == "COMPONENT_METADATA"
    assert (got.time_boot_ms, got.file_crc) == (123_456, 0xFEDCBA98)
    assert got.uri == "mftp://[;comp=1]@meta/general.json"
    assert got.to_dict()["uri"] == got.uri
    dialect.register_extra_messages()  # idempotent
    assert all(mavlink.mavlink_map[i] is cls for i, cls in EXTRA_MESSAGES.items())


@settings(max_examples=150, deadline=None)
@given(st.sampled_from(sorted(EXTRA_MESSAGES)), st.data())
def test_any_payload_decodes_or_fails_as_pymavlink_does(msg_id: int, data: st.DataObject) -> None:
    cls = EXTRA_MESSAGES[msg_id]
    payload = data.draw(st.binary(max_size=cls.unpacker.size))
    got = parse(frame_of(msg_id, payload, cls.crc_extra))
    assert got is not None and got.get_type() == cls.msgname
    str(got)
    got.pack(mavlink.MAVLink(None, 1, 1))  # what was decoded packs again


# ------------------------------------------------------------------------------- files
def crc32_bitwise(data: bytes) -> int:
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0xEDB88320 if crc & 1 else 0)
    return crc


def test_crc32_is_mavlinks_variant() -> None:
    for data in (b"", b"123456789", bytes(range(256)) * 3):
        assert mavlink_crc32(data) == crc32_bitwise(data)
    assert mavlink_crc32(b"123456789") == 0x2DFD2D88  # not zlib's 0xCBF43926


def runtime_specs() -> list[ParamSpec]:
    return declared_registry(Config()).specs()


def qgc_ftp_path(uri: str) -> str:
    """QGroundControl's FTPManager::_parseURI: drop "mftp:/" (keeping one slash), then the
    `[;comp=N]` tag."""
    path = uri[len("mftp://") - 1:] if uri.lower().startswith("mftp://") else uri
    assert "://" not in path
    if re.match(r"^/??\[;comp=(\d+)\]", path):
        path = re.sub(r"\[;comp=\d+\]", "", path)
    return path


def mavsdk_ftp_path(uri: str) -> tuple[str, int | None]:
    """MAVSDK's uri_is_mavlinkftp: drop "mftp://", then an optional leading `[;comp=N]`."""
    assert uri.lower().startswith("mftp://")
    path = uri[len("mftp://"):]
    match = re.match(r"^(?:\[;comp=(\d+)\])(.*)", path)
    return (match.group(2), int(match.group(1))) if match else (path, None)


def test_general_file_follows_the_schema_and_both_clients_find_the_files() -> None:
    cm = ComponentMetadata(runtime_specs, 1, vendor_name="Uni", model_name="fixed-wing")
    files = cm.virtual_files()
    general_bytes, params_bytes = files[GENERAL_PATH](), files[PARAMETERS_PATH]()
    general = json.loads(general_bytes)
    assert GENERAL_REQUIRED <= set(general) <= GENERAL_KEYS
    assert general["version"] == 1  # QGroundControl and MAVSDK accept no other
    (entry,) = general["metadataTypes"]
    assert METADATA_TYPE_REQUIRED <= set(entry) <= METADATA_TYPE_KEYS
    assert entry["type"] == 1  # COMP_METADATA_TYPE_PARAMETER
    # QGroundControl skips a type without fileCrc; MAVSDK wants an unsigned integer
    assert entry["fileCrc"] == mavlink_crc32(params_bytes) and 0 <= entry["fileCrc"] < 2**32
    msg = parse(cm.message(42).pack(mavlink.MAVLink(None, 1, 1)))
    assert (msg.time_boot_ms, msg.file_crc) == (42, mavlink_crc32(general_bytes))
    assert len(msg.uri) <= 99
    for uri, expected in ((msg.uri, general_bytes), (entry["uri"], params_bytes)):
        qgc = qgc_ftp_path(uri)
        mavsdk, compid = mavsdk_ftp_path(uri)
        assert compid == 1
        assert qgc.startswith("/@meta/") and mavsdk.startswith("@meta/")
        assert cm.read(qgc) == cm.read(mavsdk) == expected
        assert files[normalize_path(qgc)]() == files[normalize_path(mavsdk + "\0")]() == expected
    assert cm.read("/@meta/nothing.json") is None


def test_other_component_ids_are_named_in_the_uris() -> None:
    cm = ComponentMetadata(runtime_specs, 191)
    assert cm.uri == "mftp://[;comp=191]@meta/general.json"
    assert mavsdk_ftp_path(cm.uri) == ("@meta/general.json", 191)
    with pytest.raises(ValueError):
        ComponentMetadata(runtime_specs, 0)
    with pytest.raises(ValueError):
        ComponentMetadata(runtime_specs, 1, firmware_version="v1")


def test_every_declared_parameter_is_described() -> None:
    specs = runtime_specs()
    doc = json.loads(ComponentMetadata(lambda: specs, 1).virtual_files()[PARAMETERS_PATH]())
    assert set(doc) <= PARAMETER_FILE_KEYS
    assert doc["version"] == 1  # QGroundControl's CompInfoParam rejects any other
    entries = {e["name"]: e for e in doc["parameters"]}
    assert list(entries) == [s.name for s in specs]
    for spec in specs:
        e = entries[spec.name]
        assert set(e) <= PARAMETER_KEYS and PARAMETER_NAME_RE.match(e["name"])
        assert e["type"] == ("Int32" if spec.ptype is ParamType.INT32 else "Float")
        assert e["shortDesc"] and not e["shortDesc"].endswith(".")
        assert " ".join(spec.description.split()).startswith(e["shortDesc"])
        assert e.get("units", "") == metadata.qgc_unit(spec.unit)
        for key in ("default", "min", "max"):
            assert format_value(spec.ptype, e[key]) == format_value(spec.ptype,
                                                                    getattr(spec, key))
        assert e["group"] == spec.name.split("_")[0]
        assert e.get("readOnly", False) == spec.read_only
        assert e.get("rebootRequired", False) == spec.reboot_required
        assert isinstance(e["decimalPlaces"], int) and e["decimalPlaces"] >= 0
    assert entries["MAV_B1_V_FULL"]["units"] == "V"
    assert entries["MAV_B1_V_FULL"]["longDesc"].startswith("The board's raw unit")
    assert entries["EST_GB_RW"]["decimalPlaces"] >= 8  # shows its 1e-08 lower limit


def test_files_follow_the_spec_list_and_are_cached() -> None:
    specs = [int_param("TST_A", 1, 0, 10, "ms", "First. Second sentence.")]
    cm = ComponentMetadata(lambda: list(specs), 1)
    files = cm.virtual_files()
    params1, crc1 = files[PARAMETERS_PATH](), cm.general_crc
    assert files[PARAMETERS_PATH]() is params1  # same specs: not regenerated
    specs.append(float_param("TST_B", 0.5, 0.0, 1.0, "degC", "Temperature offset",
                             read_only=True))
    params2 = files[PARAMETERS_PATH]()
    assert params2 != params1 and cm.general_crc != crc1
    assert json.loads(files[GENERAL_PATH]())["metadataTypes"][0]["fileCrc"] == \
        mavlink_crc32(params2)
    e = json.loads(params2)["parameters"][1]
    assert (e["units"], e["readOnly"], e["type"]) == ("C", True, "Float")
    assert parse(cm.message(0).pack(mavlink.MAVLink(None, 1, 1))).file_crc == cm.general_crc


@pytest.mark.parametrize("text, short, long", [
    ("Restart intensity period, in seconds.", "Restart intensity period, in seconds", ""),
    ("Runs it. 0 = unlimited.", "Runs it", "0 = unlimited."),
    ("Rate; 0 = off. A link's own setting (e.g. `?ATTITUDE=10`) wins.", "Rate; 0 = off",
     "A link's own setting (e.g. `?ATTITUDE=10`) wins."),
    ("Raw unit unknown (thesis ch. 6), so x. Later.", "Raw unit unknown (thesis ch. 6), so x",
     "Later."),
    ("Value 1.5 is the  default", "Value 1.5 is the default", ""),
    ("", "", ""),
])
def test_descriptions_split_into_short_and_long(text: str, short: str, long: str) -> None:
    assert split_description(text) == (short, long)


def test_units_qgroundcontrol_converts_keep_its_spelling() -> None:
    assert [metadata.qgc_unit(u) for u in ("degC", "radians", "ms", "m/s", "", " V ")] == [
        "C", "rad", "ms", "m/s", "", "V"]


def test_decimal_places_show_the_limits() -> None:
    spec = ParamSpec("TST_X", ParamType.FLOAT32, 0.25, 0.001, 100.0)
    assert metadata.parameter_entry(spec)["decimalPlaces"] == 3
    spec = ParamSpec("TST_Y", ParamType.FLOAT32, 1.0, 0.0, 10.0)
    assert metadata.parameter_entry(spec)["decimalPlaces"] == 2
    spec = ParamSpec("TST_Z", ParamType.INT32, 3, 0, 10)
    assert (metadata.parameter_entry(spec)["decimalPlaces"],
            metadata.parameter_entry(spec)["increment"]) == (0, 1)
