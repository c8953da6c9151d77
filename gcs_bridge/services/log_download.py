"""Flights over MAVLink's log messages (LOG_REQUEST_LIST / _DATA / _ERASE -> LOG_ENTRY / LOG_DATA).

One log entry is one flight: the flight directory served as an uncompressed tar archive built on
the fly (`companion.logs.archive.FlightArchive`), so QGroundControl's Onboard Logs, MAVSDK's
LogFiles plugin and MAVProxy's ``log list`` / ``log download`` fetch a whole flight in one
download, and ``companion logs convert|info|report`` unpack it.

What the clients need, and why the server does what it does:

* Ids. QGroundControl numbers entries from 1 only when the vehicle claims ArduPilot and from 0
  otherwise (an entry it cannot place is dropped and its list retried until it gives up);
  MAVSDK accepts either base (it takes the smallest id seen); MAVProxy uses the ids as given.
  So ids start at `first_log_id(identity)`: 0 for the generic and PX4 identities, 1 for
  ArduPilot. With no flight the answer is one LOG_ENTRY with id 0 and num_logs 0, which all
  three read as "no logs".
* Listing. All three ask for ids 0..0xFFFF; QGroundControl and MAVSDK then re-ask narrower
  ranges for entries they missed. A request covering every id takes a new snapshot (sizes of
  the flight being recorded change); a narrower one is answered from the last snapshot, so a
  re-sent entry never disagrees with the size the client already holds.
* Data. Clients ask from offsets that are multiples of 90 and drop LOG_DATA at other offsets;
  LOG_DATA here run in 90-byte steps from the requested offset, the last one short. QGC asks for
  chunks of 512 (newer: 2048) x 90 bytes, MAVSDK for chunks of 128 x 90 bytes with exact
  counts; both stop when every byte of the listed size came, and never ask past the end.
  MAVProxy asks for 0xFFFFFFFF bytes from 0 and stops at a LOG_DATA shorter than 90 bytes or
  with count 0; when the archive ends on a 90-byte boundary it would wait, then ask again from
  the end, so a request reaching past the end is closed with a count-0 LOG_DATA at the end
  whenever its last LOG_DATA was full (and a request starting at or after the end gets just
  that). QGC and MAVSDK never see it: their requests end at or inside the archive.
* Unknown id: no LOG_DATA at all. A count-0 answer would make MAVSDK and QGC mark a piece of
  the file as received and save a wrong file; silence makes them retry and time out. MAVProxy
  waits for the first LOG_DATA; the bridge may tell the user with a STATUSTEXT.
* Erase. MAV_LOG_ERASE deletes every flight but the one being recorded.

The module is pure: no sockets, no threads of its own. `request_data` gives its LOG_DATA lazily
with a None after each few KiB, where the bridge can pace a slow link or stop on
LOG_REQUEST_END.
"""

from __future__ import annotations

import json
import logging
import re
import shutil
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from companion.logs.archive import ArchiveError, FlightArchive
from gcs_bridge.dialect import Identity, mavlink

__all__ = [
    "ALL_BYTES",
    "LOG_DATA_LEN",
    "LOG_FILE_SUFFIXES",
    "LogServer",
    "first_log_id",
]

log = logging.getLogger(__name__)

LOG_DATA_LEN = 90  # bytes of data in one LOG_DATA
ALL_BYTES = 0xFFFFFFFF  # LOG_REQUEST_DATA count meaning "to the end"
LAST_ID = 0xFFFF  # LOG_REQUEST_LIST end meaning "the last one"; ids are uint16
MAX_ENTRY_BYTES = 0xFFFFFFFF  # LOG_ENTRY.size and LOG_DATA.ofs are uint32
PIECE_MESSAGES = 46  # LOG_DATA per archive read (4140 bytes), then a None for the caller
STATUSTEXT_LEN = 50
LOG_FILE_SUFFIXES = frozenset({".bin", ".uavlog", ".tlog", ".csv"})
"""A directory under the logs root holding a file with one of these is a flight."""

_STAMP = re.compile(r"^(\d{8}T\d{6}Z)")  # `companion.runtime.new_flight_dir` names
_RUN_JSON_MAX_BYTES = 4 << 20

