"""Log writer of the runtime: producers never touch the disk, one writer thread does.

Every managed thread gets a `ThreadLog`; `ThreadLog.log` packs the record (so a bad value is
caught at the call) and appends it to one bounded queue shared by the whole `LogService`. When
the queue is full the record is dropped and counted: a control loop must never wait for a disk.
The service's single writer thread wakes every ``flush_period_ms`` (or earlier when the queue
fills up), writes each file's records with one ``os.write`` and leaves the data to the kernel,
so a killed process loses at most the last period. A write error (full disk, I/O error)
switches that one file to "logging off": it is reported in `LogService.stats` and by a logging
warning, and its producers simply see their records dropped.

Definitions, comments and Begin/End markers bypass the queue limit (they are rare and a file
without them cannot be read). Text logs (``text=True``) receive the same records and render
them in the writer thread with the converter's layout (`companion.logs.convert`).

Size: the writer thread, its queue, the per-thread handle and the text-mode variant share
one shutdown and overflow policy, which is clearer in one file.
"""

from __future__ import annotations

import json
import logging
import os
import re
import stat
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from companion.core.osthread import set_native_name
from companion.logs.convert import csv_header, csv_name, format_time, marker_line
from companion.logs.formats import FormatSpec, parse_format
from companion.logs.framing import framed_length
from companion.logs.records import (
    ARRAY,
    BEGIN,
    COMMENT,
    DATA,
    DEFINITION,
    END,
    MAX_BODY,
    TIMED_HEADER,
    TIMED_SIZE,
    DataPacker,
    encode_comment,
    encode_definition,
    encode_marker,
    split_time_ns,
)
from companion.logs.streams import column_names

__all__ = ["LogService", "RawLog", "ThreadLog", "write_run_json"]

log = logging.getLogger(__name__)

_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
_MARKER_HISTORY = 4096  # marker lines remembered for CSV files created late (text mode)


class _Sink:
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


class _BinarySink(_Sink):
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


class _TextSink(_Sink):
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


class _Producer:
    """What every producer handle shares: its sink, the service's bounded queue and the count
    of what it lost. Subclasses append to the queue inline (the hot path of every thread)."""

    def __init__(self, service: LogService, name: str, sink: _Sink) -> None:
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


class ThreadLog(_Producer):
    """The logging handle of one managed thread (one binary file, or CSVs when text)."""

    def __init__(self, service: LogService, name: str, sink: _Sink, text: bool) -> None:
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


class RawLog(_Producer):
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


