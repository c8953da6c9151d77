"""A fleet of simulated aircraft behind a real MAVProxy 1.8.75 used as a router.

Real parts only: `companion sim --vehicles 3` (three runtimes and three JSBSim worlds,
system ids 1..3), one `mavproxy.py` process routing between them and three ground-station ports,
two pymavlink ground stations and one MAVSDK instance listening on those ports at once.

How the aircraft reach the router: `--vehicles K` gives every aircraft the same `--mavlink`
endpoints (companion.sim.runner.run_fleet passes its arguments on unchanged, only the vehicle
id, legacy port and parameter file differ), so all K aircraft send `udpout` to one port and
MAVProxy has one `--master=udpin:` for the whole fleet. That works because pymavlink's `udpin`
keeps every sender as a client and writes to all of them, and each aircraft acts only on what
is addressed to its own system id (or to everyone): a PARAM_SET for system 2 reaches aircraft 1
too, which must ignore it — the test checks exactly that. (One `--master` per aircraft would
need a per-vehicle endpoint in run_fleet; see docs/ground-stations.md.)

MAVProxy runs as a pure router: `--default-modules=` (no parameter download, no module of its
own asking the aircraft for anything), `--streamrate=-1` (it does not re-rate the aircraft's
telemetry with REQUEST_DATA_STREAM), `--no-state` and `--state-basedir` in tmp_path (nothing
written into the repository).

The aircraft start from parameter files that differ (MAV_B1_V_FULL 8.1 on aircraft 1, 8.2 on
aircraft 2, 8.3 on aircraft 3), so reading the right value proves the answer came from the
aircraft asked.
"""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import pytest
from conftest import free_udp_port, quiet_mavsdk, wait_for
from pymavlink import mavutil

# MAVLink 2 for mavutil, restored afterwards (the bridge sends MAVLink 2 only)
from test_gcs_pymavlink import mavlink2  # noqa: F401

from companion.core.params import parse_param_file, to_float32

MAVPROXY = Path(sys.executable).with_name("mavproxy.py")
K = 3  # aircraft
FLIGHT_S = 300  # programmed simulated seconds: a safety net only (each test ends the fleet)
# Real time, not --fast: these tests route messages, and three runtimes and three worlds at 5x
# beside MAVProxy and MAVSDK on a loaded 2-core CI machine starved a link thread past its
# scaled watchdog window (200 ms of host time at 5x) once: a restart the routing did not cause.
START_TIMEOUT_S = 40.0  # three JSBSim worlds and runtimes on two cores: about 3 s normally
STOP_TIMEOUT_S = 15.0
PARAM = "MAV_B1_V_FULL"  # avionics battery full voltage: only scales the reported voltage
SEEDED = {i: round(8.0 + i / 10, 1) for i in range(1, K + 1)}
NEW_VALUE = 12.6


@pytest.fixture(scope="module", autouse=True)
def _mavsdk_quiet() -> Iterator[None]:
    with quiet_mavsdk():
        yield


