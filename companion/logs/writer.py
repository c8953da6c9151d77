"""Log writer of the runtime: producers never touch the disk, one writer thread does.

`LogService` holds all the logs of one runtime. Every managed thread gets a `ThreadLog`
(`companion.logs.producers`) that appends its packed records to one bounded queue shared by
the whole service; when the queue is full the record is dropped and counted. The service's
single writer thread wakes every ``flush_period_ms`` (or earlier when the queue fills up),
hands each log's records to its sink (`companion.logs.sinks`), which writes them with one
``os.write`` and leaves the data to the kernel, so a killed process loses at most the last
period. A write error (full disk, I/O error) switches that one file to "logging off": it is
reported in `LogService.stats`, by a logging warning and through `LogService.on_log_off`, and
its producers simply see their records dropped. This module owns that policy: when records
are written, how the service shuts down (a bounded wait that tells a slow disk from a hung
one) and what it counts; plus `write_run_json`, the flight's atomic ``run.json``.

Text logs (``text=True``) receive the same records and render them in the writer thread with
the converter's layout (`companion.logs.convert`).
"""

from __future__ import annotations

import json
import logging
import os
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from companion.core.osthread import set_native_name
from companion.logs.producers import Producer, RawLog, ThreadLog
from companion.logs.sinks import BinarySink, Sink, TextSink

__all__ = ["LogService", "write_run_json"]

log = logging.getLogger(__name__)

_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


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
        self._queue: deque[tuple[Sink, bytes]] = deque()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._logs: dict[str, ThreadLog] = {}
        self._raw: dict[str, RawLog] = {}
        self._sinks: list[Sink] = []
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
            sink: Sink
            if text:
                sink = TextSink(self.flight_dir, name, name)
            else:
                sink = BinarySink(self.flight_dir / f"{name}.bin", name)
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
            sink = BinarySink(self.flight_dir / filename, filename, repair)
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
            logs: list[Producer] = [*self._logs.values(), *self._raw.values()]
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
        groups: dict[Sink, list[bytes]] = {}
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
            if isinstance(sink, TextSink):
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
