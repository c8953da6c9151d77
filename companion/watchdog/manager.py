"""The thread manager: starts, supervises, restarts and stops the managed threads.

It runs in the main thread, as in the thesis. Every `MGR_WDG_GRAN_MS` it wakes, and for each
thread whose watchdog period has elapsed it compares the thread's cycle counter with the value
seen at the previous check (the alive flag, tested and reset):

- cycles advanced: alive;
- no cycle but the worker keeps returning from `step` without data: *silent* (a quiet device);
  reported, not restarted, because the driver reconnects by itself and a restart cannot make a
  device talk;
- not even that: *stalled*; the worker is stopped safely and restarted.

Restart policy uses Erlang/OTP's terms: restart type per thread, and an intensity (at most
`MGR_RST_INTENS` restarts within `MGR_RST_PER_S`) beyond which the thread is marked failed and
left down while the others keep running, or, for a thread whose row says `escalate`, the whole
runtime stops with EXIT_ESCALATED for its service manager to restart (MGR_ESCALATE).
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from companion.core.clock import Worker
from companion.core.params import ParamSpec, ParamValue, int_param
from companion.core.sync import MessageQueue
from companion.watchdog.events import EventKind, WatchdogEvent
from companion.watchdog.thread import (
    ManagedThread,
    RestartType,
    RuntimeContext,
    ThreadStatus,
)

log = logging.getLogger(__name__)

EXIT_ESCALATED = 70
"""Process exit status after an escalation (EX_SOFTWARE in sysexits.h): not 0, so that
systemd's Restart=on-failure restarts the process, and not 1 or 2, so that it is told apart
from a crash or a bad configuration."""

THREAD_ID_MAX = 255
"""Ids fit the legacy protocol's uint8 thread id field."""
FIRST_ASSIGNED_ID = 6
"""Ids below are fixed by the vehicle's data sources (IMU 1, GPS 2, servo 3, estimator 4,
control 5: the legacy protocol's contract); the manager hands out the rest."""

SUSPEND_GAP_S = 1.0
"""Host seconds between two manager wake-ups (due every granularity) beyond which the process
is taken to have been suspended rather than the threads to have stalled."""
SUSPEND_CPU_SHARE = 0.25
"""...provided the process used less than this share of one core over the gap."""
MIN_WINDOW_HOST_S = 0.1
"""The shortest watchdog window in host seconds. In flight (scale 1) every `*_WDG_MS` is longer;
in a simulation at `--speed 20` the IMU's 500 ms window would be 25 ms of host time, shorter than
the interpreter and the OS may keep a healthy thread from running on a busy machine, and the
thread would be restarted for the host's hiccup. So a window lasts at least this much host time;
a lockstep flight has no host time to hiccup."""
STALL_MIN_HOST_S = 2.0
"""With a clock faster than the host's (`--speed S` above 1), a thread is judged stalled only
after this much host time without a cycle or a heartbeat, however short its window: at 5x the
IMU's 500 ms window is 100 ms of host time, and beside a busy core and a second test worker
healthy threads went without running for 0.25 s, and once for 1.1 s (the IMU thread and the
simulator's process together), and were restarted (tests/test_sim_runtime.py). A real stall is
still caught, 2 s of host time later; silence is judged on the window; in flight (1x) the
thresholds are the parameters' own."""

