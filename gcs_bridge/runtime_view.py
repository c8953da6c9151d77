"""The runtime as every part of the bridge sees it: context, manager, vehicle ids, time.

`BridgeCore` is read by the receive and send threads of every link; it holds no per-link
state and nothing in it changes after construction except through the runtime's own
thread-safe objects (parameter registry, slots, manager). What each thread stands for comes
from its row (`Task.publishes`), not from ids kept here.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol

from companion.watchdog import RuntimeContext, ThreadManager
from gcs_bridge.dialect import COMPONENT_ID, Identity, clamp_int


class AutopilotIds(Protocol):
    """Who the autopilot said it is (`gcs_bridge.autopilot.link.AutopilotIdentity`)."""

    @property
    def system(self) -> int: ...

    @property
    def component(self) -> int: ...

    @property
    def firmware(self) -> str: ...


class AutopilotSide(Protocol):
    """The link to the flight controller as the bridge sees it (`AutopilotLink`): None until
    its first HEARTBEAT."""

    @property
    def identity(self) -> AutopilotIds | None: ...


@dataclass
class BridgeCore:
    ctx: RuntimeContext
    manager: ThreadManager
    compid: int = COMPONENT_ID
    autopilot: AutopilotSide | None = None
    """The flight controller's link when there is one: the bridge is then its companion."""
    boot_real_ns: int = 0
    boot_mono_ns: int = 0
    _cpu: tuple[float, float] = field(default=(0.0, 0.0))

    def __post_init__(self) -> None:
        self.boot_real_ns = self.ctx.clock.realtime_ns()
        self.boot_mono_ns = self.ctx.clock.monotonic_ns()
        self._cpu = (time.process_time(), time.monotonic())

    @property
    def beside_autopilot(self) -> bool:
        return self.autopilot is not None

    @property
    def sysid(self) -> int:
        """The vehicle's system id: the autopilot's once it is known, else the configured one."""
        ap = self.autopilot
        if ap is not None:
            ident = ap.identity
            if ident is not None:
                return int(ident.system)
        return int(self.ctx.vehicle_id)

    def encoding(self, claim: Identity) -> Identity:
        """The identity whose integer encoding a link claiming `claim` uses: its own, beside an
        autopilot too. QGroundControl decodes each component's integers by that component's
        own HEARTBEAT (C cast only for one that says ArduPilot), and the companion's says
        MAV_AUTOPILOT_INVALID and advertises bytewise; a link whose client takes the C cast
        for a whole ArduPilot system (MAVProxy) says ``?identity=ardupilot``
        (docs/ground-stations.md)."""
        return claim

    def now_real_ns(self) -> int:
        return self.ctx.clock.realtime_ns()

    def time_boot_ms(self, real_ns: int | None = None) -> int:
        """Milliseconds since the bridge started (MAVLink's "boot"), wrapped to uint32."""
        t = self.now_real_ns() if real_ns is None else real_ns
        return max(0, (t - self.boot_real_ns) // 1_000_000) & 0xFFFFFFFF

    def time_usec(self, real_ns: int | None = None) -> int:
        """Unix time in microseconds (MAVLink accepts epoch time in time_usec fields)."""
        t = self.now_real_ns() if real_ns is None else real_ns
        return max(0, t // 1000)

    def thread_message_ms(self, thread_id: int) -> int | None:
        """The message period of a runtime thread, None when the thread does not exist."""
        t = self.manager.find(thread_id)
        if t is None:
            return None
        try:
            return int(t.message_ms)
        except Exception:  # a thread whose parameters are not declared yet
            return None

    def cpu_load_permille(self) -> int:
        """Process CPU use since the last call, in tenths of a percent of one core."""
        cpu, wall = time.process_time(), time.monotonic()
        cpu0, wall0 = self._cpu
        self._cpu = (cpu, wall)
        if wall - wall0 <= 0:
            return 0
        return clamp_int(1000.0 * (cpu - cpu0) / (wall - wall0), 0, 1000, 0)
