"""A real SITL runtime and the real ground monitor talking the legacy protocol over loopback."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import psutil
from conftest import free_udp_port
from pymavlink import mavutil

from companion.logs import read_log
from legacy_protocol import codec, messages
from legacy_protocol.monitor_link import CommandSender, MonitorLink

CORE_THREADS = {1: "imu", 2: "gps", 3: "servo", 4: "estimator", 5: "control"}


class Sim:
    """`companion sim` in a subprocess with the legacy protocol on free loopback ports."""

    def __init__(self, tmp: Path, *extra: str, fast: bool = True, mavlink_port: int | None = None) -> None:
        self.cmd_port = free_udp_port()
        self.msg_port = free_udp_port()
        self.tmp = tmp
        cmd = [sys.executable, "-m", "companion", "sim", "--log-dir", str(tmp / "flights"),
               "--params-file", str(tmp / "params.parm"),
               "--legacy-listen", str(self.cmd_port), "--legacy-dest", f"127.0.0.1:{self.msg_port}",
               "--mavlink", f"udpout:127.0.0.1:{mavlink_port}" if mavlink_port else "none",
               *(["--fast"] if fast else []), *extra]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)

    def flight_dir(self) -> Path:
        return next((self.tmp / "flights").iterdir())

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.proc.stderr is not None:
            self.proc.stderr.close()


def poll_until(link: MonitorLink, predicate, timeout_s: float) -> bool:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        link.wait(0.1)
        link.poll()
        if predicate():
            return True
    return False


def test_monitor_sees_every_thread_sets_a_period_and_stops_the_runtime(tmp_path: Path) -> None:
    mav_port = free_udp_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{mav_port}", source_system=255)
    sim = Sim(tmp_path, mavlink_port=mav_port)
    link = MonitorLink(sim.msg_port, host="127.0.0.1")
    sender = CommandSender(("127.0.0.1", sim.cmd_port), timeout_s=3.0)
    try:
        def vehicle():  # type: ignore[no-untyped-def]
            vs = link.fleet.ordered()
            return vs[0] if vs else None

        def all_threads_seen() -> bool:
            v = vehicle()
            return v is not None and set(CORE_THREADS) <= set(v.threads)

        assert poll_until(link, all_threads_seen, 60), "not every thread's status arrived"
        v = vehicle()
        assert v is not None
        for tid, name in CORE_THREADS.items():
            st = v.threads[tid]
            assert st.name == name
            assert st.has(messages.ThreadFlag.INITIALISED) and st.has(messages.ThreadFlag.RUNNING)
        assert poll_until(link, lambda: v.latest(messages.Imu) is not None
                          and v.latest(messages.Gps) is not None
                          and v.latest(messages.Estimator) is not None, 20)
        gps = v.latest(messages.Gps)
        assert gps is not None and abs(gps.lat_deg - 43.68) < 0.1

        # a period changed from the monitor is acknowledged, applied, and seen on MAVLink
        outcome = sender.request(messages.SetThreadParams(1, 750, messages.UNCHANGED), vehicle_id=1)
        assert outcome.accepted, outcome.text
        assert poll_until(link, lambda: v.threads[1].watchdog_period_ms == 750, 20)
        bad = sender.request(messages.SetThreadParams(1, 0, messages.UNCHANGED), vehicle_id=1)
        assert bad.ack is not None and bad.ack.result == messages.AckResult.BAD_VALUE
        unknown = sender.request(messages.SetThreadParams(99, 500, messages.UNCHANGED), vehicle_id=1)
        assert unknown.ack is not None and unknown.ack.result == messages.AckResult.UNKNOWN_THREAD
        assert gcs.wait_heartbeat(timeout=30) is not None
        value = None
        deadline = time.monotonic() + 20
        while value is None and time.monotonic() < deadline:
            gcs.mav.param_request_read_send(gcs.target_system, gcs.target_component,
                                            b"IMU_WDG_MS", -1)
            msg = gcs.recv_match(type="PARAM_VALUE", blocking=True, timeout=1)
            if msg is not None and msg.param_id == "IMU_WDG_MS":
                value = msg
        assert value is not None, "no PARAM_VALUE for IMU_WDG_MS on the MAVLink side"
        raw = np.float32(value.param_value).tobytes()
        assert int.from_bytes(raw, "little", signed=True) == 750 or value.param_value == 750

        # STOP ends the runtime cleanly, with every log closed
        stop = sender.request(messages.Stop(0), vehicle_id=1)
        assert stop.accepted, stop.text
        assert sim.proc.wait(15) == 0
        fdir = sim.flight_dir()
        for name in ("imu", "gps", "servo", "estimator", "control"):
            assert read_log(fdir / f"{name}.bin").closed_cleanly, name
        assert "IMU_WDG_MS       750" in (tmp_path / "params.parm").read_text()
    finally:
        link.close()
        sender.close()
        gcs.close()
        sim.close()


def test_garbage_flood_does_not_disturb_the_aircraft(tmp_path: Path) -> None:
    sim = Sim(tmp_path, fast=False)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            imu = list((tmp_path / "flights").glob("*/imu.bin")) if (tmp_path / "flights").exists() else []
            if imu and imu[0].stat().st_size > 40_000:
                break
            assert sim.proc.poll() is None
            time.sleep(0.1)
        proc = psutil.Process(sim.proc.pid)
        rss_before = proc.memory_info().rss
        rng = np.random.default_rng(1)
        junk = [rng.integers(0, 256, int(n), dtype=np.uint8).tobytes()
                for n in rng.integers(1, 200, 500)]
        valid = codec.encode(messages.SetThreadParams(1, 400), vehicle_id=1, seq=1, t_ns=0)
        junk += [valid[:10], valid + b"x", bytes([0x81]) + valid[1:20], b"\x84" * 36]
        stop = threading.Event()
        sent = [0]

        def flood() -> None:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                t0 = time.monotonic()
                while not stop.is_set() and time.monotonic() - t0 < 10.0:
                    target = t0 + sent[0] / 10_000
                    now = time.monotonic()
                    if now < target:
                        time.sleep(target - now)
                    s.sendto(junk[sent[0] % len(junk)], ("127.0.0.1", sim.cmd_port))
                    sent[0] += 1

        flood_start = time.time()
        flooder = threading.Thread(target=flood)
        flooder.start()
        flooder.join(30)
        flood_end = time.time()
        stop.set()
        rss_after = proc.memory_info().rss
        assert sent[0] >= 90_000
        sim.proc.send_signal(signal.SIGTERM)
        assert sim.proc.wait(15) == 0
        imu = read_log(sim.flight_dir() / "imu.bin").data(1)
        t = imu["time_s"]
        window = (t > flood_start + 0.5) & (t < flood_end - 0.5)
        rate = (np.count_nonzero(window) - 1) / (t[window][-1] - t[window][0])
        # not one IMU frame lost to the flood: the device's counter steps by one throughout
        steps = np.diff(imu["counter"][window].astype(int)) % 100
        assert np.all(steps == 1), f"IMU counter jumps during the flood: {sorted(set(steps))}"
        # and the rate is the device's: the records' host times carry the scheduler's jitter
        # at the window's two ends (101.97 Hz seen beside a second test worker), a flood that
        # starved the thread would show tens of percent
        assert abs(rate / 100.0 - 1) < 0.05, f"IMU at {rate:.2f} Hz during the flood"
        assert rss_after - rss_before < 8 * 2**20, f"memory grew {(rss_after - rss_before) / 2**20:.1f} MiB"
        # the flood never changed a parameter (the one valid command was cut or padded)
        pfile = tmp_path / "params.parm"
        assert not pfile.exists() or "IMU_WDG_MS       400" not in pfile.read_text()
    finally:
        sim.close()


def test_refused_source_is_dropped(tmp_path: Path) -> None:
    """Commands from outside the allow-list never act (here: only 127.0.0.2 is allowed)."""
    sim = Sim(tmp_path, "--legacy-allow", "127.0.0.2/32")
    link = MonitorLink(sim.msg_port, host="127.0.0.1")
    sender = CommandSender(("127.0.0.1", sim.cmd_port), timeout_s=1.0)
    try:
        assert poll_until(link, lambda: bool(link.fleet.ordered()), 60)
        outcome = sender.request(messages.Stop(0), vehicle_id=1)
        assert outcome.ack is None  # dropped, not acknowledged
        time.sleep(0.5)  # nothing to wait for: the runtime must simply still be running
        assert sim.proc.poll() is None
    finally:
        link.close()
        sender.close()
        sim.close()


def test_a_second_runtime_on_the_same_command_port_is_refused() -> None:
    import pytest

    from companion.core.clock import Clock
    from companion.core.config import ConfigError
    from companion.core.params import ParamRegistry
    from companion.watchdog import RuntimeContext, ThreadManager
    from legacy_protocol.adapter import LegacyAdapter

    port = free_udp_port()
    ctx = RuntimeContext(clock=Clock(), params=ParamRegistry())
    first = LegacyAdapter(ctx, ThreadManager(ctx, []), dest="127.0.0.1:9", listen_port=port,
                          bind_host="127.0.0.1")
    try:
        ctx2 = RuntimeContext(clock=Clock(), params=ParamRegistry())
        with pytest.raises(ConfigError, match=f"cannot listen on 127.0.0.1:{port}"):
            LegacyAdapter(ctx2, ThreadManager(ctx2, []), dest="127.0.0.1:9", listen_port=port,
                          bind_host="127.0.0.1")
        # building without listening (parameter listing while a runtime flies) is fine
        ctx3 = RuntimeContext(clock=Clock(), params=ParamRegistry())
        LegacyAdapter(ctx3, ThreadManager(ctx3, []), dest="127.0.0.1:9", listen_port=port,
                      bind_host="127.0.0.1", listen=False).close()
    finally:
        first.close()
