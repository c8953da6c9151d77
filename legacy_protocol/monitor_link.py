"""Network side of the ground monitor: receive, track per-vehicle state, send commands.

Nothing here blocks unless asked to (``wait``/``request`` take bounded timeouts) and nothing starts
a thread: the caller, a TUI timer or a JSON loop, drains the sockets with ``poll()``.  That keeps
the state model single-threaded, so the UI can read it without locks.

Two sockets are used on purpose.  Messages arrive on the listen port (5501 by default), which is
opened with SO_REUSEADDR/SO_REUSEPORT so several monitors on one host can share it.  Linux hands a
*broadcast* datagram to every socket sharing the port but a *unicast* one to only one of them, so
an aircraft that unicasts to 127.0.0.1:5501 reaches only one of two local monitors; broadcast to
the network's broadcast address to feed them all.  Commands leave from a second, ephemeral socket
so that their ACKs (which the aircraft returns to the sender's address and port) always come back
to the monitor that sent them, never to a sibling sharing port 5501.
"""

from __future__ import annotations

import collections
import logging
import re
import select
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

from legacy_protocol.codec import Decoded, DecodeError, decode, encode
from legacy_protocol.messages import (
    COMMAND_TYPES,
    DEFAULT_COMMAND_PORT,
    DEFAULT_MONITOR_PORT,
    AckResult,
    Command,
    CommandAck,
    Control,
    Estimator,
    Gps,
    Imu,
    ManagerStatus,
    Message,
    MsgType,
    Servo,
    ThreadStatus,
)

__all__ = [
    "DEFAULT_HISTORY_LEN",
    "CommandOutcome",
    "CommandSender",
    "Fleet",
    "LinkError",
    "MonitorLink",
    "Received",
    "VehicleKey",
    "VehicleState",
    "open_listen_socket",
]

log = logging.getLogger(__name__)

DEFAULT_HISTORY_LEN = 120
"""Samples kept per data message type for sparklines (two minutes at the default 1 Hz)."""

_RECV_BUFFER_BYTES = 65536  # larger than any UDP payload, so nothing is silently truncated
_MAX_SEQ_GAP = 1000  # larger jumps mean the sender restarted, not that datagrams were lost

VehicleKey = tuple[int, str, int]
"""(vehicle id, source host, source port): one aircraft as the monitor hears it."""

M = TypeVar("M", ThreadStatus, ManagerStatus, CommandAck, Imu, Gps, Servo, Estimator, Control)


class LinkError(Exception):
    """A socket could not be opened or used; the message names the address."""


MAX_TALLY_KEYS = 64
_NUMBER = re.compile(r"0x[0-9A-Fa-f]+|\d+(\.\d+)?(e[+-]?\d+)?")


def _category(reason: str) -> str:
    """A decode error's reason without its values (hex type codes kept: at most 256 of them)."""
    return _NUMBER.sub(lambda m: m[0] if m[0].startswith("0x") else "N", reason.split(":")[0])[:80]


def _count_bounded(counter: collections.Counter[Any], key: Any, overflow: Any) -> None:
    if key in counter or len(counter) < MAX_TALLY_KEYS - 1:
        counter[key] += 1
    else:
        counter[overflow] += 1


@dataclass(frozen=True)
class Received:
    """One datagram as it came off the listen socket, decoded or not."""

    source: tuple[str, int]
    rx_monotonic_s: float
    rx_wall_s: float
    size: int
    result: Decoded | DecodeError


