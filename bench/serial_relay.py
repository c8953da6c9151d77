"""A telemetry radio pair in software: two pseudo-terminals joined by a byte-paced relay.

`SerialRelay(baud)` opens two pseudo-terminals, A and B; whatever is written to one side's
device (`path_a`, `path_b`) comes out of the other's, at most `baud / 10` bytes per second in
each direction (8N1: ten bit times a byte), like a pair of 57600 baud SiK radios. Each direction
holds at most `buffer_bytes` in flight (a radio's buffer); beyond that the relay stops reading,
the pseudo-terminal's own buffer fills and the writer is held back, as a serial port to a full
radio would hold it. Runs in one thread (`start`/`stop`, or as a context manager).

`taps[0]` / `taps[1]` are called with each chunk as it is delivered A->B / B->A (with the
`time.monotonic()` of delivery), so a benchmark can see what a ground station received when.
Counters: `delivered[0]`, `delivered[1]` bytes.

Run alone (`python bench/serial_relay.py [BAUD]`) it prints the two device paths and relays
until interrupted.
"""

from __future__ import annotations

import os
import select
import sys
import threading
import time
import tty
from collections.abc import Callable
from types import TracebackType

Tap = Callable[[bytes, float], None]

TICK_S = 0.002  # longest sleep between deliveries: chunks of about baud/10 * TICK_S bytes


class SerialRelay:
    def __init__(self, baud: int = 57600, *, buffer_bytes: int = 2048) -> None:
        self.baud = baud
        self.bytes_per_s = baud / 10.0
        self.buffer_bytes = buffer_bytes
        self._masters: list[int] = []
        self._slaves: list[int] = []
        self.paths: list[str] = []
        for _ in range(2):
            master, slave = os.openpty()
            tty.setraw(slave)  # no echo or line editing before a client opens it
            os.set_blocking(master, False)
            self._masters.append(master)
            self._slaves.append(slave)  # held open: the master never reads EIO between clients
            self.paths.append(os.ttyname(slave))
        self.taps: list[Tap | None] = [None, None]
        self.delivered = [0, 0]
        self.dropped_reads = 0
        self._bufs = [bytearray(), bytearray()]
        self._tokens = [0.0, 0.0]
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False

    @property
    def path_a(self) -> str:
        return self.paths[0]

    @property
    def path_b(self) -> str:
        return self.paths[1]

    def start(self) -> SerialRelay:
        self._thread = threading.Thread(target=self._run, name="serial-relay", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        burst = max(1.0, self.bytes_per_s * 0.01)  # at most 10 ms of line time at once
        last = time.monotonic()
        while not self._stop.is_set():
            readable = [m for m, buf in zip(self._masters, self._bufs, strict=True)
                        if len(buf) < self.buffer_bytes]
            pending = any(self._bufs)
            try:
                r, _, _ = select.select(readable, [], [], TICK_S if pending else 0.05)
            except (OSError, ValueError):
                return  # closed under us
            for i, master in enumerate(self._masters):
                if master in r:
                    try:
                        data = os.read(master, self.buffer_bytes - len(self._bufs[i]))
                    except BlockingIOError:
                        continue
                    except OSError:  # EIO: no client has the device open
                        self.dropped_reads += 1
                        continue
                    self._bufs[i] += data
            now = time.monotonic()
            dt, last = now - last, now
            for i in range(2):
                self._tokens[i] = min(burst, self._tokens[i] + dt * self.bytes_per_s)
                buf = self._bufs[i]
                n = min(len(buf), int(self._tokens[i]))
                if n <= 0:
                    if not buf:
                        self._tokens[i] = min(self._tokens[i], burst)
                    continue
                try:
                    sent = os.write(self._masters[1 - i], bytes(buf[:n]))
                except BlockingIOError:
                    continue  # the reader's side is full: hold the bytes, like a radio would
                except OSError:
                    sent = n  # nobody reading the far side: the bytes are lost in the air
                chunk = bytes(buf[:sent])
                del buf[:sent]
                self._tokens[i] -= sent
                self.delivered[i] += sent
                tap = self.taps[i]
                if tap is not None and chunk:
                    tap(chunk, now)

    def stop(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        for fd in self._masters + self._slaves:
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> SerialRelay:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()


def main(argv: list[str]) -> int:
    baud = int(argv[0]) if argv else 57600
    with SerialRelay(baud) as relay:
        print(f"A: {relay.path_a}  B: {relay.path_b}  ({baud} baud, {relay.bytes_per_s:.0f} B/s "
              "each way); Ctrl-C ends", flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
