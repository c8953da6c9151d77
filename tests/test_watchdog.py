"""The thread manager against real threads and real pseudo-terminals."""

from __future__ import annotations

import gc
import json
import os
import signal
import threading
import time
import tracemalloc
from pathlib import Path

import pytest
import serial
from conftest import wait_for

from companion.core.clock import Clock
from companion.core.params import ParamError, ParamErrorKind, ParamRegistry
from companion.watchdog import (
    EventKind,
    ManagedThread,
    ManagerCommand,
    RestartType,
    RuntimeContext,
    ThreadManager,
)


class Ticker(ManagedThread):
    """A timer-driven thread that can be told to misbehave in each of the three stall kinds."""

    def __init__(self, name: str = "tick", thread_id: int = 1, period_ms: float = 5.0,
                 watchdog_ms: int = 50) -> None:
        super().__init__(name, thread_id=thread_id, period_ms=period_ms, watchdog_ms=watchdog_ms)
        self.mode = "ok"  # ok | raise | pyloop | cblock | ptyblock
        self.recovered = 0
        self.setups = 0
        self.cleanups = 0
        self.port: serial.Serial | None = None
        self.master_fd: int | None = None

    def setup(self) -> None:
        self.setups += 1
        if self.mode == "ptyblock":
            master, slave = os.openpty()
            name = os.ttyname(slave)
            os.close(slave)
            self.master_fd = master
            self.port = serial.serial_for_url(name, baudrate=115200, timeout=None)

    def interrupt_io(self) -> None:
        if self.port is not None:
            self.port.cancel_read()

    def cleanup(self) -> None:
        self.cleanups += 1
        if self.port is not None:
            self.port.close()
            self.port = None
        if self.master_fd is not None:
            os.close(self.master_fd)
            self.master_fd = None

    def recover(self) -> None:
        self.recovered += 1

    def step(self) -> bool | None:
        if self.cycles < 3:
            return True
        if self.mode == "raise":
            raise RuntimeError("sensor exploded")
        if self.mode == "pyloop":
            x = 0
            while True:  # ignores the stop event on purpose
                x += 1
        if self.mode == "cblock":
            time.sleep(1.0)  # inside C: an asynchronous exception cannot land here
        if self.mode == "ptyblock" and self.port is not None:
            self.port.read(1)  # nobody writes: blocks until the port is cancelled
        return True


def make_manager(*threads: ManagedThread, **params: int) -> ThreadManager:
    ctx = RuntimeContext(clock=Clock(), params=ParamRegistry())
    mgr = ThreadManager(ctx, threads)
    ctx.params.set("MGR_WDG_GRAN_MS", 5)
    ctx.params.set("MGR_SHUTDOWN_MS", 100)
    for name, value in params.items():
        ctx.params.set(name, value)
    return mgr


class RunInBackground:
    """Runs manager.run() in a helper thread so the test can observe; stops it on exit."""

    def __init__(self, mgr: ThreadManager) -> None:
        self.mgr = mgr
        self.thread = threading.Thread(target=self._run, name="test-manager")
        self.reason: str | None = None

    def _run(self) -> None:
        self.reason = self.mgr.run()

    def __enter__(self) -> RunInBackground:
        self.mgr.start()
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.mgr.request_stop("test over")
        self.thread.join(5)
        self.mgr.shutdown()


def events_of(q, kind: EventKind) -> list:  # type: ignore[no-untyped-def]
    return [e for e in q.drain() if e.kind is kind]


@pytest.mark.parametrize("mode,expect", [
    ("ptyblock", EventKind.RESTARTED),
    ("pyloop", EventKind.INTERRUPTED),
    ("raise", EventKind.CRASH),
])
def test_stall_kinds_are_detected_and_restarted(mode: str, expect: EventKind) -> None:
    t = Ticker(watchdog_ms=50)
    t.mode = mode
    mgr = make_manager(t)
    events = mgr.subscribe_events(1024)
    seen: list = []
    with RunInBackground(mgr):
        assert wait_for(lambda: t.restarts >= 2, 5.0), f"{mode}: restarts={t.restarts}"
        seen = events.drain()
    kinds = [e.kind for e in seen]
    assert expect in kinds
    assert EventKind.RESTARTED in kinds
    assert t.recovered >= 2
    # resources acquired and released in the main thread, as many times as set up
    assert t.cleanups == t.setups
    assert t.port is None and t.master_fd is None


