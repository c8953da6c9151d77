"""Flight report and rerun live-view benchmark.

    python bench/report_bench.py [--minutes M] [--flight DIR] [--view-s S] [--pairs N] [--no-sim]
                                 [--quick]

Report: wall time of `generate_report` (figures + HTML, with and without measuring the CSV size)
on a 10-minute flight. Unless --flight names a real flight directory, the flight is synthesised
with the runtime's own log formats at the runtime's rates (IMU 100 Hz with raw bytes, GPS 10 Hz
with raw NMEA, servo 50 Hz, estimator 100 Hz, SITL truth 100 Hz): same sizes, same record counts.
Target: under 10 s.

Live view: the cost of `--rerun` to the flight threads. Two runs of the same length, with and
without a `LiveView` writing an .rrd: process CPU (all threads, rerun's native ones included) per
second of wall time, the view thread's own Python time, and the flight threads' mean step time.
First on synthetic producer threads writing the slots at flight rates (repeatable), then, unless
--no-sim, in a real SITL flight (`run_sim`, 5x). Target: under 2 % of one core.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.logs.formats import parse_format  # noqa: E402
from companion.logs.records import (  # noqa: E402
    ARRAY,
    BEGIN,
    END,
    TIMED_HEADER,
    DataPacker,
    encode_comment,
    encode_definition,
    encode_marker,
    split_time_ns,
)

T0_NS = 1_795_000_000_000_000_000
LAT0, LON0, ALT0 = 43.68, 10.39, 300.0
M_PER_DEG_LAT = 111_132.0


class _Log:
    """One binary log assembled in memory with the producer's own formats."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.packers: dict[int, DataPacker] = {}

    def define(self, index: int, fmt: str, columns: list[str]) -> None:
        if columns:
            self.parts.append(encode_comment(index, ",".join(columns)))
        self.parts.append(encode_definition(index, fmt))
        self.packers[index] = DataPacker(index, parse_format(fmt))

    def marker(self, kind: int, t_ns: int) -> None:
        self.parts.append(encode_marker(kind, t_ns))

    def block(self, index: int, t_ns: int, values: list[float] | tuple[float, ...]) -> None:
        self.parts.append(self.packers[index].pack(t_ns, values))

    def array(self, index: int, t_ns: int, payload: bytes) -> None:
        sec, nsec = split_time_ns(t_ns)
        self.parts.append(TIMED_HEADER.pack(ARRAY, index, len(payload), sec, nsec) + payload)

    def write(self, path: Path) -> int:
        data = b"".join(self.parts)
        path.write_bytes(data)
        return len(data)


def _producer_log(module: str, cls: str) -> _Log:
    import importlib

    from companion.vehicle import VEHICLE

    log = _Log()
    make = getattr(importlib.import_module(module), cls)
    # each thread is built for its row of the vehicle's table; a driver also takes a port
    row = "estimator" if "estimation" in module else module.rsplit(".", 1)[1]
    port = ("loop://",) if "drivers" in module else ()
    make(*port, task=VEHICLE[row].task).define_logs(log)
    return log


