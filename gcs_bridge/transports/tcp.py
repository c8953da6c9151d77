"""TCP links: a server (`tcpin:`) for several ground stations, a client (`tcp:`) that reconnects."""

from __future__ import annotations

import logging
import socket
import threading
import time

from gcs_bridge.transports.base import (
    MAX_PEERS,
    RECONNECT_MAX_S,
    RECONNECT_MIN_S,
    TCP_SEND_TIMEOUT_S,
    Chunk,
    SocketTransport,
    TransportError,
    quiet_close,
)
from gcs_bridge.transports.endpoints import Endpoint

log = logging.getLogger(__name__)


class TcpServerTransport(SocketTransport):
    """`tcpin:`: several ground stations may connect, leave and come back."""

    def __init__(self, endpoint: Endpoint) -> None:
        super().__init__(endpoint)
        self._listen: socket.socket | None = None
        self._clients: list[socket.socket] = []
        self._lock = threading.Lock()

    def open(self) -> None:
        ep = self.endpoint
        self._open_wake()
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(self._resolve(ep.host, ep.port))
            sock.listen(MAX_PEERS)
        except OSError as exc:
            quiet_close(sock)
            self._close_wake()
            if isinstance(exc, TransportError):
                raise
            raise TransportError(f"{ep.url}: cannot listen: {exc.strerror or exc}") from None
        sock.setblocking(False)
        self._listen = sock
        self._closed = False

    @property
    def local_port(self) -> int:
        return int(self._listen.getsockname()[1]) if self._listen is not None else 0

    @property
    def peer_count(self) -> int:
        with self._lock:
            return len(self._clients)

    def close(self) -> None:
        self._closed = True
        with self._lock:
            clients, self._clients = self._clients, []
        for c in clients:
            quiet_close(c)
        if self._listen is not None:
            quiet_close(self._listen)
            self._listen = None
        self._graveyard.close_all()
        self._close_wake()

    def _drop(self, client: socket.socket, why: str) -> None:
        with self._lock:
            if client not in self._clients:
                return
            self._clients.remove(client)
        try:
            peer = client.getpeername()
        except OSError:
            peer = "?"
        log.info("%s: ground station %s left (%s)", self.endpoint.url, peer, why)
        try:
            client.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._graveyard.bury(client)

    def recv(self, timeout_s: float) -> list[Chunk]:
        listen = self._listen
        if listen is None:
            time.sleep(min(timeout_s, 0.05))
            return []
        with self._lock:
            clients = list(self._clients)
        readable = self._select([listen, *clients], timeout_s)
        chunks: list[Chunk] = []
        for s in readable:
            if s is listen:
                self._accept(listen)
                continue
            try:
                data = s.recv(4096)
            except (BlockingIOError, InterruptedError, TimeoutError):
                continue
            except OSError as exc:
                self._drop(s, exc.strerror or str(exc))
                continue
            if not data:
                self._drop(s, "closed")
                continue
            self.counters.bytes_in += len(data)
            chunks.append((id(s), data))
        return chunks

    def _accept(self, listen: socket.socket) -> None:
        try:
            client, addr = listen.accept()
        except OSError:
            return
        with self._lock:
            full = len(self._clients) >= MAX_PEERS
            if not full:
                client.settimeout(TCP_SEND_TIMEOUT_S)
                client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self._clients.append(client)
        if full:
            self.counters.peers_refused += 1
            log.warning("%s: refused ground station %s: %d already connected",
                        self.endpoint.url, addr, MAX_PEERS)
            quiet_close(client)
            return
        self.counters.peers_seen += 1
        log.info("%s: ground station %s connected", self.endpoint.url, addr)

    def send(self, data: bytes) -> bool:
        self._graveyard.close_all()
        with self._lock:
            clients = list(self._clients)
        if not clients:
            self.counters.send_dropped += 1
            return False
        ok = False
        for c in clients:
            try:
                c.sendall(data)
                self.counters.bytes_out += len(data)
                ok = True
            except TimeoutError:
                self.counters.send_dropped += 1
                self._drop(c, "too slow")  # a half-written frame cannot be continued
            except OSError as exc:
                self.counters.send_errors += 1
                self._drop(c, exc.strerror or str(exc))
        return ok


class TcpClientTransport(SocketTransport):
    """`tcp:HOST:PORT`: connects out, and reconnects with back-off when the server goes."""

    def __init__(self, endpoint: Endpoint) -> None:
        super().__init__(endpoint)
        self._sock: socket.socket | None = None
        self._next_try = 0.0
        self._backoff_s = RECONNECT_MIN_S
        self._dest: tuple[str, int] | None = None

    def open(self) -> None:
        self._open_wake()
        self._dest = self._resolve(self.endpoint.host, self.endpoint.port)
        self._closed = False
        self._connect()

    def _connect(self) -> None:
        assert self._dest is not None
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.settimeout(0.2)
        try:
            sock.connect(self._dest)
        except OSError:
            quiet_close(sock)
            self._next_try = time.monotonic() + self._backoff_s
            self._backoff_s = min(self._backoff_s * 2, RECONNECT_MAX_S)
            return
        sock.settimeout(TCP_SEND_TIMEOUT_S)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._backoff_s = RECONNECT_MIN_S
        self.counters.reconnects += 1
        self._sock = sock
        log.info("%s: connected", self.endpoint.url)

    def _lose(self, why: str) -> None:
        sock, self._sock = self._sock, None
        if sock is None:
            return
        log.info("%s: connection lost (%s)", self.endpoint.url, why)
        try:
            sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._graveyard.bury(sock)
        self._next_try = time.monotonic() + self._backoff_s

    @property
    def peer_count(self) -> int:
        return 1 if self._sock is not None else 0

    def close(self) -> None:
        self._closed = True
        if self._sock is not None:
            quiet_close(self._sock)
            self._sock = None
        self._graveyard.close_all()
        self._close_wake()

    def recv(self, timeout_s: float) -> list[Chunk]:
        if self._sock is None:
            if time.monotonic() >= self._next_try and self._dest is not None:
                self._connect()
            if self._sock is None:
                self._select([], min(timeout_s, max(0.0, self._next_try - time.monotonic())))
                return []
        sock = self._sock
        assert sock is not None
        if not self._select([sock], timeout_s):
            return []
        try:
            data = sock.recv(4096)
        except (BlockingIOError, InterruptedError, TimeoutError):
            return []
        except OSError as exc:
            self._lose(exc.strerror or str(exc))
            return []
        if not data:
            self._lose("closed by the ground station")
            return []
        self.counters.bytes_in += len(data)
        return [("tcp", data)]

    def send(self, data: bytes) -> bool:
        self._graveyard.close_all()
        sock = self._sock
        if sock is None:
            self.counters.send_dropped += 1
            return False
        try:
            sock.sendall(data)
        except OSError:
            self.counters.send_errors += 1
            return False
        self.counters.bytes_out += len(data)
        return True
