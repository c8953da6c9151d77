"""`companion sim --lockstep`: the world and the runtime in one process, on simulated time.

The real-time and `--speed` modes fly the runtime against a world in another process, through
pseudo-terminals, on the host's clock: they test the real scheduling. A lockstep flight tests
the same code for what it computes: the world (JSBSim, the pilot, the device simulators) is a
task of a `LockstepClock`, the runtime's threads are tasks too, and device bytes go through
in-process ports (`lockstep://imu` ...) into the same drivers and decoders. Nothing waits on
real time, so a flight runs as fast as its arithmetic, and the same seed and configuration give
byte-identical logs.

Not tested in lockstep (docs/sitl.md): the ground links (MAVLink, the legacy protocol and the
live view are off: they talk to programs on real time), the OS's scheduling, serial buffering
and timing jitter, CPU budgets (a step takes no simulated time), and faults that hold a thread
(`pyloop`, `cblock`) or step the wall clock, which are refused.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import serial

from companion.core.config import Config
from companion.core.files import write_json_bounded
from companion.core.lockstep import LockstepClock
from companion.core.serialport import register_url_scheme
from companion.runtime import Runtime, RuntimeOptions, new_flight_dir
from companion.sim.faults import parse_fault, parse_thread_fault, parse_vanish
from companion.sim.plugins import simulated_devices
from companion.sim.ports import DEVICES
from companion.sim.thread_faults import ThreadFaultInjector
from companion.vehicle import VEHICLE, VehicleTable, device_settings
from companion.watchdog import RuntimeContext, ThreadManager

log = logging.getLogger(__name__)

__all__ = ["LOCKSTEP_REFUSED_FAULTS", "DevicePort", "lockstep_problems", "run_lockstep"]

SCHEME = "lockstep"
PORT_BUFFER_BYTES = 4096
"""What a device's unread bytes may pile up to; beyond it new bytes are lost, as a
pseudo-terminal's buffer (4 KiB on Linux) loses them when nobody reads."""
LOG_DRAIN_PERIOD_S = 1.0
"""How often (simulated s) the scheduler writes the queued log records to disk. Each drain
costs a write per log file whatever it holds, so draining ten times a second cost more than
the records' own encoding; a second's records (about 45 kB) wait in memory instead."""
LOCKSTEP_REFUSED_FAULTS = ("pyloop", "cblock")


class DevicePort:
    """One device's serial line in a lockstep flight.

    The device side is what `companion.sim.world.World` writes to (as to a pseudo-terminal:
    `write`, `close`, `open`, `name`, `dropped_bytes`); the driver side is `LockstepSerial`,
    opened by the driver through `open_serial_port("lockstep://<device>")`. `on_driver_write`
    gets the bytes the driver writes (the servo board's commands).
    """

    def __init__(self, device: str) -> None:
        self.device = device
        self.name = f"{SCHEME}://{device}"
        self.buffer = bytearray()
        self.dropped_bytes = 0
        self.gone = False
        self.generation = 0  # bumped when the port vanishes: an open handle is then stale
        self.on_driver_write: Callable[[bytes], None] | None = None

    def write(self, data: bytes) -> None:
        if self.gone or not data:
            return
        space = PORT_BUFFER_BYTES - len(self.buffer)
        if len(data) > space:
            self.dropped_bytes += len(data) - max(space, 0)
            data = data[:max(space, 0)]
        self.buffer += data

    def close(self) -> None:
        self.gone = True
        self.generation += 1
        self.buffer.clear()

    def open(self, avoid_name: str | None = None) -> None:
        self.gone = False


class LockstepSerial:
    """The driver's end of a `DevicePort`, with the part of pyserial's interface the drivers
    use. A read waits in simulated time: until bytes are there or its timeout has passed."""

    def __init__(self, port: DevicePort, clock: LockstepClock, timeout_s: float | None) -> None:
        self._port = port
        self._clock = clock
        self.timeout = timeout_s
        self.is_open = True
        self._generation = port.generation

    def _check(self) -> None:
        port = self._port
        if not self.is_open or port.gone or port.generation != self._generation:
            raise serial.SerialException(f"{port.name}: device disconnected")

    @property
    def in_waiting(self) -> int:
        self._check()
        return len(self._port.buffer)

    def read(self, size: int = 1) -> bytes:
        self._check()
        port = self._port
        buf = port.buffer
        if not buf:
            generation = self._generation
            timeout = 3600.0 if self.timeout is None else self.timeout
            self._clock.wait_until(
                lambda: bool(buf) or port.generation != generation, timeout)
            self._check()
        data = bytes(buf[:size])
        del buf[:size]
        return data

    def write(self, data: bytes) -> int:
        self._check()
        sink = self._port.on_driver_write
        if sink is not None:
            sink(bytes(data))
        return len(data)

    def cancel_read(self) -> None:
        """Nothing to cancel: a waiting read is woken by its task's stop."""

    def close(self) -> None:
        self.is_open = False


def lockstep_problems(thread_faults: list[str], clock_steps: list[str]) -> list[str]:
    """Why a lockstep flight cannot honour these options (empty: it can)."""
    problems = []
    for text in thread_faults:
        fault = parse_thread_fault(text)
        if fault.kind in LOCKSTEP_REFUSED_FAULTS:
            problems.append(f"--thread-fault {text}: a {fault.kind} holds the one thread a "
                            "lockstep flight runs on; fly it in real time or with --speed")
    if clock_steps:
        problems.append("--clock-step: a lockstep flight's wall time is simulated")
    return problems


