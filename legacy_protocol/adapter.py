"""Aircraft side of the legacy UDP protocol: the thesis's network thread, rebuilt.

Two managed threads share one UDP socket:
- `legacy-rx` receives commands, drops what the allow-list refuses or what does not decode
  (counted, never raised), and dispatches each command type to its own bounded queue, as the
  thesis's network thread did; HORIZON_ATTITUDE goes straight to a data slot, because only the
  newest attitude matters.
- `legacy-tx` is the only sender: thread data messages at each thread's message period
  (`<THREAD>_MSG_MS`), one THREAD_STATUS per `MGR_STATUS_MS` in rotation, MANAGER_STATUS every
  `MGR_MSTAT_MS`, and the COMMAND_ACKs.
The manager consumes the parameter queues in the main thread (a tick hook), so the legacy monitor
and the MAVLink side change the very same parameters.

Both threads sleep until there is work: the receiver until a datagram comes, the sender until
its next message is due or an acknowledgement is queued. Neither polls. Every period is in the
runtime's clock (`ctx.clock`, scaled in a `--speed` simulation), and each wait is also bounded
by a quarter of the thread's own watchdog period (converted to host seconds), so the watchdog
sees several completed cycles in each of its windows at any simulation speed: a wait that is
fixed in host time would outlast a window at 20x (a 2000 ms window is 100 ms of host time).

The messages built from the runtime's state are in `telemetry`, the wire format in `messages`
and `codec`; this module owns the socket, the two threads and the commands they apply.
"""

from __future__ import annotations

import errno
import ipaddress
import logging
import math
import socket
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from companion.core.config import ConfigError
from companion.core.params import ParamError, ParamSpec
from companion.core.state import HorizonMeasurement
from companion.core.sync import MessageQueue
from companion.watchdog import ManagedThread, ManagerCommand, RuntimeContext, Task, ThreadManager
from legacy_protocol import codec, messages
from legacy_protocol.messages import AckResult, MsgType
from legacy_protocol.telemetry import DATA_MESSAGES, thread_status

log = logging.getLogger(__name__)

MAX_DATAGRAM = 2048


def parse_hostport(text: str, default_port: int) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep:
        return text, default_port
    try:
        return host or "0.0.0.0", int(port)
    except ValueError:
        raise ValueError(f"expected HOST:PORT, got {text!r}") from None


_BIND_PATIENCE_S = 1.0
"""How long a busy command port is retried before giving up (see `_bind_patiently`)."""

WAIT_CAP_S = 0.5
"""Host seconds: the longest either thread waits, whatever its watchdog period; bounds how long
a previous runtime's receiver may keep the port (below `_BIND_PATIENCE_S`)."""
BEATS_PER_WINDOW = 4
"""A thread's wait is at most its watchdog period over this: several completed cycles fall in
each watchdog window, so a late wake-up or a slow cycle does not read as a stall."""


def bounded_wait_s(ctx: RuntimeContext, watchdog_ms: int, wait_s: float | None = None) -> float:
    """Host seconds to wait for work due in `wait_s` clock seconds (None: no deadline), bounded
    so a thread with watchdog period `watchdog_ms` (clock ms) completes several cycles per
    window at any clock scale, and by `WAIT_CAP_S` of host time."""
    bound_s = watchdog_ms / 1000.0 / BEATS_PER_WINDOW
    if wait_s is not None:
        bound_s = min(bound_s, max(0.0, wait_s))
    return min(WAIT_CAP_S, ctx.clock.to_host_s(bound_s))


def _bind_patiently(sock: socket.socket, addr: tuple[str, int]) -> None:
    """Bind, retrying for up to `_BIND_PATIENCE_S` while the port is in use.

    After a reboot the previous runtime's receive thread may still be inside `recvfrom` on the
    closed socket (its wait, at most `WAIT_CAP_S`, has not run out), and the kernel keeps the
    port bound until that call returns. A second runtime holding the port for good still fails, a second later."""
    deadline = time.monotonic() + _BIND_PATIENCE_S
    while True:
        try:
            sock.bind(addr)
            return
        except OSError as exc:
            if exc.errno != errno.EADDRINUSE or time.monotonic() >= deadline:
                raise
            time.sleep(0.02)


@dataclass
class LegacyCounters:
    received: int = 0
    accepted: int = 0
    refused_source: int = 0  # not in the allow-list: dropped
    malformed: int = 0
    unexpected_type: int = 0  # a message type where a command was expected
    other_vehicle: int = 0  # addressed to another aircraft on the same network: dropped
    queue_full: int = 0  # answered "rejected": the command was not applied
    sent: int = 0
    send_errors: int = 0


