"""Telemetry logs (`.tlog`): every MAVLink frame of a link, both directions, with its time.

The format is the de-facto standard of MAVProxy and Mission Planner, read by pymavlink's
`mavutil` and MAVExplorer: for each frame, the receive/send time as a big-endian uint64 of
microseconds since the Unix epoch, then the frame's bytes.

In a runtime the file is written by the flight logs' writer thread (`LogService.open_raw`), so
a slow or full disk costs tlog records, counted, and never a link thread's cycle; without a
log service (tools, tests) the writer appends to its own file.

Signatures are stripped (the signed flag cleared and the CRC recomputed), so a log can be
shared without handing out material for replay, and SETUP_SIGNING frames, which carry the
secret key itself, are never written.
"""

from __future__ import annotations

import logging
import struct
import threading
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

from pymavlink.dialects.v20.common import x25crc

from gcs_bridge.dialect import crc_extra_of, mavlink
from gcs_bridge.signing import SIGNATURE_LEN

if TYPE_CHECKING:
    from companion.logs.producers import RawLog
    from companion.logs.writer import LogService

log = logging.getLogger(__name__)

_NEVER_LOGGED = frozenset({mavlink.MAVLINK_MSG_ID_SETUP_SIGNING})


def frame_msg_id(frame: bytes | bytearray) -> int | None:
    """Message id of a raw MAVLink 1 or 2 frame, None if the header is incomplete."""
    if len(frame) >= 10 and frame[0] == 0xFD:
        return frame[7] | (frame[8] << 8) | (frame[9] << 16)
    if len(frame) >= 6 and frame[0] == 0xFE:
        return frame[5]
    return None


def strip_signature(frame: bytes | bytearray) -> bytes:
    """The same MAVLink 2 frame, unsigned and with a valid CRC; other frames unchanged."""
    if len(frame) < 12 or frame[0] != 0xFD or not frame[2] & 0x01:
        return bytes(frame)
    msg_id = frame_msg_id(frame)
    crc_extra = crc_extra_of(msg_id) if msg_id is not None else None
    body = bytearray(frame[:-SIGNATURE_LEN])
    body[2] &= 0xFE
    if crc_extra is None:  # unknown message: the CRC cannot be recomputed; keep it signed-less
        return bytes(body)
    crc = x25crc(body[1:-2])
    crc.accumulate(struct.pack("B", crc_extra))
    body[-2:] = struct.pack("<H", crc.crc)
    return bytes(body)


def tlog_length(data: bytes) -> int:
    """How many leading bytes of a tlog are whole records (what to keep after a crash)."""
    pos, n = 0, len(data)
    while True:
        head = pos + 8  # after the record's timestamp
        if head + 3 > n:
            break
        start, payload_len = data[head], data[head + 1]
        if start == 0xFD:
            size = 8 + 12 + payload_len + (13 if data[head + 2] & 0x01 else 0)
        elif start == 0xFE:
            size = 8 + 8 + payload_len
        else:
            break
        if pos + size > n:
            break
        pos += size
    return pos


class TlogWriter:
    """Appends frames to one `.tlog` file; shared by a link's receive and send threads."""

    def __init__(self, path: Path, service: LogService | None = None) -> None:
        self.path = Path(path)
        self._service = service
        self._raw: RawLog | None = None
        self._accepting = False
        self._fh: BinaryIO | None = None
        self._lock = threading.Lock()
        self.frames = 0
        self.errors = 0

    def open(self) -> None:
        if self._service is not None and self.path.parent == self._service.flight_dir:
            if self._raw is None:  # one file for the service's life, across thread restarts
                self._raw = self._service.open_raw(self.path.name, repair=tlog_length)
            self._accepting = True
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = open(self.path, "ab")  # noqa: SIM115 - owned until close()

    @property
    def is_open(self) -> bool:
        return self._accepting or self._fh is not None

    @property
    def dropped(self) -> int:
        """Frames lost by the log service (full queue, full disk); 0 when writing directly."""
        return self._raw.dropped if self._raw is not None else 0

    def write(self, t_us: int, frame: bytes | bytearray) -> None:
        """Record one frame (never raises: a full disk must not stop the link)."""
        if frame_msg_id(frame) in _NEVER_LOGGED:
            return
        record = struct.pack(">Q", max(0, t_us)) + strip_signature(frame)
        raw = self._raw
        if raw is not None:
            if self._accepting and raw.append(record):
                self.frames += 1
            return
        with self._lock:
            fh = self._fh
            if fh is None:
                return
            try:
                fh.write(record)
                self.frames += 1
            except (OSError, ValueError) as exc:
                self.errors += 1
                if self.errors in (1, 100):
                    log.error("tlog %s: write failed: %s", self.path, exc)

    def flush(self) -> None:
        """Hand buffered frames to the kernel (the log service's thread does that itself)."""
        with self._lock:
            if self._fh is not None:
                try:
                    self._fh.flush()
                except (OSError, ValueError):
                    self.errors += 1

    def close(self) -> None:
        """Stop recording; the log service closes its file when the service closes."""
        self._accepting = False
        with self._lock:
            fh, self._fh = self._fh, None
        if fh is not None:
            try:
                fh.close()
            except OSError as exc:
                log.error("tlog %s: close failed: %s", self.path, exc)
