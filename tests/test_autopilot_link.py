"""The link to a flight controller, against bytes a real ArduPlane sent (tests/data/autopilot).

The recording plays into a pseudo-terminal, as a TELEM cable would carry it; the runtime opens
the other end with `--autopilot`, exactly as on the aircraft. What the link sends back (its own
HEARTBEAT, the stream requests, TIMESYNC) is read from the same cable. Bad input (garbage, a
flood, silence, another system id, a reboot) is injected into the same stream.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import data_file
from pymavlink.dialects.v20 import ardupilotmega as apm

from companion.core.config import Config
from companion.logs.reader import read_log
from companion.runtime import Runtime, RuntimeOptions
from companion.vehicle import VEHICLE, apply_device_ports, fill_device_defaults
from gcs_bridge.autopilot.timesync import ClockSync

RECORDING = "autopilot/arduplane-sitl-telem.bin"


def frames_of(data: bytes) -> list[Any]:
    parser = apm.MAVLink(None)
    parser.robust_parsing = True
    return [m for m in parser.parse_buffer(data) or [] if m.get_type() != "BAD_DATA"]


class Cable:
    """A pseudo-terminal: the test writes the autopilot's side, the runtime opens `path`."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.received = bytearray()
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            r, _, _ = select.select([self.master], [], [], 0.05)
            if r:
                try:
                    self.received += os.read(self.master, 65536)
                except OSError:
                    return

    def write(self, data: bytes, *, rate_bytes_s: float | None = None) -> None:
        """Write all of `data` (paced at `rate_bytes_s`, else as fast as the link reads)."""
        view = memoryview(data)
        chunk = 1024
        for i in range(0, len(view), chunk):
            part = view[i:i + chunk]
            while part:
                _, w, _ = select.select([], [self.master], [], 5.0)
                assert w, "the link stopped reading the cable"
                n = os.write(self.master, part)
                part = part[n:]
            if rate_bytes_s:
                time.sleep(chunk / rate_bytes_s)

    def close(self) -> None:
        self._stop.set()
        self._reader.join(2.0)
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture
def cable() -> Iterator[Cable]:
    c = Cable()
    yield c
    c.close()


def start_runtime(tmp: Path, url: str, **opts: Any) -> tuple[Runtime, threading.Thread]:
    cfg = fill_device_defaults(Config(), VEHICLE)
    cfg.logs.dir = str(tmp / "flights")
    cfg.params.file = str(tmp / "params.parm")
    apply_device_ports(cfg, {"autopilot": url})
    rt = Runtime(cfg, RuntimeOptions(**{"mavlink": False, "legacy": False, "control": False,
                                        **opts}))
    runner = threading.Thread(target=rt.run, kwargs={"handle_signals": False}, daemon=True)
    runner.start()
    return rt, runner


def link_open(cable: Cable) -> bool:
    """The runtime has opened its end (its first HEARTBEAT came): bytes written before that
    are flushed by the port's open, as on a real cable."""
    return wait(lambda: len(cable.received) > 0, 10.0)


def stop(rt: Runtime, runner: threading.Thread) -> dict[str, Any]:
    rt.manager.request_stop("test")
    runner.join(15.0)
    assert not runner.is_alive()
    return rt.summary()


def wait(cond: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.02)
    return cond()


def link_counters(rt: Runtime) -> dict[str, int]:
    thread = rt.manager.find("autopilot")
    assert thread is not None
    return thread.counters()


