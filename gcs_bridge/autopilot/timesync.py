"""The autopilot's clock mapped onto the runtime's: offset, drift and link latency.

Every message an autopilot sends carries its own time stamp (`time_boot_ms` or `time_usec`,
since its boot). A sample's time in the runtime must be the time it was measured, not the
time its frame arrived (a 921600-baud link queues a burst for milliseconds; a radio, for
hundreds), so each stamp is mapped through an estimate of the two clocks' relation:

    runtime_ns = autopilot_ns + offset_ns + drift * (autopilot_ns - ref_ns)

Round trips of TIMESYNC give the estimate (MAVLink's time-synchronisation protocol: we send
``tc1 = 0, ts1 = our time``; the autopilot answers with ``tc1 = its time``, ``ts1`` echoed).
The half round trip is the link latency; the round trips with the least latency give the best
offsets (a slow one has waited in a queue on one side or the other), so the offset is fitted
to the fastest round trips of a sliding window, and the drift is the slope of those offsets.
Until a round trip has come back, a stamp is mapped by the arrival time of the first stamped
message (the offset it implies is late by the unknown latency: `synced` says which).

A jump of the autopilot's clock backwards (a reboot) or a fit far from a new round trip (more
than `STEP_S`) starts the estimate again and is counted (`resets`), so a rebooted autopilot's
samples are not mapped onto the previous boot's line.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

__all__ = ["ClockSync", "SyncEstimate"]

WINDOW = 32
"""Round trips kept for the fit (at one a second, half a minute)."""
BEST = 8
"""The fastest round trips of the window that the fit uses."""
STEP_S = 0.5
"""A new round trip this far from the fitted line is a step of a clock, not noise."""
MAX_RTT_S = 2.0
"""A round trip slower than this says nothing useful about the offset and is ignored."""


@dataclass(frozen=True)
class SyncEstimate:
    """The mapping in force and how good it is, for the thread's log and status."""

    offset_ns: int
    """runtime minus autopilot, at `ref_ns` of the autopilot's clock."""
    drift_ppm: float
    """How much faster the runtime's clock runs than the autopilot's, parts per million."""
    latency_s: float
    """Half the fastest round trip in the window: the link's one-way latency."""
    rtt_s: float
    """The last round trip."""
    synced: bool
    """True once a round trip has come back (before: from arrival times only)."""
    samples: int
    resets: int


class ClockSync:
    """Estimates the mapping from round trips and arrival times; not thread-safe (one link
    thread owns it)."""

    def __init__(self) -> None:
        self._trips: deque[tuple[int, int, int]] = deque(maxlen=WINDOW)
        """(autopilot ns at the mid-point, runtime ns at the mid-point, round trip ns)."""
        self._offset_ns: int | None = None
        self._ref_ns = 0
        self._drift = 0.0
        self._last_ap_ns: int | None = None
        self.latency_ns = 0
        self.rtt_ns = 0
        self.synced = False
        self.resets = 0

    # ------------------------------------------------------------------ inputs
    def observe_stamp(self, autopilot_ns: int, arrival_ns: int) -> None:
        """A stamped message arrived: before any round trip its arrival fixes the offset;
        a stamp that runs backwards by more than `STEP_S` is a reboot and starts again."""
        last = self._last_ap_ns
        if last is not None and autopilot_ns < last - int(STEP_S * 1e9):
            self.reset()
            last = None
        self._last_ap_ns = autopilot_ns if last is None else max(last, autopilot_ns)
        if self._offset_ns is None:
            self._offset_ns = arrival_ns - autopilot_ns
            self._ref_ns = autopilot_ns

    def observe_round_trip(self, sent_ns: int, autopilot_ns: int, received_ns: int) -> bool:
        """A TIMESYNC answer: our request left at `sent_ns`, the autopilot stamped it
        `autopilot_ns`, the answer arrived at `received_ns`. False: ignored (too slow, or
        from before our clock's time)."""
        rtt = received_ns - sent_ns
        if rtt < 0 or rtt > MAX_RTT_S * 1e9 or autopilot_ns <= 0:
            return False
        mid = sent_ns + rtt // 2
        if self.synced and abs(self.to_runtime_ns(autopilot_ns) - mid) > STEP_S * 1e9:
            self.reset()
        last = self._last_ap_ns
        self._last_ap_ns = autopilot_ns if last is None else max(last, autopilot_ns)
        self._trips.append((autopilot_ns, mid, rtt))
        self.rtt_ns = rtt
        self._fit()
        self.synced = True
        return True

    def reset(self) -> None:
        """Forget everything (the autopilot rebooted, or the link was reopened)."""
        if self._offset_ns is not None or self._trips:
            self.resets += 1
        self._trips.clear()
        self._offset_ns = None
        self._drift = 0.0
        self._last_ap_ns = None
        self.synced = False

    # ------------------------------------------------------------------ outputs
    def to_runtime_ns(self, autopilot_ns: int) -> int:
        """The runtime time at which the autopilot's clock read `autopilot_ns`."""
        if self._offset_ns is None:
            raise LookupError("no autopilot time stamp seen yet")
        return autopilot_ns + self._offset_ns + int(self._drift * (autopilot_ns - self._ref_ns))

    def map_or(self, autopilot_ns: int, fallback_ns: int) -> int:
        """`to_runtime_ns`, or `fallback_ns` (the arrival time) before any stamp was seen;
        never later than `fallback_ns` (a sample cannot be measured after it arrived)."""
        if self._offset_ns is None:
            return fallback_ns
        return min(self.to_runtime_ns(autopilot_ns), fallback_ns)

    def estimate(self) -> SyncEstimate:
        return SyncEstimate(offset_ns=self._offset_ns or 0, drift_ppm=self._drift * 1e6,
                            latency_s=self.latency_ns / 1e9, rtt_s=self.rtt_ns / 1e9,
                            synced=self.synced, samples=len(self._trips), resets=self.resets)

    def _fit(self) -> None:
        best = sorted(self._trips, key=lambda t: t[2])[:BEST]
        self.latency_ns = best[0][2] // 2
        ref = best[0][0]
        offsets = [(ap - ref, mid - ap) for ap, mid, _ in best]
        mean_x = sum(x for x, _ in offsets) / len(offsets)
        mean_y = sum(y for _, y in offsets) / len(offsets)
        sxx = sum((x - mean_x) ** 2 for x, _ in offsets)
        # a drift needs round trips spread over time (10 s at least): before, the offset only
        drift = (sum((x - mean_x) * (y - mean_y) for x, y in offsets) / sxx
                 if len(offsets) >= 3 and sxx > (10e9) ** 2 else 0.0)
        self._drift = max(-1e-3, min(1e-3, drift))  # crystals drift by ppm, not per mille
        self._ref_ns = ref
        self._offset_ns = int(round(mean_y - self._drift * mean_x))
