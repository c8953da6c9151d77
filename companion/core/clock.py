"""Time source for the runtime, so a simulated flight can run faster than real time.

Every period, deadline, timeout and timestamp in the runtime goes through one `Clock`. In flight
the scale is 1. In a `--fast` simulation the scale is >1: monotonic time and wall time both
advance `scale` times faster than the machine's clocks, so rates, watchdog periods and log
timestamps stay consistent with each other and with the simulator.

The clock is also where a runtime thread waits (`sleep`, `wait_for`, `wait_event`) and where
its worker is started (`start_thread`): a lockstep simulation
(`companion.core.lockstep.LockstepClock`) replaces all of them at once, so the same thread code
runs on simulated time without a line that knows about it. Timeouts given to these methods are
in clock seconds, never host seconds.
"""

from __future__ import annotations

import ctypes
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol


class Worker(Protocol):
    """What a thread started by `Clock.start_thread` offers (a `threading.Thread` does)."""

    name: str

    def is_alive(self) -> bool: ...

    def join(self, timeout: float | None = None) -> None: ...

    @property
    def ident(self) -> int | None: ...

    @property
    def native_id(self) -> int | None: ...


class Clock:
    #: True for a lockstep clock: time advances only when every thread waits.
    lockstep = False

    def __init__(self, scale: float = 1.0, epoch: tuple[int, int] | None = None) -> None:
        """`epoch` = (monotonic ns, realtime ns) at which both clocks agree with the host's;
        processes that share it (the simulator and the runtime) share one timeline."""
        if scale <= 0:
            raise ValueError(f"clock scale must be positive, got {scale}")
        self.scale = scale
        if epoch is None:
            epoch = (time.monotonic_ns(), time.time_ns())
        self._mono0, self._real0 = epoch

    @property
    def epoch(self) -> tuple[int, int]:
        return self._mono0, self._real0

    def monotonic_ns(self) -> int:
        """Scaled monotonic time in ns (starts at the machine's monotonic time at creation)."""
        if self.scale == 1.0:
            return time.monotonic_ns()
        return self._mono0 + int((time.monotonic_ns() - self._mono0) * self.scale)

    def monotonic(self) -> float:
        return self.monotonic_ns() / 1e9

    def realtime_ns(self) -> int:
        """Wall time in ns as it was at the epoch plus the (scaled) monotonic time since: what
        log records and datagrams carry.

        Never read from the wall clock after the epoch, also in flight: an aircraft computer
        without a real-time clock boots with a stale time and NTP or GPS time steps it later,
        often in flight, and a step (an hour forward, or backwards) in the records would break
        every time difference taken across it (rates, latencies, the log's order). The receiver's
        UTC is logged with every GPS fix, to align a flight with true time afterwards.
        """
        return self._real0 + int((time.monotonic_ns() - self._mono0) * self.scale)

    def to_host_s(self, duration_s: float) -> float:
        """Convert a duration in clock time to host seconds (what sleep/wait primitives take)."""
        return duration_s / self.scale

    def sleep(self, duration_s: float, stop: threading.Event) -> bool:
        """Wait `duration_s` of clock time, or less when `stop` is set; True when stopped."""
        return self.wait_until_ns(self.monotonic_ns() + int(duration_s * 1e9), stop)

    def wait_event(self, event: threading.Event, timeout_s: float) -> bool:
        """`event.wait` with a timeout in clock seconds; True when the event is set."""
        return event.wait(timeout_s / self.scale)

    def wait_for(self, cond: threading.Condition, ready: Callable[[], bool],
                 timeout_s: float) -> bool:
        """With `cond` held, wait until `ready()` (re-checked at each notify) or `timeout_s` of
        clock time; returns `ready()`. The lock is released while waiting, as `cond.wait` does."""
        if ready():
            return True
        deadline = time.monotonic() + timeout_s / self.scale
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return ready()
            cond.wait(remaining)
            if ready():
                return True

    def start_thread(self, target: Callable[..., None], args: tuple[Any, ...], name: str,
                     priority: int = 100) -> Worker:
        """Start a daemon worker. `priority` orders workers that are due at the same instant
        of a lockstep flight; real threads ignore it."""
        worker = threading.Thread(target=target, args=args, name=name, daemon=True)
        worker.start()
        return worker

    def interrupt_thread(self, worker: Worker, exc_type: type[BaseException]) -> bool:
        """Raise `exc_type` asynchronously inside `worker` (a pure-Python loop that ignores its
        stop event); False when there is no live worker to raise it in."""
        ident = worker.ident
        if ident is None or not worker.is_alive():
            return False
        n = ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(ident),
                                                       ctypes.py_object(exc_type))
        return n == 1

    def wait_until_ns(self, deadline_ns: int, stop: threading.Event) -> bool:
        """Sleep until the scaled monotonic deadline or until `stop` is set; True when stopped.

        Event.wait wakes on a stop request at once; it is accurate to a few tens of microseconds
        on Linux, which is within the jitter budget of a 1 kHz thread.
        """
        while True:
            remaining_ns = deadline_ns - self.monotonic_ns()
            if remaining_ns <= 0:
                return stop.is_set()
            if stop.wait(remaining_ns / 1e9 / self.scale):
                return True


def every(period_s: float, fn: Callable[[], None]) -> Callable[[], None]:
    """Wrap `fn` so that calling the wrapper often (a manager tick hook) runs it at most once per
    `period_s` of host time, for console status lines and other human-paced output."""
    last = [0.0]

    def hook() -> None:
        now = time.monotonic()
        if now - last[0] >= period_s:
            last[0] = now
            fn()

    return hook
