"""Format Definitions of the runtime's own threads, for logs that lost theirs.

A log is a chain of records whose meaning comes from Format Definitions written when the thread
opened it. If those few records are lost (a writer race, a file cut at the front), every data
record is still intact but unreadable. The thread that wrote the file knows its formats, so the
report asks it: each producer is built (nothing is opened: resources are only acquired in
``setup``) and its ``define_logs`` is recorded. Producers are imported lazily, so a module that
is missing from this build only means no restoration for its log.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

from companion.core.config import DeviceConfig
from companion.logs.records import (
    COMMENT,
    DEFINITION,
    HEADER_SIZE,
    TIMED_SIZE,
    encode_comment,
    encode_definition,
)
from companion.vehicle import VEHICLE, Row

__all__ = ["PRODUCERS", "definition_records", "known_header"]

log = logging.getLogger(__name__)

PRODUCERS: dict[str, Row] = {row.name: row for row in VEHICLE}
"""Log name -> the row of the vehicle's table whose thread writes it (a device's driver is
built on a loopback port)."""


class _Recorder:
    """Stands in for a ThreadLog and keeps the definitions a thread declares."""

    def __init__(self) -> None:
        self.records: list[bytes] = []

    def define(self, index: int, fmt: str, columns: Sequence[str]) -> None:
        names = list(columns)
        if names:
            self.records.append(encode_comment(index, ",".join(names)))
        self.records.append(encode_definition(index, fmt))


def known_header(name: str) -> bytes | None:
    """Format Comment and Definition records of log `name` as its thread writes them today."""
    row = PRODUCERS.get(name)
    if row is None:
        return None
    try:
        producer = row.build(DeviceConfig(port="loop://") if row.device is not None else None)
        rec = _Recorder()
        producer.define_logs(rec)
    except Exception as exc:  # a producer that cannot be built just means no restoration
        log.debug("no known header for %s: %s", name, exc)
        return None
    return b"".join(rec.records) or None


def definition_records(buf: bytes) -> bytes:
    """The Format Comment and Definition records among whole records `buf`, in order."""
    out = bytearray()
    off, n = 0, len(buf)
    while off + HEADER_SIZE <= n:
        rtype = buf[off]
        length = buf[off + 2] | (buf[off + 3] << 8)
        size = (HEADER_SIZE if rtype in (COMMENT, DEFINITION) else TIMED_SIZE) + length
        if rtype in (COMMENT, DEFINITION) and off + size <= n:
            out += buf[off : off + size]
        off += size
    return bytes(out)
