"""The runtime under a service manager: what it tells systemd, and when.

`companion.core.sdnotify` speaks the protocol; this module decides the messages from the thread
manager's state, once per manager wake-up, in the main thread:

- ``READY=1`` once every enabled thread has reached its periodic section (or failed), or after
  MGR_READY_S with the threads still starting named in STATUS: an aircraft whose IMU is not
  plugged in stays up and tells its ground station so, instead of being killed at systemd's
  start timeout and restarted until the start limit gives up on it;
- ``WATCHDOG=1`` every half of ``WatchdogSec``, from the manager's loop itself: only a live
  manager pings, so a hung manager gets the process killed and restarted, while a hung thread
  is the manager's to restart;
- ``STATUS=`` a one-line health summary, at most once a second and only when it changes;
- ``STOPPING=1`` with the stop reason when the runtime shuts down.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

from companion.core.sdnotify import Notifier, supervised_by_service_manager
from companion.watchdog import ThreadManager

__all__ = ["ServiceNotifications", "health_line"]

STATUS_PERIOD_S = 1.0


def health_line(manager: ThreadManager) -> str:
    """One line for ``systemctl status``: how many threads fly, what is wrong, restarts."""
    statuses = manager.thread_status()
    enabled = [s for s in statuses if s.enabled]
    failed = [s.name for s in enabled if s.failed]
    starting = [s.name for s in enabled if not s.failed and not s.in_periodic]
    silent = set(manager.silent_threads())
    quiet = [s.name for s in enabled if s.name in silent]
    restarts = sum(s.restarts for s in statuses)
    flying = len(enabled) - len(failed) - len(starting) - len(quiet)
    parts = [f"{flying}/{len(enabled)} threads ok"]
    if failed:
        parts.append("failed: " + ", ".join(failed))
    if starting:
        parts.append("starting: " + ", ".join(starting))
    if quiet:
        parts.append("silent: " + ", ".join(quiet))
    parts.append(f"{restarts} restart{'s' if restarts != 1 else ''}")
    state = "degraded" if failed or quiet else "starting" if starting else "flying"
    return f"{state}: " + "; ".join(parts)


class ServiceNotifications:
    """Attach to a manager: `tick` on every wake-up, `stopping` at shutdown."""

    def __init__(self, manager: ThreadManager, env: Mapping[str, str] | None = None) -> None:
        self.manager = manager
        self.notifier = Notifier(env)
        manager.supervised = supervised_by_service_manager(env)
        self._next_watchdog = 0.0
        self._next_status = 0.0
        self._started_at = time.monotonic()

    def tick(self) -> None:
        n = self.notifier
        if not n.enabled:
            return
        now = time.monotonic()
        interval = n.watchdog_interval_s
        if interval is not None and now >= self._next_watchdog:
            n.watchdog()
            self._next_watchdog = now + interval
        if not n.ready_sent:
            statuses = [s for s in self.manager.thread_status() if s.enabled]
            waited_s = now - self._started_at
            if (all(s.in_periodic or s.failed for s in statuses)
                    or waited_s >= float(self.manager.ctx.params.get("MGR_READY_S"))):
                n.ready(health_line(self.manager))
                self._next_status = now + STATUS_PERIOD_S
                return
        if now >= self._next_status:
            self._next_status = now + STATUS_PERIOD_S
            n.status(health_line(self.manager))

    def stopping(self, reason: str) -> None:
        if self.notifier.enabled:
            self.notifier.stopping(f"stopping ({reason}); {health_line(self.manager)}")
        self.notifier.close()
