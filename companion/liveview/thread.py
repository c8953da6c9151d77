"""The live view: a low-priority managed thread that samples the vehicle's slots into rerun.

Flight threads never see it. It only reads slots (a reference swap under a lock that no one
holds for longer than that), at 25 Hz of host time whatever the clock scale, and hands values
to rerun's SDK, which batches and sends them from its own native threads. Camera frames from
the horizon tools arrive through `LiveView.submit_frame`, a bounded queue that drops the oldest
frame rather than wait. If the viewer goes away the SDK buffers or drops; the flight goes on.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr

from companion.core.config import ConfigError
from companion.core.geo import NedFrame
from companion.core.sync import MessageQueue
from companion.liveview import entities as E
from companion.liveview.sink import Recording, ViewerError, open_recording
from companion.liveview.tail import LogTail
from companion.report.analysis import quat_xyzw
from companion.watchdog import ManagedThread, RuntimeContext, Task, ThreadManager, ThreadStatus

__all__ = ["LiveView", "LiveViewThread"]

log = logging.getLogger(__name__)

RATE_HZ = 25.0
PATH_POINTS_MAX = 2000  # per path; older points are thinned, never dropped entirely
SLOW_EVERY = 25  # ticks between path and thread-health updates (1 s at 25 Hz)
FLUSH_EVERY = 10  # ticks between batched sends to rerun (0.4 s): each send costs ~0.2 ms
TRUTH_EVERY = 10  # ticks between reads of the growing truth.bin (0.4 s)
FRAME_QUEUE = 4
TRUTH_DECIMATE = 4  # of the simulator's 100 Hz truth, 25 Hz is plenty to look at


class _Path:
    """A bounded polyline: when full, every other point goes, so the whole flight stays."""

    def __init__(self, limit: int = PATH_POINTS_MAX) -> None:
        self.points: list[tuple[float, float, float]] = []
        self.limit = limit
        self.changed = False

    def add(self, p: tuple[float, float, float]) -> None:
        self.points.append(p)
        if len(self.points) > self.limit:
            self.points = self.points[::2]
        self.changed = True


class _Columns:
    """Samples gathered between flushes, sent as one `send_columns` call per entity.

    One rerun call costs about the same for one row as for fifty (~0.2 ms), so ten ticks go out
    in one call per entity: the view's cost drops to a third, for a 0.4 s delay on screen.
    """

    def __init__(self) -> None:
        self.kind: dict[str, str] = {}
        self.times: dict[str, list[int]] = {}
        self.values: dict[str, list[tuple[float, ...]]] = {}

    def add(self, kind: str, path: str, t_ns: int, values: tuple[float, ...]) -> None:
        times = self.times.get(path)
        if times is None:
            self.kind[path] = kind
            times = self.times[path] = []
            self.values[path] = []
        times.append(t_ns)
        self.values[path].append(values)

    def flush(self, rec: rr.RecordingStream, count: Any) -> None:
        """Send everything gathered; `count(path, rows)` is told what went out."""
        for path, times in self.times.items():
            if not times:
                continue
            values = np.asarray(self.values[path], dtype=np.float64)
            idx = [rr.TimeColumn(E.TIMELINE, timestamp=np.asarray(times, dtype="datetime64[ns]"))]
            kind = self.kind[path]
            if kind == "scalars":
                cols: Any = rr.Scalars.columns(scalars=values)
            elif kind == "transform":
                q = quat_xyzw(values[:, 3], values[:, 4], values[:, 5])
                cols = rr.Transform3D.columns(translation=values[:, :3], quaternion=q)
            else:
                cols = rr.Points3D.columns(positions=values).partition(np.ones(len(times), dtype=np.int64))
            rec.send_columns(path, indexes=idx, columns=cols)
            count(path, len(times))
            times.clear()
            self.values[path].clear()


LIVEVIEW_TASK = Task("liveview", period_ms=1000.0 / RATE_HZ, paced_by="its timer (host rate)",
                     watchdog_ms=2000, param_prefix="VIEW",
                     implementation="companion.liveview.thread:LiveViewThread")
"""The live view's row; its period is scaled with the simulation speed when it is built."""