class LogService:
    """All the logs of one runtime, and the one thread that writes them."""

    def __init__(
        self,
        flight_dir: Path,
        *,
        capacity_records: int = 65536,
        flush_period_ms: int = 100,
        clock_ns: Callable[[], int] = time.time_ns,
        writer_thread: bool = True,
    ) -> None:
        """`writer_thread` False: no thread; the owner calls `drain()` (a lockstep flight,
        where the disk is written between two instants of simulated time, deterministically)."""
        if capacity_records < 1:
            raise ValueError(f"capacity_records must be >= 1, got {capacity_records}")
        if flush_period_ms <= 0:
            raise ValueError(f"flush_period_ms must be > 0, got {flush_period_ms}")
        self.flight_dir = Path(flight_dir)
        self.capacity_records = capacity_records
        self.flush_period_ms = flush_period_ms
        self._clock_ns = clock_ns
        self._queue: deque[tuple[_Sink, bytes]] = deque()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._logs: dict[str, ThreadLog] = {}
        self._raw: dict[str, RawLog] = {}
        self._sinks: list[_Sink] = []
        self._thread: threading.Thread | None = None
        self._writer_thread = writer_thread
        self._closed = False
        self._close_timed_out = False
        self._progress = 0  # batches written, for close() to tell a slow disk from a hung one
        self._in_hand = 0  # records taken off the queue and not yet written
        self._lost_at_close = 0
        #: Data records are refused (not queued, counted per log) while paused: an operator's
        #: "stop logging"; definitions and Begin/End markers still go through.
        self.paused = False
        #: Called from the writer thread, once per log, when it switches to "logging off"
        #: (label, reason): the runtime turns it into an event the ground stations see.
        self.on_log_off: Callable[[str, str], None] | None = None
        self._reported_off: set[int] = set()

    def __enter__(self) -> LogService:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        """Create the flight directory and start the writer thread."""
        if self._closed:
            raise RuntimeError("LogService is closed")
        if self._thread is not None:
            return
        self.flight_dir.mkdir(parents=True, exist_ok=True)
        if not self._writer_thread:
            return
        self._thread = threading.Thread(target=self._run, name="log-writer", daemon=True)
        self._thread.start()

    def drain(self) -> None:
        """Write what is queued now, in the caller's thread: only for a service built
        without its writer thread."""
        if self._writer_thread:
            raise RuntimeError("LogService.drain: the writer thread drains this service")
        if not self._closed:
            self._drain()

    def open(self, name: str, *, text: bool = False) -> ThreadLog:
        """A new log: ``<name>.bin``, or ``<name>_fmt<index>.csv`` files when `text`."""
        if not _NAME_RE.match(name) or name in (".", ".."):
            raise ValueError(f"log name {name!r}: use letters, digits, '_', '-', '.' (max 64)")
        with self._lock:
            if self._closed:
                raise RuntimeError("LogService is closed")
            if name in self._logs:
                raise ValueError(f"log {name!r} is already open")
            sink: _Sink
            if text:
                sink = _TextSink(self.flight_dir, name, name)
            else:
                sink = _BinarySink(self.flight_dir / f"{name}.bin", name)
            thread_log = ThreadLog(self, name, sink, text)
            self._logs[name] = thread_log
            self._sinks.append(sink)
        self._wake.set()
        return thread_log

    def open_raw(self, filename: str, *, repair: Callable[[bytes], int]) -> RawLog:
        """A file in the flight directory for records formatted by the caller.

        `repair` returns how many leading bytes of a file left by a crash are whole records,
        so appending after a crash starts on a record boundary. Pausing the flight logs does
        not pause raw logs: their owner decides (the MAVLink logging commands do both).
        """
        if not _NAME_RE.match(filename) or filename in (".", ".."):
            raise ValueError(f"log file name {filename!r}: use letters, digits, '_', '-', '.'")
        with self._lock:
            if self._closed:
                raise RuntimeError("LogService is closed")
            if filename in self._raw:
                raise ValueError(f"log file {filename!r} is already open")
            sink = _BinarySink(self.flight_dir / filename, filename, repair)
            raw = RawLog(self, filename, sink)
            self._raw[filename] = raw
            self._sinks.append(sink)
        self._wake.set()
        return raw

    def set_paused(self, paused: bool) -> None:
        self.paused = paused
        log.info("logging %s", "paused" if paused else "resumed")

    def close(self, timeout_s: float = 2.0, max_s: float = 30.0) -> None:
        """Write everything queued, close all files, stop the writer thread (bounded wait).

        The wait gives up after `timeout_s` without progress, or after `max_s` in all: a slow
        disk that still takes writes gets its records written (a flight's logs are what it
        was flown for), a hung one costs at most `timeout_s`. Records left unwritten are
        counted in `stats()["lost_at_close"]`.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            for sink in self._sinks:
                sink.accepting = False
        thread = self._thread
        self._stop.set()
        self._wake.set()
        if thread is None:
            self._final_pass()
            return
        start = last_progress_at = time.monotonic()
        seen = self._progress
        while True:
            now = time.monotonic()
            remaining = min(timeout_s - (now - last_progress_at), max_s - (now - start))
            if remaining <= 0:
                break
            thread.join(min(remaining, 0.05))
            if not thread.is_alive():
                return
            if self._progress != seen:
                seen, last_progress_at = self._progress, time.monotonic()
        self._close_timed_out = True
        self._lost_at_close = len(self._queue) + self._in_hand
        log.warning(
            "log writer did not finish within %.1f s (%.1f s without progress); "
            "%d records not written",
            time.monotonic() - start, timeout_s, self._lost_at_close,
        )

    def stats(self) -> dict[str, Any]:
        """Counters: written, dropped, rejected, bytes, files, queued, logging_off, reason."""
        with self._lock:
            sinks = list(self._sinks)
            logs: list[_Producer] = [*self._logs.values(), *self._raw.values()]
        reasons = [s.reason for s in sinks if s.reason]
        return {
            "written": sum(s.written for s in sinks),
            "dropped": sum(lg.dropped for lg in logs),
            "rejected": sum(lg.rejected for lg in logs if isinstance(lg, ThreadLog)),
            "bytes": sum(s.bytes for s in sinks),
            "files": sum(s.files for s in sinks),
            "queued": len(self._queue),
            "logging_off": bool(reasons),
            "reason": "; ".join(reasons) if reasons else None,
            "running": self._thread is not None and self._thread.is_alive(),
            "close_timed_out": self._close_timed_out,
            "lost_at_close": self._lost_at_close,
        }

    # -- writer thread -----------------------------------------------------------------------

    def _drain(self) -> None:
        with self._lock:
            sinks = list(self._sinks)
        for sink in sinks:
            if not sink.opened:
                sink.open()
        queue = self._queue
        pop = queue.popleft
        groups: dict[_Sink, list[bytes]] = {}
        taken = len(queue)
        for _ in range(taken):
            sink, record = pop()
            batch = groups.get(sink)
            if batch is None:
                batch = groups[sink] = []
            batch.append(record)
        self._in_hand = taken
        for sink, batch in groups.items():
            if not sink.opened:
                # opened by a producer after the snapshot above: open it now, or its first
                # records (the format definitions) would be lost
                sink.open()
            try:
                sink.write(batch)
            except Exception:  # a bug in one sink must not stop the others
                log.exception("log writer: %s failed; logging off for it", sink.label)
                sink.off = True
                sink.accepting = False
                sink.reason = f"{sink.label}: internal error"
                sink.lost += len(batch)
            self._in_hand -= len(batch)
            self._progress += 1
        callback = self.on_log_off
        for sink in groups:
            if sink.off and id(sink) not in self._reported_off:
                self._reported_off.add(id(sink))
                if callback is not None:
                    try:
                        callback(sink.label, sink.reason or "write error")
                    except Exception:
                        log.exception("log writer: on_log_off callback failed")

    def _final_pass(self) -> None:
        self._drain()
        with self._lock:
            sinks = list(self._sinks)
        for sink in sinks:
            if isinstance(sink, _TextSink):
                sink.finish()
            try:
                sink.close()
            except OSError as exc:
                log.warning("log writer: closing %s: %s", sink.label, exc)

    def _run(self) -> None:
        set_native_name("log-writer")
        period_s = self.flush_period_ms / 1000.0
        try:
            while True:
                stopping = self._stop.is_set()
                if stopping:
                    break
                self._drain()
                self._wake.wait(period_s)
                self._wake.clear()
        finally:
            self._final_pass()


def write_run_json(flight_dir: Path, info: Mapping[str, Any]) -> Path:
    """Write ``run.json`` atomically (temporary file, fsync, rename, fsync of the directory).

    Values JSON cannot represent are written with str() (paths, times, enums).
    """
    directory = Path(flight_dir)
    directory.mkdir(parents=True, exist_ok=True)
    target = directory / "run.json"
    text = json.dumps(dict(info), indent=2, sort_keys=True, default=str) + "\n"
    tmp = directory / f".run.json.{os.getpid()}.{threading.get_ident()}.tmp"
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    dir_fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
    return target