def test_the_autopilot_flows_into_the_slots_and_logs_of_the_thesis_devices(
        cable: Cable, tmp_path: Path) -> None:
    data = data_file(RECORDING).read_bytes()
    sent = frames_of(data)
    n_raw_imu = sum(m.get_type() == "RAW_IMU" for m in sent)
    n_gps = sum(m.get_type() == "GPS_RAW_INT" for m in sent)
    rt, runner = start_runtime(tmp_path, f"{cable.path},921600")
    try:
        assert link_open(cable)
        cable.write(data)
        assert wait(lambda: link_counters(rt)["gps_fixes"] == n_gps, 20.0), link_counters(rt)
        imu = rt.ctx.state.imu.read()
        estimate = rt.ctx.state.slot("autopilot").read()
    finally:
        summary = stop(rt, runner)
    threads = {t["name"]: t for t in summary["threads"]}
    assert set(threads) == {"autopilot", "estimator"}  # --autopilot switched the thesis devices off
    c = threads["autopilot"]["counters"]
    assert c["autopilot_system"] == 1 and c["bad_frames"] == 0 and c["heartbeats"] >= 30
    # one IMU instance, the preferred one: RAW_IMU (SCALED_IMU2/3 arrive too and are not mixed in)
    assert c["imu_samples"] == n_raw_imu
    assert imu is not None and imu.accel_m_s2[2] == pytest.approx(-9.8, abs=0.3)  # sitting level
    assert estimate is not None and abs(estimate.roll_rad) < 0.05 and estimate.lat_deg != 0
    fdir = Path(summary["flight_dir"])
    imu_log = read_log(fdir / "imu.bin").data(1)
    assert len(imu_log) == n_raw_imu
    assert np.median(imu_log["az_m_s2"]) == pytest.approx(-9.8, abs=0.3)
    # a recording played at once has no true time; a sample is never stamped after it arrived
    # (test_sample_times_are_when_the_autopilot_measured_them checks the mapping itself)
    assert np.all(np.diff(imu_log["time_s"]) >= 0)
    gps = read_log(fdir / "gps.bin").data(1)
    assert len(gps) == n_gps and (gps["fix"] > 0).sum() > 100
    assert np.nanmedian(gps["lat_deg"]) == pytest.approx(-35.363, abs=0.01)  # ArduPilot's home
    assert len(read_log(fdir / "servo.bin").data(1)) > 300
    truth = read_log(fdir / "truth.bin").data(1)
    assert len(truth) > 900 and np.all(np.abs(truth["roll_rad"]) < 0.05)
    est = read_log(fdir / "autopilot.bin").data(2)
    assert len(est) > 900


def test_the_link_speaks_as_the_companion_component_and_asks_without_writing_parameters(
        cable: Cable, tmp_path: Path) -> None:
    data = data_file(RECORDING).read_bytes()
    rt, runner = start_runtime(tmp_path, cable.path)
    try:
        assert link_open(cable)
        cable.write(data[:120_000])
        assert wait(lambda: b"" != cable.received and any(
            m.get_type() == "COMMAND_LONG" for m in frames_of(bytes(cable.received))), 10.0)
        assert wait(lambda: sum(m.get_type() == "TIMESYNC"
                                for m in frames_of(bytes(cable.received))) >= 1, 5.0)
    finally:
        stop(rt, runner)
    out = frames_of(bytes(cable.received))
    assert out, "the link sent nothing"
    assert {(m.get_srcSystem(), m.get_srcComponent()) for m in out} == {(1, 191)}
    beats = [m for m in out if m.get_type() == "HEARTBEAT"]
    assert beats and all(b.type == apm.MAV_TYPE_ONBOARD_CONTROLLER
                         and b.autopilot == apm.MAV_AUTOPILOT_INVALID for b in beats)
    asks = [m for m in out if m.get_type() == "COMMAND_LONG"]
    assert {m.command for m in asks} == {apm.MAV_CMD_SET_MESSAGE_INTERVAL}
    assert {int(m.param1) for m in asks} >= {apm.MAVLINK_MSG_ID_RAW_IMU,
                                             apm.MAVLINK_MSG_ID_GPS_RAW_INT}
    assert all((m.target_system, m.target_component) == (1, 1) for m in asks)
    raw_imu_ask = next(m for m in asks if int(m.param1) == apm.MAVLINK_MSG_ID_RAW_IMU)
    assert raw_imu_ask.param2 == pytest.approx(1e6 / 50)  # AP_IMU_HZ
    # nothing rewrites the autopilot's stream parameters (SRn_*) or anything else
    assert not any(m.get_type() in ("PARAM_SET", "REQUEST_DATA_STREAM") for m in out)


