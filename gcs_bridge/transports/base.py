"""Byte transports for MAVLink links, and the table that picks one for an endpoint.

Transports take pymavlink's connection-string syntax but are written for this bridge's
threading, which pymavlink's `mavutil` files were not: one thread receives while another sends,
a blocked receive can be woken at once (`wake`), a TCP server serves several ground stations and
notices one that leaves, a UDP server forgets peers that went quiet, and nothing is printed.
Transports never raise on I/O after `open`: they count the error, reconnect where that makes
sense, and carry on, because a ground station that goes away must not take the link down.

Sockets and ports that die are not closed by the receiving thread while the sending thread may
still hold them (the descriptor could be reused by the next `open` anywhere in the process):
they are shut down, and closed later by the sender or at `close`.

One module per kind (`udp`, `tcp`, `serial_port` in this package), imported lazily.
"""

from __future__ import annotations

import abc
import logging
import select
import socket
import threading
from collections.abc import Hashable
from dataclasses import dataclass
from typing import Any

from companion.core.lazy import load
from gcs_bridge.transports.endpoints import Endpoint

log = logging.getLogger(__name__)

UDP_PEER_TIMEOUT_S = 10.0  # a UDP ground station silent this long is no longer sent to
MAX_PEERS = 16  # UDP peers and TCP clients per link: bounds memory whatever arrives
RECV_BATCH = 64  # datagrams read per wake-up
RECONNECT_MIN_S = 0.2
RECONNECT_MAX_S = 5.0
TCP_SEND_TIMEOUT_S = 0.2  # a TCP client that cannot take data this long is dropped
SERIAL_WRITE_TIMEOUT_S = 0.5

Chunk = tuple[Hashable, bytes]


class TransportError(OSError):
    """A link that cannot be opened; the message names the endpoint and the reason."""


@dataclass
class TransportCounters:
    bytes_in: int = 0
    bytes_out: int = 0
    send_errors: int = 0
    send_dropped: int = 0  # nobody to send to, or the peer could not keep up
    reconnects: int = 0
    peers_seen: int = 0
    peers_refused: int = 0


class _Graveyard:
    """Sockets/ports retired by the receive thread, closed by the sender or at shutdown."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._items: list[Any] = []

    def bury(self, item: Any) -> None:
        with self._lock:
            self._items.append(item)
            overflow = self._items[:-64] if len(self._items) > 64 else []
            if overflow:
                self._items = self._items[-64:]
        for old in overflow:
            quiet_close(old)

    def close_all(self) -> None:
        with self._lock:
            items, self._items = self._items, []
        for item in items:
            quiet_close(item)


def quiet_close(item: Any) -> None:
    try:
        item.close()
    except Exception:  # closing a dead socket/port: nothing more can be done about it
        pass


class Transport(abc.ABC):
    """One link's bytes. `recv` runs in the receive thread, `send` in the sender thread."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint
        self.counters = TransportCounters()
        self._graveyard = _Graveyard()
        self._closed = True

    @property
    def bytes_per_s(self) -> float | None:
        """Link capacity when it is known to be small (serial radios), else None."""
        return None

    @abc.abstractmethod
    def open(self) -> None:
        """Acquire the socket/port; raises TransportError only for a configuration that can
        never work (bad address, port in use)."""

    @abc.abstractmethod
    def close(self) -> None: ...

    @abc.abstractmethod
    def recv(self, timeout_s: float) -> list[Chunk]:
        """Wait up to timeout_s for data; returns (peer, bytes) chunks, empty on timeout."""

    @abc.abstractmethod
    def send(self, data: bytes) -> bool:
        """Send to every current peer; False when nothing could be sent."""

    @abc.abstractmethod
    def wake(self) -> None:
        """Make a blocked recv return now (from another thread)."""

    @property
    def peer_count(self) -> int:
        return 1

    def accept_peer(self, peer: Hashable, trusted: bool) -> None:
        """The link accepted a frame from `peer` (`trusted`: its signature verified). A
        transport that answers whoever talks to it (udpin) sends to peers it was told of here,
        never to a source whose bytes were garbage or refused. Any thread."""
        return  # a serial port or a TCP connection has its one peer already



# ------------------------------------------------------------------------------------ sockets
class SocketTransport(Transport):
    def __init__(self, endpoint: Endpoint) -> None:
        super().__init__(endpoint)
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None

    def _open_wake(self) -> None:
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)

    def _close_wake(self) -> None:
        for s in (self._wake_r, self._wake_w):
            if s is not None:
                quiet_close(s)
        self._wake_r = self._wake_w = None

    def wake(self) -> None:
        w = self._wake_w
        if w is not None:
            try:
                w.send(b"\0")
            except OSError:  # full (already woken) or closed: either way recv will return
                pass

    def _select(self, socks: list[socket.socket], timeout_s: float) -> list[socket.socket]:
        wake_r = self._wake_r
        if wake_r is None:
            return []
        try:
            readable, _, _ = select.select([wake_r, *socks], [], [], max(0.0, timeout_s))
        except (OSError, ValueError):  # a socket closed under us: the caller re-checks
            return []
        if wake_r in readable:
            try:
                while wake_r.recv(64):
                    pass
            except OSError:
                pass
        return [s for s in readable if s is not wake_r]

    def _resolve(self, host: str, port: int) -> tuple[str, int]:
        try:
            infos = socket.getaddrinfo(host, port, socket.AF_INET)
        except socket.gaierror as exc:
            raise TransportError(f"{self.endpoint.url}: cannot resolve {host!r}: {exc}") from None
        addr = infos[0][4]
        return str(addr[0]), int(addr[1])



#: endpoint kind -> (module, class), imported on first use
TRANSPORTS: dict[str, tuple[str, str]] = {
    "udpin": ("gcs_bridge.transports.udp", "UdpTransport"),
    "udpout": ("gcs_bridge.transports.udp", "UdpTransport"),
    "udpbcast": ("gcs_bridge.transports.udp", "UdpTransport"),
    "tcpin": ("gcs_bridge.transports.tcp", "TcpServerTransport"),
    "tcp": ("gcs_bridge.transports.tcp", "TcpClientTransport"),
    "serial": ("gcs_bridge.transports.serial_port", "SerialTransport"),
}


def make_transport(endpoint: Endpoint) -> Transport:
    """The transport for an endpoint's kind (one table row per kind)."""
    try:
        module_name, class_name = TRANSPORTS[endpoint.kind]
    except KeyError:
        raise TransportError(f"{endpoint.url}: no transport for kind {endpoint.kind!r}") from None
    cls = load(f"{module_name}:{class_name}")
    transport: Transport = cls(endpoint)
    return transport
