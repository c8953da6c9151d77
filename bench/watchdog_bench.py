"""Watchdog benchmarks: detection latency, timer jitter under load, idle manager CPU.

Run: `python bench/watchdog_bench.py [--quick]` (or `make bench`). Each figure is printed next
to a baseline measured in the same run:
- jitter: our absolute-deadline loop vs the naive `sleep(period)` after the work (the drift-prone
  pattern of the 2003 program's loops);
- idle CPU: the manager vs a bare loop that only waits its granularity.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import threading
import time
from pathlib import Path

import numpy as np

from companion.core.clock import Clock
from companion.core.params import ParamRegistry
from companion.runtime import SWITCH_INTERVAL_S
from companion.watchdog import EventKind, ManagedThread, RuntimeContext, ThreadManager


class Work(ManagedThread):
    """A timer thread doing a little numpy work per cycle, like a filter step."""

    def __init__(self, name: str, thread_id: int, period_ms: float) -> None:
        super().__init__(name, thread_id=thread_id, period_ms=period_ms, watchdog_ms=1000)
        self.m = np.eye(12)
        # Every cycle's start, stamped where the naive baseline stamps its own (before the work),
        # so both loops are compared over all their cycles, not the thread's 4,096-period ring.
        self.stamps_ns: list[int] = []

    def step(self) -> bool:
        self.stamps_ns.append(time.perf_counter_ns())
        self.m = self.m @ np.eye(12) * 1.0000001
        return True


class Staller(ManagedThread):
    def __init__(self, watchdog_ms: int) -> None:
        super().__init__("staller", thread_id=9, period_ms=10.0, watchdog_ms=watchdog_ms)
        self.stall_now = threading.Event()
        self.stalled_at: float | None = None
        self.release = threading.Event()

    def interrupt_io(self) -> None:
        self.release.set()

    def step(self) -> bool:
        if self.stall_now.is_set():
            self.stall_now.clear()
            self.stalled_at = time.monotonic()
            self.release.clear()
            self.release.wait()  # blocked until the manager interrupts it
        return True


def run_manager(threads: list[ManagedThread], seconds: float, **params: int) -> ThreadManager:
    ctx = RuntimeContext(clock=Clock(), params=ParamRegistry())
    mgr = ThreadManager(ctx, threads)
    for k, v in params.items():
        ctx.params.set(k, v)
    return mgr


def detection_latency(watchdog_ms: int, stalls: int) -> list[float]:
    staller = Staller(watchdog_ms)
    mgr = run_manager([staller], 0, MGR_WDG_GRAN_MS=5, MGR_RST_INTENS=100000)
    events = mgr.subscribe_events(4096)
    latencies: list[float] = []
    runner = threading.Thread(target=mgr.run)
    mgr.start()
    runner.start()
    try:
        for _ in range(stalls):
            time.sleep(0.05 + np.random.default_rng().random() * watchdog_ms / 1000)
            staller.stall_now.set()
            deadline = time.monotonic() + 5 * watchdog_ms / 1000 + 1
            got = None
            while time.monotonic() < deadline and got is None:
                ev = events.get(0.5)
                if ev is not None and ev.kind is EventKind.RESTARTED:
                    got = time.monotonic()
            if got is not None and staller.stalled_at is not None:
                latencies.append((got - staller.stalled_at) * 1000)
    finally:
        mgr.request_stop()
        runner.join(5)
        mgr.shutdown()
    return latencies


def jitter_ours(rate_hz: float, seconds: float) -> np.ndarray:
    target = Work("target", 1, 1000.0 / rate_hz)
    others = [Work(f"load{i}", 2 + i, 10.0) for i in range(4)]
    mgr = run_manager([target, *others], seconds)
    runner = threading.Thread(target=mgr.run)
    mgr.start()
    runner.start()
    time.sleep(seconds)
    mgr.request_stop()
    runner.join(5)
    mgr.shutdown()
    return np.diff(np.array(target.stamps_ns, dtype=float))[5:] / 1e6


def jitter_naive(rate_hz: float, seconds: float) -> np.ndarray:
    """Baseline: work, then sleep(period), with the same four loaded threads beside it."""
    stop = threading.Event()
    others = [Work(f"load{i}", 2 + i, 10.0) for i in range(4)]
    mgr = run_manager(others, seconds)
    runner = threading.Thread(target=mgr.run)
    mgr.start()
    runner.start()
    period = 1.0 / rate_hz
    m = np.eye(12)
    stamps: list[int] = []
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end and not stop.is_set():
        stamps.append(time.perf_counter_ns())
        m = m @ np.eye(12) * 1.0000001
        time.sleep(period)
    mgr.request_stop()
    runner.join(5)
    mgr.shutdown()
    return np.diff(np.array(stamps, dtype=float))[5:] / 1e6


def idle_cpu(seconds: float) -> tuple[float, float]:
    """CPU % of one core: the manager supervising 5 idle threads vs a bare waiting loop."""

    class Idle(ManagedThread):
        def step(self) -> bool:
            self.stop_event.wait(0.5)
            return True

    threads: list[ManagedThread] = [Idle(f"idle{i}", thread_id=i + 1, watchdog_ms=1000)
                                    for i in range(5)]
    mgr = run_manager(threads, seconds, MGR_WDG_GRAN_MS=20)
    mgr.start()
    t0c, t0 = time.thread_time(), time.monotonic()
    mgr.run(duration_s=seconds)
    manager_pct = (time.thread_time() - t0c) / (time.monotonic() - t0) * 100
    mgr.shutdown()
    ev = threading.Event()
    t0c, t0 = time.thread_time(), time.monotonic()
    while time.monotonic() - t0 < seconds:
        ev.wait(0.02)
    bare_pct = (time.thread_time() - t0c) / (time.monotonic() - t0) * 100
    return manager_pct, bare_pct


def stats_ms(periods_ms: np.ndarray, nominal_ms: float) -> dict[str, float]:
    dev = np.abs(periods_ms - nominal_ms)
    return {"mean": float(periods_ms.mean()), "p50": float(np.percentile(dev, 50)),
            "p99": float(np.percentile(dev, 99)), "max": float(dev.max())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    logging.disable(logging.WARNING)  # the stalls are deliberate
    # the GIL switch interval the runtime runs with (companion.runtime.Runtime.start)
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    seconds = 2.0 if args.quick else 10.0
    stalls = 5 if args.quick else 20

    print("## Watchdog detection latency (stall -> restart)\n")
    print("| watchdog period | stalls | median ms | worst ms | median / period | worst / period |")
    print("|---|---|---|---|---|---|")
    for wdg in (50, 100, 200):
        lat = detection_latency(wdg, stalls)
        if lat:
            print(f"| {wdg} ms | {len(lat)} | {statistics.median(lat):.1f} | {max(lat):.1f} | "
                  f"{statistics.median(lat) / wdg:.2f} | {max(lat) / wdg:.2f} |")

    print("\n## Timer jitter with four other 100 Hz threads running\n")
    print("Deviation of each cycle-to-cycle period from nominal; baseline = `sleep(period)` "
          "after the work, in the same run.\n")
    print(f"Both loops run {seconds:g} s and every period is kept (cycle starts stamped before the "
          "work in both).\n")
    print("| rate | loop | periods | mean period ms | p50 dev ms | p99 dev ms | max dev ms | "
          "p99 vs baseline |")
    print("|---|---|---|---|---|---|---|---|")
    for rate in (50, 100, 400, 1000):
        nominal = 1000.0 / rate
        p_ours, p_naive = jitter_ours(rate, seconds), jitter_naive(rate, seconds)
        ours, naive = stats_ms(p_ours, nominal), stats_ms(p_naive, nominal)
        print(f"| {rate} Hz | managed (absolute deadlines) | {len(p_ours)} | {ours['mean']:.3f} | "
              f"{ours['p50']:.3f} | {ours['p99']:.3f} | {ours['max']:.3f} | "
              f"{ours['p99'] / max(naive['p99'], 1e-9):.2f}x |")
        print(f"| {rate} Hz | baseline sleep(period) | {len(p_naive)} | {naive['mean']:.3f} | "
              f"{naive['p50']:.3f} | {naive['p99']:.3f} | {naive['max']:.3f} | 1.00x |")

    print("\n## Idle manager CPU (three runs)\n")
    runs = [idle_cpu(seconds) for _ in range(3)]
    print("| what | run 1 | run 2 | run 3 | median |\n|---|---|---|---|---|")
    mgr = [r[0] for r in runs]
    bare = [r[1] for r in runs]
    print("| manager, 5 idle threads, 20 ms granularity, % of one core | "
          + " | ".join(f"{x:.2f}" for x in mgr) + f" | {statistics.median(mgr):.2f} |")
    print("| baseline: bare 20 ms wait loop, % of one core | "
          + " | ".join(f"{x:.2f}" for x in bare) + f" | {statistics.median(bare):.2f} |")
    print("| manager minus baseline | "
          + " | ".join(f"{m - b:.2f}" for m, b in zip(mgr, bare, strict=True))
          + f" | {statistics.median(mgr) - statistics.median(bare):.2f} |")


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("watchdog", ["companion/watchdog", "companion/core", "companion/runtime.py"], main))