_LogEntry = mavlink.MAVLink_log_entry_message
_LogData = mavlink.MAVLink_log_data_message


def first_log_id(identity: Identity) -> int:
    """The id of the first log entry on a link claiming `identity` (see the module docstring):
    QGroundControl counts from 1 for ArduPilot only."""
    return 1 if identity is Identity.ARDUPILOT else 0


@dataclass(frozen=True)
class _Entry:
    log_id: int
    archive: FlightArchive
    time_utc_s: int


class LogServer:
    """The flights under `root` as MAVLink log entries; `current` gives the flight being
    recorded (never erased), or None. Safe to call from several link threads."""

    def __init__(self, root: Path, current: Callable[[], Path | None], *,
                 first_id: int = 0) -> None:
        if first_id not in (0, 1):
            raise ValueError(f"first_id must be 0 or 1, not {first_id}")
        self.root = Path(root)
        self.current = current
        self.first_id = first_id
        self._lock = threading.Lock()
        self._entries: dict[int, _Entry] | None = None  # None: no snapshot taken yet

    # ------------------------------------------------------------------ listing
    def flight_dirs(self) -> list[Path]:
        """Flight directories under the root, sorted by name (their UTC start stamp first):
        directories, not links, holding at least one log file."""
        try:
            children = sorted(self.root.iterdir(), key=lambda p: p.name)
        except OSError as exc:
            log.warning("log server: cannot list %s: %s", self.root, exc.strerror or exc)
            return []
        out = []
        for d in children:
            if d.name.startswith(".") or d.is_symlink() or not d.is_dir():
                continue
            try:
                if any(p.suffix in LOG_FILE_SUFFIXES and p.is_file() for p in d.iterdir()):
                    out.append(d)
            except OSError as exc:
                log.warning("log server: cannot list %s: %s", d, exc.strerror or exc)
        return out

    def _snapshot(self) -> dict[int, _Entry]:
        dirs = self.flight_dirs()
        room = LAST_ID + 1 - self.first_id
        if len(dirs) > room:
            log.warning("log server: %d flights, ids for %d: listing the newest", len(dirs), room)
            dirs = dirs[-room:]
        entries: dict[int, _Entry] = {}
        for d in dirs:
            try:
                archive = FlightArchive.snapshot(d)
            except ArchiveError as exc:
                log.warning("log server: leaving out %s", exc)
                continue
            if archive.size > MAX_ENTRY_BYTES:
                log.warning("log server: leaving out %s: %d bytes, LOG_DATA reaches 4 GiB only",
                            d, archive.size)
                continue
            log_id = self.first_id + len(entries)
            entries[log_id] = _Entry(log_id, archive, _start_time_s(archive))
        return entries

    def request_list(self, start: int, end: int) -> Iterator[mavlink.MAVLink_log_entry_message]:
        """LOG_ENTRY for the ids in [start, end] (end 0xFFFF: the last); one with id 0 and
        num_logs 0 when there is no flight. A request from the first id to the last takes a new
        snapshot; a narrower one (a client re-asking for missed entries) reuses the last."""
        with self._lock:
            entries = self._entries
            if entries is None or (start <= self.first_id
                                   and (end >= LAST_ID or end >= self._last_id(entries))):
                entries = self._entries = self._snapshot()
        if not entries:
            return iter([_LogEntry(0, 0, 0, 0, 0)])
        last = self._last_id(entries)
        wanted = [e for i, e in entries.items() if start <= i <= end]
        return iter([_LogEntry(e.log_id, len(entries), last, e.time_utc_s, e.archive.size)
                     for e in wanted])

    def _last_id(self, entries: dict[int, _Entry]) -> int:
        return self.first_id + len(entries) - 1

    def archive(self, log_id: int) -> FlightArchive | None:
        """The archive served as `log_id` (taking a snapshot if none was), None if unknown."""
        with self._lock:
            if self._entries is None:
                self._entries = self._snapshot()
            entry = self._entries.get(log_id)
        return entry.archive if entry is not None else None

    # ------------------------------------------------------------------ data
    def request_data(self, log_id: int, offset: int, count: int
                     ) -> Iterator[mavlink.MAVLink_log_data_message | None]:
        """LOG_DATA with `count` bytes of log `log_id` from `offset` (0xFFFFFFFF: to the end),
        90 bytes each, the last one short, read lazily; a None after every few KiB.

        A request reaching past the end whose last LOG_DATA is full (or starting at or past the
        end) ends with a count-0 LOG_DATA at the end. An unknown id gives nothing.
        """
        archive = self.archive(log_id)
        if archive is None:
            log.warning("log server: LOG_REQUEST_DATA for log %d, which is not in the list",
                        log_id)
            return iter(())
        return _data(log_id, archive, offset, count)

    # ------------------------------------------------------------------ erase
    def erase(self) -> tuple[int, str]:
        """Delete every flight directory under the root but the one being recorded.

        Returns how many were deleted and a line for a STATUSTEXT (50 characters at most).
        Ids are void afterwards: the next list or data request takes a new snapshot.
        """
        current = self.current()
        current_real = current.resolve() if current is not None else None
        root_real = self.root.resolve()
        erased = failed = 0
        kept = current_real is not None and current_real.is_dir()
        for d in self.flight_dirs():
            real = d.resolve()
            if real.parent != root_real or d.is_symlink():
                log.error("log server: refusing to erase %s: not a directory under %s",
                          d, root_real)
                failed += 1
                continue
            if real == current_real:
                log.info("log server: keeping %s: it is being recorded", real)
                continue
            try:
                shutil.rmtree(real)
            except OSError as exc:
                log.error("log server: cannot erase %s: %s", real, exc.strerror or exc)
                failed += 1
                continue
            erased += 1
            log.info("log server: erased flight %s", real)
        with self._lock:
            self._entries = None
        text = f"Erased {erased} flight{'' if erased == 1 else 's'}"
        if failed:
            text += f", {failed} failed"
        if kept:
            text += ", current flight kept"
        return erased, text[:STATUSTEXT_LEN]