@dataclass
class VehicleState:
    """Everything the monitor knows about one aircraft, updated as datagrams arrive."""

    vehicle_id: int
    source: tuple[str, int]
    history_len: int
    first_heard_s: float
    last_heard_s: float
    threads: dict[int, ThreadStatus] = field(default_factory=dict)
    thread_heard_s: dict[int, float] = field(default_factory=dict)
    manager: ManagerStatus | None = None
    last_ack: CommandAck | None = None
    datagrams: int = 0
    malformed: int = 0
    by_type: collections.Counter[str] = field(default_factory=collections.Counter)
    lost: int = 0
    last_seq: int | None = None
    _latest: dict[type, Message] = field(default_factory=dict, repr=False)
    _history: dict[type, collections.deque[tuple[float, Message]]] = field(
        default_factory=dict, repr=False
    )

    @property
    def key(self) -> VehicleKey:
        return (self.vehicle_id, self.source[0], self.source[1])

    def silence_s(self, now_s: float) -> float:
        """Seconds since anything was heard from this aircraft (monotonic clock)."""
        return max(0.0, now_s - self.last_heard_s)

    def latest(self, cls: type[M]) -> M | None:
        """Most recent message of one type, or None before the first arrives."""
        msg = self._latest.get(cls)
        return msg if isinstance(msg, cls) else None

    def history(self, cls: type[M]) -> list[tuple[float, M]]:
        """(monotonic receive time, message) pairs, oldest first, at most ``history_len``."""
        return [(t, m) for t, m in self._history.get(cls, ()) if isinstance(m, cls)]

    def series(self, cls: type[M], attr: str) -> list[float]:
        """One numeric field over the history, ready for a sparkline."""
        return [float(getattr(m, attr)) for _, m in self.history(cls)]

    def apply(self, decoded: Decoded, now_s: float) -> None:
        """Fold one decoded message into the state."""
        self.last_heard_s = now_s
        self.datagrams += 1
        self.by_type[decoded.name] += 1
        seq = decoded.header.seq
        if self.last_seq is not None:
            gap = (seq - self.last_seq - 1) % 2**32
            if 0 < gap <= _MAX_SEQ_GAP:
                self.lost += gap
        self.last_seq = seq
        msg = decoded.payload
        if isinstance(msg, ThreadStatus):
            self.threads[msg.thread_id] = msg
            self.thread_heard_s[msg.thread_id] = now_s
        elif isinstance(msg, ManagerStatus):
            self.manager = msg
        elif isinstance(msg, CommandAck):
            self.last_ack = msg
        elif isinstance(msg, (Imu, Gps, Servo, Estimator, Control)):
            self._latest[type(msg)] = msg
            hist = self._history.get(type(msg))
            if hist is None:
                hist = self._history[type(msg)] = collections.deque(maxlen=self.history_len)
            hist.append((now_s, msg))


@dataclass
class Fleet:
    """All aircraft heard on the listen port plus counters of what could not be used."""

    history_len: int = DEFAULT_HISTORY_LEN
    vehicles: dict[VehicleKey, VehicleState] = field(default_factory=dict)
    received: int = 0
    malformed: int = 0
    malformed_reasons: collections.Counter[str] = field(default_factory=collections.Counter)
    malformed_by_source: collections.Counter[tuple[str, int]] = field(
        default_factory=collections.Counter
    )
    last_error: tuple[tuple[str, int], DecodeError] | None = None
    unexpected_commands: int = 0

    def apply(self, rx: Received) -> VehicleState | None:
        """Update the model with one datagram; returns the vehicle it belonged to, if any."""
        self.received += 1
        result = rx.result
        if isinstance(result, DecodeError):
            self.malformed += 1
            # a category, not the hostile value itself: numbers become N, and both tables stay
            # bounded whatever a sender (or a spoofed source address) puts in its datagrams
            reason = _category(result.reason)
            _count_bounded(self.malformed_reasons, reason, "other")
            _count_bounded(self.malformed_by_source, rx.source, ("other", 0))
            self.last_error = (rx.source, result)
            # The header cannot be trusted, so charge it to whichever aircraft uses that address.
            for suspect in self.vehicles.values():
                if suspect.source == rx.source:
                    suspect.malformed += 1
            return None
        if result.header.type_code in COMMAND_TYPES:
            # Another ground station's command reached our port: not ours to interpret.
            self.unexpected_commands += 1
            return None
        key: VehicleKey = (result.header.vehicle_id, rx.source[0], rx.source[1])
        state = self.vehicles.get(key)
        if state is None:
            state = VehicleState(
                vehicle_id=key[0],
                source=rx.source,
                history_len=self.history_len,
                first_heard_s=rx.rx_monotonic_s,
                last_heard_s=rx.rx_monotonic_s,
            )
            self.vehicles[key] = state
            log.info("heard vehicle %d from %s:%d", key[0], key[1], key[2])
        state.apply(result, rx.rx_monotonic_s)
        return state

    def ordered(self) -> list[VehicleState]:
        """Vehicles by id then address, so a selector lists them in a stable order."""
        return [self.vehicles[k] for k in sorted(self.vehicles)]


