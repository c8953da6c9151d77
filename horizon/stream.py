"""Sending horizon estimates to the aircraft while the video runs.

A sender is any ``Callable[[HorizonEstimate, int], None]`` taking the estimate and the frame's
capture time (Unix nanoseconds), so the loop can feed several links and tests can inject their
own. Two are provided:

* :class:`LegacyHorizonSender`: the thesis's HORIZON_ATTITUDE command (type 0x84, 36 bytes) over
  UDP, packed here with :mod:`struct` from the contract in ``specs/legacy-udp.md`` so this package
  does not depend on the legacy codec. The aircraft rejects non-finite values, so an estimate
  without pitch (no camera intrinsics) or without a horizon is not sent.
* :class:`MavlinkHorizonSender`: MAVLink through pymavlink. No standard message carries "attitude
  measured by a horizon sensor" with a quality, so the estimate goes out as **ATTITUDE** (#30)
  from its own component (MAV_COMP_ID_CAMERA, 100): roll and pitch in radians, yaw and the rates
  NaN (not measured), ``time_boot_ms`` the frame time on this component's clock, paired with a
  **NAMED_VALUE_FLOAT** ``"HZN_QUAL"`` carrying the quality with the same ``time_boot_ms``.
  SYSTEM_TIME (once a second) maps that clock to Unix time and a HEARTBEAT (MAV_TYPE_CAMERA)
  announces the component. ATTITUDE was chosen over VISION_POSITION_ESTIMATE or ATT_POS_MOCAP,
  which carry a covariance, because autopilots fuse those as external position and yaw: with the
  unknown position of a horizon sensor filled in they would corrupt the navigation solution,
  while an ATTITUDE from a non-autopilot component is ignored by autopilots and can be singled
  out by the estimator (and shown apart by a ground station) by its component id.
"""

from __future__ import annotations

import logging
import math
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from horizon.estimate import HorizonEstimate
from horizon.sources import Frame

__all__ = [
    "Sender",
    "HORIZON_ATTITUDE_TYPE",
    "HORIZON_ATTITUDE_SIZE",
    "pack_horizon_attitude",
    "LegacyHorizonSender",
    "MavlinkHorizonSender",
    "StreamStats",
    "run_stream",
]

log = logging.getLogger(__name__)

Sender = Callable[[HorizonEstimate, int], None]

HORIZON_ATTITUDE_TYPE = 0x84
HORIZON_ATTITUDE_SIZE = 36
LEGACY_COMMAND_PORT = 5500
_HEADER = struct.Struct("<BBHIiI")
_BODY = struct.Struct("<fffiI")
_NS = 1_000_000_000
MAV_COMP_ID_CAMERA = 100
QUALITY_NAME = "HZN_QUAL"


def _split_time(t_ns: int) -> tuple[int, int]:
    sec, nsec = divmod(int(t_ns), _NS)
    return sec, nsec


def pack_horizon_attitude(
    seq: int,
    vehicle_id: int,
    sent_ns: int,
    roll_rad: float,
    pitch_rad: float,
    quality: float,
    frame_ns: int,
) -> bytes:
    """The 36-byte HORIZON_ATTITUDE datagram: 16-byte header (type, vehicle, size, sequence,
    time sent) then roll, pitch (rad), quality and the frame's time, little-endian."""
    if not 1 <= vehicle_id <= 255:
        raise ValueError(f"vehicle id must be 1..255, got {vehicle_id}")
    for name, v in (("roll", roll_rad), ("pitch", pitch_rad), ("quality", quality)):
        if not math.isfinite(v):
            raise ValueError(f"HORIZON_ATTITUDE {name} must be finite, got {v}")
    s_sec, s_nsec = _split_time(sent_ns)
    f_sec, f_nsec = _split_time(frame_ns)
    header = _HEADER.pack(
        HORIZON_ATTITUDE_TYPE, vehicle_id, HORIZON_ATTITUDE_SIZE, seq & 0xFFFFFFFF, s_sec, s_nsec
    )
    return header + _BODY.pack(roll_rad, pitch_rad, min(max(quality, 0.0), 1.0), f_sec, f_nsec)