@dataclass(frozen=True)
class PendingCommand:
    payload: Any
    seq: int
    addr: tuple[str, int]


RX_TASK = Task("legacy-rx", paced_by="datagrams (waits a quarter of its watchdog period)",
               watchdog_ms=2000,
               message_ms=1000, param_prefix="LEGRX", switchable=False,
               implementation="legacy_protocol.adapter:_Rx")
TX_TASK = Task("legacy-tx", paced_by="its next due message and queued acknowledgements",
               budget_ms=5.0, watchdog_ms=1000, message_ms=1000,
               param_prefix="LEGTX", switchable=False,
               implementation="legacy_protocol.adapter:_Tx")
"""The legacy protocol's two rows; the manager hands out their ids."""


class _Rx(ManagedThread):
    def __init__(self, adapter: LegacyAdapter) -> None:
        super().__init__(RX_TASK)
        self.adapter = adapter

    def interrupt_io(self) -> None:
        self.adapter.wake_socket()

    def step(self) -> bool:
        self.adapter.receive_once(timeout_s=bounded_wait_s(self.ctx, self.watchdog_ms))
        return True  # not periodic in nature: alive as long as it loops


class _Tx(ManagedThread):
    """Sleeps until the next message is due or an acknowledgement is queued (no poll)."""

    def __init__(self, adapter: LegacyAdapter) -> None:
        super().__init__(TX_TASK)
        self.adapter = adapter
        self._wait_host_s = 0.0

    def interrupt_io(self) -> None:
        self.adapter.acks.put(None)  # wakes the wait at once

    def prologue(self) -> bool:
        self._wait_host_s = 0.0
        return True

    def step(self) -> bool:
        adapter = self.adapter
        item = adapter.acks.get(self._wait_host_s)
        if item is not None:
            adapter.send_ack(item)
        wait_ns = adapter.send_due()
        self._wait_host_s = bounded_wait_s(self.ctx, self.watchdog_ms, wait_ns / 1e9)
        return True


def declared_params() -> list[ParamSpec]:
    """The adapter's parameters (its two threads'), without building it (docs)."""
    return RX_TASK.param_specs() + TX_TASK.param_specs()


