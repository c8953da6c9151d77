"""The files of the log writer: what its thread does with each log's records, and what happens
when the disk refuses them.

A sink is the writer-thread side of one log (`companion.logs.writer.LogService` owns them):
`BinarySink` appends the records to one file (``<name>.bin``, or a raw file such as a MAVLink
.tlog) with one ``os.write`` per batch; `TextSink` renders the same records into
``<name>_fmt<index>.csv`` files with the converter's layout (`companion.logs.convert`). A file
left cut short by a crash is trimmed to whole records before appending. A write error (full
disk, I/O error) switches that one sink to "logging off": it keeps counting what it loses and
says why. This is separate from the service because it is the only part that touches the
disk; the service decides when it is called, the producers never call it.
"""

from __future__ import annotations

import logging
import os
import stat
import struct
from collections import deque
from collections.abc import Callable
from pathlib import Path

from companion.logs.convert import csv_header, csv_name, format_time, marker_line
from companion.logs.formats import FormatSpec, parse_format
from companion.logs.framing import framed_length
from companion.logs.records import (
    BEGIN,
    COMMENT,
    DATA,
    DEFINITION,
    END,
    TIMED_HEADER,
    TIMED_SIZE,
)
from companion.logs.streams import column_names

__all__ = ["BinarySink", "Sink", "TextSink"]

# The log writer's messages keep one logger name whichever of its modules sends them.
log = logging.getLogger("companion.logs.writer")

_MARKER_HISTORY = 4096  # marker lines remembered for CSV files created late (text mode)


class Sink:
    """Writer-thread side of one log: owns its file(s); only the writer thread calls it."""

    def __init__(self, label: str) -> None:
        self.label = label
        self.accepting = True  # read by producers: False once closed or logging off
        self.off = False
        self.reason: str | None = None
        self.written = 0  # records
        self.bytes = 0
        self.lost = 0  # records dequeued but not written (logging off)
        self.files = 0
        self.opened = False

    def open(self) -> None:
        raise NotImplementedError

    def write(self, records: list[bytes]) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def _fail(self, path: Path, exc: OSError) -> None:
        self.off = True
        self.accepting = False
        self.reason = f"{path}: {exc.strerror or exc} (errno {exc.errno})"
        log.warning("logging off for %s: %s", self.label, self.reason)


def _write_all(fd: int, data: bytes) -> int:
    """os.write until done; returns bytes written, raising OSError with .written set on failure."""
    view = memoryview(data)
    done = 0
    while done < len(data):
        try:
            n = os.write(fd, view[done:])
        except OSError as exc:
            exc.written = done  # type: ignore[attr-defined]
            raise
        if n <= 0:
            err = OSError(5, "short write")
            err.written = done  # type: ignore[attr-defined]
            raise err
        done += n
    return done


