"""One-hour soak: a 3600 s `companion sim --fast` flight (12 minutes of wall time) with faults
drawn at random from the fault matrix, all in the same flight.

Run: `python bench/soak_bench.py [--duration S] [--seed N]` (`make bench-soak`).

What is injected (seeded, so a run can be repeated): device faults in windows (silences, floods
of copies, a wrong baud rate, GPS UTC steps, ports that vanish and return under another name),
thread faults (an exception, a Python loop ignoring its stop event, a block inside C), wall-clock
steps, and from this process while the aircraft flies: MAVLink floods (valid and invalid frames),
legacy UDP floods, and SIGSTOP/SIGCONT of the runtime for 5 s. The figures are those of
`faults_bench.py` over the whole hour: IMU and GPS rates from the logs (per minute, the worst
minute too), restarts against the restarts the thread faults intend, memory (RSS at the start
and the end of the hour), every fault reported, and the flight's report (`companion logs report`),
whose "Faults and events" section lists each fault next to what the runtime said.

All on this machine, on loopback, against the project's own simulator.
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from faults_bench import SCALE, Flight, param_list_s, thread_of  # noqa: E402
from mavflood import flood  # noqa: E402

from companion.logs import read_log  # noqa: E402
from companion.sim.faults import parse_fault, parse_thread_fault, parse_vanish  # noqa: E402


def draw_plan(duration_s: float, rng: random.Random) -> tuple[list[str], list[float]]:
    """Command-line faults for the flight, and host-side moments (flight s) for the process and
    network faults. One fault roughly every 2 minutes of flight per family."""
    args: list[str] = []
    per_dev: dict[str, list[str]] = {"imu": [], "gps": [], "servo": []}
    t = 60.0
    while t < duration_s - 120:
        dev = rng.choice(["imu", "gps", "servo"])
        kind = rng.choice(["silence", "flood", "wrongbaud"] if dev != "servo"
                          else ["silence", "wrongbaud"])
        length = rng.uniform(1.0, 5.0)
        per_dev[dev].append(f"{kind}={t:.1f}-{t + length:.1f}")
        t += rng.uniform(60.0, 180.0)
    per_dev["gps"].append(f"utcstep={rng.uniform(300, duration_s - 300):.0f}:3600")
    for dev, items in per_dev.items():
        if items:
            args += ["--fault", f"{dev}:" + ",".join(items)]
    for dev in ("gps", "servo"):
        at = rng.uniform(200, duration_s - 200)
        args += ["--vanish", f"{dev}:{at:.0f}:{rng.uniform(1, 4):.1f}:renamed"]
    thread_faults = [("estimator", "raise"), ("control", "raise"), ("gps", "pyloop"),
                     ("estimator", "cblock")]
    for name, kind in thread_faults:
        args += ["--thread-fault", f"{name}:{kind}:{rng.uniform(120, duration_s - 120):.0f}"]
    args += ["--clock-step", f"{rng.uniform(100, duration_s - 100):.0f}:3600",
             "--clock-step", f"{rng.uniform(100, duration_s - 100):.0f}:-3600"]
    host_events = sorted(rng.uniform(90, duration_s - 90) for _ in range(12))
    return args, host_events


def random_datagrams(r: np.random.Generator) -> Callable[[], bytes]:
    return lambda: r.integers(0, 256, int(r.integers(1, 600)), dtype=np.uint8).tobytes()


def fault_windows(extra: list[str], dev: str) -> list[tuple[float, float]]:
    """Flight-time windows in which `dev`'s own rate is meant to suffer (its device faults,
    its port gone, its thread's injected fault), each widened by a few seconds; the options are
    read by the parsers `companion sim` uses."""
    out: list[tuple[float, float]] = []
    for flag, value in zip(extra, extra[1:], strict=False):
        if flag == "--fault" and value.startswith(dev + ":"):
            plan = parse_fault(value)[1]
            out += [(a - 2, b + 5) for a, b in plan.silence_s + plan.flood_s + plan.wrong_baud_s]
        elif flag == "--vanish" and value.startswith(dev + ":"):
            v = parse_vanish(value)
            out.append((v.start_s - 2, v.start_s + v.duration_s + 10))
        elif flag == "--thread-fault" and value.startswith(dev + ":"):
            at = parse_thread_fault(value).at_s
            out.append((at - 2, at + 10))
    return out


def minute_rates(path: Path, index: int, nominal_hz: float,
                 excused: list[tuple[float, float]]) -> str:
    """Rates per full minute of flight from a log: the minutes that overlap no excused window
    (that device's faults, a suspension of the whole process) are the ones held to 1 %."""
    t = read_log(path, salvage=True).time_ns(index) / 1e9
    if len(t) < 2:
        return "no records"
    t = t - t[0]
    edges = np.arange(0.0, t[-1], 60.0)
    if len(edges) < 2:
        return "shorter than a minute"
    rates = np.histogram(t, bins=edges)[0] / 60.0
    clean = [r for a, r in zip(edges[:-1], rates, strict=True)
             if not any(lo < a + 60 and a < hi for lo, hi in excused)]
    if not clean:
        return f"no minute without a fault; worst {rates.min():.2f} Hz"
    ok = sum(abs(r - nominal_hz) <= 0.01 * nominal_hz for r in clean)
    return (f"{ok} of {len(clean)} minutes without a fault within 1 % of {nominal_hz:g} Hz "
            f"(worst {min(clean):.2f} Hz); with faults, worst {rates.min():.2f} Hz "
            f"({len(rates)} minutes in all)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=3600.0, help="flight seconds (3600)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    d = args.duration
    rng = random.Random(args.seed)
    extra, host_events = draw_plan(d, rng)
    flight = Flight(d, extra)
    t0 = time.monotonic()
    flight.start()
    assert flight.proc is not None
    if not flight.wait_ready(120.0):
        print("the runtime never answered; stderr:", flight.proc.stderr.read()[-2000:]
              if flight.proc.stderr else "")
        return 1
    t_ready = time.monotonic()
    done: list[dict[str, Any]] = []
    kinds = ["mavflood", "legacyflood", "sigstop"]
    for i, at in enumerate(host_events):
        kind = kinds[i % len(kinds)]
        while time.monotonic() - t_ready < at / SCALE and flight.proc.poll() is None:
            flight.sample_rss()
            time.sleep(1.0)
        if flight.proc.poll() is not None:
            break
        t_s = (time.monotonic() - t_ready) * SCALE
        if kind == "mavflood":
            sent = flood("127.0.0.1", flight.mav_port, 5.0, seed=i, rate_per_s=2000.0)
            got = param_list_s(flight.mav_port, 20.0)
            done.append({"t_s": t_s, "kind": "MAVLink flood 5 s", "sent": sum(sent.values()),
                         "GCS after": f"{got[1]}/{got[2]} params in "
                                      f"{got[0]:.2f} s" if got[0] else "DEAF"})
        elif kind == "legacyflood":
            sent = flood("127.0.0.1", flight.legacy_port, 5.0, rate_per_s=1000.0,
                         datagram=random_datagrams(np.random.default_rng(i)))
            done.append({"t_s": t_s, "kind": "legacy UDP flood 5 s",
                         "sent": sum(sent.values())})
        else:
            os.kill(flight.proc.pid, signal.SIGSTOP)
            time.sleep(5.0)
            os.kill(flight.proc.pid, signal.SIGCONT)
            done.append({"t_s": t_s, "kind": "SIGSTOP 5 s host"})
    while flight.proc.poll() is None and time.monotonic() - t0 < d / SCALE + 300:
        flight.sample_rss()
        time.sleep(2.0)
    summary, code = flight.finish(30.0)
    wall_s = time.monotonic() - t0
    fd = flight.flight_dir()

    print(f"## One-hour soak: a {d:g} s `companion sim --fast` flight, seed {args.seed}\n")
    print(f"Wall time {wall_s / 60:.1f} min, exit code {code}. Injected on the command line:\n")
    print("```\n" + " ".join(extra) + "\n```\n")
    print("From the bench while it flew:\n")
    for e in done:
        print("- " + ", ".join(f"{k} {v}" if k != "t_s" else f"at {v:.0f} s"
                               for k, v in e.items()))
    print()
    if summary is None or fd is None:
        print("no summary: the flight did not end normally")
        return 1
    print("| figure | value |\n|---|---|")
    stops = [(e["t_s"] - 15, e["t_s"] + 5 * SCALE + 15) for e in done
             if e["kind"].startswith("SIGSTOP")]
    for name, idx, hz in (("imu", 1, 100.0), ("gps", 1, 10.0), ("servo", 1, 50.0)):
        p = fd / f"{name}.bin"
        if p.exists():
            print(f"| {name} rate (log) | "
                  f"{minute_rates(p, idx, hz, stops + fault_windows(extra, name))} |")
    for name in ("estimator", "control"):
        print(f"| {name} rate at the end | {thread_of(summary, name).get('rate_hz')} Hz |")
    restarts = {t["name"]: t["restarts"] for t in summary["threads"] if t["restarts"]}
    intended = {}
    for a in summary.get("thread_faults", []):
        intended[a["thread"]] = intended.get(a["thread"], 0) + 1
    print(f"| restarts | {restarts or 'none'} |")
    print(f"| restarts the thread faults intend | {intended or 'none'} |")
    unintended = {k: v - intended.get(k, 0) for k, v in restarts.items()
                  if v > intended.get(k, 0)}
    print(f"| unintended restarts | {unintended or 'none'} |")
    kinds_n: dict[str, int] = {}
    for e in summary["events"]:
        if e["kind"] not in ("started", "stopped"):
            key = f"{e['thread']} {e['kind']}"
            kinds_n[key] = kinds_n.get(key, 0) + 1
    print(f"| events | {'; '.join(f'{k} x{v}' for k, v in sorted(kinds_n.items()))} |")
    rss = flight.rss_mb
    if len(rss) > 20:
        k = max(len(rss) // 10, 1)
        first, last = float(np.median(rss[k:2 * k])), float(np.median(rss[-k:]))
        print(f"| RSS (median of the 2nd and of the last tenth) | {first:.0f} MB -> {last:.0f} MB "
              f"({(last - first) / first * 100:+.1f} %), peak {max(rss):.0f} MB |")
    for dev in ("imu", "gps", "servo"):
        c = thread_of(summary, dev).get("counters", {})
        print(f"| {dev} counters | " + ", ".join(f"{k} {v}" for k, v in c.items() if v) + " |")
    m = summary.get("messages", [{}])
    if m and m[0]:
        print(f"| MAVLink link | rx_frames {m[0].get('rx_frames')}, parse_errors "
              f"{m[0].get('parse_errors')}, refused {m[0].get('refused')} |")
    out = fd / "report"
    rep = subprocess.run([sys.executable, "-m", "companion", "logs", "report", str(fd), "-o",
                          str(out), "--no-csv-size"], capture_output=True, text=True,
                         timeout=600)
    print(f"| flight report | written to the flight directory, report/report.html (exit "
          f"{rep.returncode}) |")
    print(f"\nFlight directory: {fd}", file=sys.stderr)
    return 0 if code == 0 else 1


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("soak", ["companion", "gcs_bridge", "legacy_protocol",
                                   "bench/faults_bench.py", "bench/mavflood.py"], main))
