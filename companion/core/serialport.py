"""Opening a serial port, the one way the device drivers and the telemetry radio do it.

`serial.serial_for_url` accepts a device path, a pseudo-terminal and pyserial's URLs
(`loop://`, `socket://`, `rfc2217://`), so hardware, SITL and tests share the code. The write
timeout is bounded so a device that stops reading (a full USB buffer, a closed pseudo-terminal)
cannot block a thread forever; `exclusive` is left to the platform default, because a
pseudo-terminal cannot be locked.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import serial

__all__ = ["WRITE_TIMEOUT_S", "OPEN_ERRORS", "open_serial_port", "register_url_scheme"]

PortOpener = Callable[[str, "float | None"], Any]
"""(url, read timeout in clock seconds) -> an open port with pyserial's read, write,
in_waiting, close and cancel_read."""
_OPENERS: dict[str, PortOpener] = {}

WRITE_TIMEOUT_S = 0.5
OPEN_ERRORS = (serial.SerialException, OSError, ValueError)
"""What a failed open raises: a missing device, no permission, a malformed URL."""


def open_serial_port(url: str, baudrate: int, *, read_timeout_s: float | None,
                     write_timeout_s: float = WRITE_TIMEOUT_S) -> serial.SerialBase:
    """An open port; raises one of OPEN_ERRORS. `read_timeout_s` None blocks until data come."""
    scheme, sep, _ = url.partition("://")
    opener = _OPENERS.get(scheme) if sep else None
    if opener is not None:
        return opener(url, read_timeout_s)  # type: ignore[no-any-return]
    return serial.serial_for_url(url, baudrate=baudrate, timeout=read_timeout_s,
                                 write_timeout=write_timeout_s, exclusive=None)


def register_url_scheme(scheme: str, opener: PortOpener | None) -> None:
    """Serve `scheme://...` URLs with `opener` (None removes it): how a lockstep flight puts
    its in-process device ports behind the drivers' usual way of opening a port."""
    if opener is None:
        _OPENERS.pop(scheme, None)
    else:
        _OPENERS[scheme] = opener
