"""A scripted ground station and pilot for a flight of the real ArduPlane SITL.

`ArduPlaneGround` talks MAVLink (pymavlink) to the autopilot over its SERIAL1 cable
(`ArduPlaneSitl.ground_url`) and does what a pilot does before an autonomous flight, one bounded
step at a time: wait for the HEARTBEAT, ask for telemetry, wait until the autopilot is ready to
arm (pre-arm checks passed: SYS_STATUS; the EKF has attitude, velocity and an absolute position:
EKF_STATUS_REPORT; a 3D GPS fix), upload a mission (MISSION_COUNT / MISSION_ITEM_INT), arm
(MAV_CMD_COMPONENT_ARM_DISARM) and switch to AUTO. The mission (`circuit_items`) takes off to
80 m and flies a square circuit whose corners are about 570 m from home, for ever (DO_JUMP).
While it flies, `fly` records what a test scores: the height above home (GLOBAL_POSITION_INT)
and the simulator's true roll (SIMSTATE).

Every step is bounded in simulated seconds of the autopilot, turned into host seconds by
`host_bound_s` (the speed-up divides them; a floor and a slack factor cover a loaded machine,
where the autopilot runs slower than asked). A step that does not finish raises `MissionError`
naming the step and the autopilot's last STATUSTEXT. `fly_with_arduplane` runs it all: start
the autopilot, fly the mission for a while, stop, and return the `FlightReport`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.sim.ardupilot import ArduPlaneSitl

ARDUPLANE_MODES = {"MANUAL": 0, "CIRCLE": 1, "STABILIZE": 2, "FBWA": 5, "FBWB": 6, "AUTO": 10,
                   "RTL": 11, "LOITER": 12, "TAKEOFF": 13, "GUIDED": 15}
"""ArduPlane's custom modes (HEARTBEAT.custom_mode)."""
READY_EKF_FLAGS = (mavlink.EKF_ATTITUDE | mavlink.EKF_VELOCITY_HORIZ | mavlink.EKF_POS_HORIZ_ABS
                   | mavlink.EKF_POS_VERT_ABS)
STREAM_RATE_HZ = 10
"""Telemetry rate asked of the autopilot on the ground link (simulated time), up to a speed-up
of `STREAM_SPEEDUP`."""
STREAM_SPEEDUP = 10.0
TAKEOFF_ALT_M = 80.0
CIRCUIT_HALF_SIDE_M = 400.0
HOST_FLOOR_S = 10.0
HOST_SLACK = 3.0
HEARTBEAT_INTERVAL_HOST_S = 0.5
RESEND_HOST_S = 1.0
EARTH_RADIUS_M = 6_378_137.0

# Bounds of the steps, in simulated seconds.
HEARTBEAT_SIM_S = 10.0
READY_SIM_S = 120.0
UPLOAD_SIM_S = 30.0
ARM_SIM_S = 30.0
MODE_SIM_S = 10.0


def host_bound_s(sim_s: float, speedup: float) -> float:
    """Host seconds allowed for `sim_s` simulated seconds at `speedup`."""
    return HOST_FLOOR_S + HOST_SLACK * sim_s / speedup


class MissionError(RuntimeError):
    """A step of the scripted flight did not finish: the message names the step."""

    def __init__(self, step: str, why: str) -> None:
        super().__init__(f"{step}: {why}")
        self.step = step


@dataclass
class FlightReport:
    steps_s: dict[str, float] = field(default_factory=dict)
    """Host seconds from the connection to the end of each step."""
    sim_s: float = 0.0
    """The autopilot's time since boot at the last message, simulated seconds."""
    armed: bool = False
    mode: int = -1
    relative_alt_m: float = 0.0
    max_relative_alt_m: float = 0.0
    max_true_roll_deg: float = 0.0
    """Largest |roll| of the simulated aircraft (SIMSTATE), degrees."""
    statustexts: list[str] = field(default_factory=list)


def offset_deg(lat_deg: float, lon_deg: float, north_m: float, east_m: float) -> tuple[float, float]:
    """A position `north_m`, `east_m` from `lat_deg`, `lon_deg` (flat earth: fine within km)."""
    dlat = math.degrees(north_m / EARTH_RADIUS_M)
    dlon = math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(lat_deg))))
    return lat_deg + dlat, lon_deg + dlon


