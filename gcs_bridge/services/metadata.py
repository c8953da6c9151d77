"""Component metadata: the parameter documentation QGroundControl and MAVSDK download.

A ground station that asks for COMPONENT_METADATA (MAV_CMD_REQUEST_MESSAGE 397) gets a MAVLink
FTP URI and a CRC32 of the "general" metadata file; it downloads that file over MAVLink FTP,
finds in it the URI and CRC32 of the parameter metadata file, and downloads that too. Both
files are generated here from the same `ParamSpec` table that docs/parameters.md comes from,
so QGroundControl's parameter editor shows the descriptions, units, ranges, defaults and
groups the code declares, and they can never disagree.

What the clients need, and why the choices below:

- URI: `mftp://[;comp=<compid>]@meta/<file>`, the spec's `mftp://[;comp=<id>]<path>`.
  QGroundControl keeps the slash of "mftp://" and drops the `[;comp=N]` tag, so it asks for
  "/@meta/general.json"; MAVSDK drops "mftp://" and the tag, so it asks for
  "@meta/general.json". The FTP server must therefore ignore leading slashes:
  `normalize_path` (and `ComponentMetadata.read`) do. Both clients honour the component tag,
  so the files are fetched from the bridge's component even when it is not 1.
- Plain JSON, no .xz: both clients can inflate .xz, but QGroundControl's libarchive path has
  been seen to fail silently on .xz files, and the parameter file of this runtime is small
  (a few tens of KiB for ~100 parameters), so the robust choice costs little.
- CRC32: MAVLink's variant (the Gary Brown table, initial value 0, no final XOR; PX4's
  generator and MAVSDK's server compute the same) over the bytes exactly as served. Neither
  client checks a download against it: they use it as the cache key, so it must change
  whenever the content does, which it does because the files are regenerated from the spec
  list whenever that changes. QGroundControl ignores a metadata type without a `fileCrc`.
- "version": 1 in both files: QGroundControl rejects any other version (even though the
  parameter schema in mavlink/mavlink now says 3), PX4 and MAVSDK write 1.
- Parameter entries use the schema's keys: `readOnly` for read-only parameters (QGroundControl
  does not read it yet; the registry refuses the write and says why), `rebootRequired`, and
  `group` = the name's prefix, which is how QGroundControl groups parameters anyway.
"""

from __future__ import annotations

import json
import logging
import re
import threading
from collections.abc import Callable
from typing import Any

from companion.core.params import ParamSpec, ParamType, format_value
from gcs_bridge.dialect import (
    COMP_METADATA_TYPE_PARAMETER,
    ComponentMetadataMessage,
)
from gcs_bridge.services.ftp_wire import mavlink_crc32

log = logging.getLogger(__name__)

META_DIR = "/@meta"
GENERAL_PATH = f"{META_DIR}/general.json"
PARAMETERS_PATH = f"{META_DIR}/parameters.json"

URI_MAX_LEN = 99  # a char[100] field that must stay NUL-terminated (MAVSDK forces uri[99] = 0)
METADATA_VERSION = 1
CATEGORY = "Standard"
FLOAT_DECIMALS_MIN = 2
FLOAT_DECIMALS_MAX = 9

#: Unit spellings QGroundControl knows under another name; it converts and labels those (for
#: instance "C" follows the user's temperature unit). Units not listed are shown as written.
QGC_UNITS: dict[str, str] = {
    "degC": "C", "°C": "C", "celsius": "C",
    "meter": "m", "meters": "m", "metre": "m", "metres": "m",
    "radian": "rad", "radians": "rad",
    "cdeg": "centi-degrees", "centidegrees": "centi-degrees",
    "m2": "m^2", "m²": "m^2",
    "gram": "g", "grams": "g",
}

