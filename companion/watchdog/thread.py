"""The managed thread: the unit of work the thread manager supervises.

The split of responsibilities follows the thesis's design and the lessons it drew from the
older program: resources are acquired and released in the *main* thread (`setup` / `cleanup`),
so a worker that is stopped, interrupted or abandoned never leaves a file or a port open; the
worker runs an aperiodic `prologue` and then repeats `step` until asked to stop; `recover` runs in
the main thread after a stall or a crash, before the restart.

A worker proves it is alive by completing periodic cycles. A device-paced step that timed out
without data returns False, which does not count as a cycle: that is how the watchdog sees a
silent device.
"""

from __future__ import annotations

import ctypes
import enum
import logging
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from companion.core.clock import Clock
from companion.core.osthread import set_native_name
from companion.core.params import ParamRegistry, ParamSpec, int_param
from companion.core.state import VehicleState

if TYPE_CHECKING:
    from companion.watchdog.manager import ThreadManager

log = logging.getLogger(__name__)

PERIOD_RING = 4096  # cycle-period samples kept per thread for jitter statistics


class RestartType(enum.Enum):
    """OTP restart types: which terminations of a child lead to a restart."""

    PERMANENT = "permanent"  # always restarted, even after a normal exit
    TRANSIENT = "transient"  # restarted after a crash or a stall, not after a normal exit
    TEMPORARY = "temporary"  # never restarted


class ThreadInterrupted(BaseException):
    """Raised asynchronously inside a pure-Python loop that ignored its stop request.

    A BaseException so that a careless `except Exception` in user code cannot swallow it.
    """


@dataclass
class RuntimeContext:
    """What every managed thread may use: the clock, the parameters, the log service."""

    clock: Clock = field(default_factory=Clock)
    params: ParamRegistry = field(default_factory=ParamRegistry)
    logs: Any = None  # companion.logs.LogService when logging is on
    state: VehicleState = field(default_factory=VehicleState)
    vehicle_id: int = 1
    home_lla: tuple[float, float, float] | None = None  # NED origin; None = first GPS fix
    flight_dir: Path | None = None
    extras: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ThreadStatus:
    """A consistent snapshot of one thread, as the ground stations show it."""

    name: str
    thread_id: int
    initialised: bool
    running: bool
    in_periodic: bool
    alive: bool
    enabled: bool
    failed: bool
    restarts: int
    stalls: int
    crashes: int
    interrupted: int
    abandoned: int
    cycles: int
    mean_step_us: float
    worst_step_us: float
    overruns: int
    missed_deadlines: int
    rate_hz: float | None
    budget_us: float
    measured_rate_hz: float
    watchdog_ms: int
    message_ms: int
    last_error: str
    log_dropped: int


