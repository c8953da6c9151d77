"""Atomic file writes: a reader (or a crash) sees the old file or the new one, never half of one.

Parameters, run descriptions and flight summaries are rewritten while the aircraft flies; a
power cut in the middle of a plain write would leave a truncated file that the next start
refuses. Writing to a temporary file in the same directory, syncing it, renaming it over the old
one and syncing the directory makes the replacement all or nothing on POSIX file systems.
"""

from __future__ import annotations

import json
import os
import tempfile
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
