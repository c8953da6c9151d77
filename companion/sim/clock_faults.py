"""Wall-clock steps injected into the runtime's own process (`companion sim --clock-step`).

An aircraft computer's wall clock is stepped in flight when NTP or GPS time first sets it (a
Raspberry Pi has no real-time clock and boots with the time it last saved). Stepping the
machine's clock would disturb every other program on it, so the step is made in the process
under test: `time.time` and `time.time_ns` return the stepped time from the moment the flight
reaches the step's flight time. C code that reads the clock itself (`datetime.now`) is not
stepped; nothing in the runtime's timing uses it.

The step's syntax and parser are the fault catalogue's (`companion.sim.faults`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from companion.core.clock import Clock

log = logging.getLogger(__name__)

__all__ = ["WallClockSteps"]


class WallClockSteps:
    """Call `tick` often (the manager's tick hook); applies each step once its time comes."""

    def __init__(self, steps: list[tuple[float, float]], clock: Clock) -> None:
        self.pending = sorted(steps)
        self.clock = clock
        self.t0_ns = clock.monotonic_ns()
        self.offset_ns = 0
        self.applied: list[dict[str, float]] = []
        self._real_time_ns: Callable[[], int] = time.time_ns
        self._real_time: Callable[[], float] = time.time

    def tick(self) -> None:
        flight_s = (self.clock.monotonic_ns() - self.t0_ns) / 1e9
        while self.pending and flight_s >= self.pending[0][0]:
            at, step = self.pending.pop(0)
            if not self.applied:
                setattr(time, "time_ns", self._stepped_ns)  # noqa: B010
                setattr(time, "time", self._stepped_s)  # noqa: B010
            self.offset_ns += int(step * 1e9)
            self.applied.append({"at_s": round(flight_s, 3), "step_s": step})
            log.warning("fault: wall clock stepped %+.1f s at flight time %.2f s", step, flight_s)

    def _stepped_ns(self) -> int:
        return self._real_time_ns() + self.offset_ns

    def _stepped_s(self) -> float:
        return self._stepped_ns() / 1e9

    def restore(self) -> None:
        if self.applied:
            setattr(time, "time_ns", self._real_time_ns)  # noqa: B010
            setattr(time, "time", self._real_time)  # noqa: B010
