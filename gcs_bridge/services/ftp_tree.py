"""The tree a MAVLink FTP server serves: where a request path lands, and what may change.

Confinement is its own job, apart from the protocol (`ftp_wire`) and the sessions (`ftp`):
every path a request names is resolved here, under the root or refused, and every change is
checked here against the read-only call, the virtual files and the flight being recorded.
"""

from __future__ import annotations

import errno
import os
import stat
from collections.abc import Callable, Mapping
from pathlib import Path

from gcs_bridge.services.ftp_wire import (
    ERR_FAILERRNO,
    ERR_FILENOTFOUND,
    ERR_FILEPROTECTED,
    Nak,
    path_key,
)


def open_regular(path: Path, flags: int) -> int:
    """A descriptor on a regular file. O_NONBLOCK keeps a FIFO or device from stalling the caller;
    anything but a regular file is then refused (a directory with EISDIR)."""
    fd = os.open(path, flags | os.O_NONBLOCK, 0o644)
    try:
        mode = os.fstat(fd).st_mode
        if stat.S_ISDIR(mode):
            raise Nak(ERR_FAILERRNO, errno.EISDIR)
        if not stat.S_ISREG(mode):
            raise Nak(ERR_FAILERRNO, errno.EINVAL)
    except BaseException:
        os.close(fd)
        raise
    return fd


class ServedTree:
    """`root` as the client sees it: `virtual` maps absolute paths ("/@meta/general.json") to
    byte providers, and no change may touch `protected()` (the flight being recorded), anything
    under it, or a directory above it (renaming that would move the flight)."""

    def __init__(self, root: Path, virtual: Mapping[str, Callable[[], bytes]] | None,
                 protected: Callable[[], Path | None]) -> None:
        self.root = Path(root)
        self.virtual = {path_key([p for p in name.split("/") if p not in ("", ".")]): provider
                        for name, provider in (virtual or {}).items()}
        self._protected = protected

    def locate(self, parts: list[str]) -> tuple[Path, Path]:
        """(entry, target) of a path under the root: the entry names a symlink itself, the target
        is what it resolves to. Both must lie under the root.

        Outside the root is answered FILENOTFOUND: the served tree is all that exists for a
        client, clients show it as "does not exist" (MAVSDK FileDoesNotExist, MAVProxy crccmp
        MISSING), and unlike FILEPROTECTED it does not reveal that something is there.
        """
        root = self.root.resolve()
        if not parts:
            return root, root
        try:
            parent = root.joinpath(*parts[:-1]).resolve()
            entry = parent / parts[-1]
            target = entry.resolve()
        except RuntimeError as exc:  # a symlink loop (Python 3.11)
            raise Nak(ERR_FAILERRNO, errno.ELOOP) from exc
        if not (parent.is_relative_to(root) and target.is_relative_to(root)):
            raise Nak(ERR_FILENOTFOUND)
        return entry, target

    def writable(self, parts: list[str], may_write: bool) -> tuple[Path, Path]:
        """`locate` for a change: FILEPROTECTED (the spec's "write protected", which MAVSDK shows
        as FileProtected) on a read-only call, a virtual file, the root or the recorded flight."""
        if not may_write or path_key(parts) in self.virtual:
            raise Nak(ERR_FILEPROTECTED)
        entry, target = self.locate(parts)
        if entry == self.root.resolve():
            raise Nak(ERR_FILEPROTECTED)
        self.check_unprotected(entry, target)
        return entry, target

    def check_unprotected(self, *paths: Path) -> None:
        flight = self._protected()
        if flight is None:
            return
        flight = Path(flight).resolve()
        for path in paths:
            if path.is_relative_to(flight) or flight.is_relative_to(path):
                raise Nak(ERR_FILEPROTECTED)
