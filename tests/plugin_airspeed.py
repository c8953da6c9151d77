"""A device a user adds to the aircraft, in one module: an airspeed sensor on a serial port.

Everything the device needs is here (its wire format, its driver thread, its simulator) and
one row (`ROW`) puts it on the vehicle: `VEHICLE.with_rows([ROW])`. Nothing else in the
project changes. `tests/test_vehicle.py` flies it in lockstep.

Wire format (invented for the test, shaped like NMEA): ``$ASPD,<airspeed m/s, 2 decimals>*HH``
and CR LF, where HH is the XOR of the bytes between ``$`` and ``*``; ten lines a second.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.core.config import DeviceConfig
from companion.drivers.serial_device import SerialDevice
from companion.vehicle import Row
from companion.watchdog.task import Task

FMT_AIRSPEED = 1
FMT_RAW = 2
NOISE_M_S = 0.1


def encode(airspeed_m_s: float) -> bytes:
    body = f"ASPD,{airspeed_m_s:.2f}".encode("ascii")
    check = 0
    for b in body:
        check ^= b
    return b"$" + body + b"*%02X\r\n" % check


@dataclass(frozen=True)
class AirspeedSample:
    t_ns: int
    airspeed_m_s: float


class AirspeedDriver(SerialDevice):
    """Decodes the lines; each good one is a sample (a cycle) in the ``airspeed`` slot."""

    raw_format = FMT_RAW

    def __init__(self, url: str, baudrate: int = 115200, *, task: Task) -> None:
        super().__init__(task, url=url, baudrate=baudrate)
        self._buf = b""
        self.bad_lines = 0

    def define_logs(self, tlog: Any) -> None:
        tlog.define(FMT_AIRSPEED, "%.2f", ["airspeed_m_s"])
        super().define_logs(tlog)

    def decode(self, data: bytes | None, t_ns: int) -> Iterable[object]:
        if not data:
            return []
        self._buf += data
        *lines, self._buf = self._buf.split(b"\r\n")
        out = []
        for line in lines:
            try:
                value = float(line[6:-3])
                ok = line.startswith(b"$ASPD,") and encode(value) == line + b"\r\n"
            except ValueError:
                ok = False
            if ok:
                out.append(value)
            else:
                self.bad_lines += 1
        return out

    def publish(self, item: object, t_ns: int) -> int:
        assert isinstance(item, float)
        self.ctx.state.slot("airspeed").write(AirspeedSample(t_ns, item))
        if self.tlog is not None:
            self.tlog.log(FMT_AIRSPEED, item, t_ns=t_ns)
        return 1

    def counters(self) -> dict[str, int]:
        return {**super().counters(), "bad_lines": self.bad_lines}


class AirspeedSim:
    """The sensor in SITL: the true airspeed plus white noise, a line every 100 ms."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.next_s = 0.1

    def tick(self, t_s: float, truth: Any) -> bytes:
        if t_s + 1e-9 < self.next_s:
            return b""
        self.next_s += 0.1
        return encode(truth.airspeed_m_s + float(self.rng.normal(0.0, NOISE_M_S)))


ROW = Row(Task("airspeed", paced_by="airspeed lines (10 Hz)", budget_ms=2.0, watchdog_ms=1000,
               implementation="plugin_airspeed:AirspeedDriver", publishes=("airspeed",)),
          "ASCII airspeed lines, 10 a second", device=DeviceConfig(port="/dev/ttyS3"),
          simulator="plugin_airspeed:AirspeedSim")