def open_listen_socket(port: int, host: str = "0.0.0.0") -> socket.socket:
    """A non-blocking UDP socket bound so several monitors on one host can share ``port``."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if hasattr(socket, "SO_REUSEPORT"):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise LinkError(f"cannot listen on UDP {host}:{port}: {exc.strerror or exc}") from None
    sock.setblocking(False)
    return sock


class MonitorLink:
    """Listen socket plus the fleet model it feeds."""

    def __init__(
        self,
        port: int = DEFAULT_MONITOR_PORT,
        *,
        host: str = "0.0.0.0",
        history_len: int = DEFAULT_HISTORY_LEN,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self._sock = open_listen_socket(port, host)
        self._buf = bytearray(_RECV_BUFFER_BYTES)
        self._clock = clock
        self._wall_clock = wall_clock
        self.fleet = Fleet(history_len=history_len)

    @property
    def address(self) -> tuple[str, int]:
        """Bound (host, port); the port is the real one when 0 was asked for."""
        host, port = self._sock.getsockname()[:2]
        return str(host), int(port)

    def fileno(self) -> int:
        return self._sock.fileno()

    def now(self) -> float:
        """The link's monotonic clock, the time base of every ``*_s`` stamp in the fleet."""
        return self._clock()

    def wait(self, timeout_s: float) -> bool:
        """Block until a datagram is ready or ``timeout_s`` passes; True if one is ready."""
        ready, _, _ = select.select([self._sock], [], [], max(0.0, timeout_s))
        return bool(ready)

    def poll(self, max_datagrams: int = 1000) -> list[Received]:
        """Drain what is queued (at most ``max_datagrams``, so a flood cannot starve the UI)."""
        out: list[Received] = []
        for _ in range(max_datagrams):
            try:
                n, source = self._sock.recvfrom_into(self._buf)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:  # e.g. a transient ICMP error reported on the socket
                log.warning("receive on %s failed: %s", self.address, exc)
                break
            rx = Received(
                source=(str(source[0]), int(source[1])),
                rx_monotonic_s=self._clock(),
                rx_wall_s=self._wall_clock(),
                size=n,
                result=decode(memoryview(self._buf)[:n]),
            )
            if isinstance(rx.result, DecodeError):
                log.debug("malformed datagram from %s:%d: %s", *rx.source, rx.result)
            self.fleet.apply(rx)
            out.append(rx)
        return out

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> MonitorLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_RESULT_TEXT = {
    AckResult.ACCEPTED: "accepted",
    AckResult.BAD_VALUE: "rejected: bad value",
    AckResult.UNKNOWN_THREAD: "rejected: unknown thread",
    AckResult.NOT_ALLOWED: "rejected: not allowed",
}


@dataclass(frozen=True)
class CommandOutcome:
    """What became of one command: its ACK, or None if none came within the timeout."""

    seq: int
    command: Command
    vehicle_id: int
    ack: CommandAck | None
    elapsed_s: float

    @property
    def accepted(self) -> bool:
        return self.ack is not None and self.ack.result == AckResult.ACCEPTED

    @property
    def text(self) -> str:
        """Short human summary for a status line."""
        name = MsgType(self.command.TYPE).name
        if self.ack is None:
            return f"{name} #{self.seq}: no ACK after {self.elapsed_s:.1f} s"
        try:
            result = _RESULT_TEXT[AckResult(self.ack.result)]
        except ValueError:
            result = f"result {self.ack.result} (unknown)"
        return f"{name} #{self.seq}: {result} ({self.elapsed_s * 1000:.0f} ms)"


@dataclass
class _Pending:
    command: Command
    vehicle_id: int
    sent_s: float
    timeout_s: float


