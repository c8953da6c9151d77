"""`companion sim`: start the simulated world in its own process and fly the runtime against it."""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from companion.core.clock import Clock
from companion.core.config import Config
from companion.core.files import write_json_bounded
from companion.liveview import live_view_bridges
from companion.runtime import Runtime, RuntimeOptions, new_flight_dir
from companion.sim.clock_faults import WallClockSteps
from companion.sim.faults import parse_clock_step, parse_thread_fault, world_faults
from companion.sim.thread_faults import ThreadFaultInjector
from companion.vehicle import VEHICLE, device_settings
from companion.watchdog import RuntimeContext, ThreadManager

log = logging.getLogger(__name__)

FAST_SCALE = 5.0
CAMERA_NEEDS_LEGACY = ("--horizon-camera sends HORIZON_ATTITUDE to the legacy command port: "
                       "the legacy protocol must be on (drop --no-legacy)")
READY_TIMEOUT_S = 60.0
# The world closes its truth log before it reports: LogService.close may take up to 30 s on a
# slow disk that still takes writes; past that the world is hung and is killed.
WORLD_STOP_TIMEOUT_S = 40.0


class SimError(RuntimeError):
    """The simulated world could not start or died."""


@dataclass
class SimOptions:
    scenario: str = "mixed"
    seed: int = 0
    aircraft: str = "c172p"
    scale: float = 1.0
    wind_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gps_latency_s: float | None = None
    """Overrides the GPS profile's mean latency (None: the profile's)."""
    imu_seed: int | None = None
    """The IMU part's own seed (None: from ``seed``): `WorldOptions.imu_seed`."""
    gps_ashtech: bool = False
    faults: list[str] = field(default_factory=list)
    vanish: list[str] = field(default_factory=list)
    thread_faults: list[str] = field(default_factory=list)
    """`THREAD:KIND:AT_S` faults injected into the runtime's threads (companion.sim.faults)."""
    auto_switch_s: float = 20.0
    no_noise: bool = False
    level_calibration: bool = True
    """The simulated installation is level-calibrated before the flight and the runtime gets
    its trims (`EST_TRIM_ROLL/PITCH`; `--no-level-cal` flies without)."""
    """Every sensor perfect (IMU and GPS); the air calm unless `turbulence` is given."""
    imu_profile: str | None = None
    """`companion.sim.profiles` names; None: the realistic defaults (consumer MEMS, u-blox M8
    class, moderate turbulence; calm air under `no_noise`)."""
    gps_profile: str | None = None
    turbulence: str | None = None
    clock_steps: list[str] = field(default_factory=list)
    """`AT_S:STEP_S` wall-clock steps in the runtime's process (companion.sim.faults)."""
    horizon_camera: str = "off"
    """The forward camera of the horizon experiment (`companion.sim.world.HORIZON_CAMERA_CHOICES`):
    its detector's fixes reach the estimator as HORIZON_ATTITUDE on the legacy command port."""