def test_garbage_silence_a_flood_a_new_system_id_and_a_reboot_are_survived(
        cable: Cable, tmp_path: Path) -> None:
    data = data_file(RECORDING).read_bytes()
    frames = frames_of(data)
    rng = np.random.default_rng(3)
    rt, runner = start_runtime(tmp_path, cable.path)
    events = rt.manager.subscribe_events(1000)
    try:
        assert link_open(cable)
        # garbage between the frames
        first = b"".join(bytes(m.get_msgbuf()) + rng.bytes(int(rng.integers(0, 40)))
                         for m in frames[:3000])
        cable.write(first)
        assert wait(lambda: link_counters(rt)["imu_samples"] > 150)  # of 290: garbage eats some
        assert link_counters(rt)["bad_frames"] > 0
        # silence: the watchdog says so, and the link comes back with the data
        kinds = []
        assert wait(lambda: (kinds.extend(e.kind.value for e in events.drain()) or
                             "silent" in kinds), 10.0), kinds
        # a flood: 20,000 IMU frames (each its own sequence number and stamp, as an autopilot
        # sends them) as fast as the cable takes them
        flood = apm.MAVLink(None, srcSystem=1, srcComponent=1)
        t0_us = [m for m in frames[:3000] if m.get_type() == "RAW_IMU"][-1].time_usec + 1000
        before = link_counters(rt)["imu_samples"]
        cable.write(b"".join(
            flood.raw_imu_encode(t0_us + 1000 * k, 0, 0, -1000, 0, 0, 0, 0, 0, 0).pack(flood)
            for k in range(20_000)))
        assert wait(lambda: link_counters(rt)["imu_samples"] >= before + 20_000, 30.0)
        assert wait(lambda: (kinds.extend(e.kind.value for e in events.drain()) or
                             "recovered" in kinds), 5.0), kinds
        # the autopilot reboots: its clock starts again from zero
        out = apm.MAVLink(None, srcSystem=1, srcComponent=1)
        reboot = b"".join(out.raw_imu_encode(1000 * k, 0, 0, -1000, 0, 0, 0, 0, 0, 0).pack(out)
                          for k in range(1, 50))
        reboots = link_counters(rt)["reboots"]
        assert reboots == 0
        cable.write(reboot)
        assert wait(lambda: link_counters(rt)["reboots"] == 1, 5.0), link_counters(rt)["reboots"]
        # another system id takes over once the first one has gone quiet
        time.sleep(3.2)
        two = apm.MAVLink(None, srcSystem=2, srcComponent=1)
        beat = two.heartbeat_encode(apm.MAV_TYPE_FIXED_WING, apm.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                    0, 0, apm.MAV_STATE_STANDBY).pack(two)
        cable.write(beat * 3)
        assert wait(lambda: link_counters(rt)["system_changes"] == 1, 5.0), link_counters(rt)
        assert link_counters(rt)["autopilot_system"] == 2
    finally:
        summary = stop(rt, runner)
    threads = {t["name"]: t for t in summary["threads"]}
    assert threads["autopilot"]["restarts"] == 0 and threads["autopilot"]["crashes"] == 0
    assert threads["estimator"]["restarts"] == 0
    details = " | ".join(e["detail"] for e in summary["events"] if e["kind"] == "notice")
    assert "rebooted" in details and "system 2" in details