def test_stall_detected_within_two_watchdog_periods() -> None:
    t = Ticker(watchdog_ms=100)
    t.mode = "ptyblock"
    mgr = make_manager(t)
    events = mgr.subscribe_events(1024)
    with RunInBackground(mgr):
        assert wait_for(lambda: t.cycles >= 3, 2.0)
        stalled_at = time.monotonic()
        assert wait_for(lambda: t.stalls >= 1, 2.0)
        latency = time.monotonic() - stalled_at
    assert latency <= 0.2 + 0.05, f"stall seen after {latency * 1000:.0f} ms"
    assert any(e.kind is EventKind.STALL for e in events.drain())


@pytest.mark.allow_leaks
def test_thread_stuck_in_c_is_abandoned_and_replaced() -> None:
    t = Ticker(watchdog_ms=50)
    t.mode = "cblock"
    mgr = make_manager(t)
    with RunInBackground(mgr):
        assert wait_for(lambda: t.abandoned >= 1, 5.0)
        t.mode = "ok"
        before = t.cycles
        assert wait_for(lambda: t.cycles > before + 5, 3.0), "replacement worker did not run"
    assert t.restarts >= 1


def test_intensity_exceeded_marks_failed_and_others_keep_running() -> None:
    bad = Ticker("bad", 1, watchdog_ms=50)
    bad.mode = "raise"
    good = Ticker("good", 2, watchdog_ms=50)
    mgr = make_manager(bad, good, MGR_RST_INTENS=3, MGR_RST_PER_S=30)
    events = mgr.subscribe_events(1024)
    with RunInBackground(mgr):
        assert wait_for(lambda: bad.failed, 5.0)
        cycles = good.cycles
        assert wait_for(lambda: good.cycles > cycles + 10, 2.0)
        assert bad.restarts == 3
        assert not good.failed and good.restarts == 0
    failed = [e for e in events.drain() if e.kind is EventKind.FAILED]
    assert len(failed) == 1 and failed[0].thread == "bad"


def test_transient_exit_is_not_restarted_but_permanent_is() -> None:
    class Once(ManagedThread):
        def prologue(self) -> bool:
            return False

    transient = Once("once", thread_id=1, watchdog_ms=50)

    permanent = Once("forever", thread_id=2, watchdog_ms=50, restart=RestartType.PERMANENT)
    mgr = make_manager(transient, permanent, MGR_RST_INTENS=3)
    with RunInBackground(mgr):
        assert wait_for(lambda: permanent.failed, 5.0)
    assert transient.restarts == 0
    assert permanent.restarts == 3


def test_restart_command_and_enable_parameter() -> None:
    t = Ticker(watchdog_ms=50)
    mgr = make_manager(t)
    replies: list[tuple[bool, str]] = []
    with RunInBackground(mgr):
        assert wait_for(lambda: t.cycles > 3, 2.0)
        mgr.post(ManagerCommand("restart_thread", "tick", reply=lambda ok, r: replies.append((ok, r))))
        mgr.post(ManagerCommand("restart_thread", "nope", reply=lambda ok, r: replies.append((ok, r))))
        assert wait_for(lambda: len(replies) == 2, 2.0)
        assert replies[0] == (True, "") and replies[1][0] is False and "nope" in replies[1][1]
        assert t.restarts == 1
        mgr.ctx.params.set("TICK_ENABLE", 0)
        assert wait_for(lambda: not t.has_worker and not t.running, 2.0)
        cycles = t.cycles
        time.sleep(0.1)  # nothing to wait for: checking that nothing happens
        assert t.cycles == cycles
        mgr.ctx.params.set("TICK_ENABLE", 1)
        assert wait_for(lambda: t.cycles > cycles + 3, 2.0)


def test_programmed_execution_time_ends_the_run() -> None:
    t = Ticker(watchdog_ms=50)
    mgr = make_manager(t, MGR_EXEC_TIME_S=1)
    started = time.monotonic()
    mgr.start()
    reason = mgr.run()
    mgr.shutdown()
    elapsed = time.monotonic() - started
    assert reason == "duration"
    assert 0.95 <= elapsed < 1.5
    assert not t.running and t.cleanups == t.setups


