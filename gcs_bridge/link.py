"""One MAVLink link: its transport, its queue, rates, peers and tlog, shared by its two threads.

The receive thread (`gcs_bridge.link_threads`) reads the transport, parses, applies the signing
policy and dispatches; the send thread is the only one that writes to the transport. It is paced
by its queue (answers posted by the receive thread, the thread manager and parameter changes)
with a timeout set by the next telemetry stream due, so an answer leaves at once and telemetry
leaves on time.

Calls go one way: the link calls the dispatcher (`gcs_bridge.dispatch`), which calls the link's
services (`gcs_bridge.services`); neither imports this module, they see the link through the
protocols they declare (`DispatchLink`, `ServiceLink`), which `Link` implements.

Everything a link remembers between messages (rates set by ground stations, the parameter list
in progress, the thread-status rotation) lives here rather than in the threads, so a thread
restarted by the watchdog carries on where it stopped.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from companion.core.sync import MessageQueue
from companion.watchdog import ThreadStatus, WatchdogEvent
from gcs_bridge import status, telemetry
from gcs_bridge.bulk import BulkSender
from gcs_bridge.dialect import (
    MSG_ID_COMPONENT_METADATA,
    MSG_ID_PROTOCOL_VERSION,
    Identity,
    RxMessage,
    mavlink,
)
from gcs_bridge.dialect import Message as Msg
from gcs_bridge.framing import Frame, FrameSplitter
from gcs_bridge.msg_targets import COMMAND_OFFSETS, payload_u16
from gcs_bridge.router import ByteBudget, RouteCounters, Router
from gcs_bridge.runtime_view import BridgeCore
from gcs_bridge.signing import LinkPolicy, SignatureChecker, is_write, signing_timestamp
from gcs_bridge.streams import StreamScheduler, stream_for, streams_in_group
from gcs_bridge.tlog import TlogWriter
from gcs_bridge.transports.base import Transport, make_transport
from gcs_bridge.transports.endpoints import Endpoint

if TYPE_CHECKING:
    from companion.logs.writer import LogService
    from gcs_bridge.dispatch import Dispatcher
    from gcs_bridge.params.protocol import ParamProtocol
    from gcs_bridge.services.link_services import LinkServices

log = logging.getLogger(__name__)

QUEUE_CAPACITY = 2048
ITEMS_PER_CYCLE = 256
REFUSAL_REPORT_S = 5.0  # at most one STATUSTEXT about refused messages per link per this
PEER_MEMORY = 32
PARAM_BATCH_PAUSE_NS = 5_000_000  # host ns between MAV_PARAM_BURST-sized batches of a list
PEER_SILENCE_S = 5.0  # a transfer for a peer not heard from for this long is abandoned
RADIO_BULK_SHARE = 0.8  # of what the telemetry schedule leaves of a serial line

SenderItem = list[Msg] | Callable[["Link"], None] | bytes | tuple[bytes, ...]
"""What the sender sends: messages, a function of the link, or a forwarded frame's bytes."""


@dataclass(frozen=True)
class Peer:
    system: int
    component: int
    mav_type: int
    last_seen_s: float


