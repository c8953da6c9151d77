"""Format Definitions of the runtime's own threads, for logs that lost theirs.

A log is a chain of records whose meaning comes from Format Definitions written when the thread
opened it. If those few records are lost (a writer race, a file cut at the front), every data
record is still intact but unreadable. The thread that wrote the file knows its formats, so the
report asks it: each producer is built (nothing is opened: resources are only acquired in
``setup``) and its ``define_logs`` is recorded. Producers are imported lazily, so a module that
is missing from this build only means no restoration for its log.
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Sequence
from typing import Any

from companion.drivers.registry import DEVICES
from companion.logs.records import (
    COMMENT,
    DEFINITION,
    HEADER_SIZE,
    TIMED_SIZE,
    encode_comment,
    encode_definition,
)
from companion.tasks import VEHICLE_TASKS

__all__ = ["PRODUCERS", "definition_records", "known_header"]

log = logging.getLogger(__name__)

#: log name -> (module, class, constructor positional arguments)
def _producer(name: str, implementation: str) -> tuple[str, str, tuple[Any, ...]]:
    module, _, cls_name = implementation.partition(":")
    return module, cls_name, ("loop://",) if name in DEVICES else ()


PRODUCERS: dict[str, tuple[str, str, tuple[Any, ...]]] = {
    # every row of the vehicle's task table; a device's driver is built on a loopback port
    row.name: _producer(row.name, row.implementation) for row in VEHICLE_TASKS.values()
}


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
    entry = PRODUCERS.get(name)
    if entry is None:
        return None
    module, cls_name, args = entry
    try:
        cls = getattr(importlib.import_module(module), cls_name)
        producer = cls(*args)
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