_VERSION_RE = re.compile(r"^\d+\.\d+\.\d+(\.\d+)?$")
# A sentence ends at . ! or ? followed by blanks and a capital, a digit or an opening mark,
# unless the word before the point is an abbreviation ("e.g. `x`", "thesis ch. 6").
_SENTENCE_END_RE = re.compile(r"(?<=[.!?])\s+(?=[A-Z0-9`(\[\"'])")
_ABBREVIATIONS = {"e.g.", "i.e.", "ch.", "cf.", "vs.", "etc.", "approx.", "fig.", "eq.", "no.",
                  "resp.", "sec.", "min.", "max."}


def mftp_uri(compid: int, path: str) -> str:
    """The MAVLink FTP URI of a file of component `compid` (see the module docstring)."""
    return f"mftp://[;comp={int(compid)}]{path.lstrip('/')}"


def normalize_path(path: str) -> str:
    """An FTP request's path as a `virtual_files` key: one leading slash, whatever the client
    sent ("@meta/x" from MAVSDK, "/@meta/x" from QGroundControl), without NULs or blanks."""
    return "/" + path.replace("\0", "").strip().lstrip("/")


def split_description(text: str) -> tuple[str, str]:
    """(short, long): the first sentence without its final point, and the rest.

    QGroundControl shows the short one in the parameter list and the long one below the
    editor, as PX4's metadata does.
    """
    text = " ".join(text.split())
    for match in _SENTENCE_END_RE.finditer(text):
        head = text[: match.start()]
        last_word = head.rsplit(" ", 1)[-1].lower()
        if last_word.lstrip("(") in _ABBREVIATIONS:
            continue
        return head.removesuffix("."), text[match.end():]
    return text.removesuffix("."), ""


def qgc_unit(unit: str) -> str:
    """The registry's unit as QGroundControl knows it (see QGC_UNITS)."""
    return QGC_UNITS.get(unit.strip(), unit.strip())


def _json_number(spec: ParamSpec, value: float | int) -> float | int:
    """A value as the registry holds it: an int, or the shortest decimal of the float32."""
    if spec.ptype is ParamType.INT32:
        return int(value)
    return float(format_value(spec.ptype, value))


def _decimals(spec: ParamSpec) -> int:
    """Decimal places that show the default and the limits exactly (at least a couple, so a
    value between them can be typed; a float32 carries no more than about nine)."""
    if spec.ptype is ParamType.INT32:
        return 0
    needed = 0
    for value in (spec.default, spec.min, spec.max):
        text = format_value(spec.ptype, value)
        if "." in text:
            needed = max(needed, len(text.split(".", 1)[1]))
    return max(FLOAT_DECIMALS_MIN, min(FLOAT_DECIMALS_MAX, needed))


def parameter_entry(spec: ParamSpec) -> dict[str, Any]:
    """One parameter of the parameter metadata file (keys of parameter.schema.json)."""
    short, long = split_description(spec.description)
    entry: dict[str, Any] = {
        "name": spec.name,
        "type": "Int32" if spec.ptype is ParamType.INT32 else "Float",
        "shortDesc": short,
    }
    if long:
        entry["longDesc"] = long
    unit = qgc_unit(spec.unit)
    if unit:
        entry["units"] = unit
    entry["default"] = _json_number(spec, spec.default)
    entry["min"] = _json_number(spec, spec.min)
    entry["max"] = _json_number(spec, spec.max)
    entry["decimalPlaces"] = _decimals(spec)
    if spec.ptype is ParamType.INT32:
        entry["increment"] = 1
    if spec.reboot_required:
        entry["rebootRequired"] = True
    if spec.read_only:
        entry["readOnly"] = True
    entry["group"] = spec.group
    entry["category"] = CATEGORY
    return entry


def parameters_json(specs: list[ParamSpec]) -> bytes:
    """The COMP_METADATA_TYPE_PARAMETER file, in declaration order, as served (ASCII JSON)."""
    doc = {"version": METADATA_VERSION, "parameters": [parameter_entry(s) for s in specs]}
    return _dump(doc)