def _data(log_id: int, archive: FlightArchive, offset: int, count: int
          ) -> Iterator[mavlink.MAVLink_log_data_message | None]:
    size = archive.size
    start = min(max(offset, 0), size)
    stop = min(start + max(count, 0), size)
    past_end = offset + count > size
    pos = start
    piece = PIECE_MESSAGES * LOG_DATA_LEN
    while pos < stop:
        end = min(stop, pos + piece)
        try:
            blob = archive.read(pos, end - pos)
        except ArchiveError as exc:
            # nothing in LOG_DATA can say so: the client's retries find the same gap
            log.error("log server: log %d (%s): %s", log_id, archive.name, exc)
            return
        for k in range(0, len(blob), LOG_DATA_LEN):
            chunk = blob[k:k + LOG_DATA_LEN]
            yield _LogData(log_id, pos + k, len(chunk), chunk.ljust(LOG_DATA_LEN, b"\x00"))
        pos = end
        if pos < stop:
            yield None
    if past_end and (stop - start) % LOG_DATA_LEN == 0:
        yield _LogData(log_id, size, 0, bytes(LOG_DATA_LEN))


def _start_time_s(archive: FlightArchive) -> int:
    """When the flight started, in s since the epoch (LOG_ENTRY.time_utc): the UTC stamp the
    runtime names flight directories with, else run.json's started_utc, else the oldest
    modification time of its files."""
    m = _STAMP.match(archive.name)
    if m:
        try:
            return _uint32(datetime.strptime(m.group(1), "%Y%m%dT%H%M%SZ")
                           .replace(tzinfo=UTC).timestamp())
        except ValueError:
            pass
    run_json = archive.flight_dir / "run.json"
    try:
        if run_json.stat().st_size <= _RUN_JSON_MAX_BYTES:
            started = json.loads(run_json.read_text(encoding="utf-8")).get("started_utc")
            if isinstance(started, str):
                when = datetime.fromisoformat(started)
                if when.tzinfo is None:
                    when = when.replace(tzinfo=UTC)
                return _uint32(when.timestamp())
    except (OSError, ValueError, AttributeError):
        pass
    return _uint32(archive.first_mtime_s)


def _uint32(t_s: float) -> int:
    return min(max(int(t_s), 0), 0xFFFFFFFF)
