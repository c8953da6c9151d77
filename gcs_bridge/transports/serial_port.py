"""Serial links: telemetry radios, pseudo-terminals, pyserial URLs."""

from __future__ import annotations

import logging
import threading
import time

import serial

from companion.core.serialport import OPEN_ERRORS, open_serial_port
from gcs_bridge.transports.base import (
    RECONNECT_MAX_S,
    RECONNECT_MIN_S,
    SERIAL_WRITE_TIMEOUT_S,
    Chunk,
    Transport,
    quiet_close,
)
from gcs_bridge.transports.endpoints import Endpoint

log = logging.getLogger(__name__)


class SerialTransport(Transport):
    """A serial telemetry radio (or a pseudo-terminal, or a pyserial URL in tests).

    A port that is missing or fails is reopened with back-off, so a radio plugged in late, or
    unplugged and back, is served without a restart.
    """

    def __init__(self, endpoint: Endpoint, read_timeout_s: float = 0.1) -> None:
        """`read_timeout_s` is the first read's wait; later reads wait what `recv` is given."""
        super().__init__(endpoint)
        self._port: serial.SerialBase | None = None
        self._read_timeout_s = read_timeout_s
        self._next_try = 0.0
        self._backoff_s = RECONNECT_MIN_S
        self._wake_ev = threading.Event()
        self._open_failures = 0

    @property
    def bytes_per_s(self) -> float | None:
        return self.endpoint.baud / 10.0

    @property
    def peer_count(self) -> int:
        return 1 if self._port is not None else 0

    def open(self) -> None:
        self._closed = False
        self._try_open()

    def _try_open(self) -> None:
        ep = self.endpoint
        try:
            port = open_serial_port(ep.device, ep.baud, read_timeout_s=self._read_timeout_s,
                                    write_timeout_s=SERIAL_WRITE_TIMEOUT_S)
        except OPEN_ERRORS as exc:
            self._open_failures += 1
            if self._open_failures in (1, 10) or self._open_failures % 100 == 0:
                log.warning("%s: cannot open (%s); retrying", ep.url, exc)
            self._next_try = time.monotonic() + self._backoff_s
            self._backoff_s = min(self._backoff_s * 2, RECONNECT_MAX_S)
            return
        self._backoff_s = RECONNECT_MIN_S
        self._open_failures = 0
        self.counters.reconnects += 1
        self._port = port

    def _lose(self, why: str) -> None:
        port, self._port = self._port, None
        if port is None:
            return
        log.warning("%s: port failed (%s); reopening", self.endpoint.url, why)
        self._graveyard.bury(port)
        self._next_try = time.monotonic() + self._backoff_s

    def close(self) -> None:
        self._closed = True
        if self._port is not None:
            quiet_close(self._port)
            self._port = None
        self._graveyard.close_all()

    def wake(self) -> None:
        self._wake_ev.set()
        port = self._port
        if port is not None:
            try:
                port.cancel_read()
            except Exception:  # not every pyserial backend can cancel; the read times out
                pass

    def recv(self, timeout_s: float) -> list[Chunk]:
        if self._wake_ev.is_set():
            self._wake_ev.clear()
            return []
        port = self._port
        if port is None:
            if not self._closed and time.monotonic() >= self._next_try:
                self._try_open()
            if self._port is None:
                self._wake_ev.wait(min(timeout_s, max(0.0, self._next_try - time.monotonic())))
                self._wake_ev.clear()
            return []
        try:
            if timeout_s != self._read_timeout_s:  # the caller's bound (it follows the clock)
                self._read_timeout_s = port.timeout = timeout_s
            waiting = port.in_waiting
            data = port.read(waiting if waiting > 0 else 1)
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            self._lose(str(exc))
            return []
        if not data:
            return []
        self.counters.bytes_in += len(data)
        return [("serial", bytes(data))]

    def send(self, data: bytes) -> bool:
        self._graveyard.close_all()
        port = self._port
        if port is None:
            self.counters.send_dropped += 1
            return False
        try:
            port.write(data)
        except serial.SerialTimeoutException:
            self.counters.send_dropped += 1
            return False
        except (serial.SerialException, OSError, TypeError, AttributeError):
            self.counters.send_errors += 1
            return False
        self.counters.bytes_out += len(data)
        return True
