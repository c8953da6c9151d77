"""A synthetic vehicle for testing and benchmarking the bridge without devices or a simulator.

Four managed threads with the runtime's thread ids publish plausible data into the vehicle
state slots at the real devices' rates (IMU 100 Hz, GPS 10 Hz, servo board 50 Hz, estimator
100 Hz) for an aircraft flying a steady banked circle; `SyntheticVehicle` runs them with a
`MavlinkBridge` under a real `ThreadManager` in a background thread, so tests talk to it with
real ground-station clients over loopback.

Test support, not product: it lives in tests/support/ (see that package's docstring) so the
wheel does not ship it, and both tests/ and bench/ import it as `support.synthetic_vehicle`.
"""

from __future__ import annotations

import math
import select
import socket
import threading
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

from companion.core.clock import Clock
from companion.core.params import ParamRegistry, ParamSpec
from companion.core.state import EstimatorState, GpsFix, ImuSample, ImuSlowSample, ServoState
from companion.vehicle import VEHICLE
from companion.watchdog import ManagedThread, RuntimeContext, ThreadManager
from gcs_bridge.bridge import MavlinkBridge
from gcs_bridge.dialect import mavlink
from gcs_bridge.signing import signing_timestamp

ORIGIN = (43.7085, 10.4036, 12.0)  # lat, lon (deg), alt MSL (m)
SPEED_M_S = 20.0
RADIUS_M = 150.0
G0 = 9.80665


def circle_state(t_s: float) -> dict[str, Any]:
    """Position, velocity and attitude of a coordinated circle at time t_s (NED, SI)."""
    omega = SPEED_M_S / RADIUS_M
    a = omega * t_s
    n, e = RADIUS_M * math.sin(a), RADIUS_M * (1 - math.cos(a))
    vn, ve = SPEED_M_S * math.cos(a), SPEED_M_S * math.sin(a)
    yaw = math.atan2(ve, vn)
    roll = math.atan2(SPEED_M_S * omega, G0)
    return {"pos": (n, e, -100.0), "vel": (vn, ve, 0.0), "roll": roll, "pitch": 0.03,
            "yaw": yaw, "rate_z": omega}


