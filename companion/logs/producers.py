"""The logging handles of producer threads: `ThreadLog` (one log of a managed thread) and
`RawLog` (a file of records formatted by the caller, such as a MAVLink .tlog).

A handle packs a record in the caller's thread (so a bad value is caught at the call) and
appends it to the bounded queue of its `companion.logs.writer.LogService`; when the queue is
full, or its log is off, the record is dropped and counted: a control loop must never wait for
a disk. Definitions, comments and Begin/End markers bypass the queue limit (they are rare and a
file without them cannot be read). This is separate from the service because it is the hot
path of every producer thread and never touches the service's thread or files; it sees the
service only through `LogHost`.
"""

from __future__ import annotations

import logging
import struct
import threading
from collections import deque
from collections.abc import Callable, Sequence
from typing import Protocol

from companion.logs.formats import parse_format
from companion.logs.records import (
    ARRAY,
    BEGIN,
    END,
    MAX_BODY,
    TIMED_HEADER,
    DataPacker,
    encode_comment,
    encode_definition,
    encode_marker,
    split_time_ns,
)
from companion.logs.sinks import Sink

__all__ = ["LogHost", "Producer", "RawLog", "ThreadLog"]

# The log writer's messages keep one logger name whichever of its modules sends them.
log = logging.getLogger("companion.logs.writer")


class LogHost(Protocol):
    """What a handle uses of the `LogService` it logs through: the queue it appends to, its
    capacity, the event that wakes the writer thread, the clock of its time stamps, and
    whether data records are paused."""

    capacity_records: int
    paused: bool
    _queue: deque[tuple[Sink, bytes]]
    _wake: threading.Event
    _clock_ns: Callable[[], int]


class Producer:
    """What every producer handle shares: its sink, the service's bounded queue and the count
    of what it lost. Subclasses append to the queue inline (the hot path of every thread)."""

    def __init__(self, service: LogHost, name: str, sink: Sink) -> None:
        self.name = name
        self._sink = sink
        self._queue = service._queue
        self._capacity = service.capacity_records
        self._high_water = max(1, service.capacity_records // 2)
        self._wake = service._wake
        self._dropped = 0

    @property
    def dropped(self) -> int:
        """Records of this log lost: full queue, logging off, or the service closed."""
        return self._dropped + self._sink.lost

    @property
    def logging_off(self) -> bool:
        return self._sink.off


class ThreadLog(Producer):
    """The logging handle of one managed thread (one binary file, or CSVs when text)."""

    def __init__(self, service: LogHost, name: str, sink: Sink, text: bool) -> None:
        super().__init__(service, name, sink)
        self.text = text
        self._service = service
        self.paused_records = 0
        self._clock = service._clock_ns
        self._packers: dict[int, DataPacker] = {}
        self._arrays: set[int] = set()
        self.rejected = 0
        self._warned: set[int] = set()

    def _control(self, record: bytes) -> None:
        if self._sink.accepting:
            self._queue.append((self._sink, record))

    def define(self, index: int, fmt: str, columns: Sequence[str]) -> None:
        """Declare format `index` (1..255); writes its Format Comment and Definition.

        `columns` names the fields (one per conversion, no commas, not ``time_s``), or is
        empty to leave them unnamed. Redefining an index is allowed (readers start a new
        stream when the layout changes).
        """
        spec = parse_format(fmt)
        packer = DataPacker(index, spec)
        names = list(columns)
        if names:
            if len(names) != spec.n_fields:
                raise ValueError(
                    f"log {self.name!r} index {index}: {len(names)} column names for "
                    f"{spec.n_fields} fields of {fmt!r}"
                )
            for n in names:
                if not n or n != n.strip() or any(ch in n for ch in ",\n\r\x00") or n == "time_s":
                    raise ValueError(f"log {self.name!r} index {index}: bad column name {n!r}")
            if len(set(names)) != len(names):
                raise ValueError(f"log {self.name!r} index {index}: repeated column names {names}")
        records = [encode_definition(index, fmt)]
        if names:
            records.insert(0, encode_comment(index, ",".join(names)))
        for r in records:
            self._control(r)
        self._packers[index] = packer
        if spec.byte_array_ok:
            self._arrays.add(index)
        else:
            self._arrays.discard(index)

    def begin(self) -> None:
        """Begin Data: the thread (re)starts logging."""
        self._control(encode_marker(BEGIN, self._clock()))

    def end(self) -> None:
        """End Data: the thread stops cleanly."""
        self._control(encode_marker(END, self._clock()))

    def _reject(self, index: int, exc: Exception) -> bool:
        self.rejected += 1
        if index not in self._warned:
            self._warned.add(index)
            log.warning(
                "log %r index %d: record rejected (%s); further ones counted only",
                self.name,
                index,
                exc,
            )
        return False

    def log(self, index: int, *values: float | int, t_ns: int | None = None) -> bool:
        """Queue one Data Block; False when dropped (queue full, logging off) or rejected.

        Never blocks and never touches the disk. A value that does not fit its field is
        rejected (counted in `rejected`); an undefined index or a wrong number of values is a
        programming error and raises ValueError.
        """
        packer = self._packers.get(index)
        if packer is None:
            raise ValueError(f"log {self.name!r}: format index {index} is not defined")
        if self._service.paused:
            self.paused_records += 1
            return False
        if len(values) != packer.n_fields:
            raise ValueError(
                f"log {self.name!r} index {index}: {len(values)} values for {packer.n_fields} fields"
            )
        queue = self._queue
        if not self._sink.accepting or len(queue) >= self._capacity:
            self._dropped += 1
            return False
        try:
            record = packer.pack(self._clock() if t_ns is None else t_ns, values)
        except struct.error as exc:
            return self._reject(index, exc)
        queue.append((self._sink, record))
        if len(queue) > self._high_water:
            self._wake.set()
        return True

    def log_array(self, index: int, data: bytes, t_ns: int | None = None) -> bool:
        """Queue one Byte Array (each byte one element of the index's 1-byte conversion)."""
        if index not in self._arrays:
            raise ValueError(
                f"log {self.name!r}: format index {index} is not defined as one 1-byte conversion"
            )
        if self._service.paused:
            self.paused_records += 1
            return False
        payload = bytes(data)
        if len(payload) > MAX_BODY:
            raise ValueError(
                f"log {self.name!r}: byte array of {len(payload)} bytes exceeds {MAX_BODY}"
            )
        queue = self._queue
        if not self._sink.accepting or len(queue) >= self._capacity:
            self._dropped += 1
            return False
        sec, nsec = split_time_ns(self._clock() if t_ns is None else t_ns)
        try:
            header = TIMED_HEADER.pack(ARRAY, index, len(payload), sec, nsec)
        except struct.error as exc:
            return self._reject(index, exc)
        queue.append((self._sink, header + payload))
        if len(queue) > self._high_water:
            self._wake.set()
        return True


class RawLog(Producer):
    """A file of pre-formatted records written by the service's thread (a MAVLink .tlog).

    Producers hand over whole records; like `ThreadLog.log`, `append` never blocks and never
    touches the disk, so a slow or full disk costs records (counted), not a link's cycle.
    """

    def append(self, record: bytes) -> bool:
        """Queue one record; False when it was dropped."""
        queue = self._queue
        if not self._sink.accepting or len(queue) >= self._capacity:
            self._dropped += 1
            return False
        queue.append((self._sink, record))
        if len(queue) > self._high_water:
            self._wake.set()
        return True
