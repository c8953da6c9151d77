"""The service manager's notification protocol (systemd's sd_notify), spoken by the runtime.

Under systemd with ``Type=notify`` the unit's process gets ``NOTIFY_SOCKET`` (a Unix datagram
socket, ``@`` for the abstract namespace) and, with ``WatchdogSec=``, ``WATCHDOG_USEC``. The
runtime tells it ``READY=1`` once every thread is flying, pings ``WATCHDOG=1`` from the
manager's own loop (so a hung manager, not a hung thread, gets the process killed and restarted:
threads are the manager's to restart), keeps a one-line ``STATUS=`` current, and says
``STOPPING=1`` when it shuts down.

The protocol is a few datagrams of ``KEY=VALUE`` lines; it is written here rather than taken
from a package because the Python bindings of libsystemd need its headers to build and the
pure-Python ones are unmaintained, and a missing or broken socket must never stop a flight.
Without ``NOTIFY_SOCKET`` (a shell, SITL, a test) every call does nothing.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger(__name__)

__all__ = ["Notifier", "supervised_by_service_manager"]


def supervised_by_service_manager(env: Mapping[str, str] | None = None) -> bool:
    """Whether a service manager will restart this process when it exits with an error.

    ``NOTIFY_SOCKET`` is what a ``Type=notify`` unit (the one `companion install` writes) gives
    its process. ``INVOCATION_ID`` is not taken as a sign: every process started from any
    service inherits it (a shell in a CI runner's unit), and escalating there would end a
    flight that nobody restarts."""
    e = os.environ if env is None else env
    return bool(e.get("NOTIFY_SOCKET"))


class Notifier:
    """Sends notifications to ``NOTIFY_SOCKET``; every method is a no-op without one."""

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        e = os.environ if env is None else env
        path = e.get("NOTIFY_SOCKET", "")
        self._address: str | bytes | None = None
        if path.startswith("@"):
            self._address = b"\0" + path[1:].encode()
        elif path.startswith("/"):
            self._address = path
        elif path:
            log.warning("NOTIFY_SOCKET=%r is neither a path nor an abstract name; ignored", path)
        self.watchdog_interval_s: float | None = None
        """Half the service manager's watchdog timeout (systemd's advice), None without one."""
        usec = e.get("WATCHDOG_USEC", "")
        pid = e.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            self.watchdog_interval_s = int(usec) / 1e6 / 2
        self._sock: socket.socket | None = None
        self._errors = 0
        self.ready_sent = False
        self._last_status = ""

    @property
    def enabled(self) -> bool:
        return self._address is not None

    def _send(self, text: str) -> bool:
        if self._address is None:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                self._sock.setblocking(False)  # the manager's loop must never wait on it
            self._sock.sendto(text.encode("utf-8", "replace"), self._address)
            return True
        except OSError as exc:
            self._errors += 1
            if self._errors in (1, 100):
                log.warning("service manager notification failed: %s", exc)
            return False

    def ready(self, status: str = "") -> None:
        """READY=1, once: the service is up (systemd ends its start-up wait)."""
        if self.ready_sent:
            return
        self.ready_sent = True
        self._last_status = status
        self._send("READY=1\n" + (f"STATUS={_one_line(status)}\n" if status else ""))

    def status(self, text: str) -> None:
        """STATUS=..., sent only when it changed (``systemctl status`` shows the last one)."""
        line = _one_line(text)
        if line != self._last_status:
            self._last_status = line
            self._send(f"STATUS={line}\n")

    def watchdog(self) -> None:
        self._send("WATCHDOG=1\n")

    def stopping(self, status: str = "", *, extend_s: float = 45.0) -> None:
        """STOPPING=1, with time to finish: closing the logs on a slow disk may take up to
        30 s (`LogService.close`), which the unit's watchdog and stop timeout must allow."""
        usec = int(extend_s * 1e6)
        self._send("STOPPING=1\nWATCHDOG=1\n"
                   f"EXTEND_TIMEOUT_USEC={usec}\n"
                   + (f"STATUS={_one_line(status)}\n" if status else ""))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def _one_line(text: str) -> str:
    return " ".join(text.split())[:400]
