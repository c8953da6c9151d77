"""The two managed threads that run a link, the router's thread, and their task rows.

`LinkReceiver` and `LinkSender` are thin shells over `gcs_bridge.link.Link`, which holds
everything a link remembers, so a thread restarted by the watchdog carries on where it stopped.
Here is only what a thread owns: its task row (`receiver_task`, `sender_task`), its pacing and
its bounded waits. Neither thread polls: each sleeps until there is work or a deadline, and at
most a quarter of its watchdog period (`bounded_wait_s`), a clock duration turned into host
seconds, so the watchdog sees cycles in each of its windows at any simulation speed.

Beside an autopilot, `RouterThread` drains the frames the autopilot link received
(`autopilot_rx`) into the router (`gcs_bridge.router`), with the same bounded waits.
"""

from __future__ import annotations

import time
from typing import Any

from companion.core.clock import Clock
from companion.core.sync import MessageQueue
from companion.watchdog import ManagedThread, Task
from gcs_bridge import status
from gcs_bridge.link import ITEMS_PER_CYCLE, Link
from gcs_bridge.router import Router

WAIT_CAP_S = 0.5  # host seconds: the longest wait of either thread, whatever its watchdog
BEATS_PER_WINDOW = 4  # a thread waits at most its watchdog period over this
TLOG_FLUSH_S = 1.0


def bounded_wait_s(clock: Clock, watchdog_ms: int, wait_ns: int | None = None) -> float:
    """Host seconds a link thread may wait for work due in `wait_ns` clock ns (None: nothing
    due): at most a quarter of its watchdog period, so each watchdog window holds several
    completed cycles at any clock scale, and at most `WAIT_CAP_S` of host time."""
    bound_ns = watchdog_ms * 1_000_000 // BEATS_PER_WINDOW
    if wait_ns is not None:
        bound_ns = min(bound_ns, max(0, wait_ns))
    return min(WAIT_CAP_S, clock.to_host_s(bound_ns / 1e9))


def receiver_task(index: int) -> Task:
    """Link `index`'s receive thread: paced by the transport's bounded wait."""
    return Task(f"mav{index}rx", paced_by="the transport (waits a quarter of its watchdog)",
                budget_ms=5.0,
                watchdog_ms=1000, message_ms=5000, switchable=False,
                implementation="gcs_bridge.link_threads:LinkReceiver")


def sender_task(index: int) -> Task:
    """Link `index`'s send thread: paced by the earliest due message or queued answer."""
    return Task(f"mav{index}tx", paced_by="due telemetry and queued answers", budget_ms=5.0,
                watchdog_ms=1000, message_ms=5000, switchable=False,
                implementation="gcs_bridge.link_threads:LinkSender")


class LinkReceiver(ManagedThread):
    """Receives for one link; paced by the transport with a bounded wait."""

    def __init__(self, link: Link) -> None:
        super().__init__(receiver_task(link.index))
        self.link = link

    def setup(self) -> None:
        self.link.acquire()

    def cleanup(self) -> None:
        self.link.release()

    def interrupt_io(self) -> None:
        self.link.transport.wake()

    def recover(self) -> None:
        self.link.reset_parsers()

    def step(self) -> bool:
        self.link.receive(bounded_wait_s(self.ctx.clock, self.watchdog_ms), self._mark_work)
        return True  # an absent ground station is not a fault of the aircraft

    def _mark_work(self) -> None:
        self.work_t0_ns = time.perf_counter_ns()  # step time counts the work, not the wait