def test_timer_thread_keeps_absolute_deadlines() -> None:
    t = Ticker(period_ms=10.0, watchdog_ms=200)
    mgr = make_manager(t)
    with RunInBackground(mgr):
        assert wait_for(lambda: t.cycles >= 60, 3.0)
        start_cycles, start = t.cycles, time.monotonic()
        assert wait_for(lambda: t.cycles >= start_cycles + 50, 3.0)
        elapsed = time.monotonic() - start
    # 50 cycles of 10 ms: drift-free scheduling keeps the mean period at 10 ms
    assert 0.45 < elapsed < 0.56
    st = t.status()
    assert abs(st.measured_rate_hz - 100.0) < 5.0


def test_hundred_forced_restarts_leak_nothing() -> None:
    t = Ticker(watchdog_ms=20)
    t.mode = "ptyblock"
    mgr = make_manager(t, MGR_RST_INTENS=100_000, MGR_WDG_GRAN_MS=2)
    gc.collect()
    fds_before = len(os.listdir("/proc/self/fd"))
    tracemalloc.start()
    with RunInBackground(mgr):
        assert wait_for(lambda: t.restarts >= 10, 10.0)
        gc.collect()
        snap_10 = tracemalloc.take_snapshot()
        assert wait_for(lambda: t.restarts >= 100, 30.0)
        gc.collect()
        snap_100 = tracemalloc.take_snapshot()
        threads_running = [th for th in threading.enumerate() if th.name.startswith("managed-")]
        assert len(threads_running) <= 1
    tracemalloc.stop()
    assert t.abandoned == 0
    assert len(os.listdir("/proc/self/fd")) == fds_before
    # Memory allocated by the runtime's own code (pytest keeps every log record it captures,
    # so the process total is not the runtime's): 90 restarts, well under 200 B per restart.
    only_runtime = [tracemalloc.Filter(True, "*/companion/*")]
    growth = sum(
        d.size_diff
        for d in snap_100.filter_traces(only_runtime).compare_to(
            snap_10.filter_traces(only_runtime), "filename")
    )
    assert growth < 18_000, f"runtime memory grew {growth} bytes over 90 restarts"


class _SlowToStop(ManagedThread):
    """Its step takes 600 ms of C-level sleep; it honours the stop event only between steps."""

    def step(self) -> bool:
        time.sleep(0.6)
        return True


@pytest.mark.parametrize("own_timeout_ms,expect", [(None, "abandoned"), (2000, "stopped")])
def test_a_threads_own_shutdown_timeout_overrides_the_managers(
    own_timeout_ms: int | None, expect: str
) -> None:
    """MGR_SHUTDOWN_MS is 100 ms here: a thread that needs longer to stop says so, and gets it."""
    t = _SlowToStop("slow", thread_id=1, period_ms=10.0, watchdog_ms=5000,
                    shutdown_timeout_ms=own_timeout_ms)
    mgr = make_manager(t)
    mgr.start()
    try:
        assert wait_for(lambda: t.cycles >= 1, 5.0)
        time.sleep(0.05)  # inside the next step's sleep, where neither stop nor interrupt lands
        assert mgr._stop_thread(t, why="test") == expect
    finally:
        mgr.request_stop()
        mgr.shutdown()
    if expect == "abandoned":
        assert wait_for(lambda: not any(th.name == "managed-slow" and th.is_alive()
                                        for th in threading.enumerate()), 3.0)


def test_watchdog_periods_and_granularity_are_one_rule_for_every_source() -> None:
    """The registry refuses both sides of the granularity rule, whoever sets the value."""
    t = _SlowToStop("imu", thread_id=1, period_ms=10.0, watchdog_ms=500)
    mgr = make_manager(t, MGR_WDG_GRAN_MS=50)
    params = mgr.ctx.params
    with pytest.raises(ParamError) as exc:
        params.set("IMU_WDG_MS", 20)
    assert exc.value.kind is ParamErrorKind.CONFLICT and "MGR_WDG_GRAN_MS" in exc.value.reason
    with pytest.raises(ParamError) as exc:
        params.set("MGR_WDG_GRAN_MS", 600)
    assert exc.value.kind is ParamErrorKind.CONFLICT and "500 ms" in exc.value.reason
    # one request sees its own values: both change together, or neither does
    params.set_many({"IMU_WDG_MS": 1000, "MGR_WDG_GRAN_MS": 600})
    assert (params.get("IMU_WDG_MS"), params.get("MGR_WDG_GRAN_MS")) == (1000, 600)
    with pytest.raises(ParamError):
        params.set_many({"IMU_WDG_MS": 300, "MGR_STATUS_MS": 2000})
    assert (params.get("IMU_WDG_MS"), params.get("MGR_STATUS_MS")) == (1000, 1000)
    mgr.shutdown()