def _quat(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


class SyntheticSource(ManagedThread):
    """Publishes one kind of synthetic data ("imu", "gps", "servo" or "estimator")."""

    RATES_HZ = {"imu": 100.0, "gps": 10.0, "servo": 50.0, "estimator": 100.0}

    def __init__(self, kind: str, *, extra_params: Sequence[ParamSpec] = ()) -> None:
        if kind not in self.RATES_HZ:
            raise ValueError(f"unknown synthetic source {kind!r}")
        # the vehicle's row (name, id, prefix) on a timer instead of a device
        super().__init__(VEHICLE[kind].task.replace(
            period_ms=1000.0 / self.RATES_HZ[kind], budget_ms=None, watchdog_ms=500,
            implementation=""))
        self.kind = kind
        self.extra_params = list(extra_params)
        self.counter = 0
        self.battery_raw = [98, 95]
        self.on_params_changed_calls = 0

    def param_specs(self) -> list[ParamSpec]:
        return super().param_specs() + list(self.extra_params)

    def on_params_changed(self) -> None:
        self.on_params_changed_calls += 1

    def step(self) -> bool:
        clock = self.ctx.clock
        t_ns = clock.realtime_ns()
        t_s = (clock.monotonic_ns() % 10**15) / 1e9
        s = circle_state(t_s)
        state = self.ctx.state
        self.counter += 1
        if self.kind == "imu":
            state.imu.write(ImuSample(t_ns, self.counter, (0.0, 0.0, s["rate_z"]),
                                      (0.0, 0.0, -G0 / math.cos(s["roll"]))))
            if self.counter % 100 == 1:
                state.imu_slow.write(ImuSlowSample(t_ns, (0.0, 0.0, s["rate_z"]),
                                                   (0.0, 0.0, -G0), 31.5, 0))
        elif self.kind == "gps":
            lat0, lon0, alt0 = ORIGIN
            n, e, d = s["pos"]
            lat = lat0 + math.degrees(n / 6_378_137.0)
            lon = lon0 + math.degrees(e / (6_378_137.0 * math.cos(math.radians(lat0))))
            vn, ve, vd = s["vel"]
            state.gps.write(GpsFix(t_ns, (t_ns / 1e9) % 86400, lat, lon, alt0 - d, 1, 9,
                                   hdop=0.9, pdop=1.6, vdop=1.3, tdop=0.8,
                                   speed_m_s=math.hypot(vn, ve),
                                   course_deg=math.degrees(s["yaw"]) % 360, vn_m_s=vn,
                                   ve_m_s=ve, vd_m_s=vd, alt_std_m=2.5, h_std_m=1.5,
                                   latency_s=0.05))
        elif self.kind == "servo":
            pilot = (1500, 1480, 1600, 1500, 1100, 1500, 1500, 1500)
            computer = (1520, 1470, 1610, 1500, 0, 0, 0, 0)
            state.servo.write(ServoState(t_ns, self.counter & 0xFF, pilot, computer, False, False,
                                         False, self.battery_raw[0], self.battery_raw[1]))
        else:
            state.estimator.write(EstimatorState(
                t_ns, _quat(s["roll"], s["pitch"], s["yaw"]), s["roll"], s["pitch"], s["yaw"],
                s["pos"], s["vel"], (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), ORIGIN[0], ORIGIN[1],
                ORIGIN[2], rates_rad_s=(0.0, 0.0, s["rate_z"]), aligned=True))
        return True


class SyntheticVehicle:
    """A runtime with synthetic sources and a MAVLink bridge, run in a background thread.

    Use as a context manager; `stop()` ends the run (and is idempotent). `run_reason` is what
    `ThreadManager.run` returned (for example "reboot" after MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN).
    """

    def __init__(self, endpoints: Sequence[str], *, vehicle_id: int = 1,
                 kinds: Sequence[str] = ("imu", "gps", "servo", "estimator"),
                 extra_params: Sequence[ParamSpec] = (), params_file: Path | None = None,
                 flight_dir: Path | None = None, clock: Clock | None = None,
                 **bridge_kwargs: Any) -> None:
        self.ctx = RuntimeContext(clock=clock or Clock(), params=ParamRegistry(),
                                  vehicle_id=vehicle_id, flight_dir=flight_dir)
        self.sources = [SyntheticSource(k, extra_params=extra_params if i == 0 else ())
                        for i, k in enumerate(kinds)]
        self.manager = ThreadManager(self.ctx, list(self.sources))
        self.ctx.params.set("MGR_WDG_GRAN_MS", 10)
        self.bridge = MavlinkBridge(self.ctx, self.manager, list(endpoints), **bridge_kwargs)
        self.param_issues = (self.ctx.params.attach_file(params_file)
                             if params_file is not None else [])
        self.run_reason: str | None = None
        self._thread: threading.Thread | None = None
        self._stopped = False

    @property
    def params(self) -> ParamRegistry:
        return self.ctx.params

    def start(self) -> SyntheticVehicle:
        self.manager.start()
        self._thread = threading.Thread(target=self._run, name="synthetic-vehicle", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        self.run_reason = self.manager.run()

    def wait_stopped(self, timeout_s: float) -> bool:
        """Wait for the run to end by itself (a shutdown command); True if it did."""
        if self._thread is None:
            return True
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def stop(self) -> None:
        if self._stopped:
            return
        self._stopped = True
        self.manager.request_stop("test over")
        if self._thread is not None:
            self._thread.join(10.0)
        self.manager.shutdown()
        self.bridge.close()

    def __enter__(self) -> SyntheticVehicle:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()


class MiniGcs:
    """A minimal MAVLink 2 ground station over UDP for tests and benchmarks.

    `listen_port`: bind there (the bridge's `udpout:` sends to it). `connect`: send to that
    address first (the bridge's `udpin:`). Replies go to whoever spoke last, as with mavutil.
    `key`: sign everything sent (and `sign=False` to hold the key but send unsigned).
    """

    def __init__(self, *, listen_port: int = 0, connect: tuple[str, int] | None = None,
                 sysid: int = 255, compid: int = 190, key: bytes | None = None,
                 sign: bool = True) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", listen_port))
        self.dest = connect
        self.mav = mavlink.MAVLink(None, sysid, compid)
        self.mav.robust_parsing = True
        if key is not None and sign:
            self.mav.signing.secret_key = key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = 1
            self.mav.signing.timestamp = signing_timestamp(time.time_ns())
        self.pending: list[Any] = []
        self.history: deque[Any] = deque(maxlen=5000)  # everything received, consumed or not
        self.received = 0
        self.address_of: dict[int, Any] = {}  # system id -> where its frames came from

    @property
    def port(self) -> int:
        return int(self.sock.getsockname()[1])

    def send(self, msg: Any) -> bytes:
        frame = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) & 0xFF
        self.send_raw(frame)
        return frame

    def send_raw(self, data: bytes) -> None:
        if self.dest is None:
            raise RuntimeError("MiniGcs: no destination yet (nothing received)")
        self.sock.sendto(data, self.dest)

    def _pump(self, timeout_s: float) -> bool:
        r, _, _ = select.select([self.sock], [], [], max(0.0, timeout_s))
        if not r:
            return False
        data, addr = self.sock.recvfrom(65535)
        self.dest = addr
        for msg in self.mav.parse_buffer(data) or []:
            if msg.get_type() == "BAD_DATA":
                continue
            self.address_of[msg.get_srcSystem()] = addr
            self.received += 1
            self.history.append(msg)
            self.pending.append(msg)
        return True

    def seen(self, timeout_s: float, types: str | Sequence[str] | None = None,
             cond: Any = None) -> Any:
        """The first message ever received (consumed or not) that matches, waiting up to
        timeout_s for one: for things whose order relative to others is not defined."""
        wanted = {types} if isinstance(types, str) else set(types) if types else None
        deadline = time.monotonic() + timeout_s
        checked = 0
        while True:
            items = list(self.history)
            for msg in items[checked:] if checked <= len(items) else items:
                if (wanted is None or msg.get_type() in wanted) and (cond is None or cond(msg)):
                    return msg
            checked = len(items)
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            self._pump(remaining)

    def recv(self, timeout_s: float, types: str | Sequence[str] | None = None,
             cond: Any = None) -> Any:
        """The first pending or arriving message matching `types` and `cond`, else None."""
        wanted = {types} if isinstance(types, str) else set(types) if types else None
        deadline = time.monotonic() + timeout_s
        while True:
            for i, msg in enumerate(self.pending):
                if (wanted is None or msg.get_type() in wanted) and (cond is None or cond(msg)):
                    del self.pending[i]
                    return msg
            self.pending.clear()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            self._pump(remaining)

    def collect(self, duration_s: float) -> list[Any]:
        """Everything received during duration_s."""
        out = list(self.pending)
        self.pending.clear()
        deadline = time.monotonic() + duration_s
        while (remaining := deadline - time.monotonic()) > 0:
            self._pump(remaining)
            out += self.pending
            self.pending.clear()
        return out

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> MiniGcs:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