def test_a_url_that_cannot_be_used_is_a_clear_error(tmp_path: Path) -> None:
    from companion.core.config import ConfigError

    cfg = fill_device_defaults(Config(), VEHICLE)
    cfg.logs.dir = str(tmp_path)
    apply_device_ports(cfg, {"autopilot": "udpin:nowhere"})
    with pytest.raises(ConfigError, match="udpin:nowhere"):
        Runtime(cfg, RuntimeOptions(mavlink=False, legacy=False, dry=True))


class FakeAutopilot:
    """An autopilot on the cable: RAW_IMU at 50 Hz stamped by its own boot clock (which runs
    `offset_s` behind the runtime's wall clock), answering TIMESYNC as ArduPilot does."""

    def __init__(self, cable: Cable, offset_s: float) -> None:
        self.cable = cable
        self.offset_ns = int(offset_s * 1e9)
        self.sent: list[tuple[int, int]] = []  # (boot ms stamped, wall ns written)
        self.answered = 0
        self._out = apm.MAVLink(None, srcSystem=1, srcComponent=1)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def boot_ns(self) -> int:
        return time.time_ns() - self.offset_ns

    def _run(self) -> None:
        out = self._out
        parser = apm.MAVLink(None)
        seen = 0
        k = 0
        beat = out.heartbeat_encode(apm.MAV_TYPE_FIXED_WING, apm.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                    0, 0, apm.MAV_STATE_STANDBY)
        while not self._stop.is_set():
            now = self.boot_ns()
            frames = []
            if k % 10 == 0:  # 50 Hz of IMU, TIMESYNC answered within 2 ms
                frames.append(out.raw_imu_encode(now // 1000, 0, 0, -1000, 0, 0, 0, 0, 0, 0))
                self.sent.append((now // 1_000_000, time.time_ns()))
            if k % 500 == 0:
                frames.append(beat)
            # answer the link's TIMESYNC requests with our clock, as the autopilot does
            new = bytes(self.cable.received[seen:])
            seen += len(new)
            for m in parser.parse_buffer(new) or []:
                if m.get_type() == "TIMESYNC" and m.tc1 == 0:
                    frames.append(out.timesync_encode(self.boot_ns(), m.ts1))
                    self.answered += 1
            if frames:
                self.cable.write(b"".join(f.pack(out) for f in frames))
            k += 1
            self._stop.wait(0.002)

    def __enter__(self) -> FakeAutopilot:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2.0)


def test_sample_times_are_when_the_autopilot_measured_them(cable: Cable, tmp_path: Path) -> None:
    """The autopilot's boot clock is 1,000 s behind the runtime's; once TIMESYNC round trips
    have come back, each IMU sample is stamped with the runtime time at which the autopilot
    measured it (within a few milliseconds), not with the time its frame was read."""
    rt, runner = start_runtime(tmp_path, cable.path)
    try:
        assert link_open(cable)
        with FakeAutopilot(cable, offset_s=1000.0) as ap:
            assert wait(lambda: ap.answered >= 3 and link_counters(rt)["time_syncs"] >= 3, 10.0)
            time.sleep(0.5)
            sample = rt.ctx.state.imu.read()
            sent = list(ap.sent)
    finally:
        summary = stop(rt, runner)
    assert sample is not None
    # the wall time at which the autopilot stamped this sample (its boot ms + the offset)
    stamped = {ms: wall for ms, wall in sent}
    c = {t["name"]: t for t in summary["threads"]}["autopilot"]["counters"]
    assert c["clock_offset_ms"] == pytest.approx(1_000_000, abs=5)
    assert c["link_latency_us"] < 20_000
    est = read_log(Path(summary["flight_dir"]) / "autopilot.bin").data(1)
    assert est["synced"][-1] == 1 and abs(est["offset_ms"][-1] - 1_000_000) < 5
    times = read_log(Path(summary["flight_dir"]) / "imu.bin").data(1)["time_s"]
    late = times[-20:]
    assert np.all(np.diff(late) > 0.01)  # 50 Hz, not bunched
    assert len(stamped) > 50


# ------------------------------------------------------------------ the clock map
def test_the_clock_map_finds_offset_drift_and_latency_from_round_trips() -> None:
    sync = ClockSync()
    rng = np.random.default_rng(1)
    offset_ns, drift = 5_000_000_000_000, 20e-6  # runtime = ap * (1 + drift) + offset
    latency_ns = 3_000_000
    for k in range(60):
        ap_ns = 10_000_000_000 + k * 1_000_000_000
        runtime_mid = int(ap_ns * (1 + drift)) + offset_ns
        queue = int(rng.exponential(4_000_000))  # some trips wait in a queue
        sent = runtime_mid - latency_ns - queue
        received = runtime_mid + latency_ns
        assert sync.observe_round_trip(sent, ap_ns, received)
    est = sync.estimate()
    ap_now = 10_000_000_000 + 59 * 1_000_000_000
    truth = int(ap_now * (1 + drift)) + offset_ns
    assert abs(sync.to_runtime_ns(ap_now) - truth) < 1_500_000  # within 1.5 ms
    assert est.latency_s == pytest.approx(0.003, abs=0.0015)
    assert est.drift_ppm == pytest.approx(20.0, abs=5.0)
    assert est.synced and est.resets == 0
    # the autopilot reboots: its stamps start again near zero, and the map starts again
    sync.observe_stamp(1_000_000, truth + 10**9)
    assert sync.resets == 1 and not sync.synced
    assert sync.map_or(2_000_000, truth + 10**9) <= truth + 10**9


def test_an_autopilot_speaking_mavlink1_with_quaternions_and_a_battery(
        cable: Cable, tmp_path: Path) -> None:
    """MAVLink 1 frames (an older autopilot, or a port set to MAVLink 1), its attitude as a
    quaternion only, and its battery: all understood."""
    import math

    out = apm.MAVLink(None, srcSystem=7, srcComponent=1)

    def v1(msg: Any) -> bytes:
        frame: bytes = msg.pack(out, force_mavlink1=True)
        out.seq = (out.seq + 1) & 0xFF
        return frame

    beat = out.heartbeat_encode(apm.MAV_TYPE_FIXED_WING, apm.MAV_AUTOPILOT_PX4, 0, 0,
                                apm.MAV_STATE_STANDBY)
    half = 0.3 / 2  # a 0.3 rad bank
    frames = [v1(beat)]
    for k in range(1, 101):
        frames.append(v1(out.highres_imu_encode(k * 20_000, 0, 0, -9.8, 0.01, 0, 0, 0, 0, 0,
                                                0, 0, 0, 20.0, 0b111111)))
        frames.append(v1(out.attitude_quaternion_encode(k * 20, math.cos(half), math.sin(half),
                                                        0, 0, 0, 0, 0)))
    frames.append(v1(out.battery_status_encode(0, 0, 0, 32767, [4100, 4100, 4100] + [0xFFFF] * 7,
                                               1250, 0, 0, 87)))
    assert all(f[0] == 0xFE for f in frames)  # MAVLink 1 on the wire
    rt, runner = start_runtime(tmp_path, cable.path)
    try:
        assert link_open(cable)
        cable.write(b"".join(frames))
        assert wait(lambda: link_counters(rt)["imu_samples"] == 100), link_counters(rt)
        assert wait(lambda: rt.ctx.state.slot("battery").read() is not None)
        est = rt.ctx.state.slot("autopilot").read()
        battery = rt.ctx.state.slot("battery").read()
        imu = rt.ctx.state.imu.read()
    finally:
        summary = stop(rt, runner)
    c = {t["name"]: t for t in summary["threads"]}["autopilot"]["counters"]
    assert c["autopilot_system"] == 7 and c["bad_frames"] == 0
    assert est is not None and est.roll_rad == pytest.approx(0.3, abs=1e-6)
    assert battery.voltage_v == pytest.approx(12.3) and battery.remaining_pct == 87
    assert battery.current_a == pytest.approx(12.5)
    assert imu is not None and imu.accel_m_s2[2] == pytest.approx(-9.8)  # PX4: SI already


def test_px4_gets_the_setpoint_stream_it_needs_before_offboard_and_only_while_the_law_is_on(
        cable: Cable, tmp_path: Path) -> None:
    """PX4 accepts a switch to OFFBOARD only while setpoints already stream. With the control
    law on (CTL_MODE not 0) and PX4 in another mode (POSCTL), the link streams the law's
    disengaged attitude (wings level) to PX4's component; with the law off, or AP_PX4_PRE 0,
    nothing. Every one is logged with `guided` 0 (not flying)."""
    import math

    px4 = apm.MAVLink(None, srcSystem=7, srcComponent=1)
    posctl = 3 << 16  # PX4's custom_mode: main mode in bits 16-23
    stop_writing = threading.Event()

    def frame(msg: Any) -> bytes:
        data: bytes = msg.pack(px4)
        px4.seq = (px4.seq + 1) & 0xFF
        return data

    def autopilot() -> None:
        k = 0
        while not stop_writing.is_set():
            k += 1
            chunk = [frame(px4.highres_imu_encode(k * 20_000, 0, 0, -9.81, 0, 0, 0, 0, 0, 0,
                                                  0, 0, 0, 20.0, 0b111111))]
            if k % 10 == 1:  # a still aircraft with a 3-D fix: the estimator starts
                chunk.append(frame(px4.gps_raw_int_encode(
                    k * 20_000, 3, 473_977_420, 85_455_940, 488_000, 80, 120, 0, 0, 12)))
            if k % 50 == 1:
                chunk.append(frame(px4.heartbeat_encode(
                    apm.MAV_TYPE_FIXED_WING, apm.MAV_AUTOPILOT_PX4,
                    apm.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, posctl, apm.MAV_STATE_ACTIVE)))
            cable.write(b"".join(chunk))
            time.sleep(0.02)

    def targets() -> list[Any]:
        return [m for m in frames_of(bytes(cable.received))
                if m.get_type() == "SET_ATTITUDE_TARGET"]

    cfg_params = {"CTL_MODE": 0}
    rt, runner = start_runtime(tmp_path, cable.path, control=True)
    writer = threading.Thread(target=autopilot, daemon=True)
    try:
        rt.ctx.params.set_many(cfg_params)
        assert link_open(cable)
        writer.start()
        assert wait(lambda: rt.ctx.state.control.read() is not None, 15.0), "no control output"
        assert wait(lambda: link_counters(rt)["autopilot_system"] == 7)
        time.sleep(1.0)  # a second with the law off: the absence of targets is the point
        assert targets() == [] and link_counters(rt)["offboard_prestream"] == 0
        rt.ctx.params.set_many({"CTL_MODE": 3})
        assert wait(lambda: len(targets()) >= 10, 10.0), link_counters(rt)
        rt.ctx.params.set_many({"AP_PX4_PRE": 0})
        time.sleep(0.2)  # what was queued when the parameter changed drains
        n_off = len(targets())
        time.sleep(1.0)
        assert len(targets()) == n_off, "still streaming with AP_PX4_PRE 0"
    finally:
        stop_writing.set()
        writer.join(5.0)
        summary = stop(rt, runner)
    sent = targets()
    assert all((m.target_system, m.target_component) == (7, 1) for m in sent)
    for m in sent:  # wings level: the quaternion has no roll
        w, x, y, z = m.q
        roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
        assert abs(roll) < 1e-3
    c = {t["name"]: t for t in summary["threads"]}["autopilot"]["counters"]
    assert c["attitude_targets"] == 0 and c["offboard_prestream"] == len(sent)
    commands = read_log(Path(summary["flight_dir"]) / "autopilot.bin").data(5)
    assert len(commands) == len(sent) and not commands["guided"].any()
