"""Ground stations through the companion to a real ArduPlane SITL (marked `sitl`).

The autopilot is ArduPilot's own (`companion.sim.ardupilot.ArduPlaneSitl`, at speed-up 5), on a
pseudo-terminal cable to the companion's `--autopilot`; each client talks to the companion
only, over a UDP ground link, and must find both components: ArduPlane (1/1) and the companion
(1/191). pymavlink, MAVProxy 1.8.75 (as a separate process, as tests/test_gcs_mavproxy.py runs
it) and MAVSDK 4.1 (the native binding, as tests/test_gcs_mavsdk.py) each get one test.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import free_udp_port, quiet_mavsdk, wait_for
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as apm
from test_gcs_mavproxy import MavProxy
from test_gcs_router import Running, companion_config

from companion.sim.ardupilot import ArduPlaneSitl

pytestmark = pytest.mark.sitl

SPEEDUP = 5
PARAM = "MAV2_EXTRA3"
"""An ArduPlane parameter that changes nothing here: a stream rate of its second MAVLink port
(SERIAL1, not wired in these tests)."""
STREAM_HZ = {"AP_IMU_HZ": 4, "AP_ATT_HZ": 4, "AP_POS_HZ": 2, "AP_RC_HZ": 1, "AP_GPS_HZ": 1}


class Companion:
    """ArduPlane SITL + the companion runtime with `--autopilot` and one ground UDP link."""

    def __init__(self, tmp: Path, ground_port: int, *, vehicle_id: int = 7) -> None:
        self.sitl = ArduPlaneSitl(speedup=SPEEDUP, ground=False).start()
        # ArduPlane is system 1: the companion takes its id once heard. What the autopilot
        # link asks for is the ground's telemetry too: at speed-up 5 its defaults (IMU 50 Hz...)
        # come at ~2000 frames/s, more than a Python client parses on a shared machine, so
        # ask for less
        self.running = Running(companion_config(tmp, [f"udpout:127.0.0.1:{ground_port}"],
                                                self.sitl.companion_url, vehicle_id=vehicle_id),
                               params=STREAM_HZ)
        self.rt = self.running.rt

    def stats(self) -> dict[str, Any]:
        return dict(self.rt.bridges[0].stats()[0])

    def close(self) -> None:
        try:
            self.running.stop()
        finally:
            self.sitl.stop()


@pytest.fixture
def companion_for(tmp_path: Path) -> Iterator[Any]:
    made: list[Companion] = []

    def make(ground_port: int, **kw: Any) -> Companion:
        c = Companion(tmp_path, ground_port, **kw)
        made.append(c)
        return c

    yield make
    for c in made:
        c.close()


def value_in(line: str) -> float | None:
    """The value MAVProxy printed after PARAM ("NAME 1.0" or "NAME = 1.0000000")."""
    found = re.search(rf"{PARAM}\s*=?\s*(-?[0-9.]+)", line)
    return float(found.group(1)) if found else None


def answers_about(gcs: Any, name: str, timeout_s: float) -> list[Any]:
    """PARAM_VALUE and PARAM_ERROR about `name` until one came and 1 s passed without more."""
    found: list[Any] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        msg = gcs.recv_match(type=["PARAM_VALUE", "PARAM_ERROR"], blocking=True, timeout=0.2)
        if msg is not None and msg.param_id == name:
            found.append(msg)
            deadline = min(deadline, time.monotonic() + 1.0)
    return found


def test_pymavlink_sees_arduplane_and_the_companion(companion_for: Any) -> None:
    port = free_udp_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255,
                                     source_component=190, dialect="ardupilotmega")
    try:
        companion = companion_for(port)
        beats: dict[tuple[int, int], Any] = {}
        seen: set[str] = set()
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and not (
                {(1, 1), (1, 191)} <= set(beats) and "ATTITUDE" in seen):
            msg = gcs.recv_match(blocking=True, timeout=0.5)
            if msg is None:
                continue
            if msg.get_type() == "HEARTBEAT":
                beats[(msg.get_srcSystem(), msg.get_srcComponent())] = msg
            if msg.get_srcComponent() == 1:
                seen.add(msg.get_type())
        assert (1, 1) in beats and (1, 191) in beats, beats
        assert beats[(1, 1)].autopilot == apm.MAV_AUTOPILOT_ARDUPILOTMEGA
        assert beats[(1, 1)].type == apm.MAV_TYPE_FIXED_WING
        assert beats[(1, 191)].type == apm.MAV_TYPE_ONBOARD_CONTROLLER
        assert beats[(1, 191)].autopilot == apm.MAV_AUTOPILOT_INVALID
        assert "ATTITUDE" in seen
        # pymavlink addresses the autopilot's system, every component (target component 0):
        # a parameter read goes to ArduPlane and its answer comes back; the companion, which
        # has no such parameter, stays silent (no PARAM_ERROR)
        assert (gcs.target_system, gcs.target_component) == (1, 0)
        for component in (1, 0):
            gcs.mav.param_request_read_send(1, component, PARAM.encode(), -1)
            answers = answers_about(gcs, PARAM, 10.0)
            assert [(m.get_type(), m.get_srcComponent()) for m in answers] == [
                ("PARAM_VALUE", 1)], answers
        st = companion.stats()
        assert st["routed_forwarded_in"] >= 1 and st["routed_forwarded_out"] > 50
    finally:
        gcs.close()


def test_mavproxy_lists_and_sets_an_arduplane_parameter_through_the_companion(
        companion_for: Any, tmp_path: Path) -> None:
    port = free_udp_port()
    companion_for(port)
    mp = MavProxy(port, tmp_path)
    try:
        line = mp.wait_line("Received", 90.0)
        assert line is not None, "\n".join(mp.lines[-40:])
        n = int(line.split("Received")[1].split()[0])
        assert n > 500, line  # ArduPlane's list (the companion's has about a hundred)
        mark = mp.mark()
        mp.cmd(f"param show {PARAM}")
        before = mp.wait_line(PARAM, 10.0, mark)
        assert before is not None, "\n".join(mp.lines[-20:])
        new = 3 if value_in(before) != 3 else 4
        mp.cmd(f"param set {PARAM} {new}")

        def shows_new_value() -> bool:
            mark = mp.mark()
            mp.cmd(f"param fetch {PARAM}")
            line = mp.wait_line(f"{PARAM} =", 3.0, mark)  # "NAME = 3.0000000"
            return line is not None and value_in(line) == new

        assert wait_for(shows_new_value, 30.0, 0.5), "\n".join(mp.lines[-20:])
    finally:
        mp.close()


def test_mavsdk_finds_the_autopilot_through_the_companion_and_receives_attitude(
        companion_for: Any) -> None:
    from mavsdk import ComponentType, Configuration, Mavsdk
    from mavsdk.plugins.telemetry.telemetry import Telemetry

    port = free_udp_port()
    with quiet_mavsdk():
        sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        try:
            sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
            companion = companion_for(port)
            system = sdk.first_autopilot(60.0)
            assert system is not None, "MAVSDK did not discover the autopilot"
            assert system.get_system_id() == 1 and system.has_autopilot()
            attitude: list[Any] = []
            lock = threading.Lock()

            def keep(value: Any, *_: Any) -> None:
                with lock:
                    attitude.append(value)

            telemetry = Telemetry(system)  # kept: the subscription ends with the plugin
            telemetry.subscribe_attitude_euler(keep)
            assert wait_for(lambda: len(attitude) >= 5, 30.0), (
                companion.stats(), companion.rt.manager.find("autopilot").counters())
            with lock:
                last = attitude[-1]
            assert abs(last.roll_deg) < 5 and abs(last.pitch_deg) < 10  # on the ground, level
        finally:
            sdk.destroy()