class ManagedThread:
    """Base class of every supervised thread; subclasses override the hooks below.

    `period_ms` set: timer-driven on absolute monotonic deadlines (no drift, missed deadlines
    counted and skipped rather than bunched). `period_ms` None: paced by `step` itself (a
    blocking device read with a timeout, or a wait on a data slot).
    """

    #: Restart type (OTP). Transient by default: a thread that decides to terminate stays down.
    restart: RestartType = RestartType.TRANSIENT
    #: Timer threads: how many whole lost periods are caught up (run back to back) before
    #: lost cycles are dropped instead. 0 keeps the phase at any cost; an exchange with a
    #: device (the servo board) would rather catch up a short hiccup than lose commands.
    max_catch_up: int = 0

    def __init__(
        self,
        name: str,
        *,
        thread_id: int,
        period_ms: float | None = None,
        budget_ms: float | None = None,
        watchdog_ms: int = 500,
        message_ms: int = 1000,
        shutdown_timeout_ms: int | None = None,
        param_prefix: str | None = None,
    ) -> None:
        self.name = name
        self.thread_id = thread_id
        self.period_ms = period_ms
        self.budget_ms = budget_ms if budget_ms is not None else (period_ms or 10.0)
        self.shutdown_timeout_ms = shutdown_timeout_ms
        """How long this thread may take to stop (host ms); None: the manager's MGR_SHUTDOWN_MS.
        A thread whose cleanup legitimately takes longer (flushing a device) says so here."""
        self.param_prefix = (param_prefix or name).upper()[:6]
        self._default_watchdog_ms = watchdog_ms
        self._default_message_ms = message_ms
        self.ctx: RuntimeContext = RuntimeContext()
        self.tlog: Any = None  # the thread's ThreadLog, if the subclass opens one in setup()
        self._manager: ThreadManager | None = None
        # incarnation state, replaced at every (re)start
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self._params_dirty = threading.Event()
        self._unsubscribe: Any = None
        # status (written by the worker, read racily by the manager: plain attributes)
        self.initialised = False
        self.running = False
        self.in_periodic = False
        self.alive_at_last_check = False
        self.failed = False
        self.restarts = 0
        self.stalls = 0
        self.crashes = 0
        self.interrupted = 0
        self.abandoned = 0
        self.cycles = 0
        self.heartbeats = 0  # every return from step(), with or without data
        self.overruns = 0
        self.missed_deadlines = 0
        self.last_error = ""
        self._step_total_ns = 0
        self._step_count = 0
        self._step_worst_ns = 0
        self._period_ring = [0] * PERIOD_RING
        self._period_n = 0
        self._last_cycle_start_ns = 0
        self._rate_ring: list[tuple[int, int]] = [(0, 0)] * 256  # (host ns, cycles) samples
        self._rate_n = 0
        self.work_t0_ns = 0  # set by device-paced steps when data arrived (excludes the wait)
        self._exit_kind: str = ""  # "", "normal", "crash"

    # ---------------------------------------------------------------- hooks for implementers
    def declare_params(self) -> list[ParamSpec]:
        """Extra parameters this thread owns (the base adds WDG_MS, MSG_MS, ENABLE)."""
        return []

    def define_logs(self, tlog: Any) -> None:
        """Declare this thread's log formats on its ThreadLog (`tlog.define(index, fmt, columns)`)."""

    def setup(self) -> None:
        """Acquire resources (ports, files). Runs in the main thread, in declaration order."""

    def cleanup(self) -> None:
        """Release resources. Main thread, reverse order; must be idempotent."""

    def interrupt_io(self) -> None:
        """Make a blocked read return (cancel it or close the port). Called from the main
        thread while the worker may be blocked; must not wait for the worker."""

    def prologue(self) -> bool:
        """Aperiodic section in the worker. Return False to terminate without looping."""
        return True

    def step(self) -> bool | int | None:
        """One periodic cycle in the worker. Return False (or 0) when the cycle made no
        progress (timeout without data), so the watchdog is not told the thread is alive; an
        int counts the items it delivered (a read that brought two IMU frames is two cycles)."""
        return None

    def recover(self) -> None:
        """Main thread, after a stall or a crash and before the restart: reset state that may
        be inconsistent (half-parsed frames, filters)."""

    def on_params_changed(self) -> None:
        """Worker thread, between cycles, after any parameter changed."""

    # ---------------------------------------------------------------- parameters
    def base_params(self) -> list[ParamSpec]:
        p = self.param_prefix
        return [
            int_param(f"{p}_WDG_MS", self._default_watchdog_ms, 10, 600_000, "ms",
                      f"Watchdog period of the {self.name} thread: a stall is declared when no "
                      "periodic cycle completes within it."),
            int_param(f"{p}_MSG_MS", self._default_message_ms, 10, 3_600_000, "ms",
                      f"Period of the {self.name} thread's data messages to the ground."),
            int_param(f"{p}_ENABLE", 1, 0, 1, "",
                      f"1 runs the {self.name} thread, 0 stops it cleanly."),
        ]

    def param(self, suffix: str) -> Any:
        return self.ctx.params.get(f"{self.param_prefix}_{suffix}")

    @property
    def watchdog_ms(self) -> int:
        return int(self.param("WDG_MS"))

    @property
    def message_ms(self) -> int:
        return int(self.param("MSG_MS"))

    @property
    def enabled(self) -> bool:
        return bool(self.param("ENABLE"))

    # ---------------------------------------------------------------- used by implementers
    @property
    def stop_requested(self) -> bool:
        return self._stop.is_set()

    @property
    def stop_event(self) -> threading.Event:
        return self._stop

    # ---------------------------------------------------------------- status
    def status(self) -> ThreadStatus:
        n = self._step_count
        mean_us = self._step_total_ns / n / 1e3 if n else 0.0
        return ThreadStatus(
            name=self.name,
            thread_id=self.thread_id,
            initialised=self.initialised,
            running=self.running,
            in_periodic=self.in_periodic,
            alive=self.alive_at_last_check,
            enabled=self.enabled,
            failed=self.failed,
            restarts=self.restarts,
            stalls=self.stalls,
            crashes=self.crashes,
            interrupted=self.interrupted,
            abandoned=self.abandoned,
            cycles=self.cycles,
            mean_step_us=mean_us,
            worst_step_us=self._step_worst_ns / 1e3,
            overruns=self.overruns,
            missed_deadlines=self.missed_deadlines,
            rate_hz=1000.0 / self.period_ms if self.period_ms else None,
            budget_us=self.budget_ms * 1e3,
            measured_rate_hz=self.measured_rate_hz(),
            watchdog_ms=self.watchdog_ms,
            message_ms=self.message_ms,
            last_error=self.last_error,
            log_dropped=int(getattr(self.tlog, "dropped", 0) or 0),
        )

    def period_samples_ns(self) -> list[int]:
        """Recent cycle-to-cycle start intervals (host ns), oldest first."""
        n = min(self._period_n, PERIOD_RING)
        start = self._period_n - n
        return [self._period_ring[i % PERIOD_RING] for i in range(start, self._period_n)]

    def measured_rate_hz(self) -> float:
        """Cycles per second (in clock time) over the last 256 steps."""
        n = min(self._rate_n, len(self._rate_ring))
        if n < 2:
            return 0.0
        size = len(self._rate_ring)
        t_old, c_old = self._rate_ring[(self._rate_n - n) % size]
        t_new, c_new = self._rate_ring[(self._rate_n - 1) % size]
        if t_new <= t_old:
            return 0.0
        return (c_new - c_old) / ((t_new - t_old) / 1e9) / self.ctx.clock.scale

    def reset_statistics(self) -> None:
        self._step_total_ns = 0
        self._step_count = 0
        self._step_worst_ns = 0
        self._period_n = 0
        self._rate_n = 0
        self.missed_deadlines = 0
        self.overruns = 0

    # ---------------------------------------------------------------- manager side
    def _ensure_log(self) -> None:
        """Open this thread's log once per run; every (re)start then adds a Begin Data."""
        logs = self.ctx.logs
        has_formats = type(self).define_logs is not ManagedThread.define_logs
        if self.tlog is None and logs is not None and has_formats:
            text = "LOG_TEXT" in self.ctx.params and bool(self.ctx.params.get("LOG_TEXT"))
            self.tlog = logs.open(self.name, text=text)
            self.define_logs(self.tlog)

    def _start_worker(self) -> None:
        self._stop = threading.Event()
        self._params_dirty.clear()
        self._exit_kind = ""
        self._last_cycle_start_ns = 0
        stop = self._stop
        self._worker = threading.Thread(
            target=self._run, args=(stop,), name=f"managed-{self.name}", daemon=True
        )
        self._worker.start()

    def _mark_params_dirty(self, name: str, value: object) -> None:
        self._params_dirty.set()

    def _raise_async(self, exc: type[BaseException]) -> bool:
        worker = self._worker
        if worker is None or worker.ident is None or not worker.is_alive():
            return False
        n = ctypes.pythonapi.PyThreadState_SetAsyncExc(
            ctypes.c_ulong(worker.ident), ctypes.py_object(exc)
        )
        return n == 1

    # ---------------------------------------------------------------- worker side
    def _run(self, stop: threading.Event) -> None:
        set_native_name(self.name)
        clock = self.ctx.clock
        self.running = True
        tlog = self.tlog
        clean = False
        try:
            if tlog is not None:
                tlog.begin()
            if not self.prologue():
                self._exit_kind = "normal"
                clean = True
                return
            self.in_periodic = True
            period_ns = int(self.period_ms * 1e6) if self.period_ms else 0
            next_ns = clock.monotonic_ns() + period_ns
            budget_ns = int(self.budget_ms * 1e6 / clock.scale)
            while not stop.is_set():
                if self._params_dirty.is_set():
                    self._params_dirty.clear()
                    self.on_params_changed()
                self.work_t0_ns = 0
                t0 = time.perf_counter_ns()
                progressed = self.step()
                t1 = time.perf_counter_ns()
                self.heartbeats += 1
                if stop.is_set():
                    break
                if progressed is not False and progressed != 0:
                    count = progressed if type(progressed) is int else 1
                    work_t0 = self.work_t0_ns or t0
                    self._account_cycle(t0, t1 - work_t0, budget_ns, count)
                if period_ns:
                    next_ns += period_ns
                    now = clock.monotonic_ns()
                    if now > next_ns:
                        # late: run the next cycle at once, but if a whole period or more
                        # was lost, drop those cycles rather than bunch them (keeps the phase)
                        self.missed_deadlines += 1
                        behind = (now - next_ns) // period_ns
                        if behind > self.max_catch_up:
                            next_ns += behind * period_ns
                    if clock.wait_until_ns(next_ns, stop):
                        break
            self._exit_kind = "normal"
            clean = True
        except ThreadInterrupted:
            self._exit_kind = "interrupted"
        except Exception as exc:  # a crash of user code: the manager restarts via recover()
            self._exit_kind = "crash"
            self.last_error = f"{type(exc).__name__}: {exc}"
            log.debug("thread %s crashed:\n%s", self.name, traceback.format_exc())
        finally:
            if clean and tlog is not None:
                try:
                    tlog.end()
                except Exception:
                    log.exception("thread %s: could not write End Data", self.name)
            self.in_periodic = False
            self.running = False
            manager = self._manager
            if manager is not None:
                manager.wake()

    def _account_cycle(self, t0_ns: int, step_ns: int, budget_ns: int, count: int = 1) -> None:
        if self._last_cycle_start_ns:
            self._period_ring[self._period_n % PERIOD_RING] = t0_ns - self._last_cycle_start_ns
            self._period_n += 1
        self._last_cycle_start_ns = t0_ns
        self._step_total_ns += step_ns
        self._step_count += 1
        if step_ns > self._step_worst_ns:
            self._step_worst_ns = step_ns
        if step_ns > budget_ns:
            self.overruns += 1
        self.cycles += count
        self._rate_ring[self._rate_n % len(self._rate_ring)] = (t0_ns, self.cycles)
        self._rate_n += 1