def circuit_items(home_lat_deg: float, home_lon_deg: float, home_alt_m: float, *,
                  takeoff_alt_m: float = TAKEOFF_ALT_M,
                  half_side_m: float = CIRCUIT_HALF_SIDE_M, target_system: int = 1,
                  target_component: int = 1) -> list[mavlink.MAVLink_mission_item_int_message]:
    """Home, a takeoff to `takeoff_alt_m`, the four corners of a square of side `2 half_side_m`
    centred on home (clockwise from north-east) and a jump back to the first corner, for ever."""
    rel = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    rows: list[tuple[int, int, tuple[float, float, float, float], float, float, float]] = [
        (mavlink.MAV_FRAME_GLOBAL_INT, mavlink.MAV_CMD_NAV_WAYPOINT, (0, 0, 0, 0),
         home_lat_deg, home_lon_deg, home_alt_m),
        (rel, mavlink.MAV_CMD_NAV_TAKEOFF, (15, 0, 0, 0), home_lat_deg, home_lon_deg,
         takeoff_alt_m),
    ]
    for north, east in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        lat, lon = offset_deg(home_lat_deg, home_lon_deg, north * half_side_m, east * half_side_m)
        rows.append((rel, mavlink.MAV_CMD_NAV_WAYPOINT, (0, 0, 0, 0), lat, lon, takeoff_alt_m))
    rows.append((rel, mavlink.MAV_CMD_DO_JUMP, (2, -1, 0, 0), 0.0, 0.0, 0.0))  # -1: for ever
    return [mavlink.MAVLink_mission_item_int_message(
        target_system, target_component, seq, frame, command, 0, 1, *params,
        int(round(lat * 1e7)), int(round(lon * 1e7)), alt, mavlink.MAV_MISSION_TYPE_MISSION)
        for seq, (frame, command, params, lat, lon, alt) in enumerate(rows)]


