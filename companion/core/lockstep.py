"""Lockstep time: the runtime's threads run as coroutines on simulated time.

A lockstep flight (`companion sim --lockstep`) runs the same drivers, estimator, control,
supervisor and logs as a real-time one, but nothing waits on the host's clock. Every worker that
`LockstepClock.start_thread` starts is a greenlet, not an OS thread, and every wait the runtime
makes goes through the clock (`Clock.sleep`, `wait_for`, `wait_event`, `wait_until_ns`, a
lockstep serial port's read), which here records what would wake the waiter (a condition, a
deadline, its stop event) and switches to the scheduler. The scheduler resumes the first task,
in (priority, start order), that can run; when none can, simulated time jumps to the earliest
deadline. Computation takes no simulated time.

Two properties follow. The flight is deterministic: one OS thread, a fixed order among tasks
due at the same instant, and time that depends only on the simulation, so the same seed and
configuration give byte-identical logs. And it runs at the speed of the arithmetic: a switch
costs about a microsecond and an idle period costs nothing.

What it cannot do: a task that never waits (a pure-Python loop ignoring its stop event, a call
blocked inside C) holds the only thread, so the whole flight stops with it; thread faults of
that kind are refused in lockstep. Work done by other OS threads (the disk policy) is not
scheduled and must not feed the flight.
"""

from __future__ import annotations

import bisect
import logging
import threading
from collections.abc import Callable
from time import perf_counter_ns
from typing import Any

from companion.core.clock import Clock, Worker

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_REALTIME0_NS", "LockstepClock", "LockstepDeadlock", "LockstepError"]

DEFAULT_REALTIME0_NS = 1_767_268_800_000_000_000
"""2026-01-01T12:00:00Z: the wall time a lockstep flight starts at, the same every run, so two
runs' logs are byte-identical (the timestamps are part of them)."""
DEFAULT_MONOTONIC0_NS = 1_000_000_000_000
"""Where the monotonic clock starts (1000 s): far from zero, which code takes for "never"."""
MAIN_PRIORITY = 1000


class LockstepError(RuntimeError):
    """A wait outside a lockstep task, or a task that failed the scheduler."""


class LockstepDeadlock(LockstepError):
    """Every task waits for a condition, none with a deadline: simulated time cannot move."""


class _Task:
    __slots__ = ("deadline_ns", "done", "glet", "key", "name", "pending", "ready", "spent_ns",
                 "started", "stop")

    def __init__(self, name: str, key: tuple[int, int]) -> None:
        self.name = name
        self.key = key
        self.glet: Any = None
        self.started = False
        self.done = False
        self.ready: Callable[[], bool] | None = None
        self.deadline_ns: int | None = None
        self.stop: threading.Event | None = None
        self.pending: BaseException | None = None
        self.spent_ns = 0  # host time spent running this task


class _GreenWorker:
    """The `Worker` face of a lockstep task, for the thread manager's handle."""

    def __init__(self, clock: LockstepClock, task: _Task) -> None:
        self._clock = clock
        self._task = task
        self.name = task.name

    def is_alive(self) -> bool:
        return not self._task.done

    def join(self, timeout: float | None = None) -> None:
        """Wait (simulated seconds) for the task to end; other tasks run meanwhile."""
        task = self._task
        if task.done or self._clock._current is task:
            return
        deadline = None if timeout is None else self._clock.now_ns + int(timeout * 1e9)
        self._clock._wait(lambda: task.done, deadline, None)

    @property
    def ident(self) -> int | None:
        return id(self._task)

    @property
    def native_id(self) -> int | None:
        return None  # every task runs on the one thread that runs the scheduler


