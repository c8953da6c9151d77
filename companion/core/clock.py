"""Time source for the runtime, so a simulated flight can run faster than real time.

Every period, deadline and timestamp in the runtime goes through one `Clock`. In flight the
scale is 1. In a `--fast` simulation the scale is >1: monotonic time and wall time both advance
`scale` times faster than the machine's clocks, so rates, watchdog periods and log timestamps
stay consistent with each other and with the simulator.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class Clock:
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