class LinkSender(ManagedThread):
    """Sends for one link: queued answers first, then the telemetry that is due.

    Its own `<PREFIX>_MSG_MS` paces the link's statistics (named values `L<n>_...`).
    """

    def __init__(self, link: Link) -> None:
        super().__init__(sender_task(link.index))
        self.link = link
        self._wait_host_s = 0.0
        self._next_stats_ns = 0
        self._next_flush_ns = 0

    def setup(self) -> None:
        self.link.acquire()

    def cleanup(self) -> None:
        try:
            self.link.drain_on_exit()
        finally:
            self.link.release()

    def interrupt_io(self) -> None:
        self.link.queue.put(_noop)  # wakes the sender's wait at once

    def prologue(self) -> bool:
        self.link.apply_initial_rates()
        self._wait_host_s = 0.0
        return True

    def step(self) -> bool:
        link = self.link
        clock = self.ctx.clock
        awaited = link.scheduler.awaited
        if awaited is not None and self._wait_host_s > 0 and not len(link.queue):
            # a due stream waits for its next sample: wake with the sample, not after a poll
            slot, version = awaited
            slot.wait_newer(version, self._wait_host_s)
            item = link.queue.get_nowait()
        else:
            item = link.queue.get(self._wait_host_s)
        self.work_t0_ns = time.perf_counter_ns()  # step time counts the work, not the wait
        handled = 0
        while item is not None:
            # An item taken from the queue is sent even when a stop has just been asked for: it
            # may be that very stop's COMMAND_ACK, and what is left stays queued for the exit.
            link.run_item(item)
            handled += 1
            if handled >= ITEMS_PER_CYCLE or self.stop_requested:
                break
            item = link.queue.get_nowait()
        now = clock.monotonic_ns()
        wait_ns = link.scheduler.service(now, link, link.emit)
        burst = int(self.ctx.params.get("MAV_PARAM_BURST"))
        # parameter lists and downloads are paced in host time: the network is real even in a
        # --fast simulation (host ns times the scale are clock ns)
        wait_ns = min(wait_ns, int(link.param_list_step(burst) * clock.scale))
        wait_ns = min(wait_ns, int(link.bulk.step(time.monotonic_ns(), link.emit) * clock.scale))
        link.send_events()
        link.check_home()
        if now >= self._next_stats_ns:
            if self._next_stats_ns:
                link.emit(status.link_messages(link.core, link.index, link.counters))
            self._next_stats_ns = now + int(self.message_ms * 1e6)
        wait_ns = min(wait_ns, self._next_stats_ns - now)
        if now >= self._next_flush_ns and link.tlog is not None:
            link.tlog.flush()
            self._next_flush_ns = now + int(TLOG_FLUSH_S * 1e9)
        if len(link.queue):
            wait_ns = 0
        self._wait_host_s = bounded_wait_s(clock, self.watchdog_ms, wait_ns)
        return True


def _noop(_link: Link) -> None:
    """Queued only to wake the sender."""


def router_task() -> Task:
    """The router's thread beside an autopilot: paced by the autopilot's frames."""
    return Task("mavroute", paced_by="the autopilot's frames (autopilot_rx)", budget_ms=5.0,
                watchdog_ms=1000, message_ms=5000, switchable=False,
                implementation="gcs_bridge.link_threads:RouterThread")


class RouterThread(ManagedThread):
    """Hands every frame from the autopilot (`autopilot_rx`) to the router, and says in a
    NOTICE (at most one per NOTICE_INTERVAL_S) which target was not found."""

    def __init__(self, router: Router, frames: MessageQueue[Any]) -> None:
        super().__init__(router_task())
        self.router = router
        self.frames = frames
        self.routed = 0

    def interrupt_io(self) -> None:
        self.frames.put(None)  # wakes the wait at once

    def step(self) -> bool:
        item = self.frames.get(bounded_wait_s(self.ctx.clock, self.watchdog_ms))
        self.work_t0_ns = time.perf_counter_ns()
        handled = 0
        while item is not None:
            self.router.from_autopilot(item)  # the frames of one read of the autopilot link
            handled += len(item)
            if handled >= ITEMS_PER_CYCLE or self.stop_requested:
                break
            item = self.frames.get_nowait()
        self.routed += handled
        unrouted = self.router.take_unrouted()
        if unrouted is not None:
            n, latest = unrouted
            self.notice(f"{n} frame(s) for no known system/component dropped, the latest "
                        f"{latest}", key="noroute")
        return True

    def counters(self) -> dict[str, int]:
        c = self.router.autopilot
        return {"from_autopilot": self.routed, "forwarded_from_autopilot": c.forwarded_in,
                "forwarded_to_autopilot": c.forwarded_out, "dropped_no_route": c.dropped}


__all__ = ["LinkReceiver", "LinkSender", "RouterThread", "bounded_wait_s", "receiver_task",
           "router_task", "sender_task"]
