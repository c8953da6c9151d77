"""Disk policy: keep N MB free and at most M flights, deleting the oldest finished flights.

An aircraft computer that logs every flight fills its card within a season; before this, a full
disk only switched logging off mid-flight. The policy runs when the runtime starts (before the
new flight writes anything) and then every `CHECK_PERIOD_S` in a thread of its own, and deletes
whole flight directories, oldest first, until both limits hold:

- only directories named like a flight (``<UTC stamp>...``, as `new_flight_dir` makes them) are
  candidates: nothing else under the logs directory is touched;
- never the current flight, and never one that another runtime is writing: a running runtime
  holds a shared lock on its flight directory (`FlightLock`), so several aircraft of a fleet
  that share a logs directory never delete each other's live flights;
- each deletion is logged (the flight, its size, which limit asked for it).

When nothing is left to delete and the disk is still full, logging degrades as before (each
log switches itself off and says so) while the aircraft flies on.
"""

from __future__ import annotations

import fcntl
import logging
import os
import re
import shutil
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

__all__ = ["CHECK_PERIOD_S", "Deletion", "DiskPolicy", "FlightLock", "enforce", "finished_flights"]

CHECK_PERIOD_S = 10.0
_FLIGHT_NAME = re.compile(r"^\d{8}T\d{6}Z")


class FlightLock:
    """A lock on a flight directory held while a runtime writes it (flock on the directory)."""

    def __init__(self, flight_dir: Path) -> None:
        self._fd: int | None = os.open(flight_dir, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        fcntl.flock(self._fd, fcntl.LOCK_SH)

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops the lock
            self._fd = None


def _in_use(path: Path) -> bool:
    try:
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    except OSError:
        return True  # cannot tell: leave it
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)  # also releases the exclusive lock, if taken
    return False


def flights(root: Path) -> list[Path]:
    """Every flight directory under `root`, oldest first (by name: the start's UTC time)."""
    try:
        return sorted(p for p in root.iterdir()
                      if p.is_dir() and not p.is_symlink() and _FLIGHT_NAME.match(p.name))
    except OSError:
        return []


def finished_flights(root: Path, current: Path | None,
                     every: list[Path] | None = None) -> list[Path]:
    """Flight directories under `root` (or of `every`, already listed) that no runtime
    writes, oldest first."""
    cur = current.resolve() if current is not None else None
    return [p for p in (flights(root) if every is None else every)
            if p.resolve() != cur and not _in_use(p)]


def _size_bytes(path: Path) -> int:
    total = 0
    for dirpath, _dirs, files in os.walk(path):
        for f in files:
            try:
                total += os.lstat(os.path.join(dirpath, f)).st_size
            except OSError:
                pass
    return total


def _free_mb(root: Path) -> float:
    st = os.statvfs(root)
    return st.f_bavail * st.f_frsize / 1e6


@dataclass(frozen=True)
class Deletion:
    path: Path
    size_mb: float
    reason: str


def enforce(root: Path, current: Path | None, *, min_free_mb: float, max_flights: int,
            free_mb: Callable[[Path], float] = _free_mb) -> list[Deletion]:
    """Delete the oldest finished flights until `min_free_mb` are free and at most
    `max_flights` flights exist (the current one included); 0 turns a limit off."""
    if min_free_mb <= 0 and max_flights <= 0:
        return []
    done: list[Deletion] = []
    every = flights(root)
    candidates = finished_flights(root, current, every)
    total = len(every)  # live ones (this flight, another aircraft's) count too
    for path in candidates:
        too_many = max_flights > 0 and total > max_flights
        try:
            too_full = min_free_mb > 0 and free_mb(root) < min_free_mb
        except OSError:
            too_full = False
        if not (too_many or too_full):
            break
        size_mb = _size_bytes(path) / 1e6
        reason = (f"more than {max_flights} flights" if too_many
                  else f"less than {min_free_mb:g} MB free")
        try:
            shutil.rmtree(path)
        except OSError as exc:
            log.error("disk policy: cannot delete flight %s: %s", path.name, exc)
            continue
        total -= 1
        done.append(Deletion(path, size_mb, reason))
        log.warning("disk policy: deleted flight %s (%.1f MB): %s", path.name, size_mb, reason)
    return done


class DiskPolicy:
    """Runs `enforce` at once and then every `period_s` (host) in a daemon thread; the limits are
    read from `limits()` at each pass, so a ground station's change applies without a restart."""

    def __init__(self, root: Path, current: Path, limits: Callable[[], tuple[float, int]],
                 *, period_s: float = CHECK_PERIOD_S,
                 on_delete: Callable[[Deletion], None] | None = None) -> None:
        self.root = root
        self._on_delete = on_delete
        self.current = current
        self._limits = limits
        self._period_s = period_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.deleted: list[Deletion] = []

    def run_once(self) -> list[Deletion]:
        min_free_mb, max_flights = self._limits()
        try:
            done = enforce(self.root, self.current, min_free_mb=min_free_mb,
                           max_flights=max_flights)
        except Exception:  # the policy must never take the runtime down
            log.exception("disk policy: pass failed")
            return []
        self.deleted += done
        if self._on_delete is not None:
            for d in done:
                try:
                    self._on_delete(d)
                except Exception:
                    log.exception("disk policy: reporting a deletion failed")
        return done

    def start(self) -> None:
        self.run_once()
        self._thread = threading.Thread(target=self._run, name="disk-policy", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            self.run_once()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
