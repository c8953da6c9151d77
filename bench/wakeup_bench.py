"""Wake-ups and CPU of each runtime thread in a real-time simulated flight.

A thread that polls costs CPU and wake-ups whether or not it has work; on a small companion
computer both are taken from the flight threads. This runs the real `companion sim` in real time
with the default configuration (MAVLink to a UDP ground station, the legacy protocol on) and
reads, for every thread of the runtime process, its CPU time (/proc/<pid>/task/<tid>/stat) and
its voluntary context switches, i.e. the times it went to sleep and was woken
(/proc/<pid>/task/<tid>/status), over a window after start-up. Thread names are the managed
threads' names (set with companion.core.osthread).

Baseline, measured in the same run: the same flight with MAVLink and the legacy protocol off,
so the ratios say what the two bridges cost on top of the flight threads. No new default stream
is added by the bridge's wake-up work: the stream rates are today's `MAV_*_HZ` defaults.

Usage: ``python bench/wakeup_bench.py [--duration 45] [--warmup 10] [--quick]``
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CLK_TCK = os.sysconf("SC_CLK_TCK")


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def load() -> str:
    one, five, _ = os.getloadavg()
    return f"load {one:.2f} (1 min) {five:.2f} (5 min), {os.cpu_count()} CPUs"


@dataclass
class ThreadSample:
    name: str
    cpu_s: float
    wakeups: int  # voluntary context switches
    preempted: int  # involuntary context switches


def sample_threads(pid: int) -> dict[int, ThreadSample]:
    """Every thread of `pid` now: tid -> its name, CPU seconds and context switches."""
    out: dict[int, ThreadSample] = {}
    task_dir = Path(f"/proc/{pid}/task")
    for tdir in task_dir.iterdir():
        try:
            stat = (tdir / "stat").read_text()
            status = (tdir / "status").read_text()
        except OSError:
            continue  # the thread ended meanwhile
        name = stat[stat.index("(") + 1:stat.rindex(")")]
        fields = stat[stat.rindex(")") + 2:].split()
        cpu_s = (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime, stime
        vol = invol = 0
        for line in status.splitlines():
            if line.startswith("voluntary_ctxt_switches:"):
                vol = int(line.split()[1])
            elif line.startswith("nonvoluntary_ctxt_switches:"):
                invol = int(line.split()[1])
        out[int(tdir.name)] = ThreadSample(name, cpu_s, vol, invol)
    return out


def process_cpu_s(pid: int) -> float:
    """CPU seconds of the whole process (threads that ended included)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


@dataclass
class Row:
    name: str
    cpu_pct: float  # of one core
    wakeups_s: float
    preempted_s: float


@dataclass
class Flight:
    label: str
    rows: list[Row]
    total_cpu_pct: float  # the runtime process, % of one core
    load_before: str
    load_after: str
    links: list[dict[str, object]]  # the flight summary's per-link figures (whole flight)

    def by_name(self) -> dict[str, Row]:
        return {r.name: r for r in self.rows}