class WorldProcess:
    """The simulator subprocess: started, read for READY, stopped with SIGTERM, STATS collected."""

    def __init__(self, opts: SimOptions, clock: Clock, device_dir: Path, flight_dir: Path,
                 duration_s: float | None) -> None:
        mono0, real0 = clock.epoch
        cmd = [sys.executable, "-m", "companion.sim.world_process", "--scenario", opts.scenario,
               "--seed", str(opts.seed), "--aircraft", opts.aircraft, "--scale", str(clock.scale),
               "--epoch", str(mono0), str(real0), "--device-dir", str(device_dir),
               "--flight-dir", str(flight_dir),
               "--auto-switch", str(opts.auto_switch_s),
               "--wind", *(str(w) for w in opts.wind_ned_m_s)]
        if duration_s:
            cmd += ["--duration", str(duration_s + 5.0)]  # outlive the runtime, never starve it
        if opts.gps_latency_s is not None:
            cmd += ["--gps-latency", str(opts.gps_latency_s)]
        if opts.imu_seed is not None:
            cmd += ["--imu-seed", str(opts.imu_seed)]
        for option, value in (("--imu-profile", opts.imu_profile),
                              ("--gps-profile", opts.gps_profile),
                              ("--turbulence", opts.turbulence)):
            if value is not None:
                cmd += [option, value]
        if opts.gps_ashtech:
            cmd.append("--gps-ashtech")
        if opts.no_noise:
            cmd.append("--no-noise")
        if not opts.level_calibration:
            cmd.append("--no-level-cal")
        if opts.horizon_camera != "off":
            cmd += ["--horizon-camera", opts.horizon_camera]
        for kind in world_faults():  # the world applies these: its command line takes them
            for text in getattr(opts, kind.key):
                cmd += [kind.option, text]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stdin=subprocess.PIPE,
                                     text=True)
        self.stats: dict[str, Any] = {}
        self.devices = self._wait_ready()

    def _wait_ready(self) -> dict[str, Any]:
        assert self.proc.stdout is not None
        result: dict[str, Any] = {}
        done = threading.Event()

        def reader() -> None:
            assert self.proc.stdout is not None
            line = self.proc.stdout.readline()
            if line.startswith("READY "):
                result["devices"] = json.loads(line[6:])
            done.set()

        t = threading.Thread(target=reader, daemon=True)
        t.start()
        if not done.wait(READY_TIMEOUT_S) or "devices" not in result:
            self.stop(timeout_s=10.0)
            raise SimError(f"the simulator did not start (exit code {self.proc.returncode})")
        return dict(result["devices"])

    def go(self, **extra: Any) -> None:
        """Start the flight: the runtime's ports are open; `extra` is what only the started
        runtime knows (`horizon_dest`, `vehicle_id`), as JSON on the GO line."""
        assert self.proc.stdin is not None
        try:
            self.proc.stdin.write("GO" + (" " + json.dumps(extra) if extra else "") + "\n")
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError) as exc:
            raise SimError(f"the simulator died before the flight started: {exc}") from None

    def retarget(self, **dest: Any) -> None:
        """Tell the flying world where the camera's fixes go now (after a runtime reboot);
        a world already gone is the stop path's business, not this one's."""
        if not dest or self.proc.stdin is None:
            return
        try:
            self.proc.stdin.write("DEST " + json.dumps(dest) + "\n")
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError):
            log.warning("the simulator is gone: the camera was not retargeted")

    def stop(self, timeout_s: float = WORLD_STOP_TIMEOUT_S) -> dict[str, Any]:
        """SIGTERM the world and collect its STATS line. A world that gives none (killed after
        `timeout_s`, or died) still yields figures that say so, with its exit code and the
        time it was given, instead of an empty dictionary."""
        t0 = time.monotonic()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        killed = False
        try:
            out, _ = self.proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            killed = True
            self.proc.kill()
            out, _ = self.proc.communicate()
        for line in (out or "").splitlines():
            # the flight model's C++ library writes to the same stdout, maybe without a newline
            at = line.find("STATS {")
            if at >= 0:
                try:
                    self.stats = json.loads(line[at + 6:])
                except ValueError:
                    log.warning("the simulator's report is not JSON: %.200s", line[at:])
        if not self.stats:
            why = (f"killed after {timeout_s:g} s without a report" if killed
                   else f"exited with code {self.proc.returncode} without a report")
            log.warning("the simulator %s (its stderr above says why)", why)
            self.stats = {"stop": f"simulator {why}", "exit_code": self.proc.returncode,
                          "stop_wait_s": round(time.monotonic() - t0, 2)}
        return self.stats


