"""Recovering from damage in a binary flight log: is a record that does not fit in the file a
cut-short end or damage, and where do plausible records start again after damage.

The reader (`companion.logs.reader`) calls these where the record chain breaks: at the end of
the file (`tail_damage`: a last record cut short by a crash is dropped with a warning, anything
else is reported with its byte offset and kind) and, when salvaging, past a corrupt record
(`find_plausible`: the next offset where a record of a known type, with a sound header, a
defined format and a next record of a known type, starts). They are separate from the framing
(`companion.logs.framing`) because they judge records by their meaning (format definitions,
TIME fields), and from the reader's main loop because they run only on damaged or cut files.
Every search advances through the file in windows that grow, so it stays linear.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from companion.logs.formats import FormatError, FormatSpec, parse_format
from companion.logs.framing import KNOWN_LUT
from companion.logs.records import (
    ARRAY,
    ARRAY_ALT,
    BEGIN,
    COMMENT,
    DATA,
    DEFINITION,
    END,
    HEADER_SIZE,
    KNOWN_TYPES,
    NS_PER_S,
    TIMED_SIZE,
    TYPE_NAMES,
)

__all__ = ["SpecOf", "find_plausible", "tail_damage"]

SpecOf = Callable[[int], FormatSpec | None]  # the format in force for an index, if any
_SEARCH_WINDOW = 1 << 16  # most bytes examined at once when looking for a plausible record


def tail_damage(buf: bytes, off: int, spec_of: SpecOf) -> tuple[str, str] | None:
    """Classify a record at `off` that does not fit in the file: None for a cut-short last
    record, else the (kind, message) of the damage."""
    n = len(buf)
    rtype = buf[off]
    if rtype not in KNOWN_TYPES:
        return "unknown_type", f"unknown record type 0x{rtype:02X}"
    if n - off < HEADER_SIZE:
        return None
    index = buf[off + 1]
    length = buf[off + 2] | (buf[off + 3] << 8)
    name = TYPE_NAMES[rtype]
    if rtype in (BEGIN, END):
        if length:
            return "length_mismatch", f"{name} with length {length} (must be 0)"
        return None
    if rtype in (DATA, ARRAY, ARRAY_ALT):
        spec = spec_of(index)
        if spec is None:
            return (
                "undefined_index",
                f"{name} for format index {index}, which has no definition",
            )
        if rtype == DATA:
            if length != spec.size:
                return (
                    "length_mismatch",
                    f"Data Block of {length} bytes for format index {index}, whose format "
                    f"{spec.text!r} needs {spec.size}",
                )
            return None
        if not spec.byte_array_ok:
            return (
                "length_mismatch",
                f"{name} for format index {index}, whose format {spec.text!r} "
                f"is not one 1-byte conversion",
            )
    elif index == 0:
        return "bad_definition", f"{name} for format index 0 (must be 1..255)"
    # Variable-length record: cut short only if nothing plausible follows inside it.
    if find_plausible(buf, off + 1, n, spec_of) < n:
        return (
            "past_eof",
            f"{name} of length {length} runs past the end of the file ({n} bytes)",
        )
    return None


def _plausible(buf: bytes, p: int, spec_of: SpecOf) -> bool:
    """Whether a record of sound header, known format and TIME starts at `p`, followed by the
    end of the file or a record of a known type."""
    n = len(buf)
    if p + HEADER_SIZE > n:
        return False
    rtype, index = buf[p], buf[p + 1]
    length = buf[p + 2] | (buf[p + 3] << 8)
    if rtype in (COMMENT, DEFINITION):
        end = p + HEADER_SIZE + length
        if index == 0 or length == 0 or end > n:
            return False
        body = buf[p + HEADER_SIZE : end]
        if b"\x00" in body:
            return False
        try:
            text = body.decode("utf-8")
            if rtype == DEFINITION:
                parse_format(text)
        except (UnicodeDecodeError, FormatError):
            return False
    else:
        if rtype in (BEGIN, END):
            if index or length:
                return False
            end = p + TIMED_SIZE
        else:
            spec = spec_of(index)
            if spec is None:
                return False
            if rtype == DATA and length != spec.size:
                return False
            if rtype != DATA and not spec.byte_array_ok:
                return False
            end = p + TIMED_SIZE + length
        if end > n or int.from_bytes(buf[p + 8 : p + 12], "little") >= NS_PER_S:
            return False
    return end == n or bool(KNOWN_LUT[buf[end]])


def find_plausible(buf: bytes, start: int, stop: int, spec_of: SpecOf) -> int:
    """First offset in [start, stop) where a plausible record starts, else `stop`."""
    arr = np.frombuffer(buf, dtype=np.uint8)
    pos = start
    window = 64  # grows: damage is usually short, but the search must stay linear
    while pos < stop:
        end = min(stop, pos + window)
        cands = np.flatnonzero(KNOWN_LUT[arr[pos:end]])
        for c in cands.tolist():
            if _plausible(buf, pos + c, spec_of):
                return pos + c
        pos = end
        window = min(window * 2, _SEARCH_WINDOW)
    return stop
