"""Watchdog events: what the manager tells the logs, the console and the ground stations."""

from __future__ import annotations

import enum
import time
from dataclasses import dataclass, field


class EventKind(enum.Enum):
    STARTED = "started"
    STALL = "stall"  # alive flag not set within the watchdog period
    SILENT = "silent"  # the worker loops but its device sends nothing
    RECOVERED = "recovered"  # data again after a silence
    CRASH = "crash"  # step/prologue raised
    EXITED = "exited"  # left its periodic section on its own
    STOPPED = "stopped"  # stopped cooperatively within the shutdown timeout
    INTERRUPTED = "interrupted"  # needed an asynchronous exception to stop
    ABANDONED = "abandoned"  # stuck in C: left behind and replaced
    RESTARTED = "restarted"
    FAILED = "failed"  # restart intensity exceeded: given up, the others keep running
    DISABLED = "disabled"
    ENABLED = "enabled"
    RESUMED = "resumed"  # the whole process was suspended (SIGSTOP, a VM pause): windows restart
    LOG_OFF = "logging off"  # a thread's log could not be written (disk full): the thread flies on
    NOTICE = "notice"  # a thread saw something wrong in its input and coped (a device flooding)
    ESCALATED = "escalated"  # a failed thread takes the process down for its service manager


# MAVLink MAV_SEVERITY values, so bridges need no table of their own.
SEVERITY = {
    EventKind.STARTED: 6,
    EventKind.STALL: 4,
    EventKind.SILENT: 4,
    EventKind.RECOVERED: 5,
    EventKind.CRASH: 3,
    EventKind.EXITED: 5,
    EventKind.STOPPED: 6,
    EventKind.INTERRUPTED: 4,
    EventKind.ABANDONED: 3,
    EventKind.RESTARTED: 5,
    EventKind.FAILED: 2,
    EventKind.DISABLED: 5,
    EventKind.ENABLED: 5,
    EventKind.RESUMED: 4,
    EventKind.LOG_OFF: 3,
    EventKind.NOTICE: 4,
    EventKind.ESCALATED: 1,
}


@dataclass(frozen=True)
class WatchdogEvent:
    kind: EventKind
    thread: str
    detail: str = ""
    t_ns: int = field(default_factory=time.time_ns)

    @property
    def severity(self) -> int:
        return SEVERITY[self.kind]

    def text(self) -> str:
        """One line short enough (<= 50 chars where possible) for a MAVLink STATUSTEXT."""
        return f"{self.thread}: {self.kind.value}" + (f" ({self.detail})" if self.detail else "")
