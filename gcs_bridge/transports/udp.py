"""UDP links: `udpin:` answers whoever talks to it, `udpout:`/`udpbcast:` send to one address."""

from __future__ import annotations

import errno
import logging
import socket
import threading
import time
from collections.abc import Hashable

from gcs_bridge.transports.base import (
    MAX_PEERS,
    RECV_BATCH,
    UDP_PEER_TIMEOUT_S,
    Chunk,
    SocketTransport,
    TransportError,
    quiet_close,
)
from gcs_bridge.transports.endpoints import Endpoint

log = logging.getLogger(__name__)


class UdpTransport(SocketTransport):
    """`udpin:` binds and answers whoever talks to it; `udpout:`/`udpbcast:` send to a fixed
    address and accept the replies."""

    def __init__(self, endpoint: Endpoint) -> None:
        super().__init__(endpoint)
        self._sock: socket.socket | None = None
        self._dest: tuple[str, int] | None = None
        self._peers: dict[Hashable, float] = {}  # address -> host monotonic time last heard
        self._trusted: set[Hashable] = set()  # peers whose signed frames verified
        self._lock = threading.Lock()

    def open(self) -> None:
        ep = self.endpoint
        self._open_wake()
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            if ep.kind == "udpin":
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                sock.bind(self._resolve(ep.host, ep.port))
            else:
                if ep.kind == "udpbcast":
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
                self._dest = self._resolve(ep.host, ep.port)
                sock.bind(("0.0.0.0", 0))
        except OSError as exc:
            quiet_close(sock)
            self._close_wake()
            if isinstance(exc, TransportError):
                raise
            raise TransportError(f"{ep.url}: cannot open UDP socket: {exc.strerror or exc}") from None
        sock.setblocking(False)
        self._sock = sock
        self._closed = False

    def close(self) -> None:
        self._closed = True
        if self._sock is not None:
            quiet_close(self._sock)
            self._sock = None
        self._close_wake()
        with self._lock:
            self._peers.clear()
            self._trusted.clear()

    @property
    def local_port(self) -> int:
        return int(self._sock.getsockname()[1]) if self._sock is not None else 0

    @property
    def peer_count(self) -> int:
        if self.endpoint.kind != "udpin":
            return 1
        with self._lock:
            return len(self._live_peers(time.monotonic()))

    def _live_peers(self, now: float) -> list[Hashable]:
        if not self._peers:
            return []
        live = [a for a, t in self._peers.items() if now - t <= UDP_PEER_TIMEOUT_S]
        if not live:  # keep answering the last one heard, as mavutil does
            live = [max(self._peers, key=lambda a: self._peers[a])]
        return live

    def recv(self, timeout_s: float) -> list[Chunk]:
        sock = self._sock
        if sock is None:
            time.sleep(min(timeout_s, 0.05))
            return []
        if not self._select([sock], timeout_s):
            return []
        chunks: list[Chunk] = []
        for _ in range(RECV_BATCH):
            try:
                data, addr = sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                if exc.errno == errno.ECONNREFUSED:  # an ICMP answer to an earlier send
                    continue
                break
            self.counters.bytes_in += len(data)
            chunks.append((addr, data))
        return chunks

    def accept_peer(self, peer: Hashable, trusted: bool) -> None:
        """A source becomes a destination only once the link accepted a frame from it, so
        garbage and refused frames (from forged source addresses, too) cannot push a ground
        station out of the table. When the table is full, the stale go first, then the
        quietest untrusted peer; a trusted (signature-verified) peer makes way only for
        another trusted one, and an untrusted newcomer is not added when every slot is
        trusted and busy."""
        if self.endpoint.kind != "udpin":
            return
        now = time.monotonic()
        with self._lock:
            if trusted:
                self._trusted.add(peer)
            if peer not in self._peers:
                if len(self._peers) >= MAX_PEERS and not self._make_room(now, trusted):
                    self._trusted.discard(peer)
                    return
                self.counters.peers_seen += 1
                log.info("%s: ground station at %s", self.endpoint.url, peer)
            self._peers[peer] = now

    def _make_room(self, now: float, for_trusted: bool) -> bool:
        stale = [a for a, t in self._peers.items() if now - t > UDP_PEER_TIMEOUT_S]
        for a in stale:
            del self._peers[a]
            self._trusted.discard(a)
        if stale:
            return True
        untrusted = [a for a in self._peers if a not in self._trusted]
        pool = untrusted or (list(self._peers) if for_trusted else [])
        if not pool:
            return False
        quietest = min(pool, key=lambda a: self._peers[a])
        del self._peers[quietest]
        self._trusted.discard(quietest)
        return True

    def send(self, data: bytes) -> bool:
        sock = self._sock
        if sock is None:
            return False
        if self.endpoint.kind == "udpin":
            with self._lock:
                targets = self._live_peers(time.monotonic())
        else:
            targets = [self._dest] if self._dest is not None else []
        if not targets:
            self.counters.send_dropped += 1
            return False
        ok = False
        for addr in targets:
            try:
                sock.sendto(data, addr)  # type: ignore[call-overload]
                self.counters.bytes_out += len(data)
                ok = True
            except (BlockingIOError, InterruptedError):
                self.counters.send_dropped += 1
            except OSError:
                self.counters.send_errors += 1
        return ok