# ---------------------------------------------------------------------------- processes
class Fleet:
    """`companion sim --vehicles K` in its own session (a last-resort SIGKILL reaches every
    runtime and world it started); output in files under `root`, which is also its working
    directory (run_fleet's parameter files `params-v<id>.parm` are relative to it)."""

    def __init__(self, root: Path, endpoint: str, vehicles: int, *extra: str) -> None:
        self.root = root
        self.flights = root / "flights"
        self.err_path = root / "fleet.stderr"
        legacy = free_udp_port()  # run_fleet uses legacy..legacy+K-1
        cmd = [sys.executable, "-m", "companion", "sim", "--vehicles", str(vehicles),
               "--duration", str(FLIGHT_S), "--scenario", "level", "--seed", "1", "--json",
               "--log-dir", str(self.flights), "--mavlink", endpoint,
               "--legacy-listen", str(legacy), "--legacy-dest", f"127.0.0.1:{free_udp_port()}",
               *extra]
        with open(root / "fleet.stdout", "w") as out, open(self.err_path, "w") as err:
            self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=err,
                                         cwd=root, start_new_session=True)

    def stderr_tail(self) -> str:
        try:
            return self.err_path.read_text(errors="replace")[-3000:]
        except OSError:
            return ""

    def check_alive(self) -> None:
        if self.proc.poll() is not None:
            pytest.fail(f"companion sim --vehicles exited early with {self.proc.returncode}:\n"
                        f"{self.stderr_tail()}", pytrace=False)

    def stop(self) -> list[dict[str, Any]]:
        """SIGINT to run_fleet, which passes it to every aircraft; each must end cleanly."""
        self.check_alive()
        self.proc.send_signal(signal.SIGINT)
        try:
            rc = self.proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"the fleet still runs {STOP_TIMEOUT_S} s after SIGINT")
        assert rc == 0, self.stderr_tail()
        out = []
        for run in sorted(self.flights.glob("*/run.json")):
            summary = json.loads((run.parent / "summary.json").read_text())
            summary["vehicle_id"] = json.loads(run.read_text())["config"]["vehicle"]["id"]
            out.append(summary)
        return out

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                pass
        try:  # whatever is left of the session: runtimes, worlds
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.proc.wait(10)


class Router:
    """MAVProxy as a router: one master (the whole fleet), one `--out` per ground station."""

    def __init__(self, root: Path, master_port: int | list[int], out_ports: list[int]) -> None:
        if not MAVPROXY.is_file():
            pytest.fail(f"MAVProxy is a dependency and is missing: no {MAVPROXY.name} next to "
                        f"{sys.executable} (pip install MAVProxy)", pytrace=False)
        state = root / "mavproxy"
        state.mkdir()
        self.out_path = root / "mavproxy.out"
        masters = master_port if isinstance(master_port, list) else [master_port]
        cmd = [sys.executable, "-u", str(MAVPROXY),
               *(f"--master=udpin:127.0.0.1:{p}" for p in masters),
               *(f"--out=udpout:127.0.0.1:{p}" for p in out_ports),
               "--daemon", "--non-interactive", "--no-state", "--state-basedir", str(state),
               "--default-modules=", "--streamrate=-1"]
        with open(self.out_path, "w") as out:
            self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out,
                                         stderr=subprocess.STDOUT, cwd=state,
                                         start_new_session=True)

    def output(self) -> str:
        try:
            return self.out_path.read_text(errors="replace")[-3000:]
        except OSError:
            return ""

    def check_alive(self) -> None:
        if self.proc.poll() is not None:
            pytest.fail(f"MAVProxy could not start or died (exit {self.proc.returncode}):\n"
                        f"{self.output()}", pytrace=False)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)


