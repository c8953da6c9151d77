"""The simulated camera in the world: its thread, the hand-off on the world's clock, its links.

`companion.sim.camera.SimCamera` renders a frame at the true attitude and runs the real
detector; this module carries it in the world (`companion.sim.world.World.attach_camera`): a
`WorldCamera` captures when a frame is due, in a thread of its own (or inside the tick, on
simulated time), and hands each fix off ``latency`` later to a link: `LegacyHorizonLink` sends
it as the HORIZON_ATTITUDE datagram ``companion horizon stream`` sends (its
``horizon.stream.LegacyHorizonSender``) to the runtime's legacy command port; `SlotLink`, for a
lockstep flight without ground links, writes it to the runtime's ``state.horizon``. Its own
module because it is about threads, clocks and sockets, not images.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.core.clock import Clock
from companion.core.state import HorizonMeasurement
from companion.core.sync import DataSlot
from companion.sim.camera import CameraResult, CameraStats, SimCamera
from horizon.stream import LegacyHorizonSender

log = logging.getLogger(__name__)

__all__ = ["LegacyHorizonLink", "Link", "SlotLink", "WorldCamera", "attach_camera"]


class LegacyHorizonLink:
    """A :class:`CameraResult` as the HORIZON_ATTITUDE datagram ``companion horizon stream``
    sends (its :class:`~horizon.stream.LegacyHorizonSender`, nothing re-encoded here), over UDP
    to the runtime's legacy command port. ``clock_ns`` stamps the header (send time)."""

    def __init__(self, host: str, port: int, vehicle_id: int = 1,
                 clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.sender = LegacyHorizonSender(host, port, vehicle_id, clock_ns)

    def __call__(self, result: CameraResult, frame_ns: int) -> bool:
        """Send one result (frame time ``frame_ns`` in the runtime's clock); False if failed."""
        if result.failed:
            return False
        self.sender(result.estimate, frame_ns)
        return True

    def retarget(self, host: str, port: int) -> None:
        """Send to another port from now on: a rebooted runtime may have bound a new one."""
        self.sender.address = (host, port)

    @property
    def acks(self) -> int:
        return self.sender.poll_acks()

    def close(self) -> None:
        self.sender.close()


class SlotLink:
    """For a world on simulated time (lockstep), which has no ground links: the measurement
    goes straight into the runtime's ``state.horizon``, as the legacy adapter would write it
    on reception (same fields, source ``legacy``). Not the real path; the UDP one is."""

    def __init__(self, slot: DataSlot[HorizonMeasurement], source: str = "legacy") -> None:
        self.slot = slot
        self.source = source

    def __call__(self, result: CameraResult, frame_ns: int) -> bool:
        m = result.measurement(frame_ns, self.source)
        if m is None:
            return False
        self.slot.write(m)
        return True


Link = Callable[[CameraResult, int], bool]


@dataclass
class _Job:
    index: int
    t_s: float
    roll_rad: float
    pitch_rad: float
    frame_ns: int
    mono_ns: int


class WorldCamera:
    """The camera inside the world process: ``on_tick`` from the world's tick (cheap), the
    rendering and detection in a thread of its own, the hand-off at frame time + latency on the
    world's clock. A frame due while the previous one is still being detected replaces it
    (the older one is dropped and counted), as a camera pipeline that cannot keep up does.

    ``threaded=False`` does it all inside ``on_tick`` (deterministic: for tests, and for a
    world on simulated time); a tick that captures then takes the frame's cost.
    """

    def __init__(self, camera: SimCamera, link: Link, clock: Clock,
                 *, threaded: bool = True) -> None:
        self.camera = camera
        self.link = link
        self.clock = clock
        self.threaded = threaded
        self._latency_ns = int(round(camera.latency_s * 1e9))
        self._pending: list[tuple[float, CameraResult, int]] = []
        self._job: _Job | None = None
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if threaded:
            self._thread = threading.Thread(target=self._run, name="sim-camera", daemon=True)
            self._thread.start()

    @property
    def stats(self) -> CameraStats:
        return self.camera.stats

    def on_tick(self, t_s: float, roll_rad: float, pitch_rad: float) -> None:
        """Call once per world tick with the truth at ``t_s`` (flight time)."""
        n = self.camera.frame_due(t_s)
        if n is not None:
            frame_ns = self.clock.realtime_ns()
            if self.threaded:
                job = _Job(n, t_s, roll_rad, pitch_rad, frame_ns, self.clock.monotonic_ns())
                with self._cond:
                    if self._job is not None:
                        self.stats.dropped += 1
                    self._job = job
                    self._cond.notify()
                return
            r = self.camera.capture(t_s, roll_rad, pitch_rad, n)
            self._pending.append((r.handoff_s, r, frame_ns))
        while self._pending and self._pending[0][0] <= t_s + 1e-9:
            _, r, frame_ns = self._pending.pop(0)
            self._send(r, frame_ns)

    def _send(self, r: CameraResult, frame_ns: int) -> None:
        try:
            if self.link(r, frame_ns):
                self.stats.sent += 1
        except (OSError, ValueError) as exc:
            self.stats.send_errors += 1
            if self.stats.send_errors in (1, 100):
                log.warning("sim camera: sending frame %d failed: %s", r.index, exc)

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._cond:
                while self._job is None and not self._stop.is_set():
                    self._cond.wait(0.5)
                job, self._job = self._job, None
            if job is None:
                continue
            try:
                r = self.camera.capture(job.t_s, job.roll_rad, job.pitch_rad, job.index)
            except Exception:  # a renderer or detector bug must not kill the world
                log.exception("sim camera: frame %d failed", job.index)
                continue
            if self.clock.wait_until_ns(job.mono_ns + self._latency_ns, self._stop):
                return
            self._send(r, job.frame_ns)

    def close(self) -> dict[str, Any]:
        """Stop the thread and the link; the run's figures (``CameraStats.summary``)."""
        self._stop.set()
        with self._cond:
            self._cond.notify()
        if self._thread is not None:
            self._thread.join(2.0)
        close = getattr(self.link, "close", None)
        if close is not None:
            close()
        return self.stats.summary()


def attach_camera(dest: str, clock: Clock, *, vehicle_id: int = 1,
                  seed: int | np.random.Generator = 0, threaded: bool = True,
                  **camera_options: Any) -> WorldCamera:
    """A live camera for the world: frames from ``SimCamera(seed, **camera_options)``, sent as
    HORIZON_ATTITUDE to ``dest`` (``HOST:PORT``, the runtime's ``legacy.listen``) stamped with
    ``clock`` (the world's, which shares the runtime's epoch and scale)."""
    host, sep, port = dest.rpartition(":")
    if not sep or not host:
        raise ValueError(f"attach_camera: expected HOST:PORT, got {dest!r}")
    camera = SimCamera(seed, **camera_options)
    link = LegacyHorizonLink(host, int(port), vehicle_id, clock.realtime_ns)
    return WorldCamera(camera, link, clock, threaded=threaded)
