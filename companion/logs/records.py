"""Record codec of the binary flight log: record types, headers, time stamps, encoders.

Every record is a 4-byte header (type, index, length) and a body; the timed ones (Begin, End,
Data Block, Byte Array) start their body with a TIME (int32 seconds, uint32 nanoseconds). The
encoders here are what the writer uses, so the bytes on disk follow the contract by construction.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

from companion.logs.formats import FormatSpec

__all__ = [
    "ARRAY",
    "ARRAY_ALT",
    "BEGIN",
    "COMMENT",
    "DATA",
    "DEFINITION",
    "END",
    "HEADER",
    "HEADER_SIZE",
    "KNOWN_TYPES",
    "MAX_BODY",
    "NS_PER_S",
    "TIMED_HEADER",
    "TIMED_SIZE",
    "TYPE_NAMES",
    "DataPacker",
    "encode_array",
    "encode_comment",
    "encode_definition",
    "encode_marker",
    "join_time_ns",
    "split_time_ns",
]

BEGIN = 0xBD
END = 0xED
COMMENT = 0xFC
DEFINITION = 0xFD
DATA = 0xDB
ARRAY = 0xBA
ARRAY_ALT = 0xDA  # the thesis's other name for the Byte Array: read like 0xBA, never written

TYPE_NAMES = {
    BEGIN: "Begin Data",
    END: "End Data",
    COMMENT: "Format Comment",
    DEFINITION: "Format Definition",
    DATA: "Data Block",
    ARRAY: "Byte Array",
    ARRAY_ALT: "Data Array",
}
KNOWN_TYPES = frozenset(TYPE_NAMES)

HEADER = struct.Struct("<BBH")
TIMED_HEADER = struct.Struct("<BBHiI")
HEADER_SIZE = HEADER.size  # 4
TIMED_SIZE = TIMED_HEADER.size  # 12
MAX_BODY = 0xFFFF  # the length field is a uint16

NS_PER_S = 1_000_000_000  # nanoseconds per second: the TIME field's second part


def split_time_ns(t_ns: int) -> tuple[int, int]:
    """(tv_sec, tv_nsec) of a CLOCK_REALTIME time in ns; tv_nsec is always 0..999,999,999."""
    return divmod(t_ns, NS_PER_S)


def join_time_ns(tv_sec: int, tv_nsec: int) -> int:
    return tv_sec * NS_PER_S + tv_nsec


def encode_marker(record_type: int, t_ns: int) -> bytes:
    """A Begin Data or End Data record."""
    if record_type not in (BEGIN, END):
        raise ValueError(f"record type 0x{record_type:02X} is not Begin/End Data")
    sec, nsec = split_time_ns(t_ns)
    return TIMED_HEADER.pack(record_type, 0, 0, sec, nsec)


def _text_record(record_type: int, index: int, body: bytes) -> bytes:
    if not 1 <= index <= 255:
        raise ValueError(f"format index {index} outside 1..255")
    if len(body) > MAX_BODY:
        raise ValueError(f"text of {len(body)} bytes exceeds {MAX_BODY}")
    if b"\x00" in body:
        raise ValueError("text contains a NUL byte")
    return HEADER.pack(record_type, index, len(body)) + body


def encode_comment(index: int, text: str) -> bytes:
    """A Format Comment (column names, comma-separated), UTF-8."""
    return _text_record(COMMENT, index, text.encode("utf-8"))


def encode_definition(index: int, fmt: str) -> bytes:
    """A Format Definition; the format string must be ASCII."""
    try:
        body = fmt.encode("ascii")
    except UnicodeEncodeError as exc:
        raise ValueError(f"format string {fmt!r} is not ASCII") from exc
    return _text_record(DEFINITION, index, body)


def encode_array(index: int, data: bytes, t_ns: int) -> bytes:
    """A Byte Array record (type 0xBA, never the 0xDA synonym)."""
    if len(data) > MAX_BODY:
        raise ValueError(f"byte array of {len(data)} bytes exceeds {MAX_BODY}")
    sec, nsec = split_time_ns(t_ns)
    return TIMED_HEADER.pack(ARRAY, index, len(data), sec, nsec) + data


class DataPacker:
    """Packs Data Blocks of one format index with one precompiled struct (the hot path)."""

    __slots__ = ("index", "spec", "_pack", "n_fields")

    def __init__(self, index: int, spec: FormatSpec) -> None:
        if not 1 <= index <= 255:
            raise ValueError(f"format index {index} outside 1..255")
        self.index = index
        self.spec = spec
        self.n_fields = spec.n_fields
        st = struct.Struct("<BBHiI" + spec.struct_format[1:])
        self._pack = st.pack

    def pack(self, t_ns: int, values: Sequence[int | float]) -> bytes:
        """Raises struct.error when a value does not fit its field."""
        sec, nsec = divmod(t_ns, NS_PER_S)
        return self._pack(DATA, self.index, self.spec.size, sec, nsec, *values)