def fly(label: str, bridges: bool, duration_s: float, warmup_s: float) -> Flight:
    """One real-time flight; measures the runtime process over [warmup, duration - 2 s]."""
    with tempfile.TemporaryDirectory(prefix="wakeup-bench-") as tmp:
        cmd = [sys.executable, "-m", "companion", "sim", "--realtime", "--json",
               "--duration", str(duration_s), "--log-dir", f"{tmp}/flights",
               "--params-file", f"{tmp}/params.parm"]
        if bridges:
            # the default configuration: MAVLink to a UDP ground station, legacy protocol on
            cmd += ["--mavlink", f"udpout:127.0.0.1:{free_udp_port()}",
                    "--legacy-listen", str(free_udp_port()),
                    "--legacy-dest", f"127.0.0.1:{free_udp_port()}"]
        else:
            cmd += ["--mavlink", "none", "--no-legacy"]
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        try:
            window_s = duration_s - warmup_s - 2.0
            time.sleep(warmup_s)
            load_before = load()
            a, cpu_a, t_a = sample_threads(proc.pid), process_cpu_s(proc.pid), time.monotonic()
            time.sleep(window_s)
            b, cpu_b, t_b = sample_threads(proc.pid), process_cpu_s(proc.pid), time.monotonic()
            load_after = load()
            out, err = proc.communicate(timeout=duration_s + 60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        if proc.returncode != 0:
            raise RuntimeError(f"{label}: flight exited {proc.returncode}: {err[-1500:]}")
    dt = t_b - t_a
    totals: dict[str, list[float]] = {}
    for tid, end in b.items():
        start = a.get(tid)
        if start is None or start.name != end.name:
            continue  # started (restarted) inside the window: not comparable
        acc = totals.setdefault(end.name, [0.0, 0.0, 0.0])
        acc[0] += end.cpu_s - start.cpu_s
        acc[1] += end.wakeups - start.wakeups
        acc[2] += end.preempted - start.preempted
    rows = [Row(name, 100.0 * v[0] / dt, v[1] / dt, v[2] / dt) for name, v in totals.items()]
    rows.sort(key=lambda r: -r.cpu_pct)
    links = json.loads(out).get("messages", [])
    return Flight(label, rows, 100.0 * (cpu_b - cpu_a) / dt, load_before, load_after, links)


def ratio(a: float, b: float) -> str:
    return f"{a / b:.2f}" if b > 0 else "-"


def report(flights: list[Flight]) -> None:
    base = flights[0]
    for f in flights:
        print(f"\n## {f.label}: runtime process {f.total_cpu_pct:.1f} % of one core "
              f"(window {f.load_before}; after: {f.load_after})\n")
        print("| thread | CPU % of one core | wake-ups/s | preempted/s |")
        print("|---|---:|---:|---:|")
        for r in f.rows:
            print(f"| {r.name} | {r.cpu_pct:.2f} | {r.wakeups_s:.1f} | {r.preempted_s:.1f} |")
        wake = sum(r.wakeups_s for r in f.rows)
        print(f"| **all threads** | {sum(r.cpu_pct for r in f.rows):.2f} | {wake:.1f} | "
              f"{sum(r.preempted_s for r in f.rows):.1f} |")
        for link in f.links:  # what the links delivered over the whole flight
            if "tx_frames" in link:
                print(f"\nMAVLink link {link['index']}: {link['tx_frames']} frames sent, "
                      f"{link['stale_skips']} stale skips, sample-to-message latency p50 "
                      f"{link['latency_us_p50']} us, p99 {link['latency_us_p99']} us")
            elif "sent" in link:
                print(f"\nlegacy link: {link['sent']} datagrams sent")
    if len(flights) < 2:
        return
    print(f"\n## Ratios against '{base.label}' (same run)\n")
    print("| flight | runtime CPU % | ratio | wake-ups/s | ratio | bridge threads CPU % | "
          "bridge wake-ups/s |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    base_wake = sum(r.wakeups_s for r in base.rows)
    for f in flights:
        wake = sum(r.wakeups_s for r in f.rows)
        bridge = [r for r in f.rows if r.name.startswith(("mav", "legacy"))]
        print(f"| {f.label} | {f.total_cpu_pct:.1f} | {ratio(f.total_cpu_pct, base.total_cpu_pct)}"
              f" | {wake:.0f} | {ratio(wake, base_wake)} | {sum(r.cpu_pct for r in bridge):.2f}"
              f" | {sum(r.wakeups_s for r in bridge):.1f} |")
    common = base.by_name()
    print("\nFlight threads, bridges on / bridges off (CPU ratio, wake-up ratio): " + ", ".join(
        f"{r.name} {ratio(r.cpu_pct, common[r.name].cpu_pct)}/"
        f"{ratio(r.wakeups_s, common[r.name].wakeups_s)}"
        for r in flights[-1].rows if r.name in common and r.name != "python"))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=45.0, help="flight, simulated = wall s")
    parser.add_argument("--warmup", type=float, default=10.0, help="start-up left out, s")
    parser.add_argument("--quick", action="store_true", help="20 s flights, 8 s warm-up")
    args = parser.parse_args()
    if args.quick:
        args.duration, args.warmup = 20.0, 8.0
    if args.duration - args.warmup < 5.0:
        parser.error("the window (duration - warmup - 2 s) must be at least 3 s")
    print(f"real-time flights of {args.duration:.0f} s, window {args.warmup:.0f} s to "
          f"{args.duration - 2:.0f} s; {load()}; no new default stream (today's MAV_*_HZ)")
    flights = [fly("bridges off (baseline)", False, args.duration, args.warmup),
               fly("MAVLink + legacy on (default)", True, args.duration, args.warmup)]
    report(flights)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("wakeup", ["companion", "gcs_bridge", "legacy_protocol"], main))
