"""Follow a binary log while another process writes it (the SITL truth, for the live view).

Ground truth lives in the simulator process, not in the runtime's slots, so the live view reads
``truth.bin`` as it grows. Each poll reads only the new bytes, parses the whole records among
them behind the definitions seen so far, and keeps a cut-short last record for the next poll.
Everything is bounded: one poll reads at most `max_chunk_bytes`.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from companion.logs import LogFormatError, read_log_bytes
from companion.logs.framing import framed_length
from companion.report.headers import definition_records

__all__ = ["LogTail"]

log = logging.getLogger(__name__)


class LogTail:
    """New Data Blocks of one format of a growing log, as structured arrays."""

    def __init__(self, path: Path, index: int, *, max_chunk_bytes: int = 4 << 20) -> None:
        self.path = Path(path)
        self.index = index
        self.max_chunk_bytes = max_chunk_bytes
        self.offset = 0
        self._header = b""
        self._pending = b""
        self.failed: str | None = None

    def poll(self) -> np.ndarray | None:
        """Records added since the last poll (None when there are none or the file is absent)."""
        if self.failed is not None:
            return None
        try:
            with open(self.path, "rb") as f:
                size = os.fstat(f.fileno()).st_size
                if size < self.offset:  # rewritten from the start: follow the new file
                    self.offset, self._header, self._pending = 0, b"", b""
                if size == self.offset:
                    return None
                f.seek(self.offset)
                new = f.read(min(size - self.offset, self.max_chunk_bytes))
        except FileNotFoundError:
            return None
        except OSError as exc:
            self.failed = f"{self.path}: {exc.strerror or exc}"
            log.warning("live view stops following %s", self.failed)
            return None
        self.offset += len(new)
        buf = self._pending + new
        whole = framed_length(buf)
        body, self._pending = buf[:whole], buf[whole:]
        if len(self._pending) > self.max_chunk_bytes:  # not a log after all: give up cleanly
            self.failed = f"{self.path}: no whole record in {len(self._pending)} bytes"
            log.warning("live view stops following %s", self.failed)
            return None
        if not body:
            return None
        self._header += definition_records(body)
        try:
            lf = read_log_bytes(self._header + body, name=str(self.path), salvage=True)
        except LogFormatError:  # pragma: no cover - salvage reports damage, it does not raise
            return None
        if self.index not in lf.indexes:
            return None
        try:
            data = lf.data(self.index)
        except ValueError:
            return None
        return data if data.size else None