MANAGER_PARAMS: list[ParamSpec] = [
    int_param("MGR_EXEC_TIME_S", 0, 0, 864_000, "s",
              "Programmed execution time: the runtime stops cleanly after it. 0 = unlimited."),
    int_param("MGR_STATUS_MS", 1000, 50, 600_000, "ms",
              "Period of thread status messages to the ground (one thread per period, in rotation)."),
    int_param("MGR_MSTAT_MS", 2000, 100, 600_000, "ms",
              "Period of the manager status message to the ground."),
    int_param("MGR_WDG_GRAN_MS", 20, 1, 10_000, "ms",
              "Watchdog granularity: how often the manager wakes to check the threads. Must not "
              "exceed the shortest thread watchdog period."),
    int_param("MGR_RST_INTENS", 5, 1, 100_000, "",
              "Restart intensity: more restarts than this within MGR_RST_PER_S marks a thread failed."),
    int_param("MGR_RST_PER_S", 30, 1, 86_400, "s",
              "Restart intensity period, in seconds."),
    int_param("MGR_ESCALATE", 1, 0, 2, "",
              "When a flight thread fails (restart intensity exceeded): 0 leaves it down and "
              "flies on; 1 stops the runtime with exit code 70 so that a service manager "
              "(systemd) restarts the process, when one supervises it, else as 0; 2 always "
              "stops with exit code 70. Threads fed by the network never escalate."),
    int_param("MGR_READY_S", 30, 1, 3600, "s",
              "Under a service manager: READY is sent once every thread has reached its "
              "periodic section, or after this many seconds (host time) with the threads still "
              "starting named in the status, so that a missing device is reported to the "
              "ground stations rather than the process being killed for a slow start."),
    int_param("MGR_SHUTDOWN_MS", 500, 10, 60_000, "ms",
              "How long a stopping thread may take before it is interrupted, then abandoned "
              "(host time: not scaled by the simulation's --speed)."),
]


@dataclass(frozen=True)
class ManagerCommand:
    """A request to the manager from a bridge or the console; `reply(ok, reason)` acknowledges."""

    kind: str  # "stop" | "reboot" | "restart_thread" | a thread's own (`ManagedThread.COMMANDS`)
    thread: str | int | None = None
    reason: int = 0
    reply: Callable[[bool, str], None] | None = None


def _no_reply(ok: bool, reason: str) -> None:
    """A command posted without a reply hook: its outcome only goes to the log."""
    if not ok:
        log.warning("command failed: %s", reason)


@dataclass(frozen=True)
class ManagerStatus:
    elapsed_ms: int
    exec_time_s: int
    status_ms: int
    manager_status_ms: int
    granularity_ms: int
    n_threads: int
    stopping: bool
    healthy: bool  # no thread stalled, silent or failed at the last check