def synthesise_flight(root: Path, minutes: float, seed: int = 1) -> Path:
    """A flight directory like `companion sim` leaves, flying a 400 m circle at 50 m/s."""
    from companion.logs.truth import TRUTH_COLUMNS, TRUTH_FORMAT

    rng = np.random.default_rng(seed)
    d = root / "synthetic"
    d.mkdir(parents=True, exist_ok=True)
    dur = minutes * 60.0
    speed, radius, g = 50.0, 400.0, 9.80665
    roll = math.atan(speed**2 / (g * radius))
    w = speed / radius

    def state(t: np.ndarray) -> dict[str, np.ndarray]:
        yaw = (w * t + math.pi / 2) % (2 * math.pi) - math.pi
        north = radius * np.sin(w * t)
        east = radius * (1 - np.cos(w * t))
        return {"t": t, "yaw": yaw, "north": north, "east": east, "down": -0.05 * t,
                "vn": speed * np.cos(w * t), "ve": speed * np.sin(w * t)}

    lat_of = lambda n: LAT0 + n / M_PER_DEG_LAT  # noqa: E731
    lon_of = lambda e: LON0 + e / (M_PER_DEG_LAT * math.cos(math.radians(LAT0)))  # noqa: E731
    ns = lambda t: T0_NS + int(t * 1e9)  # noqa: E731

    imu = _producer_log("companion.drivers.imu", "ImuDriver")
    t = np.arange(0.0, dur, 0.01)
    imu.marker(BEGIN, T0_NS)
    jitter = rng.normal(0.0, 0.0008, t.size)
    p = rng.normal(0.0, 0.01, t.size)
    for k, tk in enumerate(t):
        tt = tk + jitter[k]
        imu.block(1, ns(tt), (k % 100, 0, p[k], 0.0, w, 0.1, 0.0, -g / math.cos(roll)))
        imu.array(3, ns(tt), bytes(24))
        if k % 100 == 99:
            imu.block(2, ns(tt), (0.0, 0.0, w, 0.0, 0.0, -g, 25.0, 0))
    imu.marker(END, ns(dur))

    gps = _producer_log("companion.drivers.gps", "GpsDriver")
    s = state(np.arange(0.0, dur, 0.1))
    gps.marker(BEGIN, T0_NS)
    noise = rng.normal(0.0, 1.5, (s["t"].size, 3))
    for k, tk in enumerate(s["t"]):
        gps.block(1, ns(tk + 0.05), (43200.0 + tk, lat_of(s["north"][k] + noise[k, 0]),
                                     lon_of(s["east"][k] + noise[k, 1]), ALT0 - s["down"][k] + noise[k, 2],
                                     1, 9, 0.9, 1.6, 1.3, float("nan"), speed, math.degrees(s["yaw"][k]) % 360,
                                     s["vn"][k], s["ve"][k], 0.05, 1.4, 1.1, 12.0, float("nan")))
        gps.array(2, ns(tk + 0.05), b"$GPGGA," + bytes(150))
    gps.marker(END, ns(dur))

    servo = _producer_log("companion.drivers.servo", "ServoDriver")
    servo.marker(BEGIN, T0_NS)
    for k, tk in enumerate(np.arange(0.0, dur, 0.02)):
        ail = 1500 + int(40 * math.sin(tk))
        servo.block(1, ns(tk), (ail, 1500, 1500, 1600, 1000, 1500, 1500, 1500,
                                1500, 1500, 1500, 1500, 1500, 1500, 1500, 1500,
                                k % 256, 0, 0, 0, 100 - int(tk / 120), 98 - int(tk / 60)))
    servo.marker(END, ns(dur))

    est = _producer_log("companion.estimation.thread", "EstimatorThread")
    s = state(np.arange(1.0, dur, 0.01))
    est.marker(BEGIN, T0_NS)
    e = rng.normal(0.0, 0.3, (s["t"].size, 3))
    for k, tk in enumerate(s["t"]):
        est.block(1, ns(tk), (roll + 0.01 * e[k, 0], 0.05, s["yaw"][k], s["north"][k] + e[k, 0],
                              s["east"][k] + e[k, 1], s["down"][k] + e[k, 2], s["vn"][k], s["ve"][k], 0.05,
                              0, 0, 0, 0, 0, 0, 0.5, 0.5, 0.8, 0.1, 0.1, 0.1, 0.01, 0.01, 0.02, 0, 1))
    est.marker(END, ns(dur))

    truth = _Log()
    truth.define(1, TRUTH_FORMAT, TRUTH_COLUMNS)
    s = state(np.arange(0.0, dur, 0.01))
    truth.marker(BEGIN, T0_NS)
    for k, tk in enumerate(s["t"]):
        truth.block(1, ns(tk), (roll, 0.05, s["yaw"][k], s["north"][k], s["east"][k], s["down"][k],
                                s["vn"][k], s["ve"][k], 0.05, 0, 0, w, 0, 0, -g, lat_of(s["north"][k]),
                                lon_of(s["east"][k]), ALT0 - s["down"][k], speed, tk))
    truth.marker(END, ns(dur))

    for name, lg in (("imu", imu), ("gps", gps), ("servo", servo), ("estimator", est), ("truth", truth)):
        lg.write(d / f"{name}.bin")
    (d / "run.json").write_text(json.dumps({
        "software": {"name": "uav-companion", "version": "bench"}, "clock_scale": 1.0,
        "config": {"vehicle": {"home": f"{LAT0},{LON0},{ALT0}"}},
        "threads": [{"name": n, "id": i} for i, n in enumerate(("imu", "gps", "servo", "estimator"), 1)],
    }))
    return d


def bench_report(flight: Path, out_root: Path) -> list[tuple[str, float, float]]:
    from companion.report import generate_report

    rows = []
    for label, csv in (("figures + HTML + CSV size", True), ("figures + HTML", False)):
        t0, c0 = time.perf_counter(), time.process_time()
        result = generate_report(flight, out_root / f"out-{csv}", measure_csv=csv)
        rows.append((label, time.perf_counter() - t0, time.process_time() - c0))
        assert len(result.figures) >= 8, result.missing
    return rows


