"""MAVLink routing between the ground links and the flight controller, by MAVLink's rules.

Beside an autopilot (`companion run --autopilot URL` with `--mavlink` links) the companion is
the autopilot's way to the ground: every frame a ground link receives and every frame the
autopilot sends (`autopilot_rx`) comes here, as bytes, and goes where MAVLink's routing rules
say (https://mavlink.io/en/guide/routing.html), untouched (a signed frame keeps its signature):

* every frame teaches which (system, component) lives behind which link (a ground link, or
  `AUTOPILOT`);
* a frame with a target (`gcs_bridge.msg_targets`) goes only where that target lives:
  target system 0 is every system; target component 0 every component of the system;
  the companion itself (the autopilot's system, component 191) is served by the dispatcher;
* a broadcast (no target, target system 0, or a message the dialect does not know) goes to
  every link but the one it came from, and to the companion;
* never back to the link it came from, and once per link (destinations are a set);
* a frame for a system/component no link has is dropped and counted, and the router thread
  names the latest such target in a NOTICE (rate-limited by `ManagedThread.notice`);
* a frame from a ground link whose source lives behind the autopilot is a loop (the ground
  side hands the autopilot's frames back): dropped and counted, never routed again.

Who sends: a frame for the autopilot is put on `autopilot_tx` (the autopilot link sends it); a
frame for a ground link is posted to that link's sender queue (one sender per link, never the
receive thread), which holds it to the link's radio budget (`ByteBudget`). Routing runs in each
ground link's receive thread and in the router thread (`gcs_bridge.link_threads.RouterThread`)
that drains `autopilot_rx`; the table and the counters are shared under one lock.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from companion.core.sync import MessageQueue
from gcs_bridge.msg_targets import target_of
from gcs_bridge.runtime_view import BridgeCore

__all__ = ["AUTOPILOT", "ByteBudget", "RouteCounters", "RoutedLink", "Router"]

AUTOPILOT = -1
"""The link key of the flight controller (ground links are keyed by their index)."""
MAX_ROUTES = 256
"""(system, component) pairs remembered; the least recently heard go first."""
BUDGET_BURST_S = 0.5
"""A radio's forwarding budget may be saved up for this long (a parameter list's burst)."""


class RoutedLink(Protocol):
    """A ground link as the router sees it (`gcs_bridge.link.Link` is one)."""

    index: int
    routes: RouteCounters

    def post(self, item: Any) -> bool: ...


@dataclass
class RouteCounters:
    """One link's routing figures (in the bridge's stats, `routed_*`)."""

    forwarded_in: int = 0
    """Frames that came in on this link and were forwarded to another."""
    forwarded_out: int = 0
    """Frames forwarded onto this link (for a ground link: handed to its sender)."""
    dropped: int = 0
    """Frames from this link addressed to a system/component no link has."""
    looped: int = 0
    """Frames from this link whose source lives on the autopilot's side (a loop)."""
    over_budget: int = 0
    """Frames for this link dropped because its radio had no room left for them."""
    queue_full: int = 0
    """Frames for this link dropped because its sender's queue was full."""


class ByteBudget:
    """A token bucket for the bytes forwarded onto a radio: `rate_bytes_s`, saved up for at
    most `BUDGET_BURST_S`. Used by the link's sender only."""

    def __init__(self, rate_bytes_s: float) -> None:
        self.rate_bytes_s = rate_bytes_s
        self._tokens = rate_bytes_s * BUDGET_BURST_S
        self._at_s = time.monotonic()

    def take(self, n_bytes: int) -> bool:
        now = time.monotonic()
        cap = self.rate_bytes_s * BUDGET_BURST_S
        self._tokens = min(cap, self._tokens + (now - self._at_s) * self.rate_bytes_s)
        self._at_s = now
        if self._tokens < n_bytes:
            return False
        self._tokens -= n_bytes
        return True


