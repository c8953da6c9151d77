"""The autopilot link's connection as a ground link's transport (endpoint `autopilot:`).

When the companion is one endpoint of the user's MAVLink router (mavlink-router, BlueOS), that
one connection carries the autopilot's frames and the ground stations' frames for the
companion alike, and the router beyond it does the routing. The autopilot link
(`--autopilot URL`) owns the connection: it puts every frame it receives on `autopilot_rx` and
sends what is put on `autopilot_tx`. This transport reads the first and writes the second, so
the bridge serves its component on that same connection and routes nothing itself (a second
connection to the router would carry the companion's component id twice, and forwarding
between the two would loop through the router).
"""

from __future__ import annotations

from typing import Any

from companion.core.sync import MessageQueue
from gcs_bridge.transports.base import Chunk, Transport
from gcs_bridge.transports.endpoints import Endpoint

__all__ = ["SharedTransport"]

PEER = "autopilot"
MAX_FRAMES_PER_RECV = 256


class SharedTransport(Transport):
    """Frames from `rx` (lists of ``(system, component, msg_id, bytes)``, one per read of
    the autopilot link), bytes to `tx`."""

    def __init__(self, endpoint: Endpoint, rx: MessageQueue[Any], tx: MessageQueue[Any]) -> None:
        super().__init__(endpoint)
        self.rx = rx
        self.tx = tx

    def open(self) -> None:
        self._closed = False

    def close(self) -> None:
        self._closed = True

    def recv(self, timeout_s: float) -> list[Chunk]:
        item = self.rx.get(timeout_s)
        out: list[Chunk] = []
        while item is not None:
            for frame in item:  # the frames of one read of the autopilot link
                data = frame[3]
                out.append((PEER, data))
                self.counters.bytes_in += len(data)
            if len(out) >= MAX_FRAMES_PER_RECV:
                break
            item = self.rx.get_nowait()
        return out

    def send(self, data: bytes) -> bool:
        self.tx.put(bytes(data))
        self.counters.bytes_out += len(data)
        return True

    def wake(self) -> None:
        self.rx.put(None)