# ------------------------------------------------------------------------------ live view cost
def _synthetic_threads() -> list[Any]:
    from companion.core.state import EstimatorState, GpsFix, ImuSample, ServoState
    from companion.watchdog import ManagedThread

    class Producer(ManagedThread):
        def __init__(self, name: str, tid: int, period_ms: float, make: Any, slot: str) -> None:
            super().__init__(name, thread_id=tid, period_ms=period_ms, watchdog_ms=2000)
            self.make, self.slot, self.k = make, slot, 0

        def step(self) -> bool:
            self.k += 1
            getattr(self.ctx.state, self.slot).write(self.make(self.ctx.clock.realtime_ns(), self.k))
            return True

    return [
        Producer("imu", 1, 10.0, lambda t, k: ImuSample(t, k % 100, (0.01, 0.02, 0.1), (0.1, 0.0, -9.8)), "imu"),
        Producer("gps", 2, 100.0, lambda t, k: GpsFix(t, 43200.0 + k / 10, LAT0 + k * 4e-6, LON0, ALT0, 1, 9,
                                                     hdop=0.9, course_deg=0.0, latency_s=0.012), "gps"),
        Producer("servo", 3, 20.0, lambda t, k: ServoState(t, k % 256, (1500,) * 8, (1500,) * 8, False,
                                                          False, False, 100, 98), "servo"),
        Producer("estimator", 4, 10.0, lambda t, k: EstimatorState(
            t, (1.0, 0.0, 0.0, 0.0), 0.1, 0.05, 0.0, (k * 0.5, 0.0, 0.0), (50.0, 0.0, 0.0), (0.0,) * 3,
            (0.0,) * 3, LAT0, LON0, ALT0), "estimator"),
    ]


class ThreadCpu:
    """CPU seconds per thread of this process (Linux /proc), sampled while threads live.

    Attributes each thread to a group: the flight threads (managed-*, but not the view), the
    view thread, rerun's native threads (not Python threads), and the rest (main, sampler).
    """

    def __init__(self, period_s: float = 0.1) -> None:
        import threading

        self._tick = os.sysconf("SC_CLK_TCK")
        self._start = self._read()
        self._last: dict[str, tuple[str, float]] = {}
        self._names: dict[str, str] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, args=(period_s,), name="cpu-sampler")
        self._thread.start()

    def _read(self) -> dict[str, float]:
        out = {}
        for tid in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{tid}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            out[tid] = (int(fields[11]) + int(fields[12])) / self._tick
        return out

    def _loop(self, period_s: float) -> None:
        import threading

        while not self._stop.wait(period_s):
            for t in threading.enumerate():
                if t.native_id:
                    self._names[str(t.native_id)] = t.name
            for tid, cpu in self._read().items():
                self._last[tid] = (self._names.get(tid, "native"), cpu - self._start.get(tid, 0.0))

    def stop(self) -> dict[str, float]:
        self._stop.set()
        self._thread.join()
        groups = {"flight": 0.0, "view": 0.0, "rerun native": 0.0, "other": 0.0}
        for name, cpu in self._last.values():
            if name == "managed-liveview":
                groups["view"] += cpu
            elif name.startswith("managed-"):
                groups["flight"] += cpu
            elif name == "native":
                groups["rerun native"] += cpu
            else:
                groups["other"] += cpu
        return groups


def _run_synthetic(seconds: float, with_view: bool, tmp: Path) -> dict[str, float]:
    """Producer threads writing the slots at flight rates for `seconds`, with or without a view."""
    from companion.liveview import LiveView
    from companion.watchdog import RuntimeContext, ThreadManager

    tmp.mkdir(parents=True, exist_ok=True)
    ctx = RuntimeContext(flight_dir=tmp)
    manager = ThreadManager(ctx, _synthetic_threads())
    view = LiveView(ctx, manager, save_path=tmp / "bench.rrd") if with_view else None
    cpu, w0 = ThreadCpu(), time.monotonic()
    try:
        manager.run(seconds)
    finally:
        manager.shutdown()
        if view is not None:
            view.close()
    wall = time.monotonic() - w0
    groups = cpu.stop()
    flight = [s for s in manager.thread_status() if s.name != "liveview"]
    out = {f"{k}_pct": 100.0 * v / wall for k, v in groups.items()}
    out.update(step_us=float(np.mean([s.mean_step_us for s in flight])), wall_s=wall,
               view_rows=float(sum(view.samples.values())) if view else 0.0)
    return out