def test_the_manager_owns_thread_ids() -> None:
    """Fixed ids (the vehicle's data sources) stay; id 0 gets the lowest free id from 6; a taken
    or out-of-range id is refused at once, naming both threads."""
    fixed = _SlowToStop("imu", thread_id=1, period_ms=10.0)
    first, second = (_SlowToStop(n, thread_id=0, period_ms=10.0) for n in ("mav0rx", "mav0tx"))
    mgr = make_manager(fixed, first)
    mgr.add(second)
    assert [t.thread_id for t in mgr.threads] == [1, 6, 7]
    with pytest.raises(ValueError, match="id 1 is taken by imu"):
        mgr.add(_SlowToStop("gps", thread_id=1, period_ms=10.0))
    with pytest.raises(ValueError, match="outside 1..255"):
        mgr.add(_SlowToStop("big", thread_id=300, period_ms=10.0))
    assert [t.name for t in mgr.threads] == ["imu", "mav0rx", "mav0tx"]  # refused, not added
    mgr.shutdown()


class _Counting(ManagedThread):
    def __init__(self, name: str, thread_id: int) -> None:
        super().__init__(name, thread_id=thread_id, period_ms=5.0, watchdog_ms=1000)
        self.notified = 0

    def on_params_changed(self) -> None:
        self.notified += 1

    def step(self) -> bool:
        return True


def test_a_parameter_change_notifies_only_its_owner() -> None:
    a, b = _Counting("alpha", 1), _Counting("beta", 2)
    mgr = make_manager(a, b)
    with RunInBackground(mgr):
        assert wait_for(lambda: a.cycles > 2 and b.cycles > 2, 5.0)
        mgr.ctx.params.set("ALPHA_MSG_MS", 250)
        assert wait_for(lambda: a.notified == 1, 5.0)
        cycles = b.cycles
        assert wait_for(lambda: b.cycles > cycles + 5, 5.0)  # beta ran on, and was not told
        assert b.notified == 0


class _SlowStart(ManagedThread):
    """Its prologue ends just before the first watchdog check, and its first step is slow:
    the estimator's start (1 s of IMU averaging against a 1000 ms watchdog) in miniature."""

    def __init__(self, name: str, thread_id: int, started: float) -> None:
        super().__init__(name, thread_id=thread_id, watchdog_ms=100)
        self.started = started
        self.first = True

    def prologue(self) -> bool:
        # end ~5 ms before the manager's first check (100 ms after its start)
        delay = self.started + 0.095 - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        return True

    def step(self) -> bool:
        if self.first:
            self.first = False
            self.stop_event.wait(0.06)  # the first step: longer than the 5 ms left of the window
        else:
            self.stop_event.wait(0.005)
        return True


def test_the_first_window_starts_with_the_periodic_section_not_the_thread() -> None:
    started = time.monotonic()
    threads = [_SlowStart(f"slow{k}", k + 1, started) for k in range(6)]
    mgr = make_manager(*threads)
    with RunInBackground(mgr):
        assert wait_for(lambda: all(t.cycles > 40 for t in threads), 5.0)
    assert [t.stalls for t in threads] == [0] * 6
    assert [t.restarts for t in threads] == [0] * 6