def run_sim(cfg: Config, sim: SimOptions, duration_s: float | None,
            *, handle_signals: bool = True, on_runtime: Any = None) -> dict[str, Any]:
    """Fly one simulated vehicle; returns the run summary (runtime and simulator figures)."""
    clock = Clock(sim.scale)
    flight_dir = new_flight_dir(Path(cfg.logs.dir),
                                suffix=f"-v{cfg.vehicle.id}" if cfg.vehicle.id != 1 else "")
    with tempfile.TemporaryDirectory(prefix="companion-sim-") as tmp:
        device_dir = Path(tmp)
        world = WorldProcess(sim, clock, device_dir, flight_dir, duration_s)
        try:
            for row in VEHICLE.devices():  # every device the world simulates
                settings = device_settings(cfg, row.name)
                if row.name in world.devices:
                    settings.port = world.devices[row.name]
                elif settings.enabled:
                    log.warning("device %s: nothing simulates it (its row names no "
                                "simulator); it is switched off in this flight", row.name)
                    settings.enabled = False
            cfg.vehicle.home = ",".join(repr(float(v)) for v in world.devices["home"])
            t0 = 0.0  # set at take-off, below
            first = True
            injectors: list[ThreadFaultInjector] = []
            faults = [parse_thread_fault(f) for f in sim.thread_faults]
            steps = WallClockSteps([parse_clock_step(c) for c in sim.clock_steps], clock)

            def inject(ctx: RuntimeContext, manager: ThreadManager) -> ThreadFaultInjector:
                injectors.append(ThreadFaultInjector(ctx, manager, faults))
                return injectors[-1]

            while True:
                rt = Runtime(cfg, RuntimeOptions(
                    clock=clock, flight_dir=flight_dir,
                    extra_run_info={"simulation": {**vars(sim), "pid": world.proc.pid,
                                                   "sensors": sensor_metadata(sim)}},
                    extra_bridges=live_view_bridges(cfg) + ([inject] if faults else [])))
                if sim.gps_ashtech:
                    rt.ctx.params.set("GPS_PASHR", 1)
                # the simulated installation's level calibration, as a user's would set them
                rt.ctx.params.set_many(world.devices.get("params", {}))
                if on_runtime is not None:
                    on_runtime(rt)
                if steps.pending:
                    rt.manager.on_tick.append(steps.tick)
                go = _camera_go(sim, rt)  # refused before anything runs
                rt.start()
                if first:
                    world.go(**go)
                    first = False
                    t0 = time.monotonic()  # the flight starts now; a reboot does not extend it
                else:
                    world.retarget(**go)  # the rebooted runtime may have bound a new port
                remaining = None
                if duration_s:
                    remaining = max(0.001, duration_s - (time.monotonic() - t0) * clock.scale)
                reason = rt.run(remaining, handle_signals=handle_signals)
                if reason != "reboot":
                    break
                # a reboot restarts the flight program; the world (the aircraft) flies on
                log.warning("reboot requested: restarting the runtime")
            host_s = time.monotonic() - t0
        finally:
            steps.restore()
            stats = world.stop()
    summary = rt.summary()
    summary["simulator"] = stats
    sensors = sensor_metadata(sim)
    summary["sensors"] = {k: sensors[k] for k in ("imu_profile", "gps_profile", "turbulence",
                                                  "no_noise")}
    if injectors:
        summary["thread_faults"] = [a for inj in injectors for a in inj.armed]
    if steps.applied:
        summary["clock_steps"] = steps.applied
    summary["host_seconds"] = round(host_s, 2)
    summary["clock_scale"] = clock.scale
    write_json_bounded(flight_dir / "summary.json", summary, 2.0)
    return summary


def _camera_go(sim: SimOptions, rt: Runtime) -> dict[str, Any]:
    """Where the world's camera sends its fixes: the legacy adapter's bound command port (it
    may have been asked for port 0), on loopback unless it listens on one address only."""
    if sim.horizon_camera == "off":
        return {}
    from legacy_protocol.adapter import LegacyAdapter

    for bridge in rt.bridges:
        if isinstance(bridge, LegacyAdapter):
            host, port = bridge.listen_addr[:2]
            host = "127.0.0.1" if host in ("0.0.0.0", "") else host
            return {"horizon_dest": f"{host}:{port}", "vehicle_id": rt.cfg.vehicle.id}
    raise SimError(CAMERA_NEEDS_LEGACY)