def _run_sim(seconds: float, with_view: bool, tmp: Path) -> dict[str, float]:
    from companion.core.config import Config
    from companion.liveview import LiveView
    from companion.sim.runner import FAST_SCALE, SimOptions, run_sim

    tmp.mkdir(parents=True, exist_ok=True)
    cfg = Config()
    cfg.logs.dir = str(tmp / "flights")
    cfg.params.file = str(tmp / "p.parm")
    cfg.mavlink.endpoints = []
    cfg.legacy.enabled = False
    views: list[LiveView] = []
    marks: dict[str, Any] = {}

    def attach(rt: Any) -> None:
        if with_view:
            views.append(LiveView(rt.ctx, rt.manager, save_path=tmp / "sim.rrd"))
            rt.bridges.append(views[-1])
        marks["cpu"], marks["wall"] = ThreadCpu(), time.monotonic()

    summary = run_sim(cfg, SimOptions(scale=FAST_SCALE), seconds, handle_signals=False, on_runtime=attach)
    wall = time.monotonic() - marks["wall"]
    groups = marks["cpu"].stop()
    threads = [t for t in summary["threads"] if t["name"] != "liveview"]
    out = {f"{k}_pct": 100.0 * v / wall for k, v in groups.items()}
    out.update(step_us=float(np.mean([t["mean_step_us"] for t in threads])), wall_s=wall,
               view_rows=float(sum(views[0].samples.values())) if views else 0.0)
    return out


def _overhead(title: str, run: Any, seconds: float, pairs: int, tmp: Path) -> None:
    """Alternate runs without and with the view; the median difference is the figure."""
    print(f"\n### {title}\n")
    print("| run | wall (s) | flight threads CPU | view thread CPU | rerun native threads CPU "
          "| flight threads mean step (us) |")
    print("|---|---|---|---|---|---|")
    on_flight, added = [], []
    for k in range(pairs):
        base = run(seconds, False, tmp / f"{k}-without")
        view = run(seconds, True, tmp / f"{k}-with")
        for label, r in (("without view", base), ("with `LiveView` (.rrd)", view)):
            print(f"| {k + 1}: {label} | {r['wall_s']:.1f} | {r['flight_pct']:.2f} % | "
                  f"{r['view_pct']:.2f} % | {r['rerun native_pct']:.2f} % | {r['step_us']:.1f} |")
        on_flight.append(view["flight_pct"] - base["flight_pct"])
        added.append(view["view_pct"] + view["rerun native_pct"] - base["rerun native_pct"])
    print(f"\n(CPU as % of one core, median of {pairs} pairs.) Cost to the flight threads: "
          f"**{float(np.median(on_flight)):+.2f} %** (target < 2 %); all the view adds: "
          f"**{float(np.median(added)):.2f} %** (its thread and rerun's native threads).")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=10.0, help="synthetic flight length")
    ap.add_argument("--flight", type=Path, help="benchmark the report on this flight directory")
    ap.add_argument("--view-s", type=float, default=20.0, help="length of each live-view run (s)")
    ap.add_argument("--no-sim", action="store_true", help="skip the SITL live-view runs")
    ap.add_argument("--pairs", type=int, default=3, help="runs without/with the view, alternated")
    ap.add_argument("--quick", action="store_true", help="2-minute flight, one 5 s pair, no SITL")
    args = ap.parse_args()
    if args.quick:
        args.minutes, args.view_s, args.no_sim, args.pairs = 2.0, 5.0, True, 1
    import logging

    logging.basicConfig(level=logging.ERROR)
    with tempfile.TemporaryDirectory(prefix="report-bench-") as tmp_s:
        tmp = Path(tmp_s)
        t0 = time.perf_counter()
        flight = args.flight or synthesise_flight(tmp, args.minutes)
        made = time.perf_counter() - t0
        size = sum(p.stat().st_size for p in flight.glob("*.bin"))
        print(f"### Report on {'a ' + str(args.minutes) + '-minute synthetic' if not args.flight else flight} "
              f"flight ({size / 1e6:.1f} MB of logs{'' if args.flight else f', made in {made:.1f} s'})\n")
        print(f"(load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)\n")
        print("| what | wall time (s) | CPU time (s) |\n|---|---|---|")
        for label, secs, cpu in bench_report(flight, tmp):
            print(f"| {label} | {secs:.2f} | {cpu:.2f} |")
        print("\ntarget: under 10 s for a 10-minute flight")
        _overhead(f"Live view on synthetic flight threads ({args.view_s:.0f} s runs)", _run_synthetic,
                  args.view_s, args.pairs, tmp / "synthetic")
        if not args.no_sim:
            _overhead(f"Live view in SITL ({args.view_s * 2:.0f} s flights at 5x)", _run_sim,
                      args.view_s * 2, args.pairs, tmp / "sitl")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("report", ["companion/report", "companion/liveview", "companion/logs"], main))