def general_json(compid: int, parameters_crc: int, *, vendor_name: str = "",
                 model_name: str = "", firmware_version: str = "") -> bytes:
    """The COMP_METADATA_TYPE_GENERAL file: which metadata exists, where, with which CRC32."""
    doc: dict[str, Any] = {"version": METADATA_VERSION}
    if vendor_name:
        doc["vendorName"] = vendor_name
    if model_name:
        doc["modelName"] = model_name
    if firmware_version:
        doc["firmwareVersion"] = firmware_version
    doc["metadataTypes"] = [{
        "type": COMP_METADATA_TYPE_PARAMETER,
        "uri": mftp_uri(compid, PARAMETERS_PATH),
        "fileCrc": parameters_crc,
    }]
    return _dump(doc)


def _dump(doc: dict[str, Any]) -> bytes:
    # compact and ASCII-only: the bytes (and so the CRC) depend on the content alone
    return json.dumps(doc, separators=(",", ":"), ensure_ascii=True,
                      allow_nan=False).encode("ascii")


class ComponentMetadata:
    """The metadata files of one component and the COMPONENT_METADATA message pointing at them.

    `specs_source` is read on every use (cheap: a list copy and a comparison), and the files
    are regenerated only when the list differs from the one they were built from, so a
    parameter declared late still reaches the next client, with new CRCs that make cached
    copies stale. Thread-safe: FTP reads and message requests come from any link's thread.
    """

    def __init__(self, specs_source: Callable[[], list[ParamSpec]], compid: int, *,
                 vendor_name: str = "", model_name: str = "",
                 firmware_version: str = "") -> None:
        if not 1 <= int(compid) <= 255:
            raise ValueError(f"component id {compid} outside 1..255")
        if firmware_version and not _VERSION_RE.match(firmware_version):
            raise ValueError(f"firmware version {firmware_version!r}: use major.minor.patch")
        self.specs_source = specs_source
        self.compid = int(compid)
        self.vendor_name = vendor_name
        self.model_name = model_name
        self.firmware_version = firmware_version
        self.uri = mftp_uri(self.compid, GENERAL_PATH)
        if len(self.uri) > URI_MAX_LEN:
            raise ValueError(f"metadata URI {self.uri!r} longer than {URI_MAX_LEN} characters")
        self._lock = threading.Lock()
        self._built_from: tuple[ParamSpec, ...] | None = None
        self._files: dict[str, bytes] = {}

    def _current(self) -> dict[str, bytes]:
        specs = tuple(self.specs_source())
        with self._lock:
            if specs != self._built_from:
                params = parameters_json(list(specs))
                general = general_json(self.compid, mavlink_crc32(params),
                                       vendor_name=self.vendor_name,
                                       model_name=self.model_name,
                                       firmware_version=self.firmware_version)
                self._files = {GENERAL_PATH: general, PARAMETERS_PATH: params}
                self._built_from = specs
                log.debug("component metadata rebuilt: %d parameters, %d + %d bytes",
                          len(specs), len(general), len(params))
            return self._files

    def virtual_files(self) -> dict[str, Callable[[], bytes]]:
        """FTP path -> the file's current bytes (see `normalize_path` for the requests)."""
        return {path: self._reader(path) for path in (GENERAL_PATH, PARAMETERS_PATH)}

    def _reader(self, path: str) -> Callable[[], bytes]:
        def read() -> bytes:
            return self._current()[path]
        return read

    def read(self, path: str) -> bytes | None:
        """A file by the path a client asked for (leading slashes ignored), None if unknown."""
        return self._current().get(normalize_path(path))

    @property
    def general_crc(self) -> int:
        return mavlink_crc32(self._current()[GENERAL_PATH])

    def message(self, time_boot_ms: int) -> ComponentMetadataMessage:
        """COMPONENT_METADATA for the files as they are now."""
        return ComponentMetadataMessage(int(time_boot_ms) & 0xFFFFFFFF, self.general_crc,
                                        self.uri)
