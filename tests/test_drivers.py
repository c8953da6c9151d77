"""Driver threads against device simulators over real pseudo-terminals."""

from __future__ import annotations

import dataclasses
import os
import select
import threading
import time
import tty
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from conftest import data_file, wait_for

from companion.core.clock import Clock
from companion.core.params import ParamRegistry
from companion.core.state import ControlOutput
from companion.drivers.gps import GpsDriver
from companion.drivers.imu import ImuDriver
from companion.drivers.servo import ServoDriver
from companion.sim.gps_sim import GpsSim
from companion.sim.imu_sim import ImuSim
from companion.sim.servo_sim import ServoBoardSim
from companion.vehicle import VEHICLE, fill_device_defaults
from companion.watchdog import EventKind, ManagedThread, RuntimeContext, ThreadManager


class FakeDevice:
    """The device end of a pseudo-terminal, reachable through a stable symlink."""

    def __init__(self, tmp: Path, name: str) -> None:
        self.link = tmp / name
        self.master = self.slave = -1
        self.open()

    def open(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        tmp = self.link.with_suffix(".new")
        tmp.symlink_to(os.ttyname(self.slave))
        os.replace(tmp, self.link)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            if fd >= 0:
                os.close(fd)
        self.master = self.slave = -1
        self.link.unlink(missing_ok=True)

    def write(self, data: bytes) -> None:
        if self.master >= 0:
            os.write(self.master, data)

    def read(self, timeout_s: float) -> bytes:
        r, _, _ = select.select([self.master], [], [], timeout_s)
        return os.read(self.master, 4096) if r else b""


class Harness:
    def __init__(self, thread: ManagedThread) -> None:
        self.ctx = RuntimeContext(clock=Clock(), params=ParamRegistry())
        self.mgr = ThreadManager(self.ctx, [thread])
        self.ctx.params.set("MGR_WDG_GRAN_MS", 5)
        self.events = self.mgr.subscribe_events(4096)
        self.runner = threading.Thread(target=self.mgr.run, name="test-manager")

    def __enter__(self) -> Harness:
        self.mgr.start()
        self.runner.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.mgr.request_stop()
        self.runner.join(5)
        self.mgr.shutdown()


@pytest.fixture
def imu_dev(tmp_path: Path) -> Iterator[FakeDevice]:
    dev = FakeDevice(tmp_path, "imu")
    yield dev
    dev.close()


def imu_stream(n: int, seed: int = 1) -> list[bytes]:
    sim = ImuSim(np.random.default_rng(seed))
    return [sim.frame((0.1, -0.05, 0.02), (0.3, 0.1, -9.7)) for _ in range(n)]


def test_imu_golden_capture_one_byte_at_a_time(imu_dev: FakeDevice) -> None:
    data = data_file("vectors", "imu-cycle.bin").read_bytes()
    drv = ImuDriver(str(imu_dev.link), task=VEHICLE["imu"].task)
    items: list[object] = []
    drv.item_sink = items.append
    with Harness(drv):
        for b in data:
            imu_dev.write(bytes([b]))
        assert wait_for(lambda: drv.decoder.counters.slow_good == 1, 5.0)
    c = drv.decoder.counters
    assert c.frames_good == 100 and c.bad_checksum == 1
    slow = drv.ctx.state.imu_slow.read()
    assert slow is not None and slow.temperature_c == pytest.approx(36.25)
    fast = drv.ctx.state.imu.read()
    assert fast is not None and fast.accel_m_s2[2] == pytest.approx(-9.80665)


def test_imu_garbage_cut_frames_and_bad_checksums(imu_dev: FakeDevice) -> None:
    frames = imu_stream(300)
    rng = np.random.default_rng(7)
    drv = ImuDriver(str(imu_dev.link), task=VEHICLE["imu"].task)
    sent_good = 0
    with Harness(drv):
        for i, f in enumerate(frames):
            kind = i % 10
            if kind == 3:
                imu_dev.write(rng.integers(0, 256, 7, dtype=np.uint8).tobytes())
                imu_dev.write(f)
                sent_good += 1
            elif kind == 5:
                imu_dev.write(f[:9])  # cut frame
            elif kind == 7:
                bad = bytearray(f)
                bad[6] ^= 0x55
                imu_dev.write(bytes(bad))
            else:
                imu_dev.write(f)
                sent_good += 1
            if i % 50 == 0:
                time.sleep(0.002)
        assert wait_for(lambda: drv.decoder.counters.frames_good >= sent_good - 2, 5.0)
    c = drv.decoder.counters
    # garbage may by chance hide one frame start; never pass a bad frame on
    assert sent_good - 2 <= c.frames_good <= sent_good
    assert c.bad_checksum + c.resyncs > 0 and c.bytes_discarded > 0
    s = drv.ctx.state.imu.read()
    assert s is not None and abs(s.rates_rad_s[0] - 0.1) < 0.05


def test_silence_is_reported_and_port_reopened(imu_dev: FakeDevice) -> None:
    drv = ImuDriver(str(imu_dev.link), task=VEHICLE["imu"].task)
    frames = imu_stream(2000)
    stop = threading.Event()
    paused = threading.Event()

    def feed() -> None:
        i = 0
        while not stop.is_set():
            if not paused.is_set():
                imu_dev.write(frames[i % len(frames)])
                i += 1
            time.sleep(0.005)

    feeder = threading.Thread(target=feed)
    with Harness(drv) as h:
        h.ctx.params.set("IMU_WDG_MS", 100)
        feeder.start()
        try:
            assert wait_for(lambda: drv.cycles > 20, 3.0)
            # silence: the watchdog says so, without restarting the thread
            paused.set()
            assert wait_for(lambda: any(e.kind is EventKind.SILENT for e in h.events.drain()), 3.0)
            assert drv.restarts == 0
            paused.clear()
            assert wait_for(lambda: any(e.kind is EventKind.RECOVERED for e in h.events.drain()), 3.0)
            # the port vanishes and comes back under the same name
            paused.set()
            time.sleep(0.02)
            imu_dev.close()
            assert wait_for(lambda: drv.port is None, 3.0)
            imu_dev.open()
            paused.clear()
            cycles = drv.cycles
            assert wait_for(lambda: drv.cycles > cycles + 20, 5.0)
            assert drv.port_counters.reconnects >= 1
            assert drv.restarts == 0 and drv.running
        finally:
            stop.set()
            feeder.join(2)


def _gps_on_pty(tmp_path: Path, seed: int) -> tuple[FakeDevice, GpsSim, GpsDriver, list[object]]:
    """A GPS driver on a pseudo-terminal, the receiver simulator that writes to it, and the
    list every decoded solution is appended to."""
    dev = FakeDevice(tmp_path, "gps")
    drv = GpsDriver(str(dev.link), task=VEHICLE["gps"].task)
    sols: list[object] = []
    drv.item_sink = sols.append
    return dev, GpsSim(np.random.default_rng(seed)), drv, sols


def test_gps_driver_groups_epochs_and_measures_latency(tmp_path: Path) -> None:
    dev, sim, drv, sols = _gps_on_pty(tmp_path, 3)
    try:
        with Harness(drv):
            for k in range(20):
                epoch = sim.epoch(43200.0 + k * 0.1, 43.7, 10.4, 300.0, 20.0, 5.0, -1.0)
                # a receiver writes its sentences over a few milliseconds
                for line in epoch.split(b"\n"):
                    if line:
                        dev.write(line + b"\n")
                        time.sleep(0.001)
                time.sleep(0.02)
            assert wait_for(lambda: len(sols) >= 20, 5.0)
        fix = drv.ctx.state.gps.read()
        assert fix is not None and fix.fix == 1
        assert abs(fix.lat_deg - 43.7) < 1e-3 and abs(fix.lon_deg - 10.4) < 1e-3
        assert fix.vn_m_s == pytest.approx(20.0, abs=0.5)
        assert fix.latency_s is not None and 0.0 < fix.latency_s < 0.05
        assert drv.decoder.counters.bad_checksum == 0
    finally:
        dev.close()


def test_gps_reads_block_between_epochs_and_wake_for_an_incomplete_one(tmp_path: Path) -> None:
    """Short read timeouts only while an epoch waits for its idle hand-off: a silent line
    costs about four wake-ups a second, not fifty, and an epoch missing a sentence still
    reaches the flight after GPS_IDLE_MS of silence."""
    from companion.drivers.gps import IDLE_READ_TIMEOUT_S

    dev, sim, drv, sols = _gps_on_pty(tmp_path, 4)
    try:
        with Harness(drv):
            assert wait_for(lambda: drv.port is not None, 3.0)
            assert drv.read_timeout_now_s() == IDLE_READ_TIMEOUT_S  # nothing open: block long
            t0 = drv.port_counters.timeouts
            time.sleep(1.0)
            idle_timeouts = drv.port_counters.timeouts - t0
            assert 1 <= idle_timeouts <= 6, idle_timeouts  # 0.02 s reads gave about 50
            epoch = sim.epoch(43200.0, 43.7, 10.4, 300.0, 20.0, 5.0, -1.0)
            # no GST: every other sentence arrives, the epoch stays open until the line is quiet
            lines = [ln for ln in epoch.split(b"\n") if ln and b"GST" not in ln]
            dev.write(b"\n".join(lines) + b"\n")
            assert wait_for(lambda: drv.decoder.holds_epoch or sols, 2.0)
            assert wait_for(lambda: len(sols) == 1, 2.0)
            assert not drv.decoder.holds_epoch
            assert drv.read_timeout_now_s() == IDLE_READ_TIMEOUT_S
            fix = drv.ctx.state.gps.read()
            assert fix is not None and abs(fix.lat_deg - 43.7) < 1e-3
            # handed off by the idle rule (20 ms of silence), not by a long read timing out
            assert fix.latency_s is not None and 0.015 < fix.latency_s < 0.15, fix.latency_s
    finally:
        dev.close()


def test_servo_exchange_closes_the_loop(tmp_path: Path) -> None:
    dev = FakeDevice(tmp_path, "servo")
    board = ServoBoardSim(np.random.default_rng(5))
    board.set_pilot((1500, 1500, 1600, 1500, 1900, 1500, 1500, 1500))  # switch in auto
    drv = ServoDriver(str(dev.link), task=VEHICLE["servo"].task)
    stop = threading.Event()

    def board_loop() -> None:
        t0 = time.monotonic()
        while not stop.is_set():
            data = dev.read(0.02)
            if data:
                dev.write(board.feed(data, time.monotonic() - t0))

    t = threading.Thread(target=board_loop)
    t.start()
    try:
        with Harness(drv) as h:
            assert wait_for(lambda: drv.cycles > 10, 3.0)
            s = h.ctx.state.servo.read()
            assert s is not None and s.auto_engaged and not s.auto_requested
            assert s.pilot_us[2] == 1600
            # the control law asks: the board obeys because the pilot's switch allows it
            for _ in range(30):
                h.ctx.state.control.write(ControlOutput(
                    h.ctx.clock.realtime_ns(), 0.5, -0.2, 0.0, 0.7, True, "test"))
                time.sleep(0.01)
            cmd = board.last_command
            assert cmd is not None and cmd.auto_requested
            assert cmd.channels_us[0] == 1750 and cmd.channels_us[1] == 1600
            assert cmd.channels_us[2] == 1700
            rate = drv.status().measured_rate_hz
            assert 45 < rate < 55
    finally:
        stop.set()
        t.join(2)
        dev.close()


def test_every_device_is_one_row_of_the_vehicle_table() -> None:
    """The runtime, the replay tool, the report and the command line take their devices from
    one table."""
    from companion.core.config import Config
    from companion.drivers.replay import KINDS, make_driver
    from companion.report.headers import PRODUCERS
    from companion.runtime import build_threads
    from companion.vehicle import device_settings

    devices = [row.name for row in VEHICLE.devices() if row.replay]
    assert devices == ["imu", "gps", "servo"] == list(KINDS)
    assert [row.name for row in VEHICLE.devices()] == [*devices, "autopilot"]
    assert set(devices) <= set(PRODUCERS)
    cfg = Config()
    device_settings(cfg, "gps").enabled = False
    assert [t.name for t in build_threads(cfg)] == ["imu", "servo", "estimator", "control"]
    for name in devices:
        drv = make_driver(name, "loop://")
        assert drv.task is VEHICLE[name].task and drv.name == name
        assert f"{type(drv).__module__}:{type(drv).__name__}" == VEHICLE[name].task.implementation
    with pytest.raises(ValueError, match="unknown device 'baro'"):
        make_driver("baro", "loop://")


def test_a_full_disk_turns_one_log_off_reports_it_and_the_driver_flies_on(
        imu_dev: FakeDevice, tmp_path: Path) -> None:
    """ENOSPC on the IMU log (its file is /dev/full, which refuses every write with it): the
    runtime says so as an event the ground stations relay, and the IMU keeps publishing."""
    from companion.core.config import Config
    from companion.runtime import Runtime, RuntimeOptions

    flight = tmp_path / "flight"
    flight.mkdir()
    os.symlink("/dev/full", flight / "imu.bin")
    cfg = Config()
    cfg.logs.dir = str(tmp_path)
    cfg.params.file = str(tmp_path / "params.parm")
    fill_device_defaults(cfg, VEHICLE)
    cfg.devices["imu"].port = str(imu_dev.link)
    cfg.devices["gps"].enabled = cfg.devices["servo"].enabled = False
    rt = Runtime(cfg, RuntimeOptions(mavlink=False, legacy=False, estimator=False,
                                     control=False, flight_dir=flight))
    events = rt.manager.subscribe_events(256)
    runner = threading.Thread(target=rt.run, kwargs={"handle_signals": False}, daemon=True)
    runner.start()
    seen: list[tuple[str, str, str]] = []
    try:
        frames = imu_stream(200)

        def fed_and_reported() -> bool:
            if frames:
                imu_dev.write(frames.pop(0))
            seen.extend((e.kind.value, e.thread, e.detail) for e in events.drain())
            return not frames and any(k == "logging off" for k, _, _ in seen)

        assert wait_for(fed_and_reported, 10.0, interval_s=0.005)
        sample = rt.ctx.state.imu.read()
        assert sample is not None and sample.counter is not None
    finally:
        rt.manager.request_stop()
        runner.join(10)
    imu = next(t for t in rt.summary()["threads"] if t["name"] == "imu")
    assert imu["restarts"] == 0 and imu["cycles"] >= 150
    off = [s for s in seen if s[0] == "logging off"]
    assert off == [("logging off", "imu", "No space left on device (errno 28)")]


def test_gps_copies_are_dropped_and_a_utc_jump_is_told_but_midnight_is_not() -> None:
    from companion.drivers.gps import GpsDriver
    from companion.drivers.gps_solution import GpsSolution

    gps = GpsDriver("loop://", task=VEHICLE["gps"].task)
    told: list[str] = []
    gps._on_notice = told.append
    t0_ns = 1_000_000_000_000

    def epoch(utc_s: float, t_s: float) -> int:
        sol = GpsSolution(utc=utc_s % 86400.0, lat_deg=47.0, lon_deg=8.0, alt_m=500.0, fix=1)
        return gps.publish(sol, t0_ns + int(t_s * 1e9))

    assert epoch(86399.8, 0.0) == 1
    assert epoch(86399.8, 0.01) == 0  # a copy of the same epoch
    assert epoch(86399.9, 0.1) == 1
    assert epoch(86400.0, 0.2) == 1  # midnight: UTC wraps to 0, time goes on
    assert gps.utc_jumps == 0 and gps.repeated == 1
    assert epoch(86400.1 + 3600.0, 0.3) == 1  # the receiver's clock steps an hour
    assert gps.utc_jumps == 1 and any("UTC jumped +3600.0 s" in t for t in told)
    assert gps.counters()["repeated"] == 1 and gps.counters()["utc_jumps"] == 1
    # the process was suspended 5 s: the epochs waiting in the port arrive at once, one
    # receiver epoch apart; late data, not a jump of the receiver's clock
    assert epoch(86400.2 + 3600.0, 5.3) == 1
    for k in range(1, 50):
        assert epoch(86400.2 + 3600.0 + 0.1 * k, 5.3 + 0.001 * k) == 1
    assert gps.utc_jumps == 1 and gps.late_epochs == 1
    assert any("arrived 4.9 s late" in t for t in told)
    assert epoch(86400.2 + 3600.0 + 10.0, 10.3) == 1  # silent 5 s, then on time again
    assert epoch(100.0, 10.4) == 1  # a reset: the receiver's clock goes back
    assert gps.utc_jumps == 2 and gps.counters()["late_epochs"] == 1


def test_gps_heading_reaches_the_flight_only_from_a_receiver_declared_to_send_it() -> None:
    """With GPS_HDT at 0 an HDT sent after the timed sentences joins the next epoch, 0.1 s
    stale: the driver passes no heading on; with GPS_HDT at 1 it does."""
    from companion.drivers.gps import GpsDriver
    from companion.drivers.gps_solution import GpsSolution

    gps = GpsDriver("loop://", task=VEHICLE["gps"].task)
    sol = GpsSolution(utc=100.0, lat_deg=47.0, lon_deg=8.0, alt_m=500.0, fix=1, heading_deg=12.5)
    assert gps.publish(sol, 1_000_000_000) == 1
    fix = gps.ctx.state.gps.read()
    assert fix is not None and fix.heading_deg is None
    gps.ctx.params.declare_all(GpsDriver.declare_params("GPS"))
    gps.ctx.params.set("GPS_HDT", 1)
    gps.configure()
    assert "HDT" in gps.decoder.expected
    assert gps.publish(dataclasses.replace(sol, utc=100.1), 1_100_000_000) == 1
    fix = gps.ctx.state.gps.read()
    assert fix is not None and fix.heading_deg == 12.5
