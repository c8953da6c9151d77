"""MavlinkBridge: the runtime's MAVLink face, one link per endpoint.

Built once per vehicle by the runtime (`companion run` / `companion sim`, `--mavlink URL`,
repeatable, or `[mavlink] endpoints`). Construction opens nothing (so a dry build for
documentation is harmless): each link's receive and send threads are handed to the thread
manager, which opens the link when it starts them and supervises them like any other thread.

Beside a flight controller (the runtime runs an autopilot link, `--autopilot URL`) the bridge
is the companion: component 191 of the autopilot's system (`BridgeCore.autopilot`), and the
router (`gcs_bridge.router`) joins every ground link to the autopilot, with a thread of its own
for the autopilot's frames. An `autopilot:` endpoint instead serves the companion on the
autopilot link's own connection and routes nothing (the companion behind the user's router).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from companion.core.params import ParamSpec
from companion.watchdog import ManagedThread, RuntimeContext, ThreadManager
from gcs_bridge import status
from gcs_bridge.autopilot.link import COMPANION_COMPONENT, RX_QUEUE, TX_QUEUE, AutopilotLink
from gcs_bridge.bridge_params import BRIDGE_PARAMS
from gcs_bridge.commands import CommandHandler, LoggingControl
from gcs_bridge.dialect import mavlink
from gcs_bridge.dispatch import Dispatcher
from gcs_bridge.link import Link
from gcs_bridge.link_threads import (
    LinkReceiver,
    LinkSender,
    RouterThread,
    receiver_task,
    sender_task,
)
from gcs_bridge.params.protocol import ParamProtocol
from gcs_bridge.router import Router
from gcs_bridge.runtime_view import AutopilotSide, BridgeCore
from gcs_bridge.services.link_services import LinkServices
from gcs_bridge.services.metadata import ComponentMetadata
from gcs_bridge.signing import LinkPolicy, read_key_file
from gcs_bridge.transports.base import Transport
from gcs_bridge.transports.endpoints import (
    DEFAULT_ENDPOINT,
    Endpoint,
    EndpointError,
    parse_endpoint,
)
from gcs_bridge.transports.shared import SharedTransport

log = logging.getLogger(__name__)

HEARTBEAT_ID = int(mavlink.MAVLINK_MSG_ID_HEARTBEAT)
MAX_LINKS = 10  # thread parameter prefixes MAV<n>RX / MAV<n>TX have room for one digit
PERSIST_QUIET_S = 0.2  # parameters are saved once changes pause this long...
PERSIST_MAX_DELAY_S = 2.0  # ...or at the latest this long after the first unsaved change


def find_autopilot(manager: ThreadManager) -> AutopilotSide | None:
    """The runtime's enabled link to a flight controller: its thread named "autopilot", or an
    `AutopilotLink` by any name; None when it has none."""
    for thread in manager.threads:
        if isinstance(thread, AutopilotLink) or (thread.task.name == "autopilot"
                                                 and hasattr(thread, "identity")):
            if _enabled(thread):
                return thread  # type: ignore[return-value]  # it has `identity`
    return None


def _enabled(thread: ManagedThread) -> bool:
    try:
        return bool(thread.enabled)
    except Exception:  # its parameters are not declared (a thread outside a manager)
        return True


def _wake(autopilot: object) -> None:
    """End the autopilot link's read wait, so it sends what the router queued for it now (its
    transport's `wake`, safe from any thread; nothing for a link without one)."""
    transport = getattr(autopilot, "transport", None)
    if transport is not None:
        transport.wake()


def declared_params(n_links: int) -> list[ParamSpec]:
    """The bridge's parameters with `n_links` endpoints, without building it (docs)."""
    specs = list(BRIDGE_PARAMS)
    for index in range(n_links):
        specs += receiver_task(index).param_specs() + sender_task(index).param_specs()
    return specs


