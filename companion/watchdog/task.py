"""A task: one row of a task table, everything the supervisor needs to know about a thread.

ArduPilot lists its scheduler's tasks in one table (`scheduler_tasks[]`) so that rates and budgets
are read in one place instead of inside each function. Here a row holds the same facts for a
managed thread: its name and id, what paces it, its time budget, its watchdog and message periods,
its OTP restart type, how long it may take to stop, and the prefix of its parameters. A thread
class supplies behaviour; the row supplies the numbers. The vehicle's rows are in
`companion.vehicle` (the runtime hands each thread it builds its row); a bridge declares its own rows next to its threads and adds them through
`ThreadManager.add`, which hands out the ids.

The row also names the class that implements it, so its parameters' metadata (descriptions,
units, ranges, defaults) can be read without building a thread, a manager or a runtime.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from companion.core.lazy import load
from companion.core.params import ParamSpec, int_param

if TYPE_CHECKING:
    from companion.core.config import DeviceConfig

__all__ = ["RestartType", "Task", "ThreadClass"]

PREFIX_MAX = 6
"""Parameter ids are at most 16 characters (MAVLink); a 6-letter prefix leaves 9 for the rest."""


class RestartType(enum.Enum):
    """OTP restart types: which terminations of a child lead to a restart."""

    PERMANENT = "permanent"  # always restarted, even after a normal exit
    TRANSIENT = "transient"  # restarted after a crash or a stall, not after a normal exit
    TEMPORARY = "temporary"  # never restarted


class ThreadClass(Protocol):
    """What a row asks of the class it names (a `ManagedThread` subclass), without this module
    importing the thread module that imports it."""

    def declare_params(self, prefix: str) -> list[ParamSpec]: ...

    def from_row(self, task: Task, settings: DeviceConfig | None) -> Any: ...


@dataclass(frozen=True)
class Task:
    """One supervised thread's row. Times are in the flight's clock unless a field says host."""

    name: str
    thread_id: int = 0
    """0: the manager hands out the lowest free id from its first assignable one."""
    period_ms: float | None = None
    """Timer-driven at this period on absolute deadlines; None: paced by `step` itself."""
    paced_by: str = ""
    """What paces a thread without a period (a device's frames, a data slot), for people."""
    budget_ms: float | None = None
    """A step longer than this is an overrun; None: the period, or 10 ms without one."""
    watchdog_ms: int = 500
    """Default of `<PREFIX>_WDG_MS`: a stall is declared when no cycle completes within it."""
    message_ms: int = 1000
    """Default of `<PREFIX>_MSG_MS`: the period of the thread's data messages to the ground."""
    restart: RestartType = RestartType.TRANSIENT
    max_catch_up: int = 0
    """Timer threads: whole lost periods run back to back before lost cycles are dropped."""
    shutdown_timeout_ms: int | None = None
    """Host ms the thread may take to stop; None: the manager's MGR_SHUTDOWN_MS."""
    param_prefix: str = ""
    """Prefix of the thread's parameters; empty: the name, upper case, cut to 6 letters."""
    implementation: str = ""
    """``module:Class`` of the thread, so its parameters can be listed without building it."""
    escalate: bool = False
    """True: when this thread fails (restart intensity exceeded), the runtime stops and exits
    with EXIT_ESCALATED so that its service manager restarts the whole process, as an OTP
    supervisor escalates to its parent (see MGR_ESCALATE). For the vehicle's own threads; never
    for a thread that the network feeds, or network input could restart the aircraft."""
    publishes: tuple[str, ...] = ()
    """The `VehicleState` slots the thread writes (``imu``, ``gps``, ``servo``...): how a bridge
    knows what a thread stands for (the MAVLink health bits of SYS_STATUS) without a list of
    thread ids of its own."""
    switchable: bool = True
    """False: `<PREFIX>_ENABLE` is read-only. For the threads that carry a ground link: a ground
    station (or anyone on an unsigned link) that switched them off would leave the aircraft
    deaf to every ground station, with no way back but the configuration."""

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("a task needs a name")
        prefix = (self.param_prefix or self.name).upper()[:PREFIX_MAX]
        object.__setattr__(self, "param_prefix", prefix)
        if self.period_ms is not None and self.period_ms <= 0:
            raise ValueError(f"task {self.name}: period_ms must be positive, not {self.period_ms}")

    @property
    def effective_budget_ms(self) -> float:
        if self.budget_ms is not None:
            return self.budget_ms
        return self.period_ms or 10.0

    def replace(self, **changes: Any) -> Task:
        """This row with some fields changed (a second instance of a thread class, a test)."""
        if "name" in changes and "param_prefix" not in changes:
            # a renamed row derives its prefix from the new name, unless one is given
            changes["param_prefix"] = ""
        return dataclasses.replace(self, **changes)

    def base_params(self) -> list[ParamSpec]:
        """The parameters every managed thread has: watchdog and message periods, enable."""
        p = self.param_prefix
        return [
            int_param(f"{p}_WDG_MS", self.watchdog_ms, 10, 600_000, "ms",
                      f"Watchdog period of the {self.name} thread: a stall is declared when no "
                      "periodic cycle completes within it."),
            int_param(f"{p}_MSG_MS", self.message_ms, 10, 3_600_000, "ms",
                      f"Period of the {self.name} thread's data messages to the ground."),
            int_param(f"{p}_ENABLE", 1, 0, 1, "",
                      f"1 runs the {self.name} thread, 0 stops it cleanly." if self.switchable
                      else f"1: the {self.name} thread runs. Read-only: it carries a ground link, "
                      "which is switched off in the configuration, not from the ground.",
                      read_only=not self.switchable),
        ]

    def thread_class(self) -> ThreadClass:
        """The implementing class, imported on demand (the table itself imports nothing)."""
        if not self.implementation:
            raise LookupError(f"task {self.name} names no implementing class")
        try:
            cls: ThreadClass = load(self.implementation)
        except LookupError as exc:
            raise LookupError(f"task {self.name}: {exc}") from exc
        return cls

    def param_specs(self) -> list[ParamSpec]:
        """Every parameter this task's thread declares, read from the class, not an instance."""
        own = self.thread_class().declare_params(self.param_prefix) if self.implementation else []
        return self.base_params() + own
