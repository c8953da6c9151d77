"""The vehicle's task table: one row per flight thread, in start order.

Read it as ArduPilot's `scheduler_tasks[]`: what runs, how often or on what, within which budget,
how the watchdog treats it and how long it may take to stop. The thread classes hold no such
numbers; a bridge adds its own rows (the MAVLink links, the legacy protocol, the live view) and
the manager hands those their ids. Ids 1..5 are fixed: the legacy protocol's data messages name
the vehicle's data sources by them.

The table imports no thread class (each row names its class as ``module:Class``), so reading it
costs nothing and the drivers can take their rows from it.
"""

from __future__ import annotations

from companion.watchdog.task import RestartType, Task

__all__ = ["VEHICLE_TASKS", "task"]

VEHICLE_TASKS: dict[str, Task] = {t.name: t for t in (
    Task("imu", thread_id=1, paced_by="IMU frames (100 Hz)", budget_ms=2.0,
         watchdog_ms=500, message_ms=1000, restart=RestartType.TRANSIENT,
         escalate=True, implementation="companion.drivers.imu:ImuDriver"),
    Task("gps", thread_id=2, paced_by="GPS epochs (10 Hz)", budget_ms=5.0,
         watchdog_ms=1000, message_ms=1000, restart=RestartType.TRANSIENT,
         escalate=True, implementation="companion.drivers.gps:GpsDriver"),
    # A lost exchange is a lost command: catch up to three periods after a hiccup.
    Task("servo", thread_id=3, period_ms=20.0, budget_ms=15.0, max_catch_up=3,
         watchdog_ms=500, message_ms=1000, restart=RestartType.TRANSIENT,
         escalate=True, implementation="companion.drivers.servo:ServoDriver"),
    Task("estimator", thread_id=4, paced_by="IMU samples (imu_stream)", budget_ms=3.0,
         watchdog_ms=1000, message_ms=1000, param_prefix="EST", restart=RestartType.TRANSIENT,
         escalate=True, implementation="companion.estimation.thread:EstimatorThread"),
    Task("control", thread_id=5, paced_by="estimates (state.estimator)", budget_ms=2.0,
         watchdog_ms=1000, message_ms=1000, param_prefix="CTL", restart=RestartType.TRANSIENT,
         escalate=True, implementation="companion.control:ControlThread"),
)}


def task(name: str) -> Task:
    """The vehicle's row `name`; a KeyError names the rows that exist."""
    try:
        return VEHICLE_TASKS[name]
    except KeyError:
        raise KeyError(f"no task {name!r} (tasks: {', '.join(VEHICLE_TASKS)})") from None