class LegacyHorizonSender:
    """HORIZON_ATTITUDE commands to ``host:port`` from one UDP socket. The aircraft answers each
    with a COMMAND_ACK; those are drained without blocking and counted."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = LEGACY_COMMAND_PORT,
        vehicle_id: int = 1,
        clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        if not 1 <= vehicle_id <= 255:
            raise ValueError(f"vehicle id must be 1..255, got {vehicle_id}")
        self.address = (host, port)
        self.vehicle_id = vehicle_id
        self._clock = clock_ns
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self._seq = 0
        self.sent = 0
        self.skipped = 0
        self.acks = 0

    def __call__(self, est: HorizonEstimate, frame_ns: int) -> None:
        self.poll_acks()
        if not est.found or est.roll_deg is None or est.pitch_deg is None:
            self.skipped += 1
            return
        self._seq += 1
        data = pack_horizon_attitude(
            self._seq,
            self.vehicle_id,
            self._clock(),
            math.radians(est.roll_deg),
            math.radians(est.pitch_deg),
            est.quality,
            frame_ns,
        )
        self._sock.sendto(data, self.address)
        self.sent += 1

    def poll_acks(self) -> int:
        """Count the COMMAND_ACKs that have arrived, without waiting; returns the total."""
        while True:
            try:
                data = self._sock.recv(2048)
            except (BlockingIOError, InterruptedError):
                return self.acks
            except OSError:
                return self.acks  # e.g. ICMP port unreachable, reported on the next call
            if len(data) >= 1 and data[0] == 0x03:
                self.acks += 1

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> LegacyHorizonSender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class MavlinkHorizonSender:
    """ATTITUDE + NAMED_VALUE_FLOAT("HZN_QUAL") per estimate on a pymavlink connection (any
    connection string pymavlink accepts, e.g. ``udpout:127.0.0.1:14550``), with a HEARTBEAT and a
    SYSTEM_TIME once a second."""

    def __init__(
        self,
        url: str = "udpout:127.0.0.1:14550",
        system_id: int = 1,
        component_id: int = MAV_COMP_ID_CAMERA,
        clock_ns: Callable[[], int] = time.time_ns,
        announce_period_s: float = 1.0,
    ) -> None:
        from pymavlink import mavutil

        if not 1 <= system_id <= 255 or not 1 <= component_id <= 255:
            raise ValueError(f"MAVLink ids must be 1..255, got system {system_id} component {component_id}")
        self._mavutil = mavutil
        try:
            self.conn = mavutil.mavlink_connection(
                url, source_system=system_id, source_component=component_id, autoreconnect=True
            )
        except Exception as exc:  # pymavlink raises many kinds for a bad connection string
            raise ValueError(f"{url}: cannot open MAVLink connection: {exc}") from None
        self._clock = clock_ns
        self._boot_ns = clock_ns()
        self._announce_ns = int(announce_period_s * _NS)
        self._next_announce_ns = 0
        self.sent = 0
        self.skipped = 0

    def _boot_ms(self, t_ns: int) -> int:
        return max(0, (t_ns - self._boot_ns) // 1_000_000) & 0xFFFFFFFF

    def _announce(self) -> None:
        now = self._clock()
        if now < self._next_announce_ns:
            return
        self._next_announce_ns = now + self._announce_ns
        m = self._mavutil.mavlink
        self.conn.mav.heartbeat_send(m.MAV_TYPE_CAMERA, m.MAV_AUTOPILOT_INVALID, 0, 0, m.MAV_STATE_ACTIVE)
        self.conn.mav.system_time_send(now // 1000, self._boot_ms(now))

    def __call__(self, est: HorizonEstimate, frame_ns: int) -> None:
        self._announce()
        if not est.found or est.roll_deg is None:
            self.skipped += 1
            return
        t_ms = self._boot_ms(frame_ns)
        pitch = math.radians(est.pitch_deg) if est.pitch_deg is not None else math.nan
        nan = math.nan
        self.conn.mav.attitude_send(t_ms, math.radians(est.roll_deg), pitch, nan, nan, nan, nan)
        self.conn.mav.named_value_float_send(t_ms, QUALITY_NAME.encode(), float(est.quality))
        self.sent += 1

    def close(self) -> None:
        self.conn.close()

    def __enter__(self) -> MavlinkHorizonSender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class StreamStats:
    frames: int = 0
    found: int = 0
    send_errors: int = 0


def run_stream(
    frames: Iterable[Frame],
    estimate: Callable[[NDArray[np.uint8]], HorizonEstimate],
    senders: Sequence[Sender],
    on_estimate: Callable[[Frame, HorizonEstimate], None] | None = None,
    stop: threading.Event | None = None,
    pace_hz: float | None = None,
) -> StreamStats:
    """Detect on each frame and hand the estimate to every sender. ``pace_hz`` plays recorded
    video at that rate on absolute deadlines (a camera paces itself); ``stop`` ends the loop
    between frames. A failing sender is logged and counted, never fatal: the link may come
    back."""
    stats = StreamStats()
    period_ns = int(_NS / pace_hz) if pace_hz else 0
    next_due = time.monotonic_ns()
    for frame in frames:
        if stop is not None and stop.is_set():
            break
        if period_ns:
            delay_s = (next_due - time.monotonic_ns()) / _NS
            if delay_s > 0 and stop is not None:
                if stop.wait(delay_s):
                    break
            elif delay_s > 0:
                time.sleep(delay_s)
            next_due += period_ns
            frame_ns = time.time_ns()
        else:
            frame_ns = frame.time_ns
        est = estimate(frame.image)
        stats.frames += 1
        stats.found += int(est.found)
        for send in senders:
            try:
                send(est, frame_ns)
            except (OSError, ValueError) as exc:
                stats.send_errors += 1
                log.warning("horizon stream: sending frame %s failed: %s", frame.label, exc)
        if on_estimate is not None:
            on_estimate(frame, est)
    return stats
