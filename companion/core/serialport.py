"""Opening a serial port, the one way the device drivers and the telemetry radio do it.

`serial.serial_for_url` accepts a device path, a pseudo-terminal and pyserial's URLs
(`loop://`, `socket://`, `rfc2217://`), so hardware, SITL and tests share the code. The write
timeout is bounded so a device that stops reading (a full USB buffer, a closed pseudo-terminal)
cannot block a thread forever; `exclusive` is left to the platform default, because a
pseudo-terminal cannot be locked.
"""

from __future__ import annotations

import serial

__all__ = ["WRITE_TIMEOUT_S", "OPEN_ERRORS", "open_serial_port"]

WRITE_TIMEOUT_S = 0.5
OPEN_ERRORS = (serial.SerialException, OSError, ValueError)
"""What a failed open raises: a missing device, no permission, a malformed URL."""


def open_serial_port(url: str, baudrate: int, *, read_timeout_s: float | None,
                     write_timeout_s: float = WRITE_TIMEOUT_S) -> serial.SerialBase:
    """An open port; raises one of OPEN_ERRORS. `read_timeout_s` None blocks until data come."""
    return serial.serial_for_url(url, baudrate=baudrate, timeout=read_timeout_s,
                                 write_timeout=write_timeout_s, exclusive=None)