class Link:
    """State shared by one link's receive and send threads (see the module docstring)."""

    def __init__(self, index: int, endpoint: Endpoint, core: BridgeCore, dispatcher: Dispatcher,
                 params: ParamProtocol, policy: LinkPolicy, *, events: MessageQueue[WatchdogEvent],
                 text_ids: status.StatusTextIds, tlog_path: Path | None,
                 tlog_enabled: Callable[[], bool], broadcast_text: Callable[[int, str], None],
                 tlog_service: LogService | None = None,
                 transport: Transport | None = None) -> None:
        self.index = index
        self.endpoint = endpoint
        self.core = core
        self.dispatcher = dispatcher
        self.params = params
        self.policy = policy
        self.events = events
        self.text_ids = text_ids
        self.transport = transport if transport is not None else make_transport(endpoint)
        self.queue: MessageQueue[SenderItem] = MessageQueue(QUEUE_CAPACITY)
        self.counters = status.LinkCounters()
        self.scheduler = StreamScheduler(core, line_bytes_s=self.transport.bytes_per_s,
                                         signed=policy.key is not None)
        self.tlog = TlogWriter(tlog_path, tlog_service) if tlog_path is not None else None
        self._tlog_enabled = tlog_enabled
        self._broadcast_text = broadcast_text
        self._refs = 0
        # receive side
        self._parsers: OrderedDict[Hashable, mavlink.MAVLink] = OrderedDict()
        self._checker = (SignatureChecker(policy.key, self._now_timestamp)
                         if policy.key is not None else None)
        self.peers: OrderedDict[tuple[int, int], Peer] = OrderedDict()
        self.refusals: dict[str, int] = {}
        self._refused_unreported = 0
        self._last_refusal_report = 0.0
        # send side
        self.mav_out = mavlink.MAVLink(None, core.sysid, core.compid)
        if policy.key is not None:
            self.mav_out.signing.secret_key = policy.key
            self.mav_out.signing.link_id = index & 0xFF
            self.mav_out.signing.sign_outgoing = True
        self._param_cursor: int | None = None
        self._rotation = 0
        self._home_origin: tuple[float, float, float] | None = None
        self.bulk = BulkSender(self._bulk_bytes_s)
        self.heard: dict[tuple[int, int], float] = {}  # peer -> last message, monotonic s
        self.signed_in = False  # whether the message being dispatched was signed and valid
        self.services: LinkServices  # set by the bridge once the link exists
        # routing beside an autopilot (`gcs_bridge.router`): set by the bridge, else None
        self.router: Router | None = None
        self.routes = RouteCounters()
        self._splitters: OrderedDict[Hashable, FrameSplitter] = OrderedDict()
        self._local_parser = mavlink.MAVLink(None, 0, 0)
        self._local_parser.robust_parsing = True
        self._budget: ByteBudget | None = None
        self._pack_errors = 0
        self._initial_rates_applied = False

    # ------------------------------------------------------------------ lifecycle (main thread)
    def acquire(self) -> None:
        """Open the transport and tlog with the first of the link's threads to start."""
        if self._refs == 0:
            self.transport.open()
            if self.tlog is not None and not self.tlog.is_open:
                try:
                    self.tlog.open()
                except OSError as exc:
                    log.error("link %d: cannot open tlog %s: %s", self.index, self.tlog.path, exc)
        self._refs += 1

    def release(self) -> None:
        """Close them with the last one to stop (idempotent per acquire)."""
        if self._refs == 0:
            return
        self._refs -= 1
        if self._refs == 0:
            self.transport.close()
            if self.tlog is not None:
                self.tlog.close()

    @property
    def identity(self) -> Identity:
        """The link's claim (`identity=`), or beside an autopilot the encoding its firmware
        dictates (`BridgeCore.encoding`)."""
        return self.core.encoding(self.endpoint.identity)

    # ------------------------------------------------------------------ posting (any thread)
    def post(self, item: SenderItem) -> bool:
        ok = self.queue.put(item)
        if not ok:
            self.counters.queue_dropped += 1
        return ok

    def post_param(self, index: int) -> bool:
        return self.post(lambda link: link.send_param(index))

    def start_param_list(self) -> bool:
        return self.post(lambda link: link.begin_param_list())

    def notify(self, severity: int, text: str) -> None:
        self.post(status.statustext(severity, text, self.text_ids))

    @staticmethod
    def can_provide(msg_id: int) -> bool:
        """Whether REQUEST_MESSAGE can be answered for this message id."""
        return (msg_id in (mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, MSG_ID_PROTOCOL_VERSION,
                           MSG_ID_COMPONENT_METADATA)
                or stream_for(msg_id) is not None)

    def request_message(self, msg_id: int, target: tuple[int, int]) -> bool:
        """REQUEST_MESSAGE: post the message's production to the sender; False if unknown."""
        if msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return self.post([status.autopilot_version(self.core, self.identity)])
        if msg_id == MSG_ID_PROTOCOL_VERSION:
            return self.post([status.protocol_version()])
        if msg_id == MSG_ID_COMPONENT_METADATA:
            return self.post([self.services.metadata_message()])
        if stream_for(msg_id) is None:
            return False
        return self.post(lambda link: link.send_stream_now(msg_id))

    def set_interval(self, msg_id: int, interval_us: int) -> bool:
        if stream_for(msg_id) is None:
            return False
        self.post(lambda link: link._apply_interval(msg_id, interval_us))
        return True

    def interval_us(self, msg_id: int) -> int:
        return self.scheduler.interval_us(msg_id)

    def data_stream(self, stream_id: int, rate_hz: int, start: bool) -> None:
        """REQUEST_DATA_STREAM (deprecated but still sent by MAVProxy and older GCSs)."""
        specs = streams_in_group(stream_id)
        if not specs:
            return
        interval = int(1e6 / rate_hz) if start and rate_hz > 0 else -1

        def apply(link: Link) -> None:
            for spec in specs:
                link._apply_interval(spec.msg_id, interval)
        self.post(apply)

    # ------------------------------------------------------------------ receive thread
    @staticmethod
    def _now_timestamp() -> int:
        # the host's wall clock, not the runtime's (which a --fast simulation speeds up): the
        # ground stations' signing clocks are real ones
        return signing_timestamp(time.time_ns())

    @property
    def _datagrams(self) -> bool:
        return self.endpoint.kind.startswith("udp")

    def reset_parsers(self) -> None:
        self._parsers.clear()
        self._splitters.clear()

    def _parser(self, peer: Hashable) -> mavlink.MAVLink:
        parser = self._parsers.get(peer)
        if parser is None:
            parser = mavlink.MAVLink(None, 0, 0)
            parser.robust_parsing = True
            self._parsers[peer] = parser
            while len(self._parsers) > PEER_MEMORY:
                self._parsers.popitem(last=False)
        else:
            self._parsers.move_to_end(peer)
        return parser

    def receive(self, timeout_s: float, on_data: Callable[[], None] | None = None) -> int:
        """Read, parse, check and dispatch what arrives within timeout_s; returns frames."""
        frames = 0
        chunks = self.transport.recv(timeout_s)
        if on_data is not None:
            on_data()
        if self.router is not None:
            return self._receive_routed(chunks, self.router)
        for peer, data in chunks:
            parser = self._parser(peer)
            try:
                msgs = parser.parse_buffer(data) or []
            except Exception as exc:  # pymavlink raises on some malformed input: drop it
                self.counters.parse_errors += 1
                log.debug("link %d: unparsable data from %s: %s", self.index, peer, exc)
                self._parsers.pop(peer, None)
                continue
            if self._datagrams and len(parser.buf) > parser.buf_index:
                # A datagram carries whole frames: what is left of one is a cut or corrupt
                # frame, and must not swallow the start of the same peer's next datagram.
                self.counters.parse_errors += 1
                _reset_parser(parser)
            accepted = trusted = False
            for msg in msgs:
                frames += 1
                if self._on_message(msg):
                    accepted = True
                    trusted = trusted or self.signed_in
            if accepted:
                self.transport.accept_peer(peer, trusted)
        return frames

    def _on_message(self, msg: RxMessage) -> bool:
        """Check and dispatch one frame; True when it was accepted (acted on)."""
        if msg.get_type() == "BAD_DATA":
            self.counters.parse_errors += 1
            return False
        frame = msg.get_msgbuf()
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if src == (self.core.sysid, self.core.compid):
            return False  # our own frames echoed (loopback radios, broadcast UDP)
        self.counters.rx_frames += 1
        self.signed_in = False
        if self._checker is not None:
            why = self._checker.check(frame) if frame[0] == 0xFD and frame[2] & 0x01 else "unsigned"
            if why is not None:
                command = getattr(msg, "command", None)
                if not (why == "unsigned" and self.policy.unsigned_reads
                        and not is_write(msg.get_msgId(), command)):
                    self.refuse(msg, why)  # counted, not written to the tlog: a flood of
                    return False           # refused frames must not fill the disk
            else:
                self.signed_in = True
        self._tlog(frame)
        self._note_heard(src)
        self.dispatcher.handle(self, msg)
        return True

    def _receive_routed(self, chunks: list[tuple[Hashable, bytes]], router: Router) -> int:
        """Beside an autopilot: cut whole frames (`FrameSplitter`), apply the signing policy
        to each, hand it to the router as bytes and dispatch the ones the companion is among
        the destinations of."""
        frames = 0
        for peer, data in chunks:
            splitter = self._splitters.get(peer)
            if splitter is None:
                splitter = self._splitters[peer] = FrameSplitter()
                while len(self._splitters) > PEER_MEMORY:
                    self._splitters.popitem(last=False)
            bad_before = splitter.bad_crc
            cut = splitter.feed(data)
            self.counters.parse_errors += splitter.bad_crc - bad_before
            if self._datagrams and splitter.pending:
                self.counters.parse_errors += 1  # a datagram's cut frame: see `receive`
                splitter.reset()
            accepted = trusted = False
            for frame in cut:
                frames += 1
                src = (frame.src_system, frame.src_component)
                if src == (self.core.sysid, self.core.compid):
                    continue  # our own frames echoed
                self.counters.rx_frames += 1
                why = self._frame_verdict(frame)
                if why is not None:
                    self._refused(src, why, self._frame_name(frame))
                    continue
                accepted = True
                signed = self.signed_in
                trusted = trusted or signed
                self._tlog(frame.data)
                self._note_heard(src)
                if not router.from_ground(self.index, frame.data, frame.msg_id, src):
                    continue
                for msg in self._local_parser.parse_buffer(frame.data) or []:
                    if msg.get_type() != "BAD_DATA":  # a message of another dialect: not ours
                        self.signed_in = signed
                        self.dispatcher.handle(self, msg)
            if accepted:
                self.transport.accept_peer(peer, trusted)
        return frames

    def _frame_verdict(self, frame: Frame) -> str | None:
        """The signing policy on a frame's bytes (None: accepted; `signed_in` says whether it
        was signed with the key). Unsigned, it passes only as a read the bridge's dialect
        knows: a message of another dialect may change the autopilot, for all we can tell."""
        self.signed_in = False
        if self._checker is None:
            return None
        data = frame.data
        why = self._checker.check(data) if data[0] == 0xFD and data[2] & 0x01 else "unsigned"
        if why is None:
            self.signed_in = True
            return None
        command_at = COMMAND_OFFSETS.get(frame.msg_id)
        command = payload_u16(data, command_at) if command_at is not None else None
        if (why == "unsigned" and self.policy.unsigned_reads
                and frame.msg_id in mavlink.mavlink_map and not is_write(frame.msg_id, command)):
            return None
        return why

    @staticmethod
    def _frame_name(frame: Frame) -> str:
        cls = mavlink.mavlink_map.get(frame.msg_id)
        name = str(cls.msgname) if cls is not None else f"message {frame.msg_id}"
        command_at = COMMAND_OFFSETS.get(frame.msg_id)
        if command_at is not None:
            name += f" {payload_u16(frame.data, command_at)}"
        return name

    def _note_heard(self, src: tuple[int, int]) -> None:
        self.heard[src] = time.monotonic()
        if len(self.heard) > 4 * PEER_MEMORY:  # a flood of forged sources: keep the recent
            for key, _t in sorted(self.heard.items(), key=lambda kv: kv[1])[:2 * PEER_MEMORY]:
                del self.heard[key]

    def peer_alive(self, src: tuple[int, int]) -> bool:
        """Whether `src` spoke within PEER_SILENCE_S (a download for a vanished client stops)."""
        return time.monotonic() - self.heard.get(src, 0.0) < PEER_SILENCE_S

    def _bulk_bytes_s(self) -> float:
        """Byte rate for downloads: a network's parameter, or what a radio's schedule leaves."""
        params = self.core.ctx.params
        line = self.transport.bytes_per_s
        if line is None:
            return float(params.get("MAV_BULK_KB_S")) * 1000.0
        return line * (1.0 - float(params.get("MAV_RADIO_PCT")) / 100.0) * RADIO_BULK_SHARE

    def refuse(self, msg: RxMessage, why: str) -> None:
        """Count a refused message and report it (rate-limited); it is never acted on."""
        what = msg.get_type()
        if what in ("COMMAND_LONG", "COMMAND_INT"):
            what += f" {getattr(msg, 'command', '?')}"
        self._refused((msg.get_srcSystem(), msg.get_srcComponent()), why, what)

    def _refused(self, src: tuple[int, int], why: str, what: str) -> None:
        self.counters.refused += 1
        self.refusals[why] = self.refusals.get(why, 0) + 1
        self._refused_unreported += 1
        now = time.monotonic()
        # Reported at most once per REFUSAL_REPORT_S, in the log as on the ground: a flood of
        # refused frames must not become a flood of log lines (disk, CPU) or of STATUSTEXT.
        log.debug("link %d: refused %s from %d/%d: %s", self.index, what, src[0], src[1], why)
        if now - self._last_refusal_report >= REFUSAL_REPORT_S:
            n, self._refused_unreported = self._refused_unreported, 0
            self._last_refusal_report = now
            log.warning("link %d: refused %d message(s) since the last report, the latest %s "
                        "from %d/%d: %s", self.index, n, what, src[0], src[1], why)
            self._broadcast_text(int(mavlink.MAV_SEVERITY_WARNING),
                                 f"link {self.index}: refused {n}: {why} {what}")

    def note_peer(self, system: int, component: int, mav_type: int) -> None:
        key = (system, component)
        if key not in self.peers:
            log.info("link %d: %s %d/%d heard", self.index,
                     "ground station" if mav_type == mavlink.MAV_TYPE_GCS else "peer",
                     system, component)
        self.peers[key] = Peer(system, component, mav_type, time.monotonic())
        self.peers.move_to_end(key)
        while len(self.peers) > PEER_MEMORY:
            self.peers.popitem(last=False)

    # ------------------------------------------------------------------ send thread
    def _tlog(self, frame: bytes | bytearray) -> None:
        if self.tlog is not None and self._tlog_enabled():
            self.tlog.write(self.core.now_real_ns() // 1000, frame)

    def emit(self, msgs: list[Msg]) -> None:
        """Pack and send messages (the send thread only)."""
        signing = self.mav_out.signing
        self.mav_out.srcSystem = self.core.sysid  # beside an autopilot: its, once known
        for msg in msgs:
            if signing.sign_outgoing:
                signing.timestamp = max(signing.timestamp, self._now_timestamp())
            try:
                frame = msg.pack(self.mav_out)
            except Exception as exc:  # a field out of its type's range: a bug, logged once
                self._pack_errors += 1
                if self._pack_errors in (1, 100):
                    log.error("link %d: cannot pack %s: %s", self.index, msg.get_type(), exc)
                continue
            self.mav_out.seq = (self.mav_out.seq + 1) & 0xFF
            if self.transport.send(frame):
                self.counters.tx_frames += 1
            self._tlog(frame)

    def run_item(self, item: SenderItem) -> None:
        if isinstance(item, list):
            self.emit(item)
        elif isinstance(item, bytes):
            self.send_forwarded(item)
        elif isinstance(item, tuple):  # the router's frames of one read of the autopilot
            for frame in item:
                self.send_forwarded(frame)
        else:
            item(self)

    def send_forwarded(self, frame: bytes) -> None:
        """A frame the router forwarded onto this link, as it came (the send thread only);
        on a radio, within MAV_RADIO_PCT of the line (else dropped and counted)."""
        bps = self.transport.bytes_per_s
        if bps is not None:
            rate = bps * float(self.core.ctx.params.get("MAV_RADIO_PCT")) / 100.0
            budget = self._budget
            if budget is None or budget.rate_bytes_s != rate:
                budget = self._budget = ByteBudget(rate)
            if not budget.take(len(frame)):
                self.routes.over_budget += 1
                return
        if self.transport.send(frame):
            self.counters.tx_frames += 1
        self._tlog(frame)

    def send_param(self, index: int) -> None:
        msg = self.params.value_message(index, bytewise=self.identity.bytewise)
        if msg is not None:
            self.emit([msg])

    def begin_param_list(self) -> None:
        self._param_cursor = 0

    def param_list_step(self, burst: int) -> int:
        """Send the next parameters of a list in progress; returns host ns until the next batch
        (the pause is for the client's socket buffer or the radio: real, whatever the clock)."""
        if self._param_cursor is None:
            return 1 << 62
        count = self.params.count()
        bps = self.transport.bytes_per_s
        if bps is not None:  # a radio: leave half the bandwidth to telemetry
            burst = max(1, min(burst, int(bps * 0.5 * 0.02 / 40)))
            pause_ns = 20_000_000
        else:  # a network: still in batches, so a busy client's socket buffer does not overflow
            pause_ns = PARAM_BATCH_PAUSE_NS
        end = min(count, self._param_cursor + burst)
        bytewise = self.identity.bytewise
        msgs = [m for i in range(self._param_cursor, end)
                if (m := self.params.value_message(i, bytewise=bytewise)) is not None]
        self.emit(msgs)
        self._param_cursor = end if end < count else None
        return pause_ns if self._param_cursor is not None else 1 << 62

    def _apply_interval(self, msg_id: int, interval_us: int) -> None:
        self.scheduler.set_interval(msg_id, interval_us, self.core.ctx.clock.monotonic_ns())

    def apply_initial_rates(self) -> None:
        if self._initial_rates_applied:
            return
        self._initial_rates_applied = True
        for msg_id, hz in self.endpoint.rates_hz.items():
            self._apply_interval(msg_id, -1 if hz <= 0 else int(1e6 / hz))

    def send_stream_now(self, msg_id: int) -> None:
        spec = stream_for(msg_id)
        if spec is None:
            return
        value: Any = None
        if spec.source is not None:
            value = getattr(self.core.ctx.state, spec.source).read()
            if value is None:
                return
        self.emit(spec.build(self.core, value, self))

    def next_thread_status(self) -> ThreadStatus | None:
        statuses = self.core.manager.thread_status()
        if not statuses:
            return None
        st = statuses[self._rotation % len(statuses)]
        self._rotation += 1
        return st

    def send_events(self) -> None:
        for event in self.events.drain():
            self.emit(status.statustext(event.severity, event.text(), self.text_ids))

    def check_home(self) -> None:
        """Announce HOME_POSITION when the estimator's origin appears or moves."""
        if self.core.beside_autopilot:
            return  # the autopilot's home is the vehicle's
        home = telemetry.home_of(self.core)
        if home is not None and home != self._home_origin:
            self._home_origin = home
            self.emit(telemetry.home_position(self.core))

    def drain_on_exit(self) -> None:
        """Send what is still queued (last words such as a shutdown's COMMAND_ACK)."""
        for item in self.queue.drain()[:ITEMS_PER_CYCLE]:
            try:
                self.run_item(item)
            except Exception:
                log.exception("link %d: sending a queued item at exit", self.index)
        if self.tlog is not None:
            self.tlog.flush()

    def describe(self) -> str:
        return f"link {self.index} ({self.endpoint.url})"


def _reset_parser(parser: mavlink.MAVLink) -> None:
    """Drop a pymavlink parser's partial frame (the state its constructor sets)."""
    parser.buf = bytearray()
    parser.buf_index = 0
    parser.expected_length = mavlink.HEADER_LEN_V1 + 2
    parser.have_prefix_error = False


__all__ = ["Link", "Peer"]
