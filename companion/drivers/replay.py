"""Feed a raw capture of a device's bytes through the real driver thread over a pseudo-terminal.

This is how a user checks a new receiver against the driver before it flies, and how tests run
recorded captures: the bytes go through the same port handling, decoder, counters and thread
lifecycle as in flight, not through a shortcut into the decoder.

A tool, not part of the flight: it builds a driver from the vehicle's table (the app layer), so
it sits in the tools layer of docs/architecture.md although it lives beside the drivers.
"""

from __future__ import annotations

import dataclasses
import os
import select
import threading
import time
import tty
from collections.abc import Callable
from typing import Any

from companion.core.clock import Clock
from companion.core.config import DeviceConfig
from companion.core.params import ParamRegistry
from companion.drivers.gps_solution import GpsSolution
from companion.drivers.imu_protocol import ImuFast, ImuSlow
from companion.drivers.serial_device import SerialDevice
from companion.drivers.servo_protocol import PilotFrame
from companion.vehicle import VEHICLE
from companion.watchdog import RuntimeContext, ThreadManager

KINDS = tuple(row.name for row in VEHICLE.devices() if row.replay)


def item_to_json(item: object) -> dict[str, Any]:
    if isinstance(item, GpsSolution):
        return item.to_json_dict()
    if isinstance(item, ImuFast):
        return {"type": "fast", "counter": item.counter, "status": item.status,
                "rates_rad_s": list(item.rates_rad_s), "accel_m_s2": list(item.accel_m_s2)}
    if isinstance(item, ImuSlow):
        return {"type": "slow", "rates_rad_s": list(item.rates_rad_s),
                "accel_m_s2": list(item.accel_m_s2), "temperature_c": item.temperature_c,
                "bit_word": item.bit_word}
    if isinstance(item, PilotFrame):
        return {"type": "pilot", "seq": item.seq, "auto_engaged": item.auto_engaged,
                "failsafe": item.failsafe, "channels_us": list(item.channels_us),
                "avionics_batt_raw": item.avionics_batt_raw, "servo_batt_raw": item.servo_batt_raw}
    if dataclasses.is_dataclass(item) and not isinstance(item, type):
        return dataclasses.asdict(item)
    return {"item": repr(item)}


def make_driver(kind: str, url: str) -> SerialDevice:
    """The driver of device `kind` (a row of the vehicle table) on `url`, set to replay."""
    if kind not in KINDS:
        raise ValueError(f"unknown device {kind!r} (known: {', '.join(KINDS)})")
    drv = VEHICLE[kind].build(DeviceConfig(port=url))
    assert isinstance(drv, SerialDevice)
    drv.prepare_for_replay()
    return drv


def replay(kind: str, data: bytes, on_item: Callable[[object], None],
           *, timeout_s: float = 600.0) -> dict[str, int]:
    """Play `data` into a pseudo-terminal read by the real `kind` driver; returns its counters."""
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    driver = make_driver(kind, path)
    driver.item_sink = on_item
    ctx = RuntimeContext(clock=Clock(), params=ParamRegistry())
    manager = ThreadManager(ctx, [driver])
    ctx.params.set("MGR_WDG_GRAN_MS", 10)
    # a replay has no real-time device behind it: silence is expected at the end, never a stall
    ctx.params.set(f"{driver.param_prefix}_WDG_MS", 600_000)
    written = threading.Event()
    stop_pump = threading.Event()

    def pump() -> None:
        view = memoryview(data)
        pos = 0
        while not stop_pump.is_set():
            want_write = pos < len(view)
            r, w, _ = select.select([master], [master] if want_write else [], [], 0.05)
            if r:
                try:
                    os.read(master, 65536)  # drain what the driver sends (servo commands)
                except OSError:
                    return
            if w and want_write:
                pos += os.write(master, view[pos:pos + 4096])
                if pos >= len(view):
                    written.set()
        written.set()

    pumper = threading.Thread(target=pump, name="replay-pump", daemon=True)
    quiet_since = [0.0]

    def check_done() -> None:
        if not written.is_set() or driver.port_counters.bytes_in < len(data):
            quiet_since[0] = 0.0
            return
        if not quiet_since[0]:
            quiet_since[0] = time.monotonic()
        elif time.monotonic() - quiet_since[0] > 0.1:
            manager.request_stop("replay done")

    manager.on_tick.append(check_done)
    try:
        manager.start()
        pumper.start()
        manager.run(timeout_s)
    finally:
        manager.shutdown()
        stop_pump.set()
        if pumper.is_alive():
            pumper.join(2)
        os.close(master)
        os.close(slave)
    for item in driver.drain_decoder(ctx.clock.realtime_ns()):
        on_item(item)
    counters = driver.counters()
    counters.pop("bytes_out", None)
    return counters