class LockstepClock(Clock):
    """A `Clock` whose time is the simulation's, advanced by a scheduler of coroutines.

    `run(main)` runs `main` as the first task and returns its result once it returns; the
    tasks it starts (the runtime's workers, the simulated world) run as it waits.
    """

    lockstep = True

    def __init__(self, realtime0_ns: int = DEFAULT_REALTIME0_NS,
                 monotonic0_ns: int = DEFAULT_MONOTONIC0_NS) -> None:
        try:
            import greenlet
        except ImportError:
            raise LockstepError("a lockstep flight needs greenlet: pip install "
                                "'uav-companion[sim]'") from None
        self._greenlet = greenlet.greenlet
        self._greenlet_exit = greenlet.GreenletExit
        super().__init__(1.0, (monotonic0_ns, realtime0_ns))
        self.now_ns = monotonic0_ns
        self._tasks: list[_Task] = []  # alive tasks, ordered by key
        self._seq = 0
        self._hub: Any = None
        self._current: _Task | None = None
        self._hooks: list[list[Any]] = []  # [period_ns, next_ns, fn]
        self.switches = 0
        self.advances = 0
        #: host ns spent in each task (by name) and in the scheduler's hooks: where a lockstep
        #: flight's time goes, for the benchmark
        self.host_ns: dict[str, int] = {}

    # ------------------------------------------------------------------ time
    def monotonic_ns(self) -> int:
        return self.now_ns

    def realtime_ns(self) -> int:
        return self._real0 + (self.now_ns - self._mono0)

    def to_host_s(self, duration_s: float) -> float:
        return duration_s

    def every(self, period_s: float, fn: Callable[[], None]) -> None:
        """Call `fn` from the scheduler each time simulated time crosses a multiple of
        `period_s` (no task runs meanwhile): how the log service is drained."""
        period_ns = int(period_s * 1e9)
        self._hooks.append([period_ns, self.now_ns + period_ns, fn])

    # ------------------------------------------------------------------ waits
    def wait_until_ns(self, deadline_ns: int, stop: threading.Event) -> bool:
        if stop.is_set():
            return True
        if deadline_ns > self.now_ns:
            self._wait(None, deadline_ns, stop)
        return stop.is_set()

    def wait_event(self, event: threading.Event, timeout_s: float) -> bool:
        if not event.is_set():
            self._wait(event.is_set, self.now_ns + int(timeout_s * 1e9), None)
        return event.is_set()

    def wait_for(self, cond: threading.Condition, ready: Callable[[], bool],
                 timeout_s: float) -> bool:
        if ready():
            return True
        cond.release()  # no other task runs before this one switches away: no race
        try:
            self._wait(ready, self.now_ns + int(timeout_s * 1e9), None)
        finally:
            cond.acquire()
        return ready()

    def wait_until(self, ready: Callable[[], bool], timeout_s: float,
                   stop: threading.Event | None = None) -> bool:
        """Wait for a condition other tasks make true (a lockstep port's data), at most
        `timeout_s` of simulated time; returns `ready()`."""
        if ready() or (stop is not None and stop.is_set()):
            return ready()
        self._wait(ready, self.now_ns + int(timeout_s * 1e9), stop)
        return ready()

    def _wait(self, ready: Callable[[], bool] | None, deadline_ns: int | None,
              stop: threading.Event | None) -> None:
        task = self._current
        if task is None or self._greenlet.getcurrent() is not task.glet:
            raise LockstepError("a lockstep wait outside a lockstep task (another OS thread, "
                                "or the scheduler itself)")
        task.ready, task.deadline_ns, task.stop = ready, deadline_ns, stop
        self._hub.switch()
        task.ready, task.deadline_ns, task.stop = None, None, None
        pending, task.pending = task.pending, None
        if pending is not None:
            raise pending

    # ------------------------------------------------------------------ tasks
    def start_thread(self, target: Callable[..., None], args: tuple[Any, ...], name: str,
                     priority: int = 100) -> Worker:
        if self._hub is None:
            raise LockstepError("start_thread before LockstepClock.run")
        self._seq += 1
        task = _Task(name, (priority, self._seq))

        def body() -> None:
            try:
                target(*args)
            except self._greenlet_exit:
                pass  # ended by the scheduler at the end of the flight
            except BaseException:  # a task's failure must not unwind the scheduler
                log.exception("lockstep task %s ended with an exception", name)
            finally:
                task.done = True

        task.glet = self._greenlet(run=body, parent=self._hub)
        bisect.insort(self._tasks, task, key=lambda t: t.key)
        return _GreenWorker(self, task)

    def interrupt_thread(self, worker: Worker, exc_type: type[BaseException]) -> bool:
        task = getattr(worker, "_task", None)
        if not isinstance(task, _Task) or task.done or not task.started:
            return False
        task.pending = exc_type()  # raised where it waits, when it next runs (at once)
        return True

    def run(self, main: Callable[[], Any]) -> Any:
        """Run `main` as a task until it returns; the scheduler's loop runs in the caller."""
        if self._hub is not None:
            raise LockstepError("LockstepClock.run is not re-entrant")
        self._hub = self._greenlet.getcurrent()
        result: dict[str, Any] = {}

        def entry() -> None:
            try:
                result["value"] = main()
            except BaseException as exc:  # handed back to the caller of run()
                result["error"] = exc

        worker = self.start_thread(entry, (), "main", MAIN_PRIORITY)
        main_task: _Task = worker._task  # type: ignore[attr-defined]
        next_ready = self._next_ready
        switches = 0
        try:
            while not main_task.done:
                task = next_ready()
                if task is None:
                    self._advance()
                    continue
                task.started = True
                self._current = task
                switches += 1
                t0 = perf_counter_ns()
                task.glet.switch()
                task.spent_ns += perf_counter_ns() - t0
                self._current = None
                if task.done:
                    self._tasks.remove(task)
                    self._account(task)
        finally:
            self.switches += switches
            for task in list(self._tasks):  # tasks left waiting (abandoned): end them quietly
                if task.glet is not None and not task.done and task.started:
                    self._current = task
                    try:
                        task.glet.throw(self._greenlet_exit)
                    except LockstepError:
                        pass
                    self._current = None
                self._account(task)
            self._tasks.clear()
            self._hub = None
        if "error" in result:
            raise result["error"]
        return result.get("value")

    def _account(self, task: _Task) -> None:
        """Fold an ended (or abandoned) task's host time into `host_ns`, by name."""
        if task.spent_ns:
            self.host_ns[task.name] = self.host_ns.get(task.name, 0) + task.spent_ns
            task.spent_ns = 0

    def _next_ready(self) -> _Task | None:
        # the first task, in priority order, with any reason to run; the cheapest tests first
        now = self.now_ns
        for task in self._tasks:
            deadline = task.deadline_ns
            if deadline is not None and deadline <= now:
                return task
            if not task.started or task.pending is not None:
                return task
            stop = task.stop
            if stop is not None and stop.is_set():
                return task
            ready = task.ready
            if ready is not None and ready():
                return task
        return None

    def _advance(self) -> None:
        deadlines = [t.deadline_ns for t in self._tasks if t.deadline_ns is not None]
        if not deadlines:
            names = ", ".join(t.name for t in self._tasks)
            raise LockstepDeadlock(f"every task waits without a deadline ({names})")
        self.now_ns = max(self.now_ns, min(deadlines))
        self.advances += 1
        for hook in self._hooks:
            if self.now_ns >= hook[1]:
                hook[1] += hook[0] * ((self.now_ns - hook[1]) // hook[0] + 1)
                t0 = perf_counter_ns()
                hook[2]()
                self.host_ns["(hooks)"] = self.host_ns.get("(hooks)", 0) + perf_counter_ns() - t0
