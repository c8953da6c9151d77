"""Base class of every serial-device driver thread: owns the port, reconnects, counts errors.

The base owns the whole path of a device-paced driver, read -> log raw -> decode -> publish, as
python-can's BusABC owns everything about a CAN interface; a driver supplies `decode` (bytes to
items) and `publish` (an item to the vehicle state and its own log), and says which log format
keeps its raw bytes. A driver that must write before it reads (the servo board) overrides
`step` and still publishes through `publish`. Ports are opened with `open_serial_port`, so a
device path, a pseudo-terminal or `loop://` all work, as for the telemetry radio.

A port that disappears (USB unplugged, pseudo-terminal closed) is closed and reopened with
exponential back-off; meanwhile `step` keeps returning False, which the watchdog reports as a
silent device rather than restarting the thread, because a restart cannot bring a device back.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, Self

import serial

from companion.core.config import DeviceConfig
from companion.core.params import ParamSpec, int_param
from companion.core.serialport import OPEN_ERRORS, open_serial_port
from companion.watchdog.thread import ManagedThread, Task

log = logging.getLogger(__name__)

REOPEN_MIN_S = 0.05
REOPEN_MAX_S = 2.0


@dataclass
class PortCounters:
    bytes_in: int = 0
    bytes_out: int = 0
    timeouts: int = 0
    reconnects: int = 0
    open_failures: int = 0
    write_errors: int = 0


class SerialDevice(ManagedThread):
    """A managed thread bound to one serial port.

    Device-paced by default (`period_ms` None): `step` blocks in a read of at most
    `read_timeout_s`, so a stop request is seen within that time even if the device is silent.
    """

    #: Log format index that keeps the device's raw bytes (a capture `companion drivers replay`
    #: plays back); None: the driver logs no raw bytes and has no `<PREFIX>_LOG_RAW` parameter.
    raw_format: int | None = None

    def __init__(
        self,
        task: Task,
        *,
        url: str,
        baudrate: int = 115200,
        read_timeout_s: float = 0.05,
        read_size: int = 256,
    ) -> None:
        super().__init__(task)
        self.url = url
        self.baudrate = baudrate
        self.read_timeout_s = read_timeout_s
        self.read_size = read_size
        self.port: serial.SerialBase | None = None
        self.port_counters = PortCounters()
        self._backoff_s = REOPEN_MIN_S
        self._next_open_ns = 0
        self._ever_opened = False
        self._port_timeout_s: float | None = read_timeout_s  # what the open port blocks for
        #: Called with every decoded item (replay tools, tests); None in flight.
        self.item_sink: Callable[[object], None] | None = None
        self.log_raw = self.raw_format is not None

    @classmethod
    def from_row(cls, task: Task, settings: DeviceConfig | None) -> Self:
        """The driver of `task` on the port its ``[devices.<name>]`` settings name. Every device
        class is built as ``cls(url, baudrate, *, task)`` (the base takes its row first)."""
        if settings is None:
            raise ValueError(f"device {task.name}: no port configured")
        make: Callable[..., Self] = cls
        return make(settings.port, settings.baud, task=task)

    # ---------------------------------------------------------------- what a driver supplies
    @classmethod
    def declare_params(cls, prefix: str) -> list[ParamSpec]:
        if cls.raw_format is None:
            return []
        return [int_param(f"{prefix}_LOG_RAW", 1, 0, 1, "",
                          "1 logs the device's raw bytes too (a capture that `companion drivers "
                          "replay` plays back).")]

    def define_logs(self, tlog: Any) -> None:
        """Subclasses define their decoded formats, then call this for the raw one."""
        if self.raw_format is not None:
            tlog.define(self.raw_format, "%02hhX", ["raw_bytes"])

    def decode(self, data: bytes | None, t_ns: int) -> Iterable[object]:
        """Items decoded from `data` (None: the read timed out; a decoder that hands off on
        silence does so here)."""
        return ()

    def read_timeout_now_s(self) -> float:
        """How long the next read may block, s of the runtime's clock. A driver whose decoder
        only needs a timeout while it holds part of a message (the GPS's idle hand-off)
        returns a longer one otherwise: each timeout is a wake-up that does nothing."""
        return self.read_timeout_s

    def publish(self, item: object, t_ns: int) -> int:
        """Write one decoded item to the vehicle state and the thread's log; returns how many
        cycles it counts for the watchdog (1 for a sample, 0 for side information)."""
        return 0

    def configure(self) -> None:
        """Read this driver's parameters (at start and after a change)."""
        if self.raw_format is not None:
            self.log_raw = bool(self.param("LOG_RAW"))

    # ---------------------------------------------------------------- the read path
    def prologue(self) -> bool:
        self.configure()
        return True

    def on_params_changed(self) -> None:
        self.configure()

    def step(self) -> int:
        """Read what the device sent, log it raw, decode it, publish every item."""
        data = self.read_chunk()
        t_ns = self.ctx.clock.realtime_ns()
        tlog = self.tlog
        if data and tlog is not None and self.log_raw and self.raw_format is not None:
            tlog.log_array(self.raw_format, data, t_ns=t_ns)
        count = 0
        sink = self.item_sink
        for item in self.decode(data, t_ns):
            if sink is not None:
                sink(item)
            count += self.publish(item, t_ns)
        return count

    # ---------------------------------------------------------------- replay hooks
    def drain_decoder(self, t_ns: int) -> list[object]:
        """What the decoder still holds at the end of a replay (a GPS epoch waiting for its
        last sentence); nothing for frame-by-frame devices."""
        return []

    def prepare_for_replay(self) -> None:
        """Called before a recorded capture is played into the port (`companion drivers
        replay`): a driver that pairs answers with its own requests relaxes that here."""

    # ---------------------------------------------------------------- port handling
    def _open(self) -> bool:
        try:
            port = open_serial_port(self.url, self.baudrate,
                                    read_timeout_s=self.ctx.clock.to_host_s(self.read_timeout_s))
        except OPEN_ERRORS as exc:
            self.port_counters.open_failures += 1
            if self.port_counters.open_failures in (1, 10, 100) or self.port_counters.open_failures % 1000 == 0:
                log.warning("%s: cannot open %s: %s", self.name, self.url, exc)
            self._next_open_ns = self.ctx.clock.monotonic_ns() + int(self._backoff_s * 1e9)
            self._backoff_s = min(self._backoff_s * 2, REOPEN_MAX_S)
            return False
        if self._ever_opened:
            self.port_counters.reconnects += 1
            target = os.path.realpath(self.url) if os.path.islink(self.url) else ""
            # a stable link (udev by-id) may now point at another kernel name: say which
            log.info("%s: reopened %s%s", self.name, self.url, f" ({target})" if target else "")
        self._ever_opened = True
        self._backoff_s = REOPEN_MIN_S
        self._port_timeout_s = self.read_timeout_s
        self.port = port
        self.on_port_opened()
        return True

    def _drop_port(self, why: str) -> None:
        log.warning("%s: port %s lost (%s); reopening with back-off", self.name, self.url, why)
        port, self.port = self.port, None
        if port is not None:
            try:
                port.close()
            except Exception:
                pass
        self._next_open_ns = self.ctx.clock.monotonic_ns() + int(self._backoff_s * 1e9)

    def setup(self) -> None:
        # A missing device is not fatal: the worker keeps trying to open it.
        self._backoff_s = REOPEN_MIN_S
        self._next_open_ns = 0
        self._open()

    def interrupt_io(self) -> None:
        port = self.port
        if port is not None and hasattr(port, "cancel_read"):
            try:
                port.cancel_read()
            except Exception:
                pass

    def cleanup(self) -> None:
        port, self.port = self.port, None
        if port is not None:
            try:
                port.close()
            except Exception:
                log.exception("%s: closing %s", self.name, self.url)

    def ensure_port(self) -> serial.SerialBase | None:
        """The open port, reopening it when its back-off has elapsed; None while absent."""
        if self.port is None:
            if self.ctx.clock.monotonic_ns() < self._next_open_ns or not self._open():
                # wait a little, but see a stop request at once
                self.ctx.clock.sleep(min(self.read_timeout_s, 0.05), self.stop_event)
                return None
        return self.port

    def read_chunk(self) -> bytes | None:
        """Bytes available now (blocking up to the read timeout); None when the port is absent."""
        port = self.ensure_port()
        if port is None:
            return None
        try:
            want_s = self.read_timeout_now_s()
            if want_s != self._port_timeout_s:
                port.timeout = self.ctx.clock.to_host_s(want_s)
                self._port_timeout_s = want_s
            waiting = port.in_waiting
            data = port.read(max(1, min(waiting, 4096)) if waiting else 1)
            if data and not waiting:
                # the first byte woke us: take whatever arrived with it
                more = port.in_waiting
                if more:
                    data += port.read(min(more, 4096))
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            # TypeError/AttributeError: pyserial after a concurrent close
            self._drop_port(str(exc) or type(exc).__name__)
            return None
        if not data:
            self.port_counters.timeouts += 1
        else:
            self.work_t0_ns = time.perf_counter_ns()  # step time counts work, not the wait
        self.port_counters.bytes_in += len(data)
        return bytes(data)

    def write(self, data: bytes) -> bool:
        port = self.port
        if port is None:
            return False
        try:
            port.write(data)
        except serial.SerialTimeoutException:
            self.port_counters.write_errors += 1
            return False
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            self.port_counters.write_errors += 1
            self._drop_port(str(exc) or type(exc).__name__)
            return False
        self.port_counters.bytes_out += len(data)
        return True

    # ---------------------------------------------------------------- for subclasses
    def on_port_opened(self) -> None:
        """Reset decoder state after a (re)open: half a frame from before is garbage now."""

    def io_bytes(self) -> int:
        return self.port_counters.bytes_in

    def counters(self) -> dict[str, int]:
        """All counters of this driver, for status and the replay summary."""
        return dict(vars(self.port_counters))