class LegacyAdapter:
    """Owns the socket and the two threads; registers them with the manager."""

    def __init__(
        self,
        ctx: RuntimeContext,
        manager: ThreadManager,
        *,
        dest: str = "255.255.255.255:5501",
        listen_port: int = 5500,
        allow: Iterable[str] = ("127.0.0.0/8",),
        bind_host: str = "0.0.0.0",
        listen: bool = True,
    ) -> None:
        self.ctx = ctx
        self.manager = manager
        self.dest = parse_hostport(dest, messages.DEFAULT_MONITOR_PORT)
        self.allow = [ipaddress.ip_network(a, strict=False) for a in allow]
        self.counters = LegacyCounters()
        self.queues: dict[int, MessageQueue[PendingCommand]] = {
            int(t): MessageQueue(64)
            for t in (
                MsgType.SET_THREAD_PARAMS,
                MsgType.SET_MANAGER_PARAMS,
                MsgType.STOP,
                MsgType.RESTART_THREAD,
            )
        }
        # None: no acknowledgement, only a wake-up of the sender (see `_Tx.interrupt_io`)
        self.acks: MessageQueue[tuple[messages.CommandAck, tuple[str, int]] | None] = (
            MessageQueue(256))
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        if listen:  # False: only build (parameter listing), never take the port
            # No SO_REUSEADDR: a second runtime on the same command port must fail here, loudly,
            # rather than silently share the port and receive half of the commands.
            try:
                _bind_patiently(self.sock, (bind_host, listen_port))
            except OSError as exc:
                self.sock.close()
                raise ConfigError(
                    f"legacy.listen: cannot listen on {bind_host}:{listen_port}: {exc.strerror} "
                    "(is another runtime using this port?)"
                ) from None
        self.listen_addr = self.sock.getsockname()
        self._rx_timeout_s = WAIT_CAP_S
        self.sock.settimeout(self._rx_timeout_s)
        self._seq = 0
        self._next_due_ns: dict[str, int] = {}
        self._soonest_ns = 0
        self._status_index = 0
        self.rx = _Rx(self)
        self.tx = _Tx(self)
        manager.add(self.rx)
        manager.add(self.tx)
        manager.on_tick.append(self.process_commands)

    # ------------------------------------------------------------------ receive side
    def wake_socket(self) -> None:
        """Unblock a recvfrom (used when the rx thread must stop): send ourselves a byte."""
        try:
            host, port = self.listen_addr
            target = "127.0.0.1" if host == "0.0.0.0" else host
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                s.sendto(b"\x00", (target, port))
        except OSError:
            pass

    def _allowed(self, host: str) -> bool:
        try:
            ip = ipaddress.ip_address(host)
        except ValueError:
            return False
        return any(ip in net for net in self.allow)

    def receive_once(self, timeout_s: float) -> None:
        """Handle one datagram, or return after `timeout_s` host seconds without one."""
        if timeout_s != self._rx_timeout_s:  # the watchdog period changed (or the first call)
            self._rx_timeout_s = timeout_s
            self.sock.settimeout(timeout_s)
        try:
            data, addr = self.sock.recvfrom(MAX_DATAGRAM)
        except (TimeoutError, BlockingIOError):
            return
        except OSError:
            self.rx.stop_event.wait(timeout_s)  # socket closed during shutdown
            return
        if self.rx.stop_requested:
            return  # the wake-up datagram sent to unblock this read
        self.handle_datagram(data, addr)

    def handle_datagram(self, data: bytes, addr: tuple[str, int]) -> None:
        c = self.counters
        c.received += 1
        if not self._allowed(addr[0]):
            c.refused_source += 1
            return
        result = codec.decode(data)
        if isinstance(result, codec.DecodeError):
            c.malformed += 1
            return
        if result.header.vehicle_id != self.ctx.vehicle_id:
            # Several aircraft may share one network and one monitor: a command for another
            # aircraft is not ours to execute, nor to answer (its addressee answers it).
            c.other_vehicle += 1
            return
        t = result.header.type_code
        pending = PendingCommand(result.payload, result.header.seq, addr)
        if isinstance(result.payload, messages.HorizonAttitude):
            p = result.payload
            if not all(math.isfinite(v) for v in (p.roll_rad, p.pitch_rad, p.quality)):
                self._ack(pending, AckResult.BAD_VALUE)
                return
            self.ctx.state.horizon.write(
                HorizonMeasurement(
                    p.frame_t_ns, p.roll_rad, p.pitch_rad, max(0.0, min(1.0, p.quality)), "legacy"
                )
            )
            c.accepted += 1
            self._ack(pending, AckResult.ACCEPTED)
            return
        queue = self.queues.get(t)
        if queue is None:
            c.unexpected_type += 1
            return
        if not queue.put(pending):
            c.queue_full += 1
            self._ack(pending, AckResult.BAD_VALUE)  # every command is answered, even this one
            return
        c.accepted += 1
        self.manager.wake()

    def _ack(self, cmd: PendingCommand, result: AckResult) -> None:
        ack = messages.CommandAck(
            command_type=int(cmd.payload.TYPE), result=int(result), command_seq=cmd.seq
        )
        self.acks.put((ack, cmd.addr))

    # ------------------------------------------------------------------ main-thread consumer
    def process_commands(self) -> None:
        """Manager tick hook: apply queued commands in the main thread, one ACK each."""
        for queue in self.queues.values():
            while (cmd := queue.get_nowait()) is not None:
                try:
                    self._apply(cmd)
                except Exception:  # a command must never take the manager down
                    log.exception("legacy command failed")
                    self._ack(cmd, AckResult.BAD_VALUE)

    def _apply(self, cmd: PendingCommand) -> None:
        p = cmd.payload
        if isinstance(p, messages.SetThreadParams):
            t = self.manager.find(p.thread_id)
            if t is None:
                self._ack(cmd, AckResult.UNKNOWN_THREAD)
                return
            changes = {}
            if p.watchdog_period_ms != messages.UNCHANGED:
                changes[f"{t.param_prefix}_WDG_MS"] = p.watchdog_period_ms
            if p.message_period_ms != messages.UNCHANGED:
                changes[f"{t.param_prefix}_MSG_MS"] = p.message_period_ms
            self._set_all(cmd, changes)
        elif isinstance(p, messages.SetManagerParams):
            changes = {}
            if p.execution_time_s != messages.UNCHANGED:
                changes["MGR_EXEC_TIME_S"] = p.execution_time_s
            if p.status_period_ms != messages.UNCHANGED:
                changes["MGR_STATUS_MS"] = p.status_period_ms
            if p.granularity_ms != messages.UNCHANGED:
                changes["MGR_WDG_GRAN_MS"] = p.granularity_ms
            self._set_all(cmd, changes)
        elif isinstance(p, messages.Stop):
            self._ack(cmd, AckResult.ACCEPTED)
            self.send_due(force_acks_only=True)
            self.manager.post(ManagerCommand("stop", reason=p.reason))
        elif isinstance(p, messages.RestartThread):
            if self.manager.find(p.thread_id) is None:
                self._ack(cmd, AckResult.UNKNOWN_THREAD)
                return
            self.manager.post(
                ManagerCommand(
                    "restart_thread",
                    p.thread_id,
                    reply=lambda ok, _r: self._ack(
                        cmd, AckResult.ACCEPTED if ok else AckResult.BAD_VALUE
                    ),
                )
            )

    def _set_all(self, cmd: PendingCommand, changes: dict[str, int]) -> None:
        """All or nothing, through the registry's one path (its rules between parameters
        included), so a refused command changes nothing. A zero period or granularity is below
        its parameter's range; an execution time of 0 (unlimited) is inside its range."""
        try:
            self.ctx.params.set_many(changes)
        except ParamError as exc:
            log.info("legacy command refused: %s", exc)
            self._ack(cmd, AckResult.BAD_VALUE)
            return
        self._ack(cmd, AckResult.ACCEPTED)

    # ------------------------------------------------------------------ send side
    def _send(self, payload: Any, addr: tuple[str, int] | None = None) -> None:
        self._seq = (self._seq + 1) & 0xFFFFFFFF
        try:
            datagram = codec.encode(
                payload,
                vehicle_id=self.ctx.vehicle_id,
                seq=self._seq,
                t_ns=self.ctx.clock.realtime_ns(),
            )
            self.sock.sendto(datagram, addr or self.dest)
            self.counters.sent += 1
        except (OSError, ValueError) as exc:
            self.counters.send_errors += 1
            if self.counters.send_errors in (1, 100) or self.counters.send_errors % 10000 == 0:
                log.warning("legacy: cannot send %s: %s", type(payload).__name__, exc)

    def _due(self, key: str, period_ms: int, now_ns: int) -> bool:
        due = self._next_due_ns.get(key, 0)
        if now_ns < due:
            self._soonest_ns = min(self._soonest_ns, due)
            return False
        due = self._next_due_ns[key] = now_ns + period_ms * 1_000_000
        self._soonest_ns = min(self._soonest_ns, due)
        return True

    def send_ack(self, item: tuple[messages.CommandAck, tuple[str, int]] | None) -> None:
        if item is not None:
            self._send(item[0], item[1])

    def send_due(self, *, force_acks_only: bool = False) -> int:
        """Send the queued acknowledgements and the messages that are due; returns the clock
        ns until the next message falls due (what the sender may sleep)."""
        for item in self.acks.drain():
            self.send_ack(item)
        if force_acks_only:
            return 0
        now = self.ctx.clock.monotonic_ns()
        self._soonest_ns = now + 3600 * 10**9  # nothing due: the caller's bound applies
        params = self.ctx.params
        threads = self.manager.threads
        if threads and self._due("thread_status", int(params.get("MGR_STATUS_MS")), now):
            self._status_index %= len(threads)
            self._send(thread_status(threads[self._status_index]))
            self._status_index += 1
        if self._due("manager_status", int(params.get("MGR_MSTAT_MS")), now):
            st = self.manager.status()
            self._send(
                messages.ManagerStatus(
                    st.elapsed_ms,
                    st.exec_time_s,
                    st.status_ms,
                    st.granularity_ms,
                    min(st.n_threads, 255),
                )
            )
        for t in threads:
            builder = DATA_MESSAGES.get(t.name)
            if builder is None or not t.enabled:
                continue
            if self._due(t.name, t.message_ms, now):
                msg = builder(self.ctx, t)
                if msg is not None:
                    self._send(msg)
        return self._soonest_ns - now

    def stats(self) -> list[dict[str, Any]]:
        """Per-link figures, one entry (the same shape as the MAVLink bridge's list)."""
        return [{"link": f"legacy udp {self.listen_addr[0]}:{self.listen_addr[1]} -> "
                         f"{self.dest[0]}:{self.dest[1]}", **vars(self.counters)}]

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass
