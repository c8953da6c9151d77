"""Whole-system SITL benchmark: CPU of a flight at nominal rates and the device threads' periods.

Run: `python bench/sitl_bench.py [--quick]` (part of `make bench`).

- CPU: the runtime process and the simulator process of a real-time `companion sim` flight, in %
  of one core (target: runtime under 15 %), the simulator reported separately.
- Periods: IMU, GPS and servo records' inter-arrival times in that flight (what the thesis's
  Figure 6-4 and its GPS-period figures show), against the nominal period, which is the
  baseline the thesis measured its 2003 program against (10 ms IMU, 100 ms GPS, 20 ms servo).
- Speed: the same flight at 5x and 10x: achieved real-time factor and whether every rate held.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import psutil

from companion.logs import read_log

NOMINAL_MS = {"imu": 10.0, "gps": 100.0, "servo": 20.0}
THESIS = {"imu": "10 ms mean, great variance and spikes", "gps": "140 ms instead of 100 ms",
          "servo": "not reported"}


def thread_cpu_s(pid: int) -> dict[int, tuple[str, float]]:
    """CPU seconds (user + system) of every thread of `pid`, by thread id, with its OS name.

    Managed threads name themselves (companion.core.osthread), so `comm` is the thread's name; the
    main thread, which runs the thread manager, carries the process's name."""
    tick = float(os.sysconf("SC_CLK_TCK"))
    out: dict[int, tuple[str, float]] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            comm = (task / "comm").read_text().strip()
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # the thread ended between the listing and the read
            continue
        tid = int(task.name)
        name = "manager (main thread)" if tid == pid else comm
        out[tid] = (name, (int(fields[11]) + int(fields[12])) / tick)
    return out


def per_thread_pct(first: dict[int, tuple[str, float]], last: dict[int, tuple[str, float]],
                   span_s: float) -> dict[str, float]:
    """% of one core per thread name between two snapshots (restarted threads summed by name)."""
    pct: dict[str, float] = {}
    for tid, (name, cpu) in last.items():
        before = first.get(tid, (name, 0.0))[1]
        pct[name] = pct.get(name, 0.0) + (cpu - before) / span_s * 100
    return pct


