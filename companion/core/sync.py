"""Thread synchronisation primitives shared by every managed thread.

The thesis's lesson: a lock must only ever guard the copy of a value, never I/O or user code,
so a thread that is stopped or stalls while it holds nothing cannot freeze the others. Every
primitive here takes its lock for the duration of a reference swap or a deque operation only.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Sized
from typing import Generic, TypeVar

from companion.core.clock import Clock

T = TypeVar("T")

_HOST = Clock()
"""The host's own time (scale 1): what a wait without a clock is measured in."""


def _waiters_of(cond: threading.Condition) -> Sized:
    """The threads blocked in `cond.wait` (CPython keeps them in `Condition._waiters`), so a
    writer can skip `notify` when nobody waits: a notify is a few Python-level calls, paid
    at every IMU sample, and in a lockstep flight no OS thread ever waits on a condition
    (the scheduler re-tests every waiter's predicate). Without that attribute (another
    Python), an always-true stand-in keeps every notify."""
    waiters = getattr(cond, "_waiters", None)
    return waiters if isinstance(waiters, deque) else _ALWAYS


class _Always:
    def __len__(self) -> int:
        return 1


_ALWAYS = _Always()


class DataSlot(Generic[T]):
    """Latest-value mailbox: writers overwrite, readers take a reference to the newest value.

    Values should be immutable (tuples, frozen dataclasses) so that the reference handed out is
    a consistent snapshot without a deep copy under the lock.
    """

    def __init__(self, initial: T | None = None) -> None:
        self._lock = threading.Lock()
        self._value: T | None = initial
        self._version = 0
        self._stamp_ns = 0

    def write(self, value: T) -> None:
        stamp = time.monotonic_ns()
        with self._lock:
            self._value = value
            self._version += 1
            self._stamp_ns = stamp

    def read(self) -> T | None:
        with self._lock:
            return self._value

    def read_versioned(self) -> tuple[T | None, int, int]:
        """Value, version counter and monotonic write time (ns): lets a reader tell stale data."""
        with self._lock:
            return self._value, self._version, self._stamp_ns

    @property
    def version(self) -> int:
        with self._lock:
            return self._version


class WaitableSlot(DataSlot[T]):
    """A data slot whose readers can block until a newer value than the one they saw arrives.

    Used to pace a consumer on its producer (the control thread on the estimator), with a timeout
    so the consumer still notices a stop request.
    """

    def __init__(self, initial: T | None = None) -> None:
        super().__init__(initial)
        self._cond = threading.Condition(self._lock)
        self._waiters = _waiters_of(self._cond)

    def write(self, value: T) -> None:
        stamp = time.monotonic_ns()
        with self._lock:  # the condition's own lock, without Condition's Python-level enter
            self._value = value
            self._version += 1
            self._stamp_ns = stamp
            if self._waiters:
                self._cond.notify_all()

    def wait_newer(self, seen_version: int, timeout_s: float,
                   clock: Clock | None = None) -> tuple[T | None, int] | None:
        """Return (value, version) once version > seen_version, or None after timeout_s.

        With a `clock`, the timeout is in its seconds and the wait is the clock's (scaled, or
        a lockstep flight's); without, host seconds."""
        with self._cond:
            if not (clock or _HOST).wait_for(self._cond, lambda: self._version > seen_version,
                                             timeout_s):
                return None
            return self._value, self._version

    def wake_all(self) -> None:
        """Wake every waiter (they see no new version and re-check their stop flag)."""
        with self._cond:
            self._cond.notify_all()


class MessageQueue(Generic[T]):
    """Bounded multi-producer multi-consumer queue that never blocks a producer.

    A full queue drops the *oldest* item when ``drop_oldest`` (telemetry: newest matters) or the
    new one otherwise (commands: first come, first served); either way the drop is counted so
    the loss is visible in thread status instead of silent.
    """

    def __init__(self, capacity: int, *, drop_oldest: bool = False) -> None:
        if capacity <= 0:
            raise ValueError(f"queue capacity must be positive, got {capacity}")
        self._capacity = capacity
        self._drop_oldest = drop_oldest
        self._items: deque[T] = deque()
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._waiters = _waiters_of(self._cond)
        self.dropped = 0
        self.put_count = 0

    def put(self, item: T) -> bool:
        """Enqueue without blocking; False when the item (or an older one) was dropped."""
        with self._lock:
            self.put_count += 1
            if len(self._items) >= self._capacity:
                self.dropped += 1
                if not self._drop_oldest:
                    return False
                self._items.popleft()
                self._items.append(item)
                if self._waiters:
                    self._cond.notify()
                return False
            self._items.append(item)
            if self._waiters:
                self._cond.notify()
            return True

    def get_nowait(self) -> T | None:
        with self._cond:
            return self._items.popleft() if self._items else None

    def get(self, timeout_s: float, clock: Clock | None = None) -> T | None:
        """Wait up to timeout_s for an item; None on timeout. With a `clock`, the timeout is
        in its seconds and the wait is the clock's; without, host seconds."""
        items = self._items
        with self._cond:
            if not (clock or _HOST).wait_for(self._cond, lambda: bool(items), timeout_s):
                return None
            return items.popleft()

    def drain(self) -> list[T]:
        with self._cond:
            items = list(self._items)
            self._items.clear()
            return items

    def wake_all(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)

    @property
    def capacity(self) -> int:
        return self._capacity
