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

import logging
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Self

from companion.core.clock import Clock, Worker
from companion.core.config import DeviceConfig
from companion.core.osthread import set_native_name
from companion.core.params import ParamRegistry, ParamSpec
from companion.core.state import VehicleState
from companion.watchdog.task import RestartType, Task

log = logging.getLogger(__name__)

PERIOD_RING = 4096  # cycle-period samples kept per thread for jitter statistics
RATE_RING = 256  # (clock time, cycles) samples the measured rate is taken over
NOTICE_INTERVAL_S = 5.0  # flight time between two NOTICE events of one thread

__all__ = ["ManagedThread", "RestartType", "RuntimeContext", "Task", "ThreadInterrupted",
           "ThreadStatus"]


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

    The numbers (id, period, budget, watchdog and message periods, restart type, shutdown
    timeout, parameter prefix) come from a `Task` row; the class supplies the behaviour.
    `period_ms` set: timer-driven on absolute monotonic deadlines (no drift, missed deadlines
    counted and skipped rather than bunched). `period_ms` None: paced by `step` itself (a
    blocking device read with a timeout, or a wait on a data slot).

    The supervisor's handle is small and explicit: `attach`, `open_log`, `start_worker`,
    `request_stop`, `interrupt_io`, `interrupt_worker`, `join_worker`, `worker_alive`,
    `outcome`, `release_worker` and `notify_params_changed`. Nothing else of a thread's
    insides is the manager's business.
    """

    @classmethod
    def from_row(cls, task: Task, settings: DeviceConfig | None) -> Self:
        """The thread of `task`, a row of the vehicle's table, as the runtime builds it.
        `settings` is the row's ``[devices.<name>]`` configuration (None for a thread that
        takes none); a device class overrides this to open its port from them."""
        return cls(task=task)

    def __init__(self, task: Task | str, **fields: Any) -> None:
        """`task` is the thread's row; a name plus keyword fields builds a row on the spot
        (custom threads and tests), and keyword fields given with a row override it."""
        if isinstance(task, str):
            task = Task(task, **fields)
        elif fields:
            task = task.replace(**fields)
        self.task = task
        self.name = task.name
        self.thread_id = task.thread_id  # the manager may assign one when the row says 0
        self.period_ms = task.period_ms
        self.budget_ms = task.effective_budget_ms
        self.shutdown_timeout_ms = task.shutdown_timeout_ms
        self.param_prefix = task.param_prefix
        self.restart = task.restart
        self.escalate = task.escalate
        self.max_catch_up = task.max_catch_up
        self.ctx: RuntimeContext = RuntimeContext()
        self.tlog: Any = None  # the thread's ThreadLog, if the subclass declares formats
        self._on_exit: Callable[[], None] | None = None
        # incarnation state, replaced at every (re)start
        self._stop = threading.Event()
        self._worker: Worker | None = None
        self._params_dirty = threading.Event()
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
        # bounded rings (one C-level append per cycle, at every thread's rate)
        self._periods: deque[int] = deque(maxlen=PERIOD_RING)
        self._last_cycle_start_ns = 0
        self._rates: deque[tuple[int, int]] = deque(maxlen=RATE_RING)  # (clock ns, cycles)
        self.work_t0_ns = 0  # set by device-paced steps when data arrived (excludes the wait)
        self.notices = 0
        self._on_notice: Callable[[str], None] | None = None
        self._notice_next_ns: dict[str, int] = {}
        self._notices_held: dict[str, int] = {}
        self._exit_kind: str = ""  # "", "normal", "crash", "interrupted"

    # ---------------------------------------------------------------- hooks for implementers
    @classmethod
    def declare_params(cls, prefix: str) -> list[ParamSpec]:
        """Extra parameters this thread class owns, named `<prefix>_...` (its row adds WDG_MS,
        MSG_MS and ENABLE). A class method: the metadata is read without building a thread."""
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

    COMMANDS: frozenset[str] = frozenset()
    """Manager commands this thread carries out itself (`post_command`)."""

    def post_command(self, kind: str, reply: Callable[[bool, str], None]) -> str | None:
        """Any thread: hand over one of `COMMANDS`; the worker calls ``reply(ok, reason)`` when
        it is done. Returns an error instead when the command cannot start (then ``reply`` is
        never called)."""
        return f"thread {self.name} does not take the command {kind!r}"

    # ---------------------------------------------------------------- parameters
    def param_specs(self) -> list[ParamSpec]:
        """Every parameter of this thread: its row's and its class's."""
        return self.task.base_params() + type(self).declare_params(self.param_prefix)

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
        return list(self._periods)

    def measured_rate_hz(self) -> float:
        """Cycles per second of clock time over the last 256 steps."""
        rates = self._rates
        try:  # the worker appends meanwhile, and a statistics reset may empty the ring
            t_old, c_old = rates[0]
            t_new, c_new = rates[-1]
        except IndexError:
            return 0.0
        if t_new <= t_old:
            return 0.0
        return (c_new - c_old) / ((t_new - t_old) / 1e9)

    def counters(self) -> dict[str, int]:
        """Thread-specific counters for the flight summary (a driver's bytes and errors)."""
        return {}

    def io_bytes(self) -> int:
        """Bytes received from outside so far: with no cycle in a window, bytes that still
        arrive tell a wrong baud rate or protocol from a device that went quiet."""
        return 0

    def notice(self, detail: str, key: str = "") -> None:
        """Report something wrong in this thread's input that it coped with (a device sending
        copies, a receiver's clock jumping): a NOTICE event to the logs and ground stations.
        At most one per NOTICE_INTERVAL_S of flight time per thread and `key` (the detail when
        empty), so a device that misbehaves every frame cannot flood the radio nor hide a
        different problem; the ones held back are counted and named in the next."""
        self.notices += 1
        key = key or detail
        now_ns = self.ctx.clock.monotonic_ns()
        if now_ns < self._notice_next_ns.get(key, 0):
            self._notices_held[key] = self._notices_held.get(key, 0) + 1
            return
        if len(self._notice_next_ns) > 64:  # keys are a driver's few kinds; never grow
            self._notice_next_ns.clear()
        self._notice_next_ns[key] = now_ns + int(NOTICE_INTERVAL_S * 1e9)
        held = self._notices_held.pop(key, 0)
        sink = self._on_notice
        if sink is not None:
            sink(detail + (f" (+{held} held back)" if held else ""))

    def reset_statistics(self) -> None:
        self._step_total_ns = 0
        self._step_count = 0
        self._step_worst_ns = 0
        self._periods.clear()
        self._rates.clear()
        self.missed_deadlines = 0
        self.overruns = 0

    # ---------------------------------------------------------------- the supervisor's handle
    def attach(self, ctx: RuntimeContext, on_exit: Callable[[], None] | None = None,
               on_notice: Callable[[str], None] | None = None) -> None:
        """Join a runtime: its context, and whom to tell when a worker ends (the manager's
        wake-up, so an exit is handled at once rather than at the next watchdog tick)."""
        self.ctx = ctx
        self._on_notice = on_notice
        self._on_exit = on_exit

    def open_log(self) -> None:
        """Open this thread's log once per run; every (re)start then adds a Begin Data."""
        logs = self.ctx.logs
        has_formats = type(self).define_logs is not ManagedThread.define_logs
        if self.tlog is None and logs is not None and has_formats:
            text = "LOG_TEXT" in self.ctx.params and bool(self.ctx.params.get("LOG_TEXT"))
            self.tlog = logs.open(self.name, text=text)
            self.define_logs(self.tlog)

    def start_worker(self) -> None:
        """Start a new incarnation: a fresh stop event, so an abandoned worker stays stopped."""
        self._stop = threading.Event()
        self._params_dirty.clear()
        self._exit_kind = ""
        self._last_cycle_start_ns = 0
        stop = self._stop
        # through the clock: a lockstep flight runs the worker as a coroutine on its time
        self._worker = self.ctx.clock.start_thread(
            self._run, (stop,), f"managed-{self.name}", priority=self.thread_id or 100)

    def request_stop(self) -> None:
        """Ask the worker to leave its loop at its next check of the stop event."""
        self._stop.set()

    @property
    def has_worker(self) -> bool:
        return self._worker is not None

    @property
    def worker_alive(self) -> bool:
        worker = self._worker
        return worker is not None and worker.is_alive()

    @property
    def outcome(self) -> str:
        """How the last worker ended: "" (running or never ran), "normal", "crash",
        "interrupted"."""
        return self._exit_kind

    @property
    def native_id(self) -> int | None:
        """The OS thread id of the current worker (per-thread CPU figures)."""
        worker = self._worker
        return None if worker is None else worker.native_id

    def join_worker(self, host_timeout_s: float) -> bool:
        """Wait (host time; a lockstep flight's time there) for the worker to end; True when
        it has (or there is none)."""
        worker = self._worker
        if worker is None or worker is threading.current_thread():
            return True
        worker.join(host_timeout_s)
        return not worker.is_alive()

    def interrupt_worker(self) -> bool:
        """Raise ThreadInterrupted inside a pure-Python loop that ignores its stop event;
        False when there is no live worker to raise it in."""
        worker = self._worker
        if worker is None:
            return False
        return self.ctx.clock.interrupt_thread(worker, ThreadInterrupted)

    def release_worker(self) -> Worker | None:
        """Forget the current worker (stopped, or abandoned inside C) and return it."""
        worker, self._worker = self._worker, None
        self.running = False
        self.in_periodic = False
        return worker

    def notify_params_changed(self, name: str) -> None:
        """A parameter of this thread changed (any thread): re-read between two cycles."""
        self._params_dirty.set()

    # ---------------------------------------------------------------- worker side
    def _run(self, stop: threading.Event) -> None:
        clock = self.ctx.clock
        if not clock.lockstep:  # a lockstep worker shares the scheduler's OS thread
            set_native_name(self.name)
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
                    self._account_cycle(t0, t1 - work_t0, budget_ns, count,
                                        clock.monotonic_ns())
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
            on_exit = self._on_exit
            if on_exit is not None:
                on_exit()

    def _account_cycle(self, t0_ns: int, step_ns: int, budget_ns: int, count: int,
                       clock_ns: int) -> None:
        """`t0_ns` and `step_ns` in host time (what the step cost); `clock_ns` the runtime's
        time at the end of the cycle, from which the rate is measured (exact in lockstep)."""
        last = self._last_cycle_start_ns
        if last:
            self._periods.append(t0_ns - last)
        self._last_cycle_start_ns = t0_ns
        self._step_total_ns += step_ns
        self._step_count += 1
        if step_ns > self._step_worst_ns:
            self._step_worst_ns = step_ns
        if step_ns > budget_ns:
            self.overruns += 1
        cycles = self.cycles = self.cycles + count
        self._rates.append((clock_ns, cycles))