class ArduPlaneGround:
    """A ground station on one of the autopilot's serial ports (`url`: ``/dev/pts/N,BAUD``)."""

    def __init__(self, url: str, *, speedup: float, target_system: int = 1,
                 source_system: int = 255, source_component: int = 190) -> None:
        self.speedup = speedup
        self.target_system = target_system
        self.conn: Any = mavutil.mavlink_connection(url, source_system=source_system,
                                                    source_component=source_component)
        self.report = FlightReport()
        self.started_at = time.monotonic()
        self._heartbeat_at = 0.0
        self._last: dict[str, Any] = {}

    def close(self) -> None:
        self.conn.close()

    def __enter__(self) -> ArduPlaneGround:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- receiving -------------------------------------------------------------------------------
    def poll(self, timeout_s: float = 0.05) -> Any:
        """One message from the autopilot (None after `timeout_s`), recorded; sends our own
        HEARTBEAT when it is due."""
        now = time.monotonic()
        if now - self._heartbeat_at >= HEARTBEAT_INTERVAL_HOST_S:
            self._heartbeat_at = now
            self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                         0, 0, mavlink.MAV_STATE_ACTIVE)
        msg = self.conn.recv_match(blocking=True, timeout=timeout_s)
        if msg is None or msg.get_srcSystem() != self.target_system:
            return None
        kind = msg.get_type()
        self._last[kind] = msg
        report = self.report
        boot_ms = getattr(msg, "time_boot_ms", None)
        if boot_ms is not None:
            report.sim_s = boot_ms / 1000.0
        if kind == "HEARTBEAT" and msg.get_srcComponent() == 1:
            report.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            report.mode = msg.custom_mode
        elif kind == "GLOBAL_POSITION_INT":
            report.relative_alt_m = msg.relative_alt / 1000.0
            report.max_relative_alt_m = max(report.max_relative_alt_m, report.relative_alt_m)
        elif kind == "SIMSTATE":
            report.max_true_roll_deg = max(report.max_true_roll_deg, abs(math.degrees(msg.roll)))
        elif kind == "STATUSTEXT":
            report.statustexts.append(msg.text)
        return msg

    def last(self, kind: str) -> Any:
        return self._last.get(kind)

    def wait(self, step: str, sim_s: float, done: Callable[[], bool],
             resend: Callable[[], None] | None = None) -> None:
        """Poll until `done()`, calling `resend` every `RESEND_HOST_S`; `MissionError` after
        `host_bound_s(sim_s)`. Records the step's end in `report.steps_s`."""
        bound_s = host_bound_s(sim_s, self.speedup)
        deadline = time.monotonic() + bound_s
        sent_at = -math.inf
        while not done():
            now = time.monotonic()
            if now > deadline:
                said = self.report.statustexts[-1] if self.report.statustexts else "nothing"
                raise MissionError(step, f"not done within {bound_s:.0f} s (host; {sim_s:g} s "
                                   f"simulated at speed-up {self.speedup:g}); the autopilot's "
                                   f"last STATUSTEXT: {said!r}")
            if resend is not None and now - sent_at >= RESEND_HOST_S:
                sent_at = now
                resend()
            self.poll()
        self.report.steps_s[step] = round(time.monotonic() - self.started_at, 3)

    # -- the steps -------------------------------------------------------------------------------
    def wait_heartbeat(self) -> None:
        self.wait("heartbeat", HEARTBEAT_SIM_S, lambda: self.report.mode >= 0)

    def request_streams(self) -> None:
        """Every stream at `STREAM_RATE_HZ`, divided beyond a speed-up of 10 so that the host
        gets no more messages a second than it parses."""
        rate_hz = max(1, round(STREAM_RATE_HZ * STREAM_SPEEDUP / max(self.speedup,
                                                                     STREAM_SPEEDUP)))
        self.conn.mav.request_data_stream_send(self.target_system, 1, mavlink.MAV_DATA_STREAM_ALL,
                                               rate_hz, 1)

    def ready_to_arm(self) -> bool:
        status, ekf, gps = (self.last(k) for k in ("SYS_STATUS", "EKF_STATUS_REPORT",
                                                   "GPS_RAW_INT"))
        return (status is not None and ekf is not None and gps is not None
                and bool(status.onboard_control_sensors_health
                         & mavlink.MAV_SYS_STATUS_PREARM_CHECK)
                and ekf.flags & READY_EKF_FLAGS == READY_EKF_FLAGS and gps.fix_type >= 3
                and self.last("GLOBAL_POSITION_INT") is not None)

    def wait_ready(self) -> None:
        self.wait("ready to arm", READY_SIM_S, self.ready_to_arm, resend=self.request_streams)

    def upload(self, items: list[mavlink.MAVLink_mission_item_int_message]) -> None:
        """The mission upload protocol: MISSION_COUNT, one MISSION_ITEM_INT per request (either
        request message), until the MISSION_ACK that ends it."""
        acked: list[int] = []
        requested = False

        def count() -> None:
            if not requested:  # the autopilot may not have heard it: say it again
                self.conn.mav.mission_count_send(self.target_system, 1, len(items),
                                                 mavlink.MAV_MISSION_TYPE_MISSION)

        def done() -> bool:
            nonlocal requested
            for kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
                req = self._last.pop(kind, None)
                if req is not None and req.mission_type == mavlink.MAV_MISSION_TYPE_MISSION:
                    requested = True
                    if not 0 <= req.seq < len(items):
                        raise MissionError("mission upload", f"item {req.seq} asked of "
                                           f"{len(items)}")
                    self.conn.mav.send(items[req.seq])
            ack = self._last.pop("MISSION_ACK", None)
            # ArduPilot answers an item that crossed its own repeated request with an
            # INVALID_SEQUENCE ack and goes on asking: only another ack ends the upload
            if (ack is not None and requested
                    and ack.type != mavlink.MAV_MISSION_INVALID_SEQUENCE):
                acked.append(ack.type)
            return bool(acked)

        self.wait("mission upload", UPLOAD_SIM_S, done, resend=count)
        if acked[0] != mavlink.MAV_MISSION_ACCEPTED:
            name = mavlink.enums["MAV_MISSION_RESULT"][acked[0]].name
            raise MissionError("mission upload", f"refused: {name}")

    def command(self, command: int, *params: float) -> None:
        padded = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
        self.conn.mav.command_long_send(self.target_system, 1, command, 0, *padded)

    def arm(self) -> None:
        self.wait("arm", ARM_SIM_S, lambda: self.report.armed,
                  resend=lambda: self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1))

    def set_mode(self, name: str) -> None:
        mode = ARDUPLANE_MODES[name]
        self.wait(f"mode {name}", MODE_SIM_S, lambda: self.report.mode == mode,
                  resend=lambda: self.command(mavlink.MAV_CMD_DO_SET_MODE,
                                              mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode))

    def start_mission(self, *, takeoff_alt_m: float = TAKEOFF_ALT_M,
                      half_side_m: float = CIRCUIT_HALF_SIDE_M) -> None:
        """Heartbeat, telemetry, ready to arm, upload `circuit_items`, arm, AUTO. Home is where
        the aircraft stands when it is ready."""
        self.wait_heartbeat()
        self.request_streams()
        self.wait_ready()
        pos = self.last("GLOBAL_POSITION_INT")
        self.upload(circuit_items(pos.lat / 1e7, pos.lon / 1e7, pos.alt / 1000.0,
                                  takeoff_alt_m=takeoff_alt_m, half_side_m=half_side_m,
                                  target_system=self.target_system))
        self.arm()
        self.set_mode("AUTO")

    def fly(self, sim_s: float, until: Callable[[FlightReport], bool] | None = None) -> None:
        """Keep the link up for `sim_s` simulated seconds, or until `until(report)`; bounded by
        `host_bound_s(sim_s)`, after which it returns (the time is up either way)."""
        end_sim_s = self.report.sim_s + sim_s
        deadline = time.monotonic() + host_bound_s(sim_s, self.speedup)
        while self.report.sim_s < end_sim_s and time.monotonic() < deadline:
            self.poll()
            if until is not None and until(self.report):
                break
        self.report.steps_s["flown"] = round(time.monotonic() - self.started_at, 3)


def fly_with_arduplane(binary: str | None = None, *, speedup: float = 10.0,
                       duration_s: float = 120.0, defaults: str | None = None,
                       instance: int = 0, until: Callable[[FlightReport], bool] | None = None,
                       on_started: Callable[[ArduPlaneSitl], None] | None = None) -> FlightReport:
    """Start the ArduPlane SITL, fly the circuit mission for `duration_s` simulated seconds after
    AUTO (or until `until(report)`), stop it and return the report. `on_started(sitl)` runs once
    the autopilot is up, before the mission: where a caller starts the companion on
    `sitl.companion_url`."""
    with ArduPlaneSitl(binary, speedup=speedup, defaults=defaults, instance=instance) as sitl:
        if on_started is not None:
            on_started(sitl)
        with ArduPlaneGround(sitl.ground_url, speedup=speedup,
                             target_system=sitl.sysid) as ground:
            ground.start_mission()
            ground.fly(duration_s, until)
            return ground.report
