"""Atomic file writes: a reader (or a crash) sees the old file or the new one, never half of one.

Parameters, run descriptions and flight summaries are rewritten while the aircraft flies; a
power cut in the middle of a plain write would leave a truncated file that the next start
refuses. Writing to a temporary file in the same directory, syncing it, renaming it over the old
one and syncing the directory makes the replacement all or nothing on POSIX file systems.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
import threading
from pathlib import Path
from typing import Any


def atomic_write_text(path: Path, text: str) -> None:
    """Replace `path` with `text` (UTF-8) atomically, creating its directory if needed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def dump_json(obj: Any) -> str:
    """Stable, readable JSON (sorted keys, indented; unknown types as their text)."""
    return json.dumps(obj, indent=2, sort_keys=True, default=str)


def write_json_atomic(path: Path, obj: Any) -> None:
    """`dump_json(obj)` written to `path` atomically."""
    atomic_write_text(path, dump_json(obj) + "\n")


def write_json_bounded(path: Path, obj: Any, timeout_s: float) -> bool:
    """`write_json_atomic` that gives up waiting after `timeout_s` (host seconds).

    Shutdown writes the flight summary after every log is closed; on a disk whose fsync takes
    seconds (a dying SD card) or never returns (a hung USB stick) it would keep the process
    from exiting, and with it the service manager's restart. The write goes on in a daemon
    thread; False (and a warning) when it was not confirmed in time or failed.
    """
    error: list[BaseException] = []

    def write() -> None:
        try:
            write_json_atomic(path, obj)
        except BaseException as exc:  # reported below, in the caller's thread
            error.append(exc)

    worker = threading.Thread(target=write, name=f"write {path.name}", daemon=True)
    worker.start()
    worker.join(timeout_s)
    if worker.is_alive():
        logging.getLogger(__name__).warning(
            "%s: not confirmed on disk within %.1f s (slow or hung disk); not waiting", path,
            timeout_s)
        return False
    if error:
        logging.getLogger(__name__).error("cannot write %s: %s", path, error[0])
        return False
    return True