class CommandSender:
    """Sends commands to one aircraft address and pairs each with its COMMAND_ACK.

    Commands are not retried: a lost command surfaces as a timeout and the operator decides
    whether to send it again, which matters for commands such as STOP.
    """

    def __init__(
        self,
        target: tuple[str, int] = ("127.0.0.1", DEFAULT_COMMAND_PORT),
        *,
        timeout_s: float = 1.0,
        bind_host: str = "0.0.0.0",
        first_seq: int = 1,
        clock: Callable[[], float] = time.monotonic,
        wall_clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.target = target
        self.timeout_s = timeout_s
        self._clock = clock
        self._wall_clock_ns = wall_clock_ns
        self._seq = first_seq % 2**32
        self._pending: dict[int, _Pending] = {}
        self._resolved: dict[int, CommandOutcome] = {}
        self._buf = bytearray(_RECV_BUFFER_BYTES)
        self.unmatched_acks = 0
        self.malformed = 0
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
            sock.bind((bind_host, 0))
        except OSError as exc:
            sock.close()
            raise LinkError(f"cannot open command socket on {bind_host}: {exc}") from None
        sock.setblocking(False)
        self._sock = sock

    @property
    def address(self) -> tuple[str, int]:
        """Local (host, port) commands leave from and ACKs return to."""
        host, port = self._sock.getsockname()[:2]
        return str(host), int(port)

    @property
    def pending(self) -> int:
        return len(self._pending)

    def fileno(self) -> int:
        return self._sock.fileno()

    def send(self, command: Command, *, vehicle_id: int, timeout_s: float | None = None) -> int:
        """Send one command now; returns its sequence number for matching the ACK.

        The command is reported by ``poll()`` once its ACK arrives or ``timeout_s`` (default: the
        sender's ``timeout_s``) passes without one.
        """
        seq = self._seq
        self._seq = (self._seq + 1) % 2**32
        datagram = encode(command, vehicle_id=vehicle_id, seq=seq, t_ns=self._wall_clock_ns())
        try:
            self._sock.sendto(datagram, self.target)
        except OSError as exc:
            raise LinkError(
                f"cannot send {MsgType(command.TYPE).name} to {self.target[0]}:{self.target[1]}:"
                f" {exc.strerror or exc}"
            ) from None
        limit_s = self.timeout_s if timeout_s is None else timeout_s
        self._pending[seq] = _Pending(command, vehicle_id, self._clock(), limit_s)
        log.info("sent %s #%d to vehicle %d", MsgType(command.TYPE).name, seq, vehicle_id)
        return seq

    def poll(self) -> list[CommandOutcome]:
        """Read waiting ACKs and expire old commands; returns every command settled since."""
        self._pump()
        done = sorted(self._resolved.values(), key=lambda o: o.seq)
        self._resolved.clear()
        return done

    def request(
        self, command: Command, *, vehicle_id: int, timeout_s: float | None = None
    ) -> CommandOutcome:
        """Send and wait (bounded) for this command's ACK; other settled commands stay queued."""
        seq = self.send(command, vehicle_id=vehicle_id, timeout_s=timeout_s)
        while True:
            self._pump()
            outcome = self._resolved.pop(seq, None)
            if outcome is not None:
                return outcome
            pending = self._pending[seq]
            left_s = pending.sent_s + pending.timeout_s - self._clock()
            select.select([self._sock], [], [], max(left_s, 0.0))

    def _pump(self) -> None:
        while True:
            try:
                n, source = self._sock.recvfrom_into(self._buf)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                log.warning("command socket receive failed: %s", exc)
                break
            self._take(decode(memoryview(self._buf)[:n]), (str(source[0]), int(source[1])))
        now = self._clock()
        for seq, p in list(self._pending.items()):
            if now - p.sent_s >= p.timeout_s:
                del self._pending[seq]
                self._resolved[seq] = CommandOutcome(
                    seq, p.command, p.vehicle_id, None, now - p.sent_s
                )

    def _take(self, result: Decoded | DecodeError, source: tuple[str, int]) -> None:
        if isinstance(result, DecodeError):
            self.malformed += 1
            log.debug("malformed datagram on command socket from %s: %s", source, result)
            return
        ack = result.payload
        if not isinstance(ack, CommandAck):
            self.unmatched_acks += 1
            return
        pending = self._pending.get(ack.command_seq)
        if pending is None or pending.command.TYPE != ack.command_type:
            self.unmatched_acks += 1
            log.debug("ACK for unknown command #%d from %s", ack.command_seq, source)
            return
        del self._pending[ack.command_seq]
        elapsed = self._clock() - pending.sent_s
        self._resolved[ack.command_seq] = CommandOutcome(
            ack.command_seq, pending.command, pending.vehicle_id, ack, elapsed
        )

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> CommandSender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