def run_lockstep(cfg: Config, sim: Any, duration_s: float | None, *,
                 handle_signals: bool = True,
                 on_runtime: Callable[[Runtime], None] | None = None,
                 vehicle: VehicleTable = VEHICLE) -> dict[str, Any]:
    """Fly one simulated vehicle in lockstep; returns the run summary (as `run_sim`).

    `vehicle` is the table the runtime builds (a plug-in device's row brings its simulator)."""
    from companion.sim.world import World, WorldOptions

    problems = lockstep_problems(sim.thread_faults, sim.clock_steps)
    if problems:
        raise ValueError("; ".join(problems))
    clock = LockstepClock()
    flight_dir = new_flight_dir(Path(cfg.logs.dir),
                                suffix=f"-v{cfg.vehicle.id}" if cfg.vehicle.id != 1 else "")
    extra = simulated_devices(vehicle)
    devices = (*DEVICES, *extra)
    ports = {dev: DevicePort(dev) for dev in devices}
    world = World(WorldOptions(
        scenario=sim.scenario, seed=sim.seed, aircraft=sim.aircraft,
        wind_ned_m_s=tuple(sim.wind_ned_m_s), flight_dir=flight_dir,
        gps_latency_s=sim.gps_latency_s, gps_ashtech=sim.gps_ashtech,
        imu_seed=getattr(sim, "imu_seed", None),
        faults=dict(parse_fault(f, devices) for f in sim.faults),
        vanish=[parse_vanish(v, devices) for v in sim.vanish], imu_noise=not sim.no_noise,
        imu_profile=getattr(sim, "imu_profile", None), gps_profile=getattr(sim, "gps_profile", None),
        turbulence=getattr(sim, "turbulence", None),
        auto_switch_s=sim.auto_switch_s, horizon_camera=getattr(sim, "horizon_camera", "off"),
        level_calibration=getattr(sim, "level_calibration", True), extra_devices=extra),
        ports=ports, clock=clock)
    ports["servo"].on_driver_write = world.answer_servo

    def opener(url: str, timeout_s: float | None) -> LockstepSerial:
        device = url.partition("://")[2]
        port = ports.get(device)
        if port is None or port.gone:
            raise serial.SerialException(f"{url}: no such device")
        return LockstepSerial(port, clock, timeout_s)

    for row in vehicle.devices():
        settings = device_settings(cfg, row.name, vehicle)
        if row.name in ports:
            settings.port = ports[row.name].name
        elif settings.enabled:
            log.warning("device %s: nothing simulates it (its row names no simulator); it is "
                        "switched off in this flight", row.name)
            settings.enabled = False
    frame = world.model.frame
    cfg.vehicle.home = ",".join(repr(float(v)) for v in
                                (frame.lat0_deg, frame.lon0_deg, frame.alt0_m))
    injectors: list[ThreadFaultInjector] = []
    faults = [parse_thread_fault(f) for f in sim.thread_faults]

    def inject(ctx: RuntimeContext, manager: ThreadManager) -> ThreadFaultInjector:
        injectors.append(ThreadFaultInjector(ctx, manager, faults))
        return injectors[-1]

    register_url_scheme(SCHEME, opener)
    try:
        rt = Runtime(cfg, RuntimeOptions(
            clock=clock, flight_dir=flight_dir, mavlink=False, legacy=False,
            log_writer_thread=False, vehicle=vehicle,
            extra_run_info={"simulation": {**vars(sim), "lockstep": True,
                                           "sensors": world.sensors.metadata()}},
            extra_bridges=[inject] if faults else []))
        if sim.gps_ashtech:
            rt.ctx.params.set("GPS_PASHR", 1)
        # the installation's level calibration and receiver settings (runner.py)
        rt.ctx.params.set_many(world.runtime_params())
        if on_runtime is not None:
            on_runtime(rt)
        # no ground links here: the camera's fixes go into the slot the legacy adapter writes,
        # and each frame is detected inside the world's tick (simulated time stands still)
        from companion.sim.world_camera import SlotLink

        world.attach_camera(SlotLink(rt.ctx.state.horizon), threaded=False)

        def drain() -> None:
            if rt.logs is not None:
                rt.logs.drain()
            if world.logs is not None and world.tlog is not None:
                world.logs.drain()

        clock.every(LOG_DRAIN_PERIOD_S, drain)

        def main() -> str:
            stop = threading.Event()
            world_task = clock.start_thread(world.run_lockstep, (stop,), "world", priority=0)
            try:
                return rt.run(duration_s, handle_signals=handle_signals)
            finally:
                stop.set()
                world_task.join(1.0)

        t0 = time.monotonic()
        reason = clock.run(main)
        host_s = time.monotonic() - t0
    finally:
        register_url_scheme(SCHEME, None)
    stats = world.close_lockstep(host_s)
    summary = rt.summary()
    summary["stop_reason"] = reason
    summary["simulator"] = stats
    sensors = world.sensors.metadata()
    summary["sensors"] = {k: sensors[k] for k in ("imu_profile", "gps_profile", "turbulence",
                                                  "no_noise")}
    if injectors:
        summary["thread_faults"] = [a for inj in injectors for a in inj.armed]
    sim_s = (clock.monotonic_ns() - clock.epoch[0]) / 1e9
    summary["host_seconds"] = round(host_s, 2)
    summary["clock_scale"] = 1.0
    summary["lockstep"] = {"sim_seconds": round(sim_s, 3),
                           "speed": round(sim_s / host_s, 1) if host_s > 0 else None,
                           "switches": clock.switches, "advances": clock.advances,
                           "host_s_by_task": {k: round(v / 1e9, 3) for k, v in
                                              sorted(clock.host_ns.items())}}
    write_json_bounded(flight_dir / "summary.json", summary, 2.0)
    return summary