class ThreadManager:
    """Owns the threads' lifecycle; all its methods except `post`, `wake`, `request_stop` and
    the status readers must be called from the main thread."""

    def __init__(self, ctx: RuntimeContext, threads: Sequence[ManagedThread]) -> None:
        self.ctx = ctx
        self.threads = list(threads)
        names = [t.name for t in self.threads]
        if len(set(names)) != len(names):
            raise ValueError(f"thread names must be unique: {names}")
        self.commands: MessageQueue[ManagerCommand] = MessageQueue(256)
        self._wake = threading.Event()
        self._stop_reason: str | None = None
        self._subscribers: list[MessageQueue[WatchdogEvent]] = []
        self._sub_lock = threading.Lock()
        self._start_mono_ns = 0
        self._next_check_ns: dict[str, int] = {}
        self._seen_cycles: dict[str, int] = {}
        self._seen_beats: dict[str, int] = {}
        self._seen_bytes: dict[str, int] = {}
        self._silent: dict[str, bool] = {}
        self._progress_host_ns: dict[str, int] = {}  # last check that saw a cycle or beat
        self._armed: dict[str, bool] = {}  # the periodic section's first window has begun
        self._restart_times: dict[str, deque[float]] = {}
        self._abandoned_workers: list[Worker] = []
        self._started = False
        #: Set by the runtime when a service manager will restart the process (MGR_ESCALATE 1).
        self.supervised = False
        #: The thread whose failure stopped the runtime, once it has escalated.
        self.escalated: str | None = None
        self.on_tick: list[Callable[[], None]] = []  # called every wake, in the main thread
        ctx.params.declare_all(MANAGER_PARAMS)
        for t in self.threads:
            self._adopt(t)
        self._param_unsub = ctx.params.subscribe(self._on_param_changed)
        self._rule_remove = ctx.params.add_rule(self._watchdog_rule)

    def _adopt(self, t: ManagedThread) -> None:
        self._assign_id(t)
        t.attach(self.ctx, on_exit=self.wake, on_notice=functools.partial(
            self._emit, EventKind.NOTICE, t.name))
        self.ctx.params.declare_all(t.param_specs())
        self._restart_times.setdefault(t.name, deque())

    def _assign_id(self, t: ManagedThread) -> None:
        """The manager owns thread ids: a thread built with id 0 gets the lowest free one from
        FIRST_ASSIGNED_ID; a fixed id (the vehicle's data sources, 1..5) must be unique. The
        ground protocols (MAVLink named values, the legacy THREAD_STATUS) use these ids as they
        are, so nothing downstream renumbers."""
        taken = {other.thread_id: other.name for other in self.threads if other is not t}
        if t.thread_id == 0:
            t.thread_id = next(i for i in range(FIRST_ASSIGNED_ID, THREAD_ID_MAX + 2)
                               if i not in taken)
        if not 1 <= t.thread_id <= THREAD_ID_MAX:
            raise ValueError(f"thread {t.name}: id {t.thread_id} outside 1..{THREAD_ID_MAX}")
        if t.thread_id in taken:
            raise ValueError(f"thread {t.name}: id {t.thread_id} is taken by {taken[t.thread_id]}")

    def add(self, t: ManagedThread) -> None:
        """Add a thread after construction (bridges that need the manager); before start()."""
        if self._started:
            raise RuntimeError("threads must be added before the manager starts")
        if self.find(t.name) is not None:
            raise ValueError(f"a thread named {t.name!r} exists already")
        self._adopt(t)  # assigns or checks its id first: a refused thread never joins the list
        self.threads.append(t)

    # ---------------------------------------------------------------- public, any thread
    def post(self, command: ManagerCommand) -> bool:
        ok = self.commands.put(command)
        self._wake.set()
        return ok

    def wake(self) -> None:
        self._wake.set()

    def request_stop(self, reason: str = "requested") -> None:
        """Ask the run loop to end (signal handlers, STOP commands). Safe from any thread."""
        if self._stop_reason is None:
            self._stop_reason = reason
        self._wake.set()

    def report(self, kind: EventKind, thread: str, detail: str = "") -> None:
        """Publish an event about a thread from outside the manager (the log writer's
        "logging off"): logged, and sent to every subscriber like the manager's own. Any thread."""
        self._emit(kind, thread, detail)

    def subscribe_events(self, capacity: int = 256) -> MessageQueue[WatchdogEvent]:
        q: MessageQueue[WatchdogEvent] = MessageQueue(capacity, drop_oldest=True)
        with self._sub_lock:
            self._subscribers.append(q)
        return q

    def find(self, key: str | int) -> ManagedThread | None:
        for t in self.threads:
            if t.name == key or t.thread_id == key:
                return t
        return None

    def thread_status(self) -> list[ThreadStatus]:
        return [t.status() for t in self.threads]

    def silent_threads(self) -> list[str]:
        """Threads whose device or input is quiet at the last check (reported `silent`, not
        yet `recovered`)."""
        return [t.name for t in self.threads if self._silent.get(t.name) and not t.failed]

    def status(self) -> ManagerStatus:
        p = self.ctx.params
        elapsed = (
            (self.ctx.clock.monotonic_ns() - self._start_mono_ns) // 1_000_000
            if self._start_mono_ns else 0
        )
        healthy = all(
            (t.failed is False) and (not t.enabled or not t.in_periodic or t.alive_at_last_check
                                     or self._seen_cycles.get(t.name) is None)
            for t in self.threads
        )
        return ManagerStatus(
            elapsed_ms=int(elapsed),
            exec_time_s=int(p.get("MGR_EXEC_TIME_S")),
            status_ms=int(p.get("MGR_STATUS_MS")),
            manager_status_ms=int(p.get("MGR_MSTAT_MS")),
            granularity_ms=int(p.get("MGR_WDG_GRAN_MS")),
            n_threads=len(self.threads),
            stopping=self._stop_reason is not None,
            healthy=healthy,
        )

    @property
    def stop_reason(self) -> str | None:
        return self._stop_reason

    # ---------------------------------------------------------------- lifecycle (main thread)
    def start(self) -> None:
        """Set up and start every enabled thread, in declaration order."""
        self._start_mono_ns = self.ctx.clock.monotonic_ns()
        self._started = True
        for t in self.threads:
            if t.enabled:
                self._start_thread(t, first=True)

    def run(self, duration_s: float | None = None) -> str:
        """Supervise until stopped; returns the stop reason ("duration", "signal", "stop", ...).

        `duration_s` overrides MGR_EXEC_TIME_S when given.
        """
        if not self._started:
            self.start()
        clock = self.ctx.clock
        # the suspension check reads the process's CPU time: a lockstep flight (whose time
        # stops with the process, nothing to rebase) skips it
        watch_suspend = not clock.lockstep
        last_host_s, last_cpu_s = time.monotonic(), time.process_time()
        while self._stop_reason is None:
            gran_ms = int(self.ctx.params.get("MGR_WDG_GRAN_MS"))
            wait_host_s = clock.to_host_s(gran_ms / 1000.0)
            clock.wait_event(self._wake, gran_ms / 1000.0)
            self._wake.clear()
            if watch_suspend:
                now_host_s, now_cpu_s = time.monotonic(), time.process_time()
                gap_s = now_host_s - last_host_s
                # Suspended, not starved by one of our own threads: the process used (almost)
                # no CPU over the gap. A thread holding the interpreter lock inside C for as
                # long burns CPU the whole time, and is judged as usual.
                if (gap_s > max(SUSPEND_GAP_S, 10 * wait_host_s)
                        and now_cpu_s - last_cpu_s < SUSPEND_CPU_SHARE * gap_s):
                    self._rebase(gap_s)
            self._process_commands()
            if self._stop_reason is not None:
                break
            self._check_threads()
            for hook in list(self.on_tick):
                try:
                    hook()
                except Exception:
                    log.exception("manager tick hook failed")
            # the gap is measured over the wait only: the manager's own work (joining a thread
            # that will not stop takes up to twice MGR_SHUTDOWN_MS) is not a suspension
            if watch_suspend:
                last_host_s, last_cpu_s = time.monotonic(), time.process_time()
            limit_s = duration_s if duration_s is not None else int(
                self.ctx.params.get("MGR_EXEC_TIME_S"))
            if limit_s and clock.monotonic_ns() - self._start_mono_ns >= limit_s * 1e9:
                self.request_stop("duration")
        return self._stop_reason or "stop"

    def shutdown(self) -> None:
        """Stop every thread in reverse order and release its resources."""
        for t in reversed(self.threads):
            if t.has_worker or t.initialised:
                self._stop_thread(t, why="shutdown")
                self._emit(EventKind.STOPPED, t.name, "shutdown")
        self._param_unsub()
        self._rule_remove()
        try:
            self.ctx.params.flush()
        except OSError as exc:
            log.error("could not save parameters: %s", exc)

    # ---------------------------------------------------------------- internals
    def _emit(self, kind: EventKind, thread: str, detail: str = "") -> None:
        event = WatchdogEvent(kind, thread, detail, self.ctx.clock.realtime_ns())
        level = logging.WARNING if event.severity <= 4 else logging.INFO
        log.log(level, "watchdog: %s", event.text())
        with self._sub_lock:
            subscribers = list(self._subscribers)
        for q in subscribers:
            q.put(event)

    def _on_param_changed(self, name: str, value: object) -> None:
        # Runs in the setter's thread: only flag things; the work happens in the main loop.
        # Only the owner (the thread whose prefix the name carries) re-reads its parameters.
        for t in self.threads:
            if name.startswith(t.param_prefix + "_"):
                t.notify_params_changed(name)
        self._wake.set()

    def _start_thread(self, t: ManagedThread, *, first: bool = False) -> bool:
        try:
            t.open_log()
            t.setup()
            t.initialised = True
        except Exception as exc:
            t.last_error = f"setup: {type(exc).__name__}: {exc}"
            log.error("thread %s: setup failed: %s", t.name, exc)
            try:
                t.cleanup()
            except Exception:
                log.exception("thread %s: cleanup after failed setup", t.name)
            t.initialised = False
            self._emit(EventKind.CRASH, t.name, t.last_error)
            self._schedule_check(t, self.ctx.clock.monotonic_ns())
            return False
        self._seen_cycles[t.name] = t.cycles
        self._seen_beats[t.name] = t.heartbeats
        self._seen_bytes[t.name] = t.io_bytes()
        self._silent[t.name] = False
        self._armed[t.name] = False
        t.start_worker()
        self._schedule_check(t, self.ctx.clock.monotonic_ns())
        if first:
            self._emit(EventKind.STARTED, t.name)
        return True

    def _host_hiccup(self, t: ManagedThread) -> bool:
        """A window with no cycle and no heartbeat that is still too short, in host time, to
        be a stall (`STALL_MIN_HOST_S`, only with a clock faster than the host's)."""
        clock = self.ctx.clock
        if clock.lockstep or clock.scale <= 1.0:
            return False
        since = self._progress_host_ns.get(t.name)
        return since is not None and time.monotonic_ns() - since < STALL_MIN_HOST_S * 1e9

    def _schedule_check(self, t: ManagedThread, now_ns: int) -> None:
        window_ns = int(t.watchdog_ms * 1e6)
        clock = self.ctx.clock
        if not clock.lockstep:
            window_ns = max(window_ns, int(MIN_WINDOW_HOST_S * clock.scale * 1e9))
        self._next_check_ns[t.name] = now_ns + window_ns

    def _stop_thread(self, t: ManagedThread, *, why: str) -> str:
        """Stop the worker safely and release its resources; returns how it ended:
        "stopped", "interrupted" or "abandoned"."""
        # Host time, not the flight's clock: how long the OS takes to let a thread leave a blocking
        # call does not shrink when the simulation runs faster (at --speed 5, a scaled 500 ms left
        # 100 ms, and a loaded machine abandoned healthy threads that still held their ports).
        timeout_ms = (t.shutdown_timeout_ms if t.shutdown_timeout_ms is not None
                      else int(self.ctx.params.get("MGR_SHUTDOWN_MS")))
        host_timeout_s = timeout_ms / 1000
        outcome = "stopped"
        t.request_stop()
        try:
            t.interrupt_io()
        except Exception:
            log.exception("thread %s: interrupt_io failed", t.name)
        if not t.join_worker(host_timeout_s):
            # A pure-Python loop that ignores its stop event: interrupt it.
            t.interrupt_worker()
            outcome = "interrupted"
            if not t.join_worker(host_timeout_s):
                # Stuck inside C: nothing can stop it. Leave it behind (daemon) and replace.
                outcome = "abandoned"
                t.abandoned += 1
                self._emit(EventKind.ABANDONED, t.name, why)
            else:
                t.interrupted += 1
                self._emit(EventKind.INTERRUPTED, t.name, why)
        worker = t.release_worker()
        if outcome == "abandoned" and worker is not None:
            self._abandoned_workers.append(worker)
        try:
            t.cleanup()
        except Exception:
            log.exception("thread %s: cleanup failed", t.name)
        t.initialised = False
        return outcome

    def _restart(self, t: ManagedThread, why: str) -> None:
        """Stop, recover and start again, unless the restart type or intensity says no."""
        if t.restart is RestartType.TEMPORARY and why != "command":
            self._stop_thread(t, why=why)
            return
        now = self.ctx.clock.monotonic()  # flight time, as the period is
        times = self._restart_times[t.name]
        period_s = int(self.ctx.params.get("MGR_RST_PER_S"))
        intensity = int(self.ctx.params.get("MGR_RST_INTENS"))
        while times and now - times[0] > period_s:
            times.popleft()
        if len(times) >= intensity and why != "command":
            self._stop_thread(t, why=why)
            t.failed = True
            self._emit(EventKind.FAILED, t.name,
                       f"{len(times) + 1} restarts within {period_s} s; left down")
            self._maybe_escalate(t)
            return
        times.append(now)
        self._stop_thread(t, why=why)
        try:
            t.recover()
        except Exception:
            log.exception("thread %s: recover failed", t.name)
        t.restarts += 1
        if self._start_thread(t):
            self._emit(EventKind.RESTARTED, t.name, why)

    def _maybe_escalate(self, t: ManagedThread) -> None:
        mode = int(self.ctx.params.get("MGR_ESCALATE"))
        if not t.escalate or mode == 0 or (mode == 1 and not self.supervised):
            return
        if self.escalated is None:
            self.escalated = t.name
            self._emit(EventKind.ESCALATED, t.name,
                       f"runtime stops (exit {EXIT_ESCALATED}) for a restart of the process")
            self.request_stop(f"escalated: {t.name} failed")

    def _rebase(self, gap_s: float) -> None:
        """The manager itself did not run for `gap_s` (the process was stopped, the machine
        suspended): no thread could cycle either, so judging them on that window would restart
        every one of them at once. Every thread's window starts again from now."""
        now = self.ctx.clock.monotonic_ns()
        for t in self.threads:
            self._armed[t.name] = False
            self._schedule_check(t, now)
        self._emit(EventKind.RESUMED, "manager", f"not run for {gap_s:.1f} s; windows restarted")

    def _check_threads(self) -> None:
        for t in self.threads:
            # Read the clock per thread: restarting one thread may take the manager up to twice
            # MGR_SHUTDOWN_MS (a worker that will not stop), and a window scheduled from a time
            # read before that would end almost at once and find a healthy thread "stalled".
            now = self.ctx.clock.monotonic_ns()
            if t.failed:
                continue
            enabled = t.enabled
            if not enabled:
                if t.has_worker or t.initialised:
                    self._stop_thread(t, why="disabled")
                    self._emit(EventKind.DISABLED, t.name)
                continue
            if not t.has_worker:
                if t.initialised is False and self._next_check_ns.get(t.name, 0) <= now:
                    # never started, re-enabled, or a setup that failed: (re)try
                    was_enabled_event = t.restarts == 0 and t.cycles == 0
                    if self._start_thread(t) and not was_enabled_event:
                        self._emit(EventKind.ENABLED, t.name)
                continue
            if not t.worker_alive:
                kind = t.outcome
                if kind == "crash":
                    t.crashes += 1
                    self._emit(EventKind.CRASH, t.name, t.last_error[:80])
                    self._restart(t, "crash")
                else:
                    self._emit(EventKind.EXITED, t.name)
                    if t.restart is RestartType.PERMANENT:
                        self._restart(t, "exited")
                    else:
                        self._stop_thread(t, why="exited")
                        t.initialised = True  # keep it from being restarted as "never started"
                continue
            if now < self._next_check_ns.get(t.name, 0):
                continue
            self._schedule_check(t, now)
            if not t.in_periodic:
                continue  # the aperiodic prologue is not under the watchdog
            cycles, beats = t.cycles, t.heartbeats
            if not self._armed.get(t.name):
                # The first window starts at the first check that finds the thread periodic,
                # not at its start: a prologue that ends just before a check (the estimator's
                # 1 s of IMU averaging against its 1000 ms watchdog) would otherwise be judged
                # on a window in which its first step had no time to finish.
                self._armed[t.name] = True
                self._progress_host_ns[t.name] = time.monotonic_ns()
                self._seen_cycles[t.name] = cycles
                self._seen_beats[t.name] = beats
                self._seen_bytes[t.name] = t.io_bytes()
                continue
            if cycles != self._seen_cycles.get(t.name):
                t.alive_at_last_check = True
                if self._silent.get(t.name):
                    self._silent[t.name] = False
                    self._emit(EventKind.RECOVERED, t.name, "data again")
            elif beats != self._seen_beats.get(t.name):
                t.alive_at_last_check = False
                if not self._silent.get(t.name):
                    self._silent[t.name] = True
                    if t.io_bytes() > self._seen_bytes.get(t.name, 0):
                        # bytes come in but nothing decodes: a wrong baud rate or protocol,
                        # not a device that went quiet (short enough for one STATUSTEXT)
                        self._emit(EventKind.SILENT, t.name, "bytes arrive, none decode")
                    else:
                        self._emit(EventKind.SILENT, t.name, f"no data for {t.watchdog_ms} ms")
            else:
                if self._host_hiccup(t):
                    continue  # too little host time yet to call it a stall: the next window
                t.alive_at_last_check = False
                t.stalls += 1
                self._emit(EventKind.STALL, t.name, f"no cycle in {t.watchdog_ms} ms")
                self._restart(t, "stall")
                continue
            self._seen_cycles[t.name] = cycles
            self._seen_beats[t.name] = beats
            self._seen_bytes[t.name] = t.io_bytes()
            self._progress_host_ns[t.name] = time.monotonic_ns()

    def _process_commands(self) -> None:
        while (cmd := self.commands.get_nowait()) is not None:
            ok, reason = True, ""
            if cmd.kind in ("stop", "reboot"):
                self.request_stop(cmd.kind)
            elif cmd.kind == "restart_thread":
                t = self.find(cmd.thread) if cmd.thread is not None else None
                if t is None:
                    ok, reason = False, f"unknown thread {cmd.thread!r}"
                else:
                    t.failed = False
                    self._restart(t, "command")
            else:
                takers = [t for t in self.threads if cmd.kind in t.COMMANDS]
                if not takers:
                    ok, reason = False, f"unknown command {cmd.kind!r}"
                else:
                    # the thread replies itself once the command is done
                    error = takers[0].post_command(cmd.kind, cmd.reply or _no_reply)
                    if error is None:
                        continue
                    ok, reason = False, error
            if cmd.reply is not None:
                try:
                    cmd.reply(ok, reason)
                except Exception:
                    log.exception("command reply failed")

    def _watchdog_rule(self, name: str, value: ParamValue,
                       value_of: Callable[[str], ParamValue]) -> str | None:
        """The watchdog checks a thread once per granularity, so a watchdog period shorter than
        the granularity cannot be honoured: refuse either side of that (the legacy contract's
        rule, applied to every source of a change)."""
        wdg_names = {f"{t.param_prefix}_WDG_MS" for t in self.threads}
        if name == "MGR_WDG_GRAN_MS":
            periods = [int(value_of(n)) for n in sorted(wdg_names) if n in self.ctx.params]
            shortest = min(periods, default=int(value))
            if int(value) > shortest:
                return f"{int(value)} ms exceeds the shortest watchdog period {shortest} ms"
        elif name in wdg_names:
            granularity = int(value_of("MGR_WDG_GRAN_MS"))
            if int(value) < granularity:
                return f"{int(value)} ms below MGR_WDG_GRAN_MS {granularity} ms"
        return None
