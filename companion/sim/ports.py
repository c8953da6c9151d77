"""The simulated world's device ports: which devices it serves and the pseudo-terminal of each.

Its own module because two parts name the devices without flying anything: the fault catalogue
(`companion.sim.faults`: the devices a fault may name) and the world (`companion.sim.world`:
the ports it writes to). A lockstep flight replaces the pseudo-terminals with in-process ports
of the same interface (`companion.sim.lockstep.DevicePort`).

Device paths are stable symlinks (`<device dir>/imu` ...) to the current pseudo-terminal, as
udev's /dev/serial/by-id links are to a USB adapter's ttyUSBn: a port can vanish and come back
(a fault the drivers must survive), also under another kernel name, and the stable name follows.
"""

from __future__ import annotations

import os
import tty
from pathlib import Path

__all__ = ["DEVICES", "Pty"]

DEVICES = ("imu", "gps", "servo")
"""The thesis aircraft's devices, which the world simulates itself (their timing is the
world's); a device added later brings its simulator in its row of the vehicle's table
(`companion.sim.plugins`)."""


class Pty:
    """One pseudo-terminal pair whose slave path is published through a stable symlink."""

    def __init__(self, link: Path) -> None:
        self.link = link
        self.master = -1
        self.slave = -1
        self.dropped_bytes = 0
        self.name = ""
        self.open()

    def open(self, avoid_name: str | None = None) -> None:
        master, slave = os.openpty()
        held: list[int] = []
        while avoid_name is not None and os.ttyname(slave) == avoid_name and len(held) < 8:
            held += [master, slave]  # keep the old number taken until we have another one
            master, slave = os.openpty()
        for fd in held:
            os.close(fd)
        self.name = os.ttyname(slave)
        tty.setraw(slave)  # no echo, no line discipline: bytes pass unchanged
        os.set_blocking(master, False)
        self.master, self.slave = master, slave
        tmp = self.link.with_suffix(".tmp")
        try:
            tmp.unlink()
        except FileNotFoundError:
            pass
        tmp.symlink_to(self.name)
        os.replace(tmp, self.link)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = -1
        try:
            self.link.unlink()
        except FileNotFoundError:
            pass

    def write(self, data: bytes) -> None:
        if self.master < 0 or not data:
            return
        try:
            n = os.write(self.master, data)
        except BlockingIOError:
            n = 0
        except OSError:
            n = 0
        self.dropped_bytes += len(data) - n  # a reader that does not keep up loses bytes, as on a UART