class Router:
    """The routing table and the forwarding decisions, shared by every link's thread."""

    def __init__(self, core: BridgeCore, links: Sequence[RoutedLink],
                 to_autopilot: MessageQueue[Any],
                 wake_autopilot: Callable[[], None] | None = None) -> None:
        self.core = core
        self.links = {link.index: link for link in links}
        self.to_autopilot = to_autopilot
        self.wake_autopilot = wake_autopilot
        """Called after a frame is queued for the autopilot: the autopilot link sends its queue
        between two reads, so without it a frame waits for the end of the link's read wait."""
        self.autopilot = RouteCounters()
        self._routes: OrderedDict[tuple[int, int], set[int]] = OrderedDict()
        self._lock = threading.Lock()
        self._unrouted = 0
        self._unrouted_latest = ""

    # ------------------------------------------------------------------ entry points
    def from_ground(self, index: int, data: bytes, msg_id: int, src: tuple[int, int]) -> bool:
        """Route a frame that ground link `index` received (its receive thread). True: the
        companion is among its destinations, so the caller dispatches it."""
        with self._lock:
            known = self._routes.get(src)
            if known is not None and AUTOPILOT in known:
                self.links[index].routes.looped += 1
                return False
            self._learn(src, index)
        return self._route(index, data, msg_id, src)

    def from_autopilot(self, frames: Sequence[tuple[int, int, int, bytes]]) -> None:
        """Route the frames the autopilot link read in one go, each ``(system, component,
        msg_id, bytes)`` (the router thread). What is for the companion was the autopilot
        link's already (it reads every frame it receives). One batch takes the lock once and
        hands each ground link one item: at a flight controller's line rate a frame costs a
        few microseconds here instead of three lock round trips and a queue hand-off."""
        per_link: dict[int, list[bytes]] = {}
        with self._lock:
            for src_system, src_component, msg_id, data in frames:
                src = (src_system, src_component)
                self._learn(src, AUTOPILOT)
                dests, _local = self._destinations(AUTOPILOT, data, msg_id, src)
                for key in dests:  # never AUTOPILOT: the source is discarded
                    per_link.setdefault(key, []).append(data)
        for key, batch in per_link.items():
            link = self.links[key]
            ok = link.post(tuple(batch))
            with self._lock:
                if ok:
                    link.routes.forwarded_out += len(batch)
                else:
                    link.routes.queue_full += len(batch)

    def take_unrouted(self) -> tuple[int, str] | None:
        """Frames dropped for want of a route since the last call, and the latest one's
        description (for the router thread's NOTICE); None when there were none."""
        with self._lock:
            if not self._unrouted:
                return None
            n, self._unrouted = self._unrouted, 0
            return n, self._unrouted_latest

    def routes(self) -> dict[tuple[int, int], list[int]]:
        """A copy of the table: (system, component) -> link keys (`AUTOPILOT` = -1)."""
        with self._lock:
            return {k: sorted(v) for k, v in self._routes.items()}

    # ------------------------------------------------------------------ internals
    def _learn(self, src: tuple[int, int], key: int) -> None:
        """Under the lock: `src` was heard on link `key`."""
        if src == (self.core.sysid, self.core.compid):
            return  # ourselves, echoed
        where = self._routes.get(src)
        if where is None:
            where = self._routes[src] = set()
        where.add(key)
        self._routes.move_to_end(src)
        while len(self._routes) > MAX_ROUTES:
            self._routes.popitem(last=False)

    def _counters(self, key: int) -> RouteCounters:
        return self.autopilot if key == AUTOPILOT else self.links[key].routes

    def _destinations(self, source: int, data: bytes, msg_id: int,
                      src: tuple[int, int]) -> tuple[set[int], bool]:
        """Under the lock: the link keys a frame from link `source` goes to (never `source`),
        and whether the companion is among its destinations. Counts it as forwarded or as
        dropped for want of a route."""
        target = target_of(data, msg_id)
        local = True
        if target is None or target[0] == 0:
            dests = set(self.links) | {AUTOPILOT}
        else:
            system, component = target
            local = (system == self.core.sysid and component in (0, self.core.compid))
            dests = set()
            for (s, c), where in self._routes.items():
                if s == system and (component == 0 or c == component):
                    dests |= where
            if not dests and not local:
                self._counters(source).dropped += 1
                self._unrouted += 1
                self._unrouted_latest = (f"message {msg_id} from {src[0]}/{src[1]} for "
                                         f"{system}/{component}")
                return dests, False
        dests.discard(source)
        if dests:
            self._counters(source).forwarded_in += 1
        return dests, local

    def _route(self, source: int, data: bytes, msg_id: int, src: tuple[int, int]) -> bool:
        with self._lock:
            dests, local = self._destinations(source, data, msg_id, src)
        for key in dests:
            if key == AUTOPILOT:
                self.to_autopilot.put(data)
                with self._lock:
                    self.autopilot.forwarded_out += 1
                if self.wake_autopilot is not None:
                    self.wake_autopilot()
                continue
            link = self.links[key]
            ok = link.post(data)
            with self._lock:
                if ok:
                    link.routes.forwarded_out += 1
                else:
                    link.routes.queue_full += 1
        return local
