"""Managed threads and the thread manager (software watchdog) of the on-board runtime."""

from __future__ import annotations

from companion.watchdog.events import EventKind, WatchdogEvent
from companion.watchdog.manager import ManagerCommand, ManagerStatus, ThreadManager
from companion.watchdog.task import Task
from companion.watchdog.thread import (
    ManagedThread,
    RestartType,
    RuntimeContext,
    ThreadInterrupted,
    ThreadStatus,
)

__all__ = [
    "EventKind",
    "ManagedThread",
    "ManagerCommand",
    "ManagerStatus",
    "RestartType",
    "RuntimeContext",
    "Task",
    "ThreadInterrupted",
    "ThreadManager",
    "ThreadStatus",
    "WatchdogEvent",
]
