"""The simulated world: JSBSim flight, a scripted pilot and the devices, tick by tick.

The world is the aircraft and everything around it: the flight model, the scripted pilot on
the servo board's pilot channels, the device simulators writing to the device ports, the world
faults of the catalogue (`companion.sim.faults`: byte faults and vanishing ports) and the truth
log. Two things run it:

* its own process (`companion.sim.world_process`, started by `companion sim`), with
  pseudo-terminals as ports (`companion.sim.ports`), so the runtime under test is exactly the
  flight program: it opens the device paths it is given and reads bytes, without knowing they
  come from a simulator. Both processes share one `Clock` epoch and scale, so ground truth and
  the runtime's logs share a timeline, also faster than real time (`World.run`);
* a lockstep flight (`companion.sim.lockstep`), with in-process ports, running its tick as a
  task on simulated time (`World.run_lockstep`).

With `horizon_camera` set, the world also carries the forward camera of the thesis's horizon
experiment (`companion.sim.camera`): frames rendered at the true attitude go through the real
detector, and its fixes reach the runtime as HORIZON_ATTITUDE datagrams on the runtime's legacy
command port, which the runtime names in its GO line (it may have bound port 0).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import select
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.core.clock import Clock
from companion.logs.truth import FMT_SURFACES, FMT_TRUTH, define_truth_log
from companion.sim.byte_faults import FaultInjector
from companion.sim.faults import FaultPlan, Vanish
from companion.sim.flight import FlightModel, FlightModelError
from companion.sim.gps_sim import GpsSim
from companion.sim.imu_sim import ImuSim
from companion.sim.pilot import Pilot, Surfaces, surfaces_from_channels
from companion.sim.plugins import DeviceSimulator, build_simulator
from companion.sim.ports import DEVICES, Pty
from companion.sim.profiles import resolve_sensors
from companion.sim.servo_sim import ServoBoardSim
from companion.sim.truth import TruthState

if TYPE_CHECKING:
    from companion.sim.camera import CameraResult
    from companion.sim.world_camera import WorldCamera

log = logging.getLogger(__name__)

IMU_DT_S = 0.01
GPS_EVERY = 10  # IMU ticks per GPS epoch at 10 Hz; a GPS profile's rate sets the world's own
PILOT_EVERY = 2  # IMU ticks per servo-board frame (50 Hz)
TRUTH_EVERY = 1
HORIZON_CAMERA_CHOICES = ("off", "clean", "light", "thesis")
"""`--horizon-camera`: no camera, or the camera with that level of video disturbance
(`companion.sim.camera.DISTURBANCE_LEVELS`, where "clean" is "none")."""



@dataclass
class WorldOptions:
    scenario: str = "mixed"
    seed: int = 0
    aircraft: str = "c172p"
    wind_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = 1.0
    epoch: tuple[int, int] | None = None
    device_dir: Path = Path(".")
    flight_dir: Path | None = None
    duration_s: float = 0.0  # 0: until signalled
    gps_latency_s: float | None = None
    """Overrides the GPS profile's mean latency (None: the profile's)."""
    imu_seed: int | None = None
    """Seed of the IMU part (None: from ``seed``): the part of the flight with that seed,
    switched on again (`ImuErrorModel.power_on_again`: same scale, cross-axis, misalignment and
    temperature coefficients; turn-on bias and noise from this flight's seed), e.g. to try
    the gyro calibration one flight learnt in the next."""
    gps_ashtech: bool = False
    faults: dict[str, FaultPlan] = field(default_factory=dict)
    vanish: list[Vanish] = field(default_factory=list)
    imu_noise: bool = True
    """False (`--no-noise`): every sensor perfect, the air calm unless `turbulence` says."""
    imu_profile: str | None = None
    """IMU, GPS and air profiles (`companion.sim.profiles`; None: the realistic defaults)."""
    gps_profile: str | None = None
    turbulence: str | None = None
    auto_switch_s: float = 20.0
    settle_s: float = 3.0
    horizon_camera: str = "off"
    """`HORIZON_CAMERA_CHOICES`: no camera, or one whose frames are clean or disturbed as the
    thesis's radio video link disturbed them (light, thesis)."""
    extra_devices: dict[str, str] = field(default_factory=dict)
    """Devices the world does not simulate itself: name -> ``module:Class`` of the simulator
    their row of the vehicle table names (`companion.sim.plugins`), in table order."""
    level_calibration: bool = True
    """Level-calibrate the installation before the flight, as a user does (`ImuSim.level_calibration`;
    profiles without a levelling error have none): the runtime gets the trims as parameters."""


class World:
    """The aircraft and its devices. `ports` replaces the pseudo-terminals (a lockstep flight
    hands its in-process ports, with `answer_servo` wired to the servo port's writes) and
    `clock` the scaled clock built from the options."""

    def __init__(self, opts: WorldOptions, *, ports: Mapping[str, Any] | None = None,
                 clock: Clock | None = None) -> None:
        self.opts = opts
        self.clock = clock if clock is not None else Clock(opts.scale, opts.epoch)
        rng = np.random.default_rng(opts.seed)
        self.sensors = sensors = resolve_sensors(
            opts.imu_profile, opts.gps_profile, opts.turbulence, no_noise=not opts.imu_noise,
            gps_latency_s=opts.gps_latency_s, gps_ashtech=opts.gps_ashtech)
        self.model = FlightModel(opts.aircraft, wind_ned_m_s=opts.wind_ned_m_s, seed=opts.seed,
                                 turbulence_severity=sensors.turbulence_severity)
        trim_throttle = float(self.model.trim_controls.throttle)
        self.pilot = Pilot(opts.scenario, opts.seed, aircraft=opts.aircraft,
                           auto_switch_s=opts.auto_switch_s, trim_throttle=trim_throttle)
        self.settle_sticks = [1500, 1500, int(round(1000 + 1000 * trim_throttle)), 1500,
                              1000, 1500, 1500, 1500]
        self.imu = ImuSim.of_part(np.random.default_rng(rng.integers(2**63)), sensors.imu,
                                  opts.imu_seed)
        self.gps = GpsSim(np.random.default_rng(rng.integers(2**63)), sensors.gps)
        self.gps_every = int(round(1.0 / (IMU_DT_S * sensors.gps.rate_hz)))
        self.board = ServoBoardSim(np.random.default_rng(rng.integers(2**63)))
        self.injectors = {dev: FaultInjector(plan, np.random.default_rng(rng.integers(2**63)))
                          for dev, plan in opts.faults.items()}
        # drawn after every other stream, so a calibration changes no sensor's draws
        level_rng = np.random.default_rng(rng.integers(2**63))
        self.level_cal = self.imu.level_calibration(level_rng) if opts.level_calibration else None
        # a plug-in device's generator comes after all of those: it changes no other draw
        self.extra: dict[str, DeviceSimulator] = {
            name: build_simulator(spec, np.random.default_rng(rng.integers(2**63)))
            for name, spec in opts.extra_devices.items()}
        self.device_names = (*DEVICES, *self.extra)
        if ports is None:
            opts.device_dir.mkdir(parents=True, exist_ok=True)
            self.ptys: dict[str, Any] = {dev: Pty(opts.device_dir / dev)
                                         for dev in self.device_names}
        else:
            self.ptys = dict(ports)
        self._board_lock = threading.Lock()
        self._stop = threading.Event()
        self.t_s = 0.0
        self.ticks = 0
        self.gps_queue: list[tuple[float, bytes]] = []
        self.logs: Any = None
        self.tlog: Any = None
        self.late_ticks = 0
        self.start_utc_s = 12 * 3600.0
        self.stop_reason = "stopped"
        self._truth: TruthState | None = None
        self._effective_seen: tuple[int, ...] | None = None
        self._surfaces: Surfaces | None = None
        self.camera: WorldCamera | None = None
        self._camera_stats: dict[str, Any] | None = None

    # ------------------------------------------------------------------ horizon camera
    def attach_camera(self, link: Callable[[CameraResult, int], bool] | str,
                      *, vehicle_id: int = 1, threaded: bool = True) -> None:
        """Start the camera (`opts.horizon_camera`): its fixes go to `link`, either a
        callable (lockstep: `SlotLink`) or the runtime's legacy command port as `HOST:PORT`.
        Its generator is seeded from the world's seed alone, so adding a camera changes no
        other sensor's draws."""
        from companion.sim.camera import LATENCY_S as CAMERA_LATENCY_S
        from companion.sim.camera import SimCamera, camera_seed
        from companion.sim.world_camera import LegacyHorizonLink, WorldCamera

        if self.opts.horizon_camera == "off":
            return
        level = self.opts.horizon_camera
        camera = SimCamera(camera_seed(self.opts.seed), latency_s=CAMERA_LATENCY_S,
                           disturbance="none" if level == "clean" else level)
        if isinstance(link, str):
            host, port = _host_port(link)
            link = LegacyHorizonLink(host, port, vehicle_id, self.clock.realtime_ns)
        self.camera = WorldCamera(camera, link, self.clock, threaded=threaded)

    def retarget_camera(self, dest: str) -> bool:
        """Point the camera's fixes at another `HOST:PORT` (the runtime was rebooted and bound
        a new legacy port); False when the camera does not send over UDP."""
        from companion.sim.world_camera import LegacyHorizonLink

        link = self.camera.link if self.camera is not None else None
        if not isinstance(link, LegacyHorizonLink):
            return False
        host, port = _host_port(dest)
        link.retarget(host, port)
        return True

    def _close_camera(self) -> dict[str, Any] | None:
        if self.camera is None:
            return None
        camera, self.camera = self.camera, None
        return camera.close()

    # ------------------------------------------------------------------ servo board (own thread)
    def _board_loop(self) -> None:
        """Answer each command frame at once, as the real board does, from the latest sticks."""
        while not self._stop.is_set():
            pty = self.ptys["servo"]
            fd = pty.master
            if fd < 0:
                self._stop.wait(0.01)
                continue
            try:
                r, _, _ = select.select([fd], [], [], 0.05)
            except (OSError, ValueError):
                continue
            if not r:
                continue
            try:
                data = os.read(fd, 4096)
            except (BlockingIOError, OSError):
                continue
            self.answer_servo(data)

    def answer_servo(self, data: bytes) -> None:
        """The board's answer to command bytes, written back to the servo port at once."""
        with self._board_lock:
            answer = self.board.feed(data, self.t_s)
        self.ptys["servo"].write(self._inject("servo", answer))

    def _inject(self, dev: str, data: bytes) -> bytes:
        inj = self.injectors.get(dev)
        return inj.apply(data, self.t_s) if inj is not None else data

    # ------------------------------------------------------------------ truth log
    def _open_truth_log(self, *, writer_thread: bool = True) -> None:
        if self.opts.flight_dir is None:
            return
        from companion.logs import LogService

        self.logs = LogService(self.opts.flight_dir, clock_ns=self.clock.realtime_ns,
                               writer_thread=writer_thread)
        self.logs.start()
        self.tlog = self.logs.open("truth")
        define_truth_log(self.tlog)
        self.tlog.define(FMT_SURFACES, ",".join(["%hu"] * 8) + ",%hhu,%.4f,%.4f,%.4f,%.4f",
                         [f"servo{i}_us" for i in range(1, 9)]
                         + ["auto_active", "aileron", "elevator", "rudder", "throttle"])
        self.tlog.begin()

    # ------------------------------------------------------------------ vanishing ports
    def _vanish_faults(self) -> None:
        for v in self.opts.vanish:
            if v.done:
                continue
            if not v.gone and self.t_s >= v.start_s:
                log.info("fault: %s port vanishes at %.2f s", v.device, self.t_s)
                self.ptys[v.device].close()
                v.gone = True
            elif v.gone and self.t_s >= v.start_s + v.duration_s:
                pty = self.ptys[v.device]
                pty.open(avoid_name=pty.name if v.renamed else None)
                log.info("fault: %s port returns at %.2f s as %s", v.device, self.t_s, pty.name)
                v.done = True

    # ------------------------------------------------------------------ main loop
    def run(self) -> dict[str, Any]:
        sys.setswitchinterval(0.0005)  # the board thread must answer within a millisecond
        self._open_truth_log()
        board = threading.Thread(target=self._board_loop, name="servo-board", daemon=True)
        board.start()
        clock = self.clock
        period_ns = int(IMU_DT_S * 1e9)
        next_ns = clock.monotonic_ns()
        t0_host = time.monotonic()
        stop_reason = "signal"
        model = self.model
        parent = os.getppid()
        try:
            while not self._stop.is_set():
                if self.ticks % 50 == 0 and os.getppid() != parent:
                    stop_reason = "runtime gone"  # never outlive the flight program
                    break
                if self.opts.duration_s and self.t_s >= self.opts.duration_s:
                    stop_reason = "duration"
                    break
                self._tick(model)
                next_ns += period_ns
                now = clock.monotonic_ns()
                if now > next_ns + period_ns:
                    self.late_ticks += 1
                if clock.wait_until_ns(next_ns, self._stop):
                    break
        except FlightModelError as exc:
            stop_reason = f"flight model: {exc}"
            log.error("flight model stopped: %s", exc)
        except Exception as exc:
            # a fault in a device simulator is a bug to see, but the flight's truth log and
            # figures are still closed and reported, with the reason, not lost with a traceback
            stop_reason = f"simulator error: {type(exc).__name__}: {exc}"
            log.exception("the world stopped at %.3f s", self.t_s)
        finally:
            self._stop.set()
            board.join(1.0)
            self._camera_stats = self._close_camera()
            if self.tlog is not None:
                self.tlog.end()
            if self.logs is not None:
                self.logs.close()
            for pty in self.ptys.values():
                pty.close()
        return self._stats(stop_reason, time.monotonic() - t0_host)

    def run_lockstep(self, stop: threading.Event) -> None:
        """The world as a task of a lockstep flight: one tick per IMU period of simulated time,
        the servo board answering from `answer_servo`; the truth log is drained by the owner
        and closed by `close_lockstep`."""
        self._open_truth_log(writer_thread=False)
        clock = self.clock
        period_ns = int(IMU_DT_S * 1e9)
        next_ns = clock.monotonic_ns()
        try:
            while not stop.is_set():
                if self.opts.duration_s and self.t_s >= self.opts.duration_s:
                    self.stop_reason = "duration"
                    break
                self._tick(self.model)
                next_ns += period_ns
                if clock.wait_until_ns(next_ns, stop):
                    break
        except FlightModelError as exc:
            self.stop_reason = f"flight model: {exc}"
            log.error("flight model stopped: %s", exc)

    def runtime_params(self) -> dict[str, float]:
        """Parameters a user would set for this installation: the level calibration's trims,
        and GPS_HDT when the receiver sends a heading every epoch."""
        params: dict[str, float] = dict(self.level_cal.params()) if self.level_cal else {}
        if "HDT" in self.gps.config.sentences:
            params["GPS_HDT"] = 1
        return params

    def close_lockstep(self, host_s: float) -> dict[str, Any]:
        """End a lockstep world: its truth log closed, its figures."""
        self._camera_stats = self._close_camera()
        if self.tlog is not None:
            self.tlog.end()
            self.tlog = None
        if self.logs is not None:
            self.logs.close()
        return self._stats(self.stop_reason, host_s)

    def _stats(self, stop_reason: str, elapsed: float) -> dict[str, Any]:
        return {
            "stop": stop_reason,
            "sim_time_s": round(self.t_s, 3),
            "real_time_factor": round(self.t_s / elapsed, 2) if elapsed > 0 else None,
            "late_ticks": self.late_ticks,
            "servo_answers": self.board.answered,
            "dropped_bytes": {d: p.dropped_bytes for d, p in self.ptys.items()},
            "faults": {d: dataclasses.asdict(i.counts) for d, i in self.injectors.items()},
            "gps_outages": self.gps.outages,
            **({"level_calibration": self.level_cal.metadata()} if self.level_cal else {}),
            **({"camera": self._camera_stats} if self._camera_stats is not None else {}),
        }

    def _tick(self, model: FlightModel) -> None:
        truth = self._truth if self._truth is not None else model.truth()
        k = self.ticks
        if k % PILOT_EVERY == 0:
            # the pilot flies straight and level (centred sticks on a trimmed aircraft) while
            # the runtime starts up, as a pilot would when the computer is switched on
            settle = self.opts.settle_s
            sticks = (self.pilot.channels_us(self.t_s - settle, truth) if self.t_s >= settle
                      else self.settle_sticks)
            with self._board_lock:
                self.board.set_pilot(sticks)
        with self._board_lock:
            effective = self.board.effective_channels_us(self.t_s)
            auto = self.board.auto_active(self.t_s)
        if effective != self._effective_seen:
            # the servos' pulse widths change at the board's 50 Hz, not every tick
            self._effective_seen = effective
            self._surfaces = surfaces_from_channels(effective)
        surfaces = self._surfaces
        assert surfaces is not None
        model.set_controls(*surfaces)
        model.step(IMU_DT_S)
        truth = self._truth = model.truth()  # also the next tick's state before its step
        self.t_s = (k + 1) * IMU_DT_S
        self.ticks = k + 1
        self._vanish_faults()
        frame = self.imu.frame((truth.p_rad_s, truth.q_rad_s, truth.r_rad_s),
                               (truth.ax_m_s2, truth.ay_m_s2, truth.az_m_s2),
                               model.propeller_rpm(), self.imu.temperature_at(self.t_s))
        self.ptys["imu"].write(self._inject("imu", frame))
        if self.camera is not None:
            self.camera.on_tick(self.t_s, truth.roll_rad, truth.pitch_rad)
        if self.ticks % self.gps_every == 0:
            epoch = self.gps.epoch(self.start_utc_s + self.t_s + self._utc_step_s(),
                                   truth.lat_deg, truth.lon_deg,
                                   truth.alt_m, truth.vn_m_s, truth.ve_m_s, truth.vd_m_s,
                                   math.degrees(truth.yaw_rad))
            # each epoch late by its own draw; the serial line keeps them in order
            self.gps_queue.append((self.t_s + self.gps.last_latency_s, epoch))
        while self.gps_queue and self.gps_queue[0][0] <= self.t_s + 1e-9:
            _, data = self.gps_queue.pop(0)
            self.ptys["gps"].write(self._inject("gps", data))
        for name, device in self.extra.items():
            data = device.tick(self.t_s, truth)
            if data:
                self.ptys[name].write(self._inject(name, data))
        if self.tlog is not None and self.ticks % TRUTH_EVERY == 0:
            self.tlog.log(FMT_TRUTH, truth.roll_rad, truth.pitch_rad, truth.yaw_rad,
                          truth.north_m, truth.east_m, truth.down_m, truth.vn_m_s, truth.ve_m_s,
                          truth.vd_m_s, truth.p_rad_s, truth.q_rad_s, truth.r_rad_s,
                          truth.ax_m_s2, truth.ay_m_s2, truth.az_m_s2, truth.lat_deg,
                          truth.lon_deg, truth.alt_m, truth.airspeed_m_s, self.t_s)
            if self.ticks % PILOT_EVERY == 0:
                self.tlog.log(FMT_SURFACES, *effective, int(auto), *surfaces)

    def stop(self) -> None:
        self._stop.set()

    def _utc_step_s(self) -> float:
        plan = self.opts.faults.get("gps")
        if plan is None:
            return 0.0
        return sum(delta for at, delta in plan.utc_step_s if self.t_s >= at)


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"horizon camera: expected HOST:PORT, got {text!r}")
    return host, int(port)