class MavlinkBridge:
    """MAVLink 2 endpoints for one vehicle (see docs/ground-stations.md).

    `endpoints`: pymavlink connection strings, each optionally with `?` settings (see
    `gcs_bridge.transports.endpoints`). `key_file`: signing passphrase file (`companion keys
    new`); when given, writes must be signed on every link that does not say `signing=off`, and
    unsigned reads are accepted where `allow_unsigned_reads` (or the link's `unsigned_reads=`)
    says so.
    `logging_control(start) -> error or None`: starts/stops the runtime's logs on
    MAV_CMD_LOGGING_START/STOP (the tlogs follow those commands in any case).
    """

    def __init__(
        self,
        ctx: RuntimeContext,
        manager: ThreadManager,
        endpoints: Sequence[str | Endpoint] = (DEFAULT_ENDPOINT,),
        *,
        key_file: str | Path | None = None,
        allow_unsigned_reads: bool = True,
        logging_control: LoggingControl | None = None,
        tlog: bool = True,
        flight_root: Path | None = None,
    ) -> None:
        parsed = [e if isinstance(e, Endpoint) else parse_endpoint(e) for e in endpoints]
        if len(parsed) > MAX_LINKS:
            raise EndpointError(", ".join(e.text for e in parsed[MAX_LINKS:]),
                                f"at most {MAX_LINKS} MAVLink endpoints")
        key: bytes | None = None
        if key_file:
            key, _passphrase = read_key_file(Path(key_file))
        ctx.params.declare_all(BRIDGE_PARAMS)
        self.ctx = ctx
        self.manager = manager
        autopilot = find_autopilot(manager)
        shared = any(e.kind == "autopilot" for e in parsed)
        if shared and autopilot is None:
            raise EndpointError(next(e.text for e in parsed if e.kind == "autopilot"),
                                "serves the companion on the autopilot link's connection: "
                                "give the autopilot's URL too (--autopilot URL)")
        self.core = (BridgeCore(ctx, manager) if autopilot is None else
                     BridgeCore(ctx, manager, compid=COMPANION_COMPONENT, autopilot=autopilot))
        self.params = ParamProtocol(self.core)
        self._tlog_recording = True
        self.commands = CommandHandler(self.core, logging_control=logging_control,
                                       set_tlog_recording=self._set_tlog_recording)
        self.dispatcher = Dispatcher(self.core, self.params, self.commands)
        self.text_ids = status.StatusTextIds()
        # parameter descriptions for QGC and MAVSDK, from the registry's metadata
        self.metadata = ComponentMetadata(ctx.params.specs, self.core.compid)
        self.links: list[Link] = []
        self.threads: list[LinkReceiver | LinkSender | RouterThread] = []
        self._senders: list[LinkSender] = []
        # flights are served from the directory holding this one (`companion run` and `sim`
        # make one directory per flight under `[logs] dir`)
        root = flight_root
        if root is None and ctx.flight_dir is not None:
            root = Path(ctx.flight_dir).parent
        for index, ep in enumerate(parsed):
            signing_on = key is not None and ep.signing is not False
            unsigned_reads = allow_unsigned_reads if ep.unsigned_reads is None else ep.unsigned_reads
            policy = LinkPolicy(key if signing_on else None, unsigned_reads)
            tlog_path = (Path(ctx.flight_dir) / f"mavlink-{index}.tlog"
                         if tlog and ctx.flight_dir is not None else None)
            transport: Transport | None = None
            if ep.kind == "autopilot":
                transport = SharedTransport(ep, ctx.state.queue(RX_QUEUE),
                                            ctx.state.queue(TX_QUEUE))
                # the autopilot link beats for the companion on this connection already: a
                # second HEARTBEAT of the same component would interleave its sequence numbers
                ep = dataclasses.replace(ep, rates_hz={HEARTBEAT_ID: 0.0, **ep.rates_hz})
            link = Link(index, ep, self.core, self.dispatcher, self.params, policy,
                        events=manager.subscribe_events(), text_ids=self.text_ids,
                        tlog_path=tlog_path, tlog_enabled=self._tlog_on,
                        broadcast_text=self.broadcast_text, tlog_service=ctx.logs,
                        transport=transport)
            link.services = LinkServices(link, root, self._current_flight, self.metadata)
            rx = LinkReceiver(link)  # the manager hands out the ids
            tx = LinkSender(link)
            manager.add(rx)
            manager.add(tx)
            self.links.append(link)
            self.threads += [rx, tx]
            self._senders.append(tx)
            log.info("MAVLink %s: identity %s, signing %s%s", link.describe(),
                     ep.identity.value, "on" if policy.signing else "off",
                     ", unsigned reads accepted" if policy.signing and unsigned_reads else "")
        self.router: Router | None = None
        if autopilot is not None and not shared:
            self.router = Router(self.core, self.links, ctx.state.queue(TX_QUEUE),
                                 wake_autopilot=lambda: _wake(autopilot))
            for link in self.links:
                link.router = self.router
            route_thread = RouterThread(self.router, ctx.state.queue(RX_QUEUE))
            manager.add(route_thread)
            self.threads.append(route_thread)
            log.info("MAVLink: the companion (component %d) beside the autopilot, routing "
                     "between it and %d link(s)", COMPANION_COMPONENT, len(self.links))
        self._first_unsaved = 0.0
        self._last_change = 0.0
        self._unsubscribe = ctx.params.subscribe(self._on_param_changed)
        manager.on_tick.append(self._persist_params)
        self._ids_checked = autopilot is None
        manager.on_tick.append(self._check_system_id)
        self._closed = False

    # ------------------------------------------------------------------ fan-out
    def broadcast_text(self, severity: int, text: str) -> None:
        """STATUSTEXT to every link (watchdog-like news that concerns every ground station)."""
        msgs = status.statustext(severity, text, self.text_ids)
        for link in self.links:
            link.post(list(msgs))

    def _on_param_changed(self, name: str, _value: object) -> None:
        # Runs in whichever thread changed the parameter: only queue the announcement.
        now = time.monotonic()
        if not self._first_unsaved:
            self._first_unsaved = now
        self._last_change = now
        index = self.params.index_of(name)
        if index is None:
            return
        for link, sender in zip(self.links, self._senders, strict=True):
            if sender.running:  # values loaded at start-up are not news
                link.post_param(index)

    def _persist_params(self) -> None:
        """Manager tick hook (main thread): save changed parameters once changes pause."""
        if not self._first_unsaved:
            return
        now = time.monotonic()
        if now - self._last_change < PERSIST_QUIET_S and now - self._first_unsaved < PERSIST_MAX_DELAY_S:
            return
        self._first_unsaved = 0.0
        try:
            self.ctx.params.flush()
        except OSError as exc:
            log.error("could not save parameters: %s", exc)

    def _check_system_id(self) -> None:
        """Manager tick hook: once the autopilot has said its system id, say (once) when the
        configuration's differs. Until then the companion spoke as the configured system, and
        a client that heard it first may keep a second, phantom system (MAVSDK does)."""
        if self._ids_checked:
            return
        ap = self.core.autopilot
        ident = ap.identity if ap is not None else None
        if ident is None:
            return
        self._ids_checked = True
        if int(ident.system) != int(self.ctx.vehicle_id):
            text = (f"autopilot is system {ident.system}, [vehicle] id is {self.ctx.vehicle_id}:"
                    f" set id = {ident.system}")
            log.warning("MAVLink: %s (the companion speaks as the autopilot's system; before "
                        "it was heard, as the configured one)", text)
            self.broadcast_text(int(mavlink.MAV_SEVERITY_NOTICE), text)

    def _current_flight(self) -> Path | None:
        return None if self.ctx.flight_dir is None else Path(self.ctx.flight_dir)

    def _set_tlog_recording(self, on: bool) -> None:
        self._tlog_recording = on
        log.info("MAVLink tlogs %s", "recording" if on else "paused")

    def _tlog_on(self) -> bool:
        return self._tlog_recording

    # ------------------------------------------------------------------ inspection
    def stats(self) -> list[dict[str, Any]]:
        """Per-link figures (frames, refusals, peers, stream counts, latencies)."""
        out = []
        for link in self.links:
            c = link.counters
            lat = sorted(link.scheduler.latencies_us)
            out.append({
                "index": link.index,
                "endpoint": link.endpoint.text,
                "signing": link.policy.signing,
                "rx_frames": c.rx_frames,
                "tx_frames": c.tx_frames,
                "parse_errors": c.parse_errors,
                "refused": c.refused,
                "refusals": dict(link.refusals),
                "queue_dropped": c.queue_dropped,
                "stale_skips": c.stale_skips,
                "peers": [(p.system, p.component) for p in link.peers.values()],
                "transport": vars(link.transport.counters).copy(),
                "streams_sent": link.scheduler.stats().sent,
                "latency_us_p50": lat[len(lat) // 2] if lat else None,
                "latency_us_p99": lat[min(len(lat) - 1, int(len(lat) * 0.99))] if lat else None,
                "tlog": str(link.tlog.path) if link.tlog is not None else None,
                "tlog_frames": link.tlog.frames if link.tlog is not None else 0,
                "tlog_dropped": link.tlog.dropped if link.tlog is not None else 0,
            })
            if link.router is not None:
                out[-1].update({f"routed_{k}": v for k, v in vars(link.routes).items()})
        return out

    def close(self) -> None:
        """Detach from the registry and the manager (after the manager's shutdown)."""
        if self._closed:
            return
        self._closed = True
        self._unsubscribe()
        for link in self.links:
            link.services.close()
        for hook in (self._persist_params, self._check_system_id):
            try:
                self.manager.on_tick.remove(hook)
            except ValueError:
                pass
        if self._first_unsaved:
            self._first_unsaved = 0.0
            try:
                self.ctx.params.flush()
            except OSError as exc:
                log.error("could not save parameters: %s", exc)