class GroundStation:
    """A pymavlink ground station on `udpin:127.0.0.1:PORT`, read by a thread of its own so
    the socket never overflows while the test waits on the other one; sends and reads share a
    lock (the mavfile is not thread-safe)."""

    def __init__(self, port: int, sysid: int) -> None:
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=sysid,
                                               source_component=190, dialect="common")
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.heartbeats: dict[int, Any] = {}  # system id -> last component-1 HEARTBEAT
        self.param_values: list[tuple[int, str, float]] = []  # (system id, name, value)
        self._thread = threading.Thread(target=self._read, name=f"gcs{sysid}", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                m = self.conn.recv_msg()
            if m is None:
                select.select([self.conn.fd], [], [], 0.05)
                continue
            kind = m.get_type()
            if kind == "HEARTBEAT" and m.get_srcComponent() == 1:
                with self._lock:
                    self.heartbeats[m.get_srcSystem()] = m
            elif kind == "PARAM_VALUE":
                with self._lock:
                    self.param_values.append((m.get_srcSystem(), m.param_id, m.param_value))

    def systems(self) -> set[int]:
        with self._lock:
            return set(self.heartbeats)

    def mark(self) -> int:
        with self._lock:
            return len(self.param_values)

    def values_since(self, mark: int, sysid: int, name: str) -> list[float]:
        with self._lock:
            return [v for s, n, v in self.param_values[mark:] if s == sysid and n == name]

    def read_param(self, sysid: int, name: str, timeout_s: float = 10.0) -> float:
        """PARAM_REQUEST_READ by name to `sysid` (repeated each second: UDP); the first answer
        from that system that arrives after the request."""
        deadline = time.monotonic() + timeout_s
        mark = self.mark()
        while time.monotonic() < deadline:
            with self._lock:
                self.conn.mav.param_request_read_send(sysid, 1, name.encode(), -1)
            if wait_for(lambda: bool(self.values_since(mark, sysid, name)), 1.0, 0.01):
                return self.values_since(mark, sysid, name)[0]
        pytest.fail(f"no PARAM_VALUE {name} from system {sysid} within {timeout_s} s")

    def set_param(self, sysid: int, name: str, value: float, timeout_s: float = 10.0) -> None:
        """PARAM_SET to `sysid` only, until that system announces the new value."""
        deadline = time.monotonic() + timeout_s
        mark = self.mark()
        while time.monotonic() < deadline:
            with self._lock:
                self.conn.mav.param_set_send(sysid, 1, name.encode(), value,
                                             mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
            if wait_for(lambda: to_float32(value) in self.values_since(mark, sysid, name),
                        1.0, 0.01):
                return
        pytest.fail(f"system {sysid} did not take {name}={value} within {timeout_s} s")

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.conn.close()


@contextmanager
def mavsdk_on(port: int) -> Iterator[Any]:
    from mavsdk import ComponentType, Configuration, Mavsdk

    sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        yield sdk
    finally:
        sdk.destroy()


def saved(path: Path) -> dict[str, float]:
    return {name: value for _, name, _, value, problem in parse_param_file(path)
            if name is not None and problem is None}


# ---------------------------------------------------------------------------- the test
def test_fleet_behind_mavproxy_two_gcs_and_mavsdk(tmp_path: Path, mavlink2: None) -> None:  # noqa: F811
    for sysid, value in SEEDED.items():
        (tmp_path / f"params-v{sysid}.parm").write_text(f"{PARAM} {value}\n")
    master, g1, g2, g3 = (free_udp_port() for _ in range(4))
    with ExitStack() as stack:
        # the router first, so the aircraft's first HEARTBEATs already reach it
        router = Router(tmp_path, master, [g1, g2, g3])
        stack.callback(router.close)
        gcs1 = GroundStation(g1, 201)
        stack.callback(gcs1.close)
        gcs2 = GroundStation(g2, 202)
        stack.callback(gcs2.close)
        sdk = stack.enter_context(mavsdk_on(g3))
        fleet = Fleet(tmp_path, f"udpout:127.0.0.1:{master}", K)
        stack.callback(fleet.close)

        def both_see_everyone() -> bool:
            router.check_alive()
            fleet.check_alive()
            return gcs1.systems() >= set(SEEDED) and gcs2.systems() >= set(SEEDED)

        assert wait_for(both_see_everyone, START_TIMEOUT_S, 0.05), (
            f"HEARTBEATs: gcs1 {gcs1.systems()}, gcs2 {gcs2.systems()}\n{router.output()}")

        # each ground station reads the parameter of each aircraft, addressed by system id
        for gcs in (gcs1, gcs2):
            for sysid, value in SEEDED.items():
                assert gcs.read_param(sysid, PARAM) == to_float32(value), (gcs, sysid)

        # GCS 1 changes aircraft 2 only; GCS 2 reads every aircraft back
        gcs1.set_param(2, PARAM, NEW_VALUE)
        assert gcs2.read_param(2, PARAM) == to_float32(NEW_VALUE)
        for sysid in set(SEEDED) - {2}:
            assert gcs2.read_param(sysid, PARAM) == to_float32(SEEDED[sysid]), sysid
            # and it never announced a change: it ignored the PARAM_SET for system 2
            assert to_float32(NEW_VALUE) not in gcs1.values_since(0, sysid, PARAM)
            assert to_float32(NEW_VALUE) not in gcs2.values_since(0, sysid, PARAM)

        # MAVSDK behind the same router discovers every system. Its Python binding (4.x,
        # native) exposes every discovered system through Mavsdk.get_systems(), each with its
        # own id and autopilot flag, so no mavsdk_server output is needed.
        def mavsdk_sees_all() -> bool:
            router.check_alive()
            return {s.get_system_id() for s in sdk.get_systems()
                    if s.has_autopilot()} == set(SEEDED)

        assert wait_for(mavsdk_sees_all, 20.0, 0.05), \
            [s.get_system_id() for s in sdk.get_systems()]
        assert sdk.system_count() == K

        router.check_alive()
        summaries = fleet.stop()
        assert sorted(s["vehicle_id"] for s in summaries) == list(range(1, K + 1))
        for s in summaries:
            assert s["stop_reason"] == "signal SIGINT", s["stop_reason"]
            threads = {t["name"]: t for t in s["threads"]}
            for name in ("imu", "gps", "servo", "estimator", "control", "mav0rx", "mav0tx"):
                assert threads[name]["restarts"] == 0 and not threads[name]["failed"], \
                    threads[name]
        # the change persisted in aircraft 2's parameter file only
        for sysid, value in {**SEEDED, 2: NEW_VALUE}.items():
            assert saved(tmp_path / f"params-v{sysid}.parm")[PARAM] == pytest.approx(value, abs=1e-5)


def test_one_master_per_aircraft_with_a_port_step(tmp_path: Path, mavlink2: None) -> None:  # noqa: F811
    """`--mavlink-port-step 1`: aircraft i sends to the endpoint's port + i - 1, so the router
    has one `--master` per aircraft, and a request for one system goes down its link only."""
    for sysid, value in SEEDED.items():
        (tmp_path / f"params-v{sysid}.parm").write_text(f"{PARAM} {value}\n")
    base = free_udp_port()
    while not all(_udp_free(base + i) for i in range(K)):
        base = free_udp_port()
    gcs_port = free_udp_port()
    with ExitStack() as stack:
        router = Router(tmp_path, [base + i for i in range(K)], [gcs_port])
        stack.callback(router.close)
        gcs = GroundStation(gcs_port, 201)
        stack.callback(gcs.close)
        fleet = Fleet(tmp_path, f"udpout:127.0.0.1:{base}", K, "--mavlink-port-step", "1")
        stack.callback(fleet.close)
        assert wait_for(lambda: (router.check_alive(), fleet.check_alive(),
                                 gcs.systems() >= set(SEEDED))[-1], START_TIMEOUT_S, 0.05), (
            f"HEARTBEATs: {gcs.systems()}\n{router.output()}")
        for sysid, value in SEEDED.items():
            assert gcs.read_param(sysid, PARAM) == to_float32(value), sysid
        fleet.stop()


def _udp_free(port: int) -> bool:
    import socket

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind(("127.0.0.1", port))
        return True
    except OSError:
        return False
    finally:
        s.close()


def test_endpoint_ports_shift_per_aircraft() -> None:
    from companion.sim.runner import shift_endpoint_port

    assert shift_endpoint_port("udpout:127.0.0.1:14550", 2) == "udpout:127.0.0.1:14552"
    assert shift_endpoint_port("udpin:0.0.0.0:14550?signing=off", 1) == \
        "udpin:0.0.0.0:14551?signing=off"
    assert shift_endpoint_port("tcp:127.0.0.1:5760", 3) == "tcp:127.0.0.1:5763"
    assert shift_endpoint_port("/dev/ttyUSB0,57600", 5) == "/dev/ttyUSB0,57600"
    assert shift_endpoint_port("udpout:127.0.0.1:14550", 0) == "udpout:127.0.0.1:14550"