class LiveViewThread(ManagedThread):
    """Samples `ctx.state` into a rerun recording (see the module docstring)."""

    def __init__(self, *, spawn: bool = False, save_path: Path | None = None, serve: bool = False,
                 clock_scale: float = 1.0, rate_hz: float = RATE_HZ,
                 task: Task = LIVEVIEW_TASK) -> None:
        period_ms = 1000.0 / rate_hz * clock_scale  # clock time, so the host rate stays rate_hz
        super().__init__(task.replace(period_ms=period_ms, budget_ms=period_ms,
                                      watchdog_ms=max(task.watchdog_ms, int(20 * period_ms))))
        self.spawn = spawn
        self.save_path = save_path
        self.serve = serve
        self.recording: Recording | None = None
        self.frames: MessageQueue[tuple[int, np.ndarray, Any]] = MessageQueue(FRAME_QUEUE, drop_oldest=True)
        self.events: Any = None  # MessageQueue[WatchdogEvent] from the manager
        self.thread_status: Callable[[], list[ThreadStatus]] | None = None  # the manager's
        self.samples: dict[str, int] = {}  # rows sent per entity; read it with sample_counts()
        self._samples_lock = threading.Lock()
        self.logging_ns = 0  # thread CPU time spent in step(), for the overhead figure
        self._seen: dict[str, int] = {}
        self._tick = 0
        self._frame: NedFrame | None = None
        self._origin_offset: dict[tuple[float, float, float], tuple[float, float, float]] = {}
        self._paths = {E.GPS_PATH: _Path(), E.ESTIMATE_PATH: _Path(), E.TRUTH_PATH: _Path()}
        self._truth: LogTail | None = None
        self._cols = _Columns()

    # ------------------------------------------------------------------ lifecycle (main thread)
    def setup(self) -> None:
        if self.recording is None:  # one recording for the whole run, across restarts
            name = self.ctx.flight_dir.name if self.ctx.flight_dir is not None else "live"
            self.recording = open_recording(spawn=self.spawn, save_path=self.save_path,
                                            serve=self.serve, name=name)
            if self.recording.web_url:
                log.warning("rerun web viewer at %s (gRPC %s)", self.recording.web_url,
                            self.recording.url)
        if self._truth is None and self.ctx.flight_dir is not None:
            self._truth = LogTail(self.ctx.flight_dir / "truth.bin", 1)

    def cleanup(self) -> None:
        rec = self.recording
        if rec is not None:
            try:
                self._cols.flush(rec.stream, self._count)
                rec.stream.flush(timeout_sec=0.0)  # start it; the main thread does not wait here
            except Exception as exc:  # a viewer that went away must not fail a shutdown
                log.debug("live view flush: %s", exc)

    def close(self) -> None:
        """End of the run: flush and detach the sinks (the .rrd is complete after this)."""
        rec, self.recording = self.recording, None
        if rec is not None:
            try:
                rec.close(timeout_s=5.0)
            except ViewerError as exc:  # the flight is over and fine; the view was not
                log.warning("live view: %s", exc)

    # ------------------------------------------------------------------ worker
    def _count(self, path: str, rows: int) -> None:
        with self._samples_lock:
            self.samples[path] = self.samples.get(path, 0) + rows

    def sample_counts(self) -> dict[str, int]:
        """Rows sent per entity path so far (safe from any thread)."""
        with self._samples_lock:
            return dict(self.samples)

    def _log(self, path: str, value: Any, t_ns: int) -> None:
        """One immediate rerun call, for rare items (paths, images, events)."""
        rec = self.recording
        if rec is None:
            return
        rec.stream.set_time(E.TIMELINE, timestamp=np.datetime64(int(t_ns), "ns"))
        rec.stream.log(path, value)
        self._count(path, 1)

    def _scalars(self, path: str, t_ns: int, *values: float) -> None:
        self._cols.add("scalars", path, t_ns, values)

    def _fresh(self, key: str, slot: Any) -> Any:
        value, version, _ = slot.read_versioned()
        if value is None or self._seen.get(key) == version:
            return None
        self._seen[key] = version
        return value

    def step(self) -> bool:
        t0 = time.thread_time_ns()
        st = self.ctx.state
        self._tick += 1
        imu = self._fresh("imu", st.imu)
        if imu is not None:
            p, q, r = imu.rates_rad_s
            self._scalars(E.IMU_RATES, imu.t_ns, math.degrees(p), math.degrees(q), math.degrees(r))
            self._scalars(E.IMU_FORCE, imu.t_ns, *imu.accel_m_s2)
        servo = self._fresh("servo", st.servo)
        if servo is not None:
            self._scalars(E.SERVO_PILOT, servo.t_ns, *servo.pilot_us)
            self._scalars(E.SERVO_COMMAND, servo.t_ns, *servo.computer_us)
            self._scalars(E.SERVO_BATTERY, servo.t_ns, servo.avionics_batt_raw, servo.servo_batt_raw)
        est = self._fresh("estimator", st.estimator)
        if est is not None:
            self._estimate(est)
        gps = self._fresh("gps", st.gps)  # after the estimate: it places the aircraft if present
        if gps is not None:
            self._gps(gps)
        ctl = self._fresh("control", st.control)
        if ctl is not None:
            self._scalars(E.CONTROL, ctl.t_ns, ctl.aileron, ctl.elevator, ctl.rudder, ctl.throttle)
        hz = self._fresh("horizon", st.horizon)
        if hz is not None:
            self._scalars(E.HORIZON, hz.t_ns, math.degrees(hz.roll_rad), math.degrees(hz.pitch_rad))
            self._scalars(E.HORIZON_QUALITY, hz.t_ns, hz.quality)
        self._camera()
        if self._tick % TRUTH_EVERY == 0:
            self._truth_poll()
        if self._tick % SLOW_EVERY == 0:
            self._slow()
        if self._tick % FLUSH_EVERY == 0 and self.recording is not None:
            self._cols.flush(self.recording.stream, self._count)
        self.logging_ns += time.thread_time_ns() - t0
        return True

    def _gps(self, gps: Any) -> None:
        t = gps.t_ns
        for path, value in ((E.GPS_SATS, gps.sats), (E.GPS_FIX_TYPE, gps.fix), (E.GPS_HDOP, gps.hdop),
                            (E.GPS_ALT_STD, gps.alt_std_m)):
            if value is not None:
                self._scalars(path, t, float(value))
        if gps.latency_s is not None:
            self._scalars(E.GPS_LATENCY, t, gps.latency_s * 1e3)
        if gps.fix <= 0 or gps.lat_deg is None or gps.lon_deg is None or gps.alt_m is None:
            return
        ned = self._to_ned(gps.lat_deg, gps.lon_deg, gps.alt_m)
        if ned is None:
            return
        self._paths[E.GPS_PATH].add(ned)
        self._cols.add("points", E.GPS_FIX, t, ned)
        if "estimator" not in self._seen and gps.course_deg is not None:
            # No estimator: show the aircraft at the GPS position, heading along its track.
            self._cols.add("transform", E.AIRCRAFT, t, (*ned, 0.0, 0.0, math.radians(gps.course_deg)))

    def _to_ned(self, lat: float, lon: float, alt: float) -> tuple[float, float, float] | None:
        try:
            if self._frame is None:
                self._frame = NedFrame(lat, lon, alt)
            return self._frame.to_ned(lat, lon, alt)
        except ValueError:  # a receiver reporting nonsense: skip that fix
            return None

    def _estimate(self, est: Any) -> None:
        t = est.t_ns
        self._scalars(E.ATTITUDE_ESTIMATE, t, math.degrees(est.roll_rad), math.degrees(est.pitch_rad),
                      math.degrees(est.yaw_rad))
        n, e, d = est.pos_ned_m
        if est.origin_lat_deg is not None and est.origin_lon_deg is not None and est.origin_alt_m is not None:
            origin = (est.origin_lat_deg, est.origin_lon_deg, est.origin_alt_m)
            off = self._origin_offset.get(origin)
            if off is None:
                off = self._to_ned(*origin)
                if off is None:
                    return
                self._origin_offset[origin] = off
            n, e, d = n + off[0], e + off[1], d + off[2]
        pos = (float(n), float(e), float(d))
        if not all(math.isfinite(v) for v in pos):
            return
        self._paths[E.ESTIMATE_PATH].add(pos)
        self._cols.add("transform", E.AIRCRAFT, t, (*pos, est.roll_rad, est.pitch_rad, est.yaw_rad))

    def _truth_poll(self) -> None:
        if self._truth is None or self.recording is None:
            return
        data = self._truth.poll()
        if data is None:
            return
        data = data[::TRUTH_DECIMATE]
        names = data.dtype.names or ()
        if not all(c in names for c in ("roll_rad", "pitch_rad", "yaw_rad", "lat_deg", "lon_deg", "alt_m")):
            return
        t_ns = (np.asarray(data["time_s"]) * 1e9).astype("int64").astype("datetime64[ns]")
        idx = [rr.TimeColumn(E.TIMELINE, timestamp=t_ns)]
        att = np.degrees(np.column_stack([data["roll_rad"], data["pitch_rad"], data["yaw_rad"]]))
        rec = self.recording.stream
        rec.send_columns(E.ATTITUDE_TRUTH, indexes=idx, columns=rr.Scalars.columns(scalars=att))
        ned = [self._to_ned(float(a), float(b), float(c))
               for a, b, c in zip(data["lat_deg"], data["lon_deg"], data["alt_m"], strict=True)]
        ok = np.array([p is not None for p in ned])
        if ok.any():
            pts = np.array([p for p in ned if p is not None], dtype=np.float64)
            q = quat_xyzw(np.asarray(data["roll_rad"])[ok], np.asarray(data["pitch_rad"])[ok],
                          np.asarray(data["yaw_rad"])[ok])
            rec.send_columns(E.TRUTH_AIRCRAFT, indexes=[rr.TimeColumn(E.TIMELINE, timestamp=t_ns[ok])],
                             columns=rr.Transform3D.columns(translation=pts, quaternion=q))
            for p in pts[:: max(1, len(pts) // 20)]:
                self._paths[E.TRUTH_PATH].add((float(p[0]), float(p[1]), float(p[2])))
        self._count(E.ATTITUDE_TRUTH, len(data))
        self._count(E.TRUTH_AIRCRAFT, int(ok.sum()))

    def _camera(self) -> None:
        frames = self.frames.drain()
        if not frames:
            return
        t_ns, image, horizon = frames[-1]  # only the newest: the view must keep up, not queue
        self._log(E.CAMERA_IMAGE, rr.Image(image), t_ns)
        p1, p2 = getattr(horizon, "p1", None), getattr(horizon, "p2", None)
        if getattr(horizon, "found", False) and p1 is not None and p2 is not None:
            self._log(E.CAMERA_HORIZON, rr.LineStrips2D([[p1, p2]], colors=[[255, 200, 0]], radii=1.5), t_ns)
        else:
            self._log(E.CAMERA_HORIZON, rr.Clear(recursive=False), t_ns)

    def _slow(self) -> None:
        now = self.ctx.clock.realtime_ns()
        for path, poly in self._paths.items():
            if poly.changed and len(poly.points) >= 2:
                poly.changed = False
                self._log(path, rr.LineStrips3D([poly.points]), now)
        source = self.thread_status
        if source is None:
            return
        for s in source():
            if s.name == self.name:
                continue
            self._scalars(E.thread_path(s.name, "rate_hz"), now, s.measured_rate_hz)
            self._scalars(E.thread_path(s.name, "restarts"), now, s.restarts)
            self._scalars(E.thread_path(s.name, "mean_step_us"), now, s.mean_step_us)
            self._scalars(E.thread_path(s.name, "log_dropped"), now, s.log_dropped)
        if self.events is not None:
            for ev in self.events.drain():
                level = "ERROR" if ev.severity <= 3 else "WARN" if ev.severity == 4 else "INFO"
                self._log(E.THREAD_EVENTS, rr.TextLog(ev.text(), level=level), ev.t_ns)


class LiveView:
    """Adds a `LiveViewThread` to `manager` (before it starts) and closes the stream at the end.

    Construct it where the runtime assembles its bridges, and call `close()` after the manager
    shut down (`Runtime.shutdown` calls `close()` on every bridge).
    """

    def __init__(self, ctx: RuntimeContext, manager: ThreadManager, *, spawn: bool = False,
                 save_path: Path | None = None, serve: bool = False) -> None:
        if save_path is not None:
            save_path = Path(save_path)
            if not save_path.parent.is_dir():  # a configuration error: the CLI reports it by name
                raise ConfigError(f"rerun.save (--rerun-save) {save_path}: directory "
                                  f"{save_path.parent} does not exist")
        if not (spawn or save_path or serve):
            spawn = True
        self.thread = LiveViewThread(spawn=spawn, save_path=save_path, serve=serve,
                                     clock_scale=ctx.clock.scale)
        # Subscribe now, so the STARTED events of threads set up before the view are seen.
        self.thread.events = manager.subscribe_events(256)
        self.thread.thread_status = manager.thread_status
        manager.add(self.thread)

    def submit_frame(self, t_ns: int, image: np.ndarray, horizon: Any = None) -> bool:
        """Queue a camera frame (and its `horizon.HorizonEstimate`) for the view; never blocks.

        The oldest queued frame is dropped when the view is behind; returns False then.
        """
        return self.thread.frames.put((t_ns, image, horizon))

    @property
    def samples(self) -> dict[str, int]:
        """Rows logged per entity path so far."""
        return self.thread.sample_counts()

    def close(self) -> None:
        self.thread.close()

    def stats(self) -> list[dict[str, Any]]:
        """The live view sends nothing to a ground station: no message counts."""
        return []
