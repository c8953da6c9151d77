"""Every serial device the aircraft knows, one row each, imported only when used.

A new device is one driver module and one row here (as python-can's interface table): the
runtime builds a driver for each enabled row of the configuration's ``[devices.<name>]``, and the
driver replay tool, its CLI and the flight report take their device names from the same table.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from companion.drivers.serial_device import SerialDevice

__all__ = ["DEVICES", "Device", "make_driver"]


@dataclass(frozen=True)
class Device:
    name: str
    """The device's one name: its `[devices.<name>]` configuration table, its thread, its log
    (`<name>.bin`) and its word on the command line."""
    module: str
    driver: str
    """The `SerialDevice` subclass in `module` that reads, decodes and publishes it."""
    summary: str

    def driver_class(self) -> Callable[[str, int], SerialDevice]:
        """The driver's class, called as ``cls(url, baudrate)`` like every device driver."""
        cls: Callable[[str, int], SerialDevice] = getattr(importlib.import_module(self.module),
                                                          self.driver)
        return cls


DEVICES: dict[str, Device] = {d.name: d for d in (
    Device("imu", "companion.drivers.imu", "ImuDriver",
           "20-byte binary frames at 100 Hz and a slow block once a second"),
    Device("gps", "companion.drivers.gps", "GpsDriver",
           "NMEA 0183 and Ashtech $PASHR,POS sentences, 10 epochs a second"),
    Device("servo", "companion.drivers.servo", "ServoDriver",
           "command and pilot frames exchanged every 20 ms"),
)}


def make_driver(name: str, url: str, baudrate: int = 115200) -> SerialDevice:
    """The driver of device `name` on `url` (a device path, a pseudo-terminal or a pyserial URL)."""
    try:
        device = DEVICES[name]
    except KeyError:
        raise ValueError(f"unknown device {name!r} (known: {', '.join(DEVICES)})") from None
    return device.driver_class()(url, baudrate)
