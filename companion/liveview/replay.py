"""`companion logs view`: a recorded flight replayed into rerun on the log timestamps.

Whole columns go to rerun at once (`send_columns`), not one call per sample, so a 10-minute
flight replays in about a second. Entity paths are those of the live view.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rerun as rr

from companion.liveview import entities as E
from companion.liveview.sink import Recording, open_recording
from companion.report.analysis import (
    Track,
    estimate_track,
    gps_frame,
    gps_track,
    quat_xyzw,
    truth_track,
)
from companion.report.flight import FlightData, load_flight

__all__ = ["ReplayResult", "replay_flight", "replay_into"]

log = logging.getLogger(__name__)


@dataclass
class ReplayResult:
    """What went to rerun: rows per entity path, and what the flight lacked."""

    samples: dict[str, int]
    problems: list[str]
    recording: Recording | None = None  # still open when replay_flight(close=False)
    missing: list[str] = field(default_factory=list)


def _times(time_s: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(time_s, dtype=np.float64) * 1e9).astype("int64").astype("datetime64[ns]")


class _Sender:
    def __init__(self, rec: rr.RecordingStream) -> None:
        self.rec = rec
        self.samples: dict[str, int] = {}

    def scalars(self, path: str, time_s: np.ndarray, values: np.ndarray) -> None:
        v = np.asarray(values, dtype=np.float64)
        if v.shape[0] == 0:
            return
        self.rec.send_columns(path, indexes=[rr.TimeColumn(E.TIMELINE, timestamp=_times(time_s))],
                              columns=rr.Scalars.columns(scalars=v))
        self.samples[path] = self.samples.get(path, 0) + int(v.shape[0])

    def transforms(self, path: str, time_s: np.ndarray, ned: np.ndarray, quat: np.ndarray) -> None:
        if ned.shape[0] == 0:
            return
        self.rec.send_columns(path, indexes=[rr.TimeColumn(E.TIMELINE, timestamp=_times(time_s))],
                              columns=rr.Transform3D.columns(translation=ned, quaternion=quat))
        self.samples[path] = self.samples.get(path, 0) + int(ned.shape[0])

    def points(self, path: str, time_s: np.ndarray, ned: np.ndarray) -> None:
        if ned.shape[0] == 0:
            return
        self.rec.send_columns(path, indexes=[rr.TimeColumn(E.TIMELINE, timestamp=_times(time_s))],
                              columns=rr.Points3D.columns(positions=ned).partition(np.ones(len(ned), dtype=np.int64)))
        self.samples[path] = self.samples.get(path, 0) + int(ned.shape[0])

    def path(self, path: str, track: Track | None, colour: tuple[int, int, int]) -> None:
        if track is None or track.n < 2:
            return
        pts = track.ned()
        step = max(1, len(pts) // 20000)
        self.rec.log(path, rr.LineStrips3D([pts[::step]], colors=[colour]), static=True)
        self.samples[path] = self.samples.get(path, 0) + 1

    def text(self, path: str, t_ns: int, text: str, level: str) -> None:
        self.rec.set_time(E.TIMELINE, timestamp=np.datetime64(int(t_ns), "ns"))
        self.rec.log(path, rr.TextLog(text, level=level))
        self.samples[path] = self.samples.get(path, 0) + 1


def _cols(data: np.ndarray, names: list[str], scale: float = 1.0) -> np.ndarray | None:
    if not all(n in (data.dtype.names or ()) for n in names):
        return None
    return np.column_stack([np.asarray(data[n], dtype=np.float64) * scale for n in names])


def replay_into(fd: FlightData, rec: rr.RecordingStream) -> ReplayResult:
    """Send everything `fd` holds to `rec`; returns rows per entity and what was missing."""
    s = _Sender(rec)
    missing: list[str] = []
    deg = 180.0 / math.pi
    imu = fd.block("imu", 1)
    if imu is not None:
        rates = _cols(imu, ["p_rad_s", "q_rad_s", "r_rad_s"], deg)
        force = _cols(imu, ["ax_m_s2", "ay_m_s2", "az_m_s2"])
        if rates is not None:
            s.scalars(E.IMU_RATES, imu["time_s"], rates)
        if force is not None:
            s.scalars(E.IMU_FORCE, imu["time_s"], force)
    else:
        missing.append(fd.why_missing("imu", 1))
    gps = fd.block("gps", 1)
    if gps is not None:
        for path, col in ((E.GPS_SATS, "sats"), (E.GPS_FIX_TYPE, "fix"), (E.GPS_HDOP, "hdop"),
                          (E.GPS_LATENCY, "latency_ms"), (E.GPS_ALT_STD, "alt_std_m")):
            v = _cols(gps, [col])
            if v is not None:
                s.scalars(path, gps["time_s"], v[:, 0])
    else:
        missing.append(fd.why_missing("gps", 1))
    servo = fd.block("servo", 1)
    if servo is not None:
        for path, names in ((E.SERVO_PILOT, [f"pilot{k}_us" for k in range(1, 9)]),
                            (E.SERVO_COMMAND, [f"cmd{k}_us" for k in range(1, 9)]),
                            (E.SERVO_BATTERY, ["avionics_batt", "servo_batt"])):
            v = _cols(servo, names)
            if v is not None:
                s.scalars(path, servo["time_s"], v)
    else:
        missing.append(fd.why_missing("servo", 1))
    control = fd.block("control", 1, ("aileron", "elevator", "rudder", "throttle"))
    if control is not None:
        s.scalars(E.CONTROL, control["time_s"], _cols(control, ["aileron", "elevator", "rudder", "throttle"]))  # type: ignore[arg-type]

    frame = gps_frame(fd)
    t0 = fd.t0_ns / 1e9
    gps_tr = gps_track(fd, frame) if frame is not None else None
    truth_tr = truth_track(fd, frame) if frame is not None else None
    est = fd.block("estimator", 1, ("roll_rad", "pitch_rad", "yaw_rad"))
    est_found = estimate_track(fd, frame) if frame is not None else None
    est_tr = est_found[0] if est_found is not None else None
    if gps_tr is not None:
        s.points(E.GPS_FIX, gps_tr.t_s + t0, gps_tr.ned())
        s.path(E.GPS_PATH, gps_tr, (40, 110, 220))
    if est is not None:
        s.scalars(E.ATTITUDE_ESTIMATE, est["time_s"], _cols(est, ["roll_rad", "pitch_rad", "yaw_rad"], deg))  # type: ignore[arg-type]
    else:
        missing.append(fd.why_missing("estimator", 1, ("roll_rad", "pitch_rad", "yaw_rad")))
    if est is not None and est_tr is not None and est_tr.n:
        t_est = fd.rel_s(est["time_s"])
        keep = np.isin(t_est, est_tr.t_s)
        q = quat_xyzw(est["roll_rad"][keep], est["pitch_rad"][keep], est["yaw_rad"][keep])
        s.transforms(E.AIRCRAFT, est_tr.t_s + t0, est_tr.ned(), q)
        s.path(E.ESTIMATE_PATH, est_tr, (220, 60, 40))
    elif gps is not None and gps_tr is not None and gps_tr.n and "course_deg" in (gps.dtype.names or ()):
        valid = gps[gps["fix"] > 0]
        course = np.radians(np.asarray(valid["course_deg"], dtype=np.float64))
        if course.size == gps_tr.n:
            course = np.nan_to_num(course)
            zeros = np.zeros_like(course)
            s.transforms(E.AIRCRAFT, gps_tr.t_s + t0, gps_tr.ned(), quat_xyzw(zeros, zeros, course))
    truth = fd.block("truth", 1, ("roll_rad", "pitch_rad", "yaw_rad"))
    if truth is not None:
        s.scalars(E.ATTITUDE_TRUTH, truth["time_s"], _cols(truth, ["roll_rad", "pitch_rad", "yaw_rad"], deg))  # type: ignore[arg-type]
        if truth_tr is not None and truth_tr.n == truth.size:
            q = quat_xyzw(truth["roll_rad"], truth["pitch_rad"], truth["yaw_rad"])
            s.transforms(E.TRUTH_AIRCRAFT, truth_tr.t_s + t0, truth_tr.ned(), q)
        s.path(E.TRUTH_PATH, truth_tr, (90, 90, 90))
    # Thread health from the logs: (re)starts and clean stops, and the record period.
    for name, st in fd.logs.items():
        if st.log is None:
            continue
        begins = 0
        for m in st.log.markers:
            if m.kind == "begin":
                begins += 1
                s.text(E.THREAD_EVENTS, m.time_ns, f"{name}: {'started' if begins == 1 else 'restarted'}",
                       "INFO" if begins == 1 else "WARN")
            else:
                s.text(E.THREAD_EVENTS, m.time_ns, f"{name}: stopped", "INFO")
        for p in st.problems:
            s.text(E.THREAD_EVENTS, fd.t0_ns, f"{name}.bin: {p}", "WARN")
        data = fd.block(name, 1)
        if data is not None and data.size > 1:
            t = np.asarray(data["time_s"], dtype=np.float64)
            s.scalars(E.thread_path(name, "period_ms"), t[1:], np.diff(t) * 1e3)
    return ReplayResult(samples=s.samples, problems=list(fd.problems), missing=missing)


def replay_flight(flight_dir: str | Path, save_path: str | Path | None = None, *, spawn: bool = False,
                  serve: bool = False, close: bool = True) -> ReplayResult:
    """Replay `flight_dir` to a spawned viewer, an .rrd file and/or a served web viewer.

    With none of them, a viewer is spawned. `close=False` leaves the stream open (serving keeps
    running until the caller closes `result.recording`). Raises FileNotFoundError for a missing
    directory and `ViewerError` when the destination cannot be set up.
    """
    fd = load_flight(flight_dir)
    if not (spawn or save_path or serve):
        spawn = True
    recording = open_recording(spawn=spawn, save_path=save_path, serve=serve, name=fd.flight_dir.name)
    try:
        result = replay_into(fd, recording.stream)
    except BaseException:
        recording.stream.disconnect()
        raise
    if close:
        recording.close()
    else:
        result.recording = recording
    return result