def _open_append(path: Path, *, repair: Callable[[bytes], int]) -> int:
    """Open for appending; a regular file left cut short by a crash is trimmed first."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_CLOEXEC, 0o644)
    try:
        st = os.fstat(fd)
        if stat.S_ISREG(st.st_mode) and st.st_size > 0:
            with open(path, "rb") as f:
                keep = repair(f.read(st.st_size))
            if keep < st.st_size:
                log.warning("%s: trimming %d bytes cut short by a crash", path, st.st_size - keep)
                os.truncate(fd, keep)
    except OSError:
        os.close(fd)
        raise
    return fd


def _csv_keep(data: bytes) -> int:
    return data.rfind(b"\n") + 1


class BinarySink(Sink):
    def __init__(self, path: Path, label: str,
                 repair: Callable[[bytes], int] = framed_length) -> None:
        super().__init__(label)
        self.path = path
        self.fd: int | None = None
        self._repair = repair

    def open(self) -> None:
        self.opened = True
        try:
            self.fd = _open_append(self.path, repair=self._repair)
            self.files = 1
        except OSError as exc:
            self._fail(self.path, exc)

    def write(self, records: list[bytes]) -> None:
        if self.fd is None or self.off:
            self.lost += len(records)
            return
        data = b"".join(records)
        try:
            _write_all(self.fd, data)
        except OSError as exc:
            done = getattr(exc, "written", 0)
            whole, total = 0, 0
            for r in records:
                total += len(r)
                if total > done:
                    break
                whole += 1
            self.written += whole
            self.bytes += done
            self.lost += len(records) - whole
            self._fail(self.path, exc)
            return
        self.written += len(records)
        self.bytes += len(data)

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


class _CsvFile:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.fd = _open_append(path, repair=_csv_keep)
        self.pending: list[bytes] = []
        self.records = 0


class TextSink(Sink):
    """Renders the binary records of one log into CSV files, as the converter would."""

    def __init__(self, flight_dir: Path, name: str, label: str) -> None:
        super().__init__(label)
        self.dir = flight_dir
        self.name = name
        self.specs: dict[int, FormatSpec] = {}
        self.comments: dict[int, tuple[str, ...]] = {}
        self.files_by_key: dict[tuple[int, str, str, tuple[str, ...]], _CsvFile] = {}
        self.count_by_index: dict[int, int] = {}
        self.markers: deque[str] = deque(maxlen=_MARKER_HISTORY)

    def open(self) -> None:
        self.opened = True

    def _file(self, index: int, kind: str) -> _CsvFile:
        spec = self.specs[index]
        columns = column_names(self.comments.get(index), spec, kind)
        key = (index, kind, spec.text, columns)
        f = self.files_by_key.get(key)
        if f is None:
            number = self.count_by_index.get(index, 0) + 1
            f = _CsvFile(self.dir / csv_name(self.name, index, number))
            self.count_by_index[index] = number
            self.files += 1
            f.pending.append(
                csv_header(spec, columns, kind, source=f"{self.name} (text log)").encode()
            )
            f.pending.extend(m.encode() for m in self.markers)
            self.files_by_key[key] = f
        return f

    def _handle(self, rec: bytes) -> None:
        rtype, index = rec[0], rec[1]
        if rtype == COMMENT:
            self.comments[index] = tuple(rec[4:].decode("utf-8").split(","))
        elif rtype == DEFINITION:
            self.specs[index] = parse_format(rec[4:].decode("latin-1"))
        elif rtype in (BEGIN, END):
            _, _, _, sec, nsec = TIMED_HEADER.unpack_from(rec)
            line = marker_line("begin" if rtype == BEGIN else "end", sec * 1_000_000_000 + nsec)
            self.markers.append(line)
            data = line.encode()
            for f in self.files_by_key.values():
                f.pending.append(data)
        else:
            _, _, _, sec, nsec = TIMED_HEADER.unpack_from(rec)
            t = format_time(sec * 1_000_000_000 + nsec)
            spec = self.specs[index]
            if rtype == DATA:
                values = struct.unpack_from(spec.struct_format, rec, TIMED_SIZE)
                end = "" if spec.text.endswith("\n") else "\n"
                line = t + "," + spec.render(values) + end
                f = self._file(index, "block")
            else:
                conv = spec.conversions[0]
                elems = struct.unpack(
                    f"<{len(rec) - TIMED_SIZE}{conv.struct_code}", rec[TIMED_SIZE:]
                )
                line = ",".join([t, *(conv.render(v) for v in elems)]) + "\n"
                f = self._file(index, "array")
            f.pending.append(line.encode("latin-1"))
            f.records += 1

    def write(self, records: list[bytes]) -> None:
        if self.off:
            self.lost += len(records)
            return
        path = self.dir
        try:
            for rec in records:
                self._handle(rec)
            for f in self.files_by_key.values():
                if f.pending:
                    path = f.path
                    data = b"".join(f.pending)
                    f.pending.clear()
                    _write_all(f.fd, data)
                    self.bytes += len(data)
        except OSError as exc:
            self.lost += len(records)
            self._fail(path, exc)
            return
        self.written += len(records)

    def finish(self) -> None:
        """Formats defined but never used still get their (empty) CSV, like the converter's."""
        if self.off:
            return
        try:
            for index in self.specs:
                if index not in self.count_by_index:
                    f = self._file(index, "block")
                    _write_all(f.fd, b"".join(f.pending))
                    f.pending.clear()
        except OSError as exc:
            self._fail(self.dir, exc)

    def close(self) -> None:
        for f in self.files_by_key.values():
            os.close(f.fd)
        self.files_by_key.clear()
