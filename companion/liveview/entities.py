"""Entity paths and static layout shared by the live view and the replay.

A recorded flight replayed with `companion logs view` and a live `--rerun` stream use the same
paths, names and timeline, so a viewer layout (blueprint) made for one works for the other.
The 3-D world is the flight's local NED frame (x north, y east, z down), origin at the first
GPS fix, as in the report.
"""

from __future__ import annotations

import numpy as np
import rerun as rr

__all__ = ["TIMELINE", "log_static_layout"]

#: Timestamp timeline: the runtime clock of each sample (the log timestamps on replay).
TIMELINE = "flight_time"

WORLD = "world"
AIRCRAFT = "world/aircraft"  # transform: estimate (else truth, else GPS position)
AIRCRAFT_SHAPE = "world/aircraft/shape"
TRUTH_AIRCRAFT = "world/truth_aircraft"
TRUTH_AIRCRAFT_SHAPE = "world/truth_aircraft/shape"
GPS_PATH = "world/gps/path"
GPS_FIX = "world/gps/fix"
ESTIMATE_PATH = "world/estimate/path"
TRUTH_PATH = "world/truth/path"

IMU_RATES = "imu/rates_deg_s"
IMU_FORCE = "imu/specific_force_m_s2"
ATTITUDE_ESTIMATE = "attitude/estimate_deg"
ATTITUDE_TRUTH = "attitude/truth_deg"
GPS_SATS = "gps/sats"
GPS_FIX_TYPE = "gps/fix_type"
GPS_HDOP = "gps/hdop"
GPS_LATENCY = "gps/latency_ms"
GPS_ALT_STD = "gps/alt_std_m"
SERVO_PILOT = "servo/pilot_us"
SERVO_COMMAND = "servo/command_us"
SERVO_BATTERY = "servo/battery_raw"
CONTROL = "control/surfaces"
HORIZON = "horizon/attitude_deg"
HORIZON_QUALITY = "horizon/quality"
CAMERA_IMAGE = "camera/image"
CAMERA_HORIZON = "camera/image/horizon"
THREAD_EVENTS = "threads/events"


def thread_path(thread: str, what: str) -> str:
    """``threads/<thread>/<what>`` with the thread name escaped for rerun."""
    return f"threads/{rr.escape_entity_path_part(thread)}/{what}"


SERIES_NAMES: dict[str, list[str]] = {
    IMU_RATES: ["p", "q", "r"],
    IMU_FORCE: ["ax", "ay", "az"],
    ATTITUDE_ESTIMATE: ["roll", "pitch", "yaw"],
    ATTITUDE_TRUTH: ["roll (truth)", "pitch (truth)", "yaw (truth)"],
    SERVO_PILOT: [f"pilot {k}" for k in range(1, 9)],
    SERVO_COMMAND: [f"computer {k}" for k in range(1, 9)],
    SERVO_BATTERY: ["avionics", "servos"],
    CONTROL: ["aileron", "elevator", "rudder", "throttle"],
    HORIZON: ["roll", "pitch"],
}

# A stick aircraft in body axes (x forward, y right, z down), metres: big enough to see from a
# few hundred metres, small enough not to hide the path.
_SPAN_M = 12.0
_LENGTH_M = 9.0


def aircraft_strips() -> list[np.ndarray]:
    nose, tail = 0.55 * _LENGTH_M, -0.45 * _LENGTH_M
    half = _SPAN_M / 2
    return [
        np.array([[nose, 0, 0], [tail, 0, 0]]),  # fuselage
        np.array([[0.1 * _LENGTH_M, -half, 0], [0.1 * _LENGTH_M, half, 0]]),  # wing
        np.array([[tail, -0.35 * half, 0], [tail, 0.35 * half, 0]]),  # tailplane
        np.array([[tail, 0, 0], [tail, 0, -0.2 * _LENGTH_M]]),  # fin (up is -z)
    ]


def log_static_layout(rec: rr.RecordingStream) -> None:
    """World axes, the aircraft shapes and the series names: logged once, before any data."""
    rec.log(WORLD, rr.ViewCoordinates.FRD, static=True)  # x north, y east, z down
    rec.log(AIRCRAFT_SHAPE, rr.LineStrips3D(aircraft_strips(), colors=[[230, 60, 40]]), static=True)
    rec.log(TRUTH_AIRCRAFT_SHAPE, rr.LineStrips3D(aircraft_strips(), colors=[[120, 120, 120]]),
            static=True)
    for path, names in SERIES_NAMES.items():
        rec.log(path, rr.SeriesLines(names=names), static=True)