def test_a_suspended_process_restarts_nothing_on_resume() -> None:
    """SIGSTOP for 1.5 s (ten watchdog periods): every window is missed, by every thread and
    the manager alike; on SIGCONT the manager sees it was not run, says so and restarts no one."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        import json, os, signal, sys, threading, time
        sys.path.insert(0, "tests")
        from test_watchdog import Ticker, make_manager
        from companion.watchdog import EventKind
        threads = [Ticker(f"t{k}", thread_id=k + 1, period_ms=5.0, watchdog_ms=150)
                   for k in range(4)]
        mgr = make_manager(*threads)
        events = mgr.subscribe_events(1000)
        runner = threading.Thread(target=mgr.run, daemon=True)
        runner.start()
        t0 = time.monotonic()
        while min(t.cycles for t in threads) < 50 and time.monotonic() - t0 < 5:
            time.sleep(0.01)
        print("READY", flush=True)
        sys.stdin.readline()  # the test stops and continues us meanwhile
        c0 = [t.cycles for t in threads]
        t0 = time.monotonic()
        while min(t.cycles - c for t, c in zip(threads, c0)) < 100 and time.monotonic() - t0 < 5:
            time.sleep(0.01)
        mgr.request_stop()
        runner.join(5)
        mgr.shutdown()
        kinds = [e.kind.value for e in events.drain()]
        print(json.dumps({"restarts": [t.restarts for t in threads], "kinds": kinds}), flush=True)
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, cwd=str(Path(__file__).parents[1]))
    try:
        assert proc.stdout is not None and proc.stdin is not None
        assert proc.stdout.readline().strip() == "READY"
        os.kill(proc.pid, signal.SIGSTOP)
        time.sleep(1.5)  # the fault itself: the process stays stopped this long
        os.kill(proc.pid, signal.SIGCONT)
        proc.stdin.write("\n")
        proc.stdin.flush()
        out, _ = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    result = json.loads(out.strip().splitlines()[-1])
    assert result["restarts"] == [0, 0, 0, 0]
    assert "resumed" in result["kinds"] and "stall" not in result["kinds"]


def test_a_slow_restart_does_not_shorten_the_other_threads_windows() -> None:
    """Stopping a thread that ignores its stop event takes the manager twice MGR_SHUTDOWN_MS.
    The threads checked after it in the same pass used to get a window scheduled from before
    that wait, which ended at the next tick: a healthy thread whose cycle is longer than a tick
    was declared stalled and restarted (in SITL: the estimator when the GPS thread hung)."""
    # same watchdog period, started together: their checks fall due in the same pass, as the
    # runtime's threads with 1000 ms watchdogs do
    bad = Ticker("bad", thread_id=1, period_ms=5.0, watchdog_ms=200)
    good = [Ticker(f"good{k}", thread_id=k + 2, period_ms=40.0, watchdog_ms=200)
            for k in range(4)]
    bad.mode = "pyloop"  # from its fourth cycle on
    mgr = make_manager(bad, *good, MGR_RST_INTENS=1, MGR_SHUTDOWN_MS=300)  # stop > a window
    with RunInBackground(mgr):
        assert wait_for(lambda: bad.failed, 10.0)
        cycles = [g.cycles for g in good]
        assert wait_for(lambda: all(g.cycles > c + 10 for g, c in zip(good, cycles, strict=True)), 5.0)
    assert bad.interrupted >= 1
    assert [g.stalls for g in good] == [0, 0, 0, 0]
    assert [g.restarts for g in good] == [0, 0, 0, 0]


class Babbler(ManagedThread):
    """Device-paced thread whose input arrives (io_bytes grows) but never decodes, and which
    reports a notice at every step."""

    def __init__(self) -> None:
        super().__init__("babbler", thread_id=1, watchdog_ms=50)
        self.bytes_in = 0
        self.decodes = True

    def io_bytes(self) -> int:
        return self.bytes_in

    def step(self) -> int:
        time.sleep(0.002)
        self.bytes_in += 10
        self.notice("copies dropped")
        return 1 if self.decodes or self.cycles < 3 else 0


def test_a_silent_device_with_bytes_arriving_is_reported_as_undecodable() -> None:
    b = Babbler()
    mgr = make_manager(b)
    q = mgr.subscribe_events()
    seen: list = []  # type: ignore[type-arg]
    with RunInBackground(mgr):
        assert wait_for(lambda: b.cycles > 3, 5.0)
        b.decodes = False
        assert wait_for(lambda: bool(seen.extend(q.drain()) or
                                     any(e.kind is EventKind.SILENT for e in seen)), 5.0)
        b.decodes = True
        assert wait_for(lambda: bool(seen.extend(q.drain()) or
                                     any(e.kind is EventKind.RECOVERED for e in seen)), 5.0)
    silent = [e for e in seen if e.kind is EventKind.SILENT]
    assert silent[0].detail == "bytes arrive, none decode"
    # a notice at every step (hundreds of them) reaches the ground at most once per 5 s
    notices = [e for e in seen if e.kind is EventKind.NOTICE]
    assert len(notices) == 1 and b.notices > 50, (len(notices), b.notices)
    assert b.restarts == 0
