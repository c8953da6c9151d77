"""Assembles one vehicle's runtime from its configuration and runs it until told to stop.

The same assembly serves a real flight (`companion run`) and a simulated one (`companion sim`,
which only points the device settings at the simulator's pseudo-terminals), so what is tested
in simulation is what flies.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

from companion import __version__
from companion.core.clock import Clock
from companion.core.config import Config
from companion.core.files import write_json_bounded
from companion.core.params import FileIssue, ParamRegistry, ParamSpec, int_param
from companion.core.state import VehicleState
from companion.logs.retention import DiskPolicy, FlightLock
from companion.service import ServiceNotifications
from companion.vehicle import VEHICLE, Row, VehicleTable, fill_device_defaults
from companion.watchdog import EventKind, ManagedThread, RuntimeContext, Task, ThreadManager
from companion.watchdog.manager import MANAGER_PARAMS

log = logging.getLogger(__name__)

SWITCH_INTERVAL_S = 0.0005
SUMMARY_WRITE_TIMEOUT_S = 2.0  # host seconds shutdown waits for summary.json on a slow disk

RUNTIME_PARAMS: list[ParamSpec] = [
    int_param("LOG_TEXT", 0, 0, 1, "",
              "1 writes CSV text logs (one file per format) instead of binary logs.", reboot=True),
    int_param("LOG_MIN_FREE_MB", 0, 0, 10_000_000, "MB",
              "Disk policy: delete the oldest finished flights (never the current one) while "
              "less than this is free on the logs' disk; checked at start and every 10 s. "
              "0 = off (`companion install` sets 500)."),
    int_param("LOG_MAX_FLIGHTS", 0, 0, 1_000_000, "",
              "Disk policy: keep at most this many flight directories (the current one "
              "included), deleting the oldest finished ones. 0 = no limit."),
    int_param("SYS_VEHICLE_ID", 1, 1, 255, "",
              "MAVLink system id and legacy vehicle id (from the configuration).", read_only=True),
]


def new_flight_dir(root: Path, *, suffix: str = "") -> Path:
    """`root/<UTC timestamp>` (with a counter when two runs start in the same second)."""
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    root.mkdir(parents=True, exist_ok=True)
    for n in range(1000):
        name = stamp + suffix + (f"-{n}" if n else "")
        path = root / name
        try:
            path.mkdir()
            return path
        except FileExistsError:
            continue
    raise RuntimeError(f"cannot create a flight directory under {root}")


BridgeFactory = Callable[[RuntimeContext, ThreadManager], "Bridge"]
"""Makes a bridge for a runtime being built; the bridge may add threads to the manager."""


def _already_stopping(signum: int, _frame: object) -> None:
    """A stop signal after the runtime has stopped on one: nothing more to do."""
    log.info("signal %s: already stopping", signal.Signals(signum).name)


@dataclass
class RuntimeOptions:
    """What the command line adds to the configuration for one run."""

    mavlink: bool = True
    legacy: bool = True
    estimator: bool = True
    control: bool = True
    flight_dir: Path | None = None
    clock: Clock = field(default_factory=Clock)
    dry: bool = False  # build only (parameter listing, docs): no files, no sockets
    extra_run_info: dict[str, Any] = field(default_factory=dict)
    extra_bridges: list[BridgeFactory] = field(default_factory=list)
    """Built after the MAVLink and legacy bridges, each with (ctx, manager): how the layers above
    the runtime (the live view) attach without the runtime importing them. Not built when dry."""
    log_writer_thread: bool = True
    """False: the logs are written when the owner calls `rt.logs.drain()` (a lockstep flight)."""
    vehicle: VehicleTable = VEHICLE
    """The sources and threads this vehicle runs (a plug-in or a test extends the table)."""


def vehicle_rows(cfg: Config, opts: RuntimeOptions) -> list[Row]:
    """The rows of the vehicle's table this run builds, in the table's (start) order: a
    device's row when its ``[devices.<name>]`` is enabled, a switchable row (the estimator,
    the control law) unless its `RuntimeOptions` flag is off."""
    rows = []
    for row in opts.vehicle:
        if row.device is not None:
            settings = cfg.devices.get(row.name, row.device)
            if settings.enabled:
                rows.append(row)
        elif not row.switch or getattr(opts, row.switch):
            rows.append(row)
    return rows


def vehicle_tasks(cfg: Config, opts: RuntimeOptions) -> list[Task]:
    """The supervision rows of `vehicle_rows`."""
    return [row.task for row in vehicle_rows(cfg, opts)]


def build_threads(cfg: Config, opts: RuntimeOptions | None = None) -> list[ManagedThread]:
    """One thread per row of `vehicle_rows`, each built by its class from its row."""
    opts = opts or RuntimeOptions()
    return [row.build(cfg.devices.get(row.name)) for row in vehicle_rows(cfg, opts)]


class Bridge(Protocol):
    """What the runtime asks of everything that talks to the ground (MAVLink, the legacy
    protocol, the live view): to be closed after the manager stopped, and its message counts."""

    def close(self) -> None: ...

    def stats(self) -> list[dict[str, Any]]: ...


class Runtime:
    """One vehicle: parameters, slots, logs, threads, manager and bridges."""

    def __init__(self, cfg: Config, opts: RuntimeOptions | None = None) -> None:
        self.cfg = cfg
        self.opts = opts or RuntimeOptions()
        fill_device_defaults(cfg, self.opts.vehicle)  # run.json records every device's settings
        clock = self.opts.clock
        params = ParamRegistry()
        params.declare_all(RUNTIME_PARAMS)
        params.set("SYS_VEHICLE_ID", cfg.vehicle.id, force=True)
        dry = self.opts.dry
        if dry:
            self.flight_dir = Path(cfg.logs.dir) / "dry-run"
        else:
            self.flight_dir = self.opts.flight_dir or new_flight_dir(Path(cfg.logs.dir))
            self.flight_dir.mkdir(parents=True, exist_ok=True)
        self.logs: Any = None
        self._log_stats: dict[str, Any] = {}
        # held while this runtime writes the flight: the disk policy of another runtime
        # sharing the logs directory (a fleet) never deletes it
        self._flight_lock = None if dry else FlightLock(self.flight_dir)
        self.disk_policy: DiskPolicy | None = None
        if cfg.logs.enabled and not dry:
            from companion.logs import LogService

            self.logs = LogService(self.flight_dir, clock_ns=clock.realtime_ns,
                                   writer_thread=self.opts.log_writer_thread)
            # set after the manager exists (below): a full disk is reported like a watchdog event
        self.ctx = RuntimeContext(clock=clock, params=params, logs=self.logs,
                                  state=VehicleState(), vehicle_id=cfg.vehicle.id,
                                  home_lla=cfg.vehicle.home_lla(), flight_dir=self.flight_dir)
        self.manager = ThreadManager(self.ctx, build_threads(cfg, self.opts))
        if self.logs is not None:
            manager = self.manager
            self.logs.on_log_off = lambda label, reason: manager.report(
                EventKind.LOG_OFF, label, reason.rsplit(": ", 1)[-1])
        self.bridges: list[Bridge] = []
        try:
            self._build_bridges(cfg, dry)
        except BaseException:
            for bridge in self.bridges:  # release the sockets of those already built
                try:
                    bridge.close()
                except Exception:
                    log.exception("closing %s after a failed start", type(bridge).__name__)
            if self._flight_lock is not None:
                self._flight_lock.release()
            if not dry and self.opts.flight_dir is None:
                # a start refused (a bad key file, a port in use) is not a flight: leave no
                # empty directory for the log tools and the ground stations to list
                with contextlib.suppress(OSError):
                    self.flight_dir.rmdir()
            raise
        self.service = ServiceNotifications(self.manager)
        self.manager.on_tick.append(self.service.tick)
        self.events = self.manager.subscribe_events(capacity=10_000)
        self.event_log: list[dict[str, Any]] = []
        self.manager.on_tick.append(self._collect_events)
        # every parameter is declared now: load the persisted values over the defaults
        self.param_issues: list[FileIssue] = (
            [] if dry else params.attach_file(Path(cfg.params.file)))
        self._started = False

    def _build_bridges(self, cfg: Config, dry: bool) -> None:
        """MAVLink, legacy protocol and live view: everything that talks to the ground."""
        if self.opts.mavlink and cfg.mavlink.endpoints:
            from gcs_bridge import MavlinkBridge

            self.bridges.append(MavlinkBridge(
                self.ctx, self.manager, endpoints=list(cfg.mavlink.endpoints),
                key_file=cfg.mavlink.key_file or None,
                allow_unsigned_reads=cfg.mavlink.allow_unsigned_reads,
                logging_control=self._logging_control,
                tlog=not dry))
        if self.opts.legacy and cfg.legacy.enabled:
            from legacy_protocol.adapter import LegacyAdapter

            self.bridges.append(LegacyAdapter(
                self.ctx, self.manager, dest=cfg.legacy.dest, listen_port=cfg.legacy.listen,
                allow=list(cfg.legacy.allow), bind_host=cfg.legacy.bind, listen=not dry))
        if not dry:
            for make in self.opts.extra_bridges:
                self.bridges.append(make(self.ctx, self.manager))

    # ------------------------------------------------------------------ running
    def run_info(self) -> dict[str, Any]:
        return {
            "software": {"name": "uav-companion", "version": __version__},
            "started_utc": datetime.now(UTC).isoformat(),
            "clock_scale": self.ctx.clock.scale,
            "config": self.cfg.to_dict(),
            "parameters": self.ctx.params.snapshot(),
            "parameter_file_issues": [str(i) for i in self.param_issues],
            "threads": [{"name": t.name, "id": t.thread_id} for t in self.manager.threads],
            **self.opts.extra_run_info,
        }

    def start(self) -> None:
        # Device threads wait for the GIL after their read returns; CPython's default 5 ms
        # switch interval would make that wait longer than a servo period at 5x simulation.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        if not self.opts.dry:
            params = self.ctx.params
            self.disk_policy = DiskPolicy(
                self.flight_dir.parent, self.flight_dir,
                lambda: (float(params.get("LOG_MIN_FREE_MB")), int(params.get("LOG_MAX_FLIGHTS"))),
                on_delete=lambda d: self.manager.report(
                    EventKind.NOTICE, "logs",
                    f"deleted flight {d.path.name} ({d.size_mb:.0f} MB): {d.reason}"))
            self.disk_policy.start()
        if self.logs is not None:
            from companion.logs import write_run_json

            self.logs.start()
            write_run_json(self.flight_dir, self.run_info())
        self.manager.start()
        self._started = True

    def run(self, duration_s: float | None = None, *, handle_signals: bool = True) -> str:
        """Run until the duration, a signal, or a STOP command; always shuts down cleanly."""
        with self._signals(handle_signals):
            try:
                if not self._started:
                    self.start()
                return self.manager.run(duration_s)
            finally:
                self.shutdown()

    def _logging_control(self, start: bool) -> str | None:
        """MAVLink start/stop logging: pause or resume the flight logs (None = done)."""
        if self.logs is None:
            return "logging is disabled in the configuration"
        self.logs.set_paused(not start)
        return None

    def _collect_events(self) -> None:
        for e in self.events.drain():
            self.event_log.append({"t_s": e.t_ns / 1e9, "kind": e.kind.value, "thread": e.thread,
                                   "detail": e.detail, "severity": e.severity})

    def shutdown(self) -> None:
        self.service.stopping(self.manager.stop_reason or "stop")
        self.manager.shutdown()
        self._collect_events()
        for bridge in self.bridges:
            try:
                bridge.close()
            except Exception:
                log.exception("closing bridge %s", type(bridge).__name__)
        if self.disk_policy is not None:
            self.disk_policy.stop()
        if self.logs is not None:
            self.logs.close()
            self._log_stats = self.logs.stats()
            self.logs = None
        if self._flight_lock is not None:
            self._flight_lock.release()
        if not self.opts.dry and self._started:
            write_json_bounded(self.flight_dir / "summary.json", self.summary(),
                               SUMMARY_WRITE_TIMEOUT_S)

    @contextlib.contextmanager
    def _signals(self, enabled: bool) -> Iterator[None]:
        if not enabled or threading.current_thread() is not threading.main_thread():
            yield
            return

        signalled: list[int] = []

        def handler(signum: int, _frame: object) -> None:
            signalled.append(signum)
            self.manager.request_stop(f"signal {signal.Signals(signum).name}")

        old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield
        finally:
            for s, h in old.items():
                # A process a signal has stopped is ending: a repeated stop signal (a fleet
                # resends SIGINT to aircraft that may have started with it ignored) must not
                # become a KeyboardInterrupt in what is left to do (reports, the world's exit).
                signal.signal(s, _already_stopping if signalled else h)

    # ------------------------------------------------------------------ reporting
    def summary(self) -> dict[str, Any]:
        files = sorted(p for p in self.flight_dir.iterdir() if p.is_file())
        return {
            "flight_dir": str(self.flight_dir),
            "stop_reason": self.manager.stop_reason,
            "escalated": self.manager.escalated,
            "threads": [
                {"name": s.name, "cycles": s.cycles, "restarts": s.restarts, "stalls": s.stalls,
                 "failed": s.failed, "rate_hz": round(s.measured_rate_hz, 2),
                 "mean_step_us": round(s.mean_step_us, 1),
                 "worst_step_us": round(s.worst_step_us, 1), "overruns": s.overruns,
                 "crashes": s.crashes, "interrupted": s.interrupted, "abandoned": s.abandoned,
                 "missed_deadlines": s.missed_deadlines,
                 "log_dropped": s.log_dropped,
                 **({"counters": c} if (c := t.counters()) else {})}
                for s, t in zip(self.manager.thread_status(), self.manager.threads, strict=True)
            ],
            "files": {p.name: p.stat().st_size for p in files},
            "events": list(self.event_log),
            "messages": [s for b in self.bridges for s in b.stats()],
            # the writer's own account: records dropped in flight and left unwritten at the
            # end (a disk too slow to finish within the close's patience), files logging off
            "logs": {k: v for k, v in self._log_stats.items() if k != "running"},
            "disk_policy_deleted": [
                {"flight": d.path.name, "size_mb": round(d.size_mb, 1), "reason": d.reason}
                for d in (self.disk_policy.deleted if self.disk_policy is not None else [])],
        }


def declared_specs(cfg: Config) -> list[ParamSpec]:
    """Every parameter the runtime declares for `cfg`, read from the task rows and the bridges'
    declarations: nothing is built, opened or bound."""
    specs = list(RUNTIME_PARAMS) + list(MANAGER_PARAMS)
    for task in vehicle_tasks(cfg, RuntimeOptions()):
        specs += task.param_specs()
    if cfg.mavlink.endpoints:
        from gcs_bridge.bridge import declared_params as mavlink_params

        specs += mavlink_params(len(cfg.mavlink.endpoints))
    if cfg.legacy.enabled:
        from legacy_protocol.adapter import declared_params as legacy_params

        specs += legacy_params()
    return specs


def declared_registry(cfg: Config) -> ParamRegistry:
    """A registry holding `declared_specs(cfg)` at their defaults (docs, `companion params`)."""
    reg = ParamRegistry()
    reg.declare_all(declared_specs(cfg))
    reg.set("SYS_VEHICLE_ID", cfg.vehicle.id, force=True)
    return reg


def status_line(manager: ThreadManager) -> str:
    parts = []
    for s in manager.thread_status():
        led = "".join(c if on else "." for c, on in (
            ("I", s.initialised), ("R", s.running), ("P", s.in_periodic), ("A", s.alive)))
        parts.append(f"{s.name}[{led}] {s.measured_rate_hz:5.1f}Hz r{s.restarts}")
    st = manager.status()
    return f"t={st.elapsed_ms / 1000:7.1f}s " + "  ".join(parts)