def sensor_metadata(sim: SimOptions) -> dict[str, Any]:
    """The flight's sensor and air profiles, names and resolved numbers, for run.json (the
    world resolves them the same way from the same options)."""
    from companion.sim.profiles import resolve_sensors

    return resolve_sensors(sim.imu_profile, sim.gps_profile, sim.turbulence,
                           no_noise=sim.no_noise, gps_latency_s=sim.gps_latency_s,
                           gps_ashtech=sim.gps_ashtech).metadata()


def shift_endpoint_port(url: str, offset: int) -> str:
    """`udpout:127.0.0.1:14550` + 2 -> `udpout:127.0.0.1:14552` (options after `?` kept);
    a serial endpoint (no network port) is returned unchanged."""
    if offset == 0 or not url.startswith(("udp", "tcp")):
        return url
    head, sep, options = url.partition("?")
    match = re.search(r":(\d+)$", head)
    if match is None:
        return url
    return f"{head[:match.start()]}:{int(match.group(1)) + offset}{sep}{options}"


def _fleet_argv(argv: list[str], offset: int) -> list[str]:
    out, it = [], iter(argv)
    for a in it:
        if a == "--mavlink":
            out += [a, shift_endpoint_port(next(it, ""), offset)]
        elif a.startswith("--mavlink="):
            out.append("--mavlink=" + shift_endpoint_port(a.split("=", 1)[1], offset))
        else:
            out.append(a)
    return out


def run_fleet(argv_base: list[str], vehicles: int, legacy_listen: int,
              *, mavlink_port_step: int = 0) -> int:
    """`--vehicles K`: K independent `companion sim` processes, vehicle ids 1..K; with a port
    step, each aircraft's MAVLink endpoints move by it (one link per aircraft)."""
    procs = []
    for i in range(1, vehicles + 1):
        argv = _fleet_argv(argv_base, mavlink_port_step * (i - 1))
        cmd = [sys.executable, "-m", "companion", *argv, "--vehicle-id", str(i),
               "--legacy-listen", str(legacy_listen + i - 1),
               "--params-file", f"params-v{i}.parm", "--seed-offset", str(i - 1)]
        procs.append(subprocess.Popen(cmd, env={**os.environ}))

    stopping: list[int] = []

    def stop_all(signum: int, _frame: object) -> None:
        # every aircraft lands its logs on SIGINT; a fleet stopped with SIGTERM (systemd, kill)
        # must not leave them flying as orphans
        log.info("fleet: signal %d, stopping %d aircraft", signum, len(procs))
        stopping.append(signum)
        _interrupt(procs)

    # explicit handlers, not Python's KeyboardInterrupt: a fleet started with SIGINT ignored
    # (`nohup ... &`, a CI job's background step) would otherwise never stop on it
    stops = (signal.SIGINT, signal.SIGTERM)
    old = ({s: signal.signal(s, stop_all) for s in stops}
           if threading.current_thread() is threading.main_thread() else {})
    codes = []
    try:
        for p in procs:
            while True:
                try:
                    codes.append(p.wait(timeout=FLEET_RESEND_S))
                    break
                except subprocess.TimeoutExpired:
                    if stopping:
                        # an aircraft that was still starting when the signal came may have
                        # had SIGINT ignored (inherited) until its runtime took it over
                        _interrupt(procs)
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)
    return max(codes) if codes else 0


FLEET_RESEND_S = 1.0
"""While a stopping fleet waits for its aircraft, it repeats SIGINT this often to those still
running (a stop request is idempotent in the runtime)."""


def _interrupt(procs: list[subprocess.Popen[bytes]]) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
