"""The real ArduPlane SITL beside the companion (`companion.sim.ardupilot`, `.ardupilot_mission`).

Tests marked `sitl` start ArduPilot's own autopilot (ARDUPILOT_SITL names the binary; without it
they are deselected, with one line saying so: README, "Testing against a real autopilot"). The
others check what needs no autopilot: the cable, the mission's geometry and the one-line errors.
"""

from __future__ import annotations

import math
import os
import select
import time
from pathlib import Path

import psutil
import pytest
from conftest import peer_tool
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.sim.ardupilot import (
    SITL_ENV,
    ArduPlaneSitl,
    PtyCable,
    SitlError,
    SitlNotFound,
    find_binary,
    find_defaults,
)
from companion.sim.ardupilot_mission import (
    ARDUPLANE_MODES,
    FlightReport,
    circuit_items,
    fly_with_arduplane,
    host_bound_s,
)


def _read_until(fd: int, want: bytes, timeout_s: float) -> bytes:
    got = b""
    deadline = time.monotonic() + timeout_s
    while want not in got and time.monotonic() < deadline:
        r, _, _ = select.select([fd], [], [], 0.05)
        if r:
            got += os.read(fd, 4096)
    return got


def test_a_cable_carries_bytes_both_ways_and_closes_clean() -> None:
    cable = PtyCable("t")
    try:
        a = os.open(cable.autopilot_path, os.O_RDWR | os.O_NOCTTY)
        b = os.open(cable.companion_path, os.O_RDWR | os.O_NOCTTY)
        try:
            os.write(a, b"\x00\xfd to the companion \r\n\x03")  # raw: no echo, no line editing
            assert _read_until(b, b"\x03", 5.0) == b"\x00\xfd to the companion \r\n\x03"
            os.write(b, b"to the autopilot")
            assert _read_until(a, b"autopilot", 5.0) == b"to the autopilot"
            assert _read_until(a, b"x", 0.2) == b""  # nothing echoed back
        finally:
            os.close(a)
            os.close(b)
        assert cable.companion_url == f"{cable.companion_path},921600"
    finally:
        cable.close()