def fly(tmp: Path, duration_s: float, speed: float | None) -> tuple[dict, dict[str, Any], Path]:
    cmd = [sys.executable, "-m", "companion", "sim", "--duration", str(duration_s),
           "--log-dir", str(tmp / "flights"), "--params-file", str(tmp / "p.parm"),
           "--mavlink", "udpout:127.0.0.1:14550", "--json", "--scenario", "mixed"]
    if speed:
        cmd += ["--speed", str(speed)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    ps = psutil.Process(proc.pid)
    samples: list[tuple[float, float, float]] = []  # (wall, runtime cpu, world cpu)
    threads: list[dict[int, tuple[str, float]]] = []  # per-thread snapshot at each sample
    start = time.monotonic()
    while proc.poll() is None:
        try:
            kids = ps.children()
            world = sum(kids[0].cpu_times()[:2]) if kids else 0.0
            snap = thread_cpu_s(proc.pid)
            samples.append((time.monotonic() - start, sum(ps.cpu_times()[:2]), world))
            threads.append(snap)
        except (psutil.Error, OSError):
            pass
        time.sleep(0.2)
    # steady state only: from a quarter into the flight (start-up imports and trim are over)
    # to the last sample before shutdown
    i_first = next(i for i, s in enumerate(samples) if s[0] >= samples[-1][0] * 0.25)
    # ... while every thread still runs: on a loaded machine shutdown spans several samples,
    # and a thread that has ended is missing from the last snapshots
    n_threads = [len(t) for t in threads]
    full = max(n_threads[i_first:])
    i_last = max(i for i in range(i_first, len(samples)) if n_threads[i] == full)
    i_last = max(i_first + 1, min(i_last, len(samples) - 2)) if len(samples) > 2 else i_last
    first, last = samples[i_first], samples[i_last]
    span = last[0] - first[0]
    cpu: dict[str, Any] = {
        "wall": samples[-1][0], "span": span,
        "runtime": (last[1] - first[1]) / span, "world": (last[2] - first[2]) / span,
        "threads": per_thread_pct(threads[i_first], threads[i_last], span),
    }
    out, _ = proc.communicate()
    summary = json.loads(out)
    fdir = Path(summary["flight_dir"])
    return summary, cpu, fdir


def periods_ms(fdir: Path, name: str) -> np.ndarray:
    t = read_log(fdir / f"{name}.bin").data(1)["time_s"]
    lo, hi = np.percentile(t, [5, 95])  # steady state, not start-up or shutdown
    t = t[(t >= lo) & (t <= hi)]
    return np.diff(t) * 1000.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    duration = 20.0 if args.quick else 60.0
    with tempfile.TemporaryDirectory() as tmp:
        summary, cpu, fdir = fly(Path(tmp) / "rt", duration, None)
        print(f"## Real-time flight, {duration:.0f} s, scenario mixed, every thread on\n")
        print("| process | CPU % of one core |\n|---|---|")
        rt_pct = cpu["runtime"] * 100
        print(f"| runtime (all threads, MAVLink and legacy links, logs) | {rt_pct:.1f} |")
        print(f"| simulator (JSBSim, pilot, device simulators) | {cpu['world'] * 100:.1f} |")
        print(f"| runtime vs the 15 % budget | {rt_pct / 15:.2f}x |")
        print(f"\n(steady state over {cpu['span']:.1f} s of the {cpu['wall']:.1f} s run; start-up "
              f"imports and trim excluded)\n")
        print("Per thread of the runtime (OS thread names; /proc/<pid>/task, same window):\n")
        print("| thread | CPU % of one core |\n|---|---|")
        ranked = sorted(cpu["threads"].items(), key=lambda kv: -kv[1])
        for name, pct in ranked:
            if pct >= 0.05:
                print(f"| {name} | {pct:.1f} |")
        rest = sum(pct for _, pct in ranked if pct < 0.05)
        print(f"| others ({sum(1 for _, p in ranked if p < 0.05)} threads) | {rest:.1f} |")
        print(f"| sum | {sum(cpu['threads'].values()):.1f} |\n")
        print("## Device thread periods in that flight (baseline: the nominal period)\n")
        print("| thread | nominal ms | mean ms | p50 dev ms | p99 dev ms | max dev ms | "
              "mean / nominal | thesis 2003 |")
        print("|---|---|---|---|---|---|---|---|")
        for name, nominal in NOMINAL_MS.items():
            p = periods_ms(fdir, name)
            dev = np.abs(p - nominal)
            print(f"| {name} | {nominal:.0f} | {p.mean():.3f} | {np.percentile(dev, 50):.3f} | "
                  f"{np.percentile(dev, 99):.3f} | {dev.max():.3f} | {p.mean() / nominal:.4f} | "
                  f"{THESIS[name]} |")
        print("\n(arrival times in the runtime: IMU and GPS records are stamped when their bytes "
              "are read, so these include the pseudo-terminal and scheduling delays)\n")
        print("## Faster than real time\n")
        print("| speed | real-time factor achieved | IMU Hz | GPS Hz | servo Hz | restarts |")
        print("|---|---|---|---|---|---|")
        for speed in (5.0, 10.0):
            s, _cpu, _f = fly(Path(tmp) / f"x{speed:g}", duration, speed)
            rates = {t["name"]: t["rate_hz"] for t in s["threads"]}
            restarts = sum(t["restarts"] for t in s["threads"])
            print(f"| {speed:g}x | {s['simulator']['real_time_factor']} | {rates.get('imu')} | "
                  f"{rates.get('gps')} | {rates.get('servo')} | {restarts} |")


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("sitl", ["companion", "gcs_bridge", "legacy_protocol"], main))