def test_a_missing_binary_is_one_line_saying_how_to_give_one(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv(SITL_ENV, raising=False)
    not_executable = tmp_path / "arduplane"
    not_executable.write_text("")
    for given in (None, tmp_path / "nowhere", not_executable):
        with pytest.raises(SitlNotFound) as err:
            ArduPlaneSitl(given)
        message = str(err.value)
        assert "\n" not in message
        assert "--autopilot-binary PATH" in message and f"{SITL_ENV}=PATH" in message
    monkeypatch.setenv(SITL_ENV, str(tmp_path / "nowhere"))
    with pytest.raises(SitlNotFound, match="nowhere"):
        find_binary()
    not_executable.chmod(0o755)
    with pytest.raises(SitlNotFound, match="--autopilot-defaults PATH") as err:
        find_defaults(find_binary(not_executable))  # no plane.parm beside it
    assert "\n" not in str(err.value)


def test_an_autopilot_that_exits_at_once_is_an_error_with_its_last_words(tmp_path: Path) -> None:
    binary = tmp_path / "arduplane"
    binary.write_text("#!/bin/sh\necho starting\necho 'bad option: --model' >&2\nexit 3\n")
    binary.chmod(0o755)
    (tmp_path / "plane.parm").write_text("")
    before = _children()
    sitl = ArduPlaneSitl(binary)
    with pytest.raises(SitlError, match=r"exited with code 3: bad option: --model"):
        sitl.start()
    assert sitl.proc is None and sitl.workdir is None and sitl.companion_cable is None
    assert _children() == before


def test_the_circuit_takes_off_and_circles_away_from_home_for_ever() -> None:
    home = (-35.363262, 149.165237, 584.0)
    items = circuit_items(*home)
    assert [i.seq for i in items] == list(range(len(items)))
    commands = [i.command for i in items]
    assert commands == [mavlink.MAV_CMD_NAV_WAYPOINT, mavlink.MAV_CMD_NAV_TAKEOFF,
                        *[mavlink.MAV_CMD_NAV_WAYPOINT] * 4, mavlink.MAV_CMD_DO_JUMP]
    assert items[1].z == 80.0
    for wp in items[2:6]:
        north = math.radians(wp.x / 1e7 - home[0]) * 6_378_137.0
        east = math.radians(wp.y / 1e7 - home[1]) * 6_378_137.0 * math.cos(math.radians(home[0]))
        assert 400.0 <= math.hypot(north, east) <= 600.0
        assert wp.frame == mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT and wp.z == 80.0
    jump = items[-1]
    assert (jump.param1, jump.param2) == (2, -1)  # to the first corner, for ever
    assert host_bound_s(100.0, 10.0) < host_bound_s(100.0, 1.0)


def _children() -> list[psutil.Process]:
    return psutil.Process().children(recursive=True)


@pytest.mark.sitl
def test_the_autopilot_streams_to_the_companion_over_its_cable() -> None:
    before = _children()
    sitl = ArduPlaneSitl(peer_tool("sitl"), speedup=5, ground=False)
    t0 = time.monotonic()
    with sitl:
        workdir = sitl.workdir
        assert workdir is not None and workdir.is_dir()
        conn = mavutil.mavlink_connection(sitl.companion_url, source_system=254)
        seen: dict[str, float] = {}
        try:
            deadline = time.monotonic() + 20.0
            while not {"HEARTBEAT", "RAW_IMU", "GPS_RAW_INT"} <= seen.keys():
                assert time.monotonic() < deadline, f"only {sorted(seen)} within 20 s"
                msg = conn.recv_match(type=["HEARTBEAT", "RAW_IMU", "GPS_RAW_INT"],
                                      blocking=True, timeout=0.2)
                if msg is None:
                    continue
                if msg.get_type() == "HEARTBEAT":
                    assert (msg.autopilot, msg.type) == (mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                         mavlink.MAV_TYPE_FIXED_WING)
                    assert (msg.get_srcSystem(), msg.get_srcComponent()) == (1, 1)
                seen.setdefault(msg.get_type(), time.monotonic() - t0)
        finally:
            conn.close()
        assert sitl.running()
        print(f"SITL x5: opened its ports {sitl.opened_s:.3f} s, first HEARTBEAT "
              f"{seen['HEARTBEAT']:.3f} s, RAW_IMU {seen['RAW_IMU']:.3f} s after the start")
    assert sitl.proc is None and not workdir.exists()
    assert _children() == before


@pytest.mark.sitl
def test_two_instances_fly_side_by_side_as_two_systems() -> None:
    with ArduPlaneSitl(peer_tool("sitl"), speedup=2, instance=0, ground=False) as one, \
            ArduPlaneSitl(peer_tool("sitl"), speedup=2, instance=1, ground=False) as two:
        for sitl, sysid in ((one, 1), (two, 2)):
            conn = mavutil.mavlink_connection(sitl.companion_url, source_system=254)
            try:
                msg = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=15.0)
            finally:
                conn.close()
            assert msg is not None and msg.get_srcSystem() == sysid


@pytest.mark.sitl
def test_the_scripted_mission_takes_off_and_turns() -> None:
    def climbed_and_turned(r: FlightReport) -> bool:
        return r.max_relative_alt_m > 40.0 and r.max_true_roll_deg > 15.0

    t0 = time.monotonic()
    # at 5x, not faster: a loaded machine keeps a 10x autopilot from its simulated time
    report = fly_with_arduplane(peer_tool("sitl"), speedup=5, duration_s=300.0,
                                until=climbed_and_turned)
    host_s = time.monotonic() - t0
    assert report.armed and report.mode == ARDUPLANE_MODES["AUTO"], report
    assert climbed_and_turned(report), report
    assert "Mission: 1 Takeoff" in report.statustexts
    print(f"SITL x5: steps {report.steps_s} (host s), {report.sim_s:.1f} s simulated, "
          f"{host_s:.1f} s in all")
    assert host_s < 150.0
