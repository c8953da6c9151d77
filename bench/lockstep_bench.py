"""Lockstep SITL and campaigns: how fast, where the time goes, and that it repeats exactly.

    python bench/lockstep_bench.py            # 300 s flights; a campaign of 100 x 300 s, 2 jobs
    python bench/lockstep_bench.py --quick    # 60 s flights; a campaign of 10 x 60 s

Part 1 flies one aircraft (default scenario, seed 1) for the same simulated time three ways,
each a real `companion sim` process: `--lockstep` twice (their logs must be byte-identical),
and `--fast` (5x on the wall clock, the real scheduling) as the baseline. It prints the wall
time and speed of each, the ratio lockstep / fast, the rates every thread reached, and where
a lockstep flight's host time goes (per task, ms of host time per simulated second).

Part 2 flies a campaign (`--campaign`, lockstep, seeds 1..N, alternating still air and 8 m/s
wind, both aircraft) with `--jobs 2` and prints its wall time against the serial estimate
(N x the part-1 lockstep flight's wall time), and the export of the dataset.
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

NOMINAL_HZ = {"imu": 100.0, "gps": 10.0, "servo": 50.0, "estimator": 100.0, "control": 100.0}


def fly(tmp: Path, label: str, duration_s: float, *mode: str) -> tuple[dict[str, Any], float]:
    cmd = [sys.executable, "-m", "companion", "sim", *mode, "--duration", str(duration_s),
           "--seed", "1", "--json", "--mavlink", "none", "--no-legacy",
           "--log-dir", str(tmp / label), "--params-file", str(tmp / f"{label}.parm")]
    t0 = time.monotonic()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=duration_s * 2 + 300)
    wall_s = time.monotonic() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{label}: exit {proc.returncode}: {proc.stderr[-1500:]}")
    return json.loads(proc.stdout), wall_s


def logs_of(summary: dict[str, Any]) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(Path(summary["flight_dir"]).glob("*.bin"))}


def part1(tmp: Path, duration_s: float) -> float:
    a, wall_a = fly(tmp, "lockstep-a", duration_s, "--lockstep")
    b, wall_b = fly(tmp, "lockstep-b", duration_s, "--lockstep")
    fast, wall_fast = fly(tmp, "fast", duration_s, "--fast")
    logs_a, logs_b = logs_of(a), logs_of(b)
    same = [n for n in logs_a if logs_b.get(n) == logs_a[n]]
    print(f"## One aircraft, {duration_s:.0f} simulated s (scenario mixed, seed 1)\n")
    print("| mode | wall s (process) | speed (sim s / wall s) | in-loop speed | restarts |")
    print("|---|---|---|---|---|")
    for label, s, wall in (("--lockstep (1)", a, wall_a), ("--lockstep (2)", b, wall_b),
                           ("--fast (baseline)", fast, wall_fast)):
        inner = (s.get("lockstep") or {}).get("speed")
        restarts = sum(t["restarts"] for t in s["threads"])
        print(f"| {label} | {wall:.2f} | {duration_s / wall:.1f} | "
              f"{inner if inner is not None else '-'} | {restarts} |")
    print(f"\nlockstep / fast: {wall_fast / wall_a:.2f}x less wall time for the same flight; "
          f"logs byte-identical between the two lockstep runs: {len(same)}/{len(logs_a)} files "
          f"({', '.join(sorted(logs_a))})\n")
    print("| thread | lockstep rate Hz | fast rate Hz | nominal |")
    print("|---|---|---|---|")
    rates_fast = {t["name"]: t["rate_hz"] for t in fast["threads"]}
    for t in a["threads"]:
        print(f"| {t['name']} | {t['rate_hz']:.2f} | {rates_fast.get(t['name'], 0):.2f} | "
              f"{NOMINAL_HZ.get(t['name'], 0):.0f} |")
    host = a["lockstep"]["host_s_by_task"]
    sim_s = a["lockstep"]["sim_seconds"]
    total = sum(host.values())
    print(f"\nWhere a lockstep flight's host time goes ({total:.2f} s in tasks for {sim_s:.0f} "
          f"simulated s; the rest of the loop, the scheduler itself, "
          f"{max(0.0, sim_s / a['lockstep']['speed'] - total):.2f} s):\n")
    print("| task | ms per simulated s | share |")
    print("|---|---|---|")
    for name, s in sorted(host.items(), key=lambda kv: -kv[1]):
        print(f"| {name} | {s / sim_s * 1e3:.2f} | {s / total:.0%} |")
    print(f"\nscheduler switches {a['lockstep']['switches']}, time advances "
          f"{a['lockstep']['advances']}")
    return wall_a


def part2(tmp: Path, flights: int, duration_s: float, serial_wall_s: float) -> None:
    lines = [f"duration_s = {duration_s}", 'scenario = "mixed"']
    for i in range(flights):
        wind = "[0, 0, 0]" if i % 2 == 0 else "[0, 8, 0]"
        aircraft = "c172p" if (i // 2) % 2 == 0 else "j3cub"
        lines += ["[[flight]]", f"seed = {i + 1}", f"wind = {wind}", f'aircraft = "{aircraft}"']
    spec = tmp / "campaign.toml"
    spec.write_text("\n".join(lines) + "\n", encoding="utf-8")
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "companion", "sim", "--campaign", str(spec),
                           "--jobs", "2", "--campaign-dir", str(tmp / "campaign"), "--json"],
                          capture_output=True, text=True, timeout=flights * duration_s + 3600)
    wall_s = time.monotonic() - t0
    if not proc.stdout.strip():
        raise SystemExit(f"campaign: exit {proc.returncode}: {proc.stderr[-1500:]}")
    result = json.loads(proc.stdout)
    serial = serial_wall_s * flights
    print(f"\n## A campaign: {flights} flights of {duration_s:.0f} simulated s, --jobs 2\n")
    print("| flights ok | failed | restarts | wall s | simulated s | speed | "
          "serial estimate s | ratio | dataset export s |")
    print("|---|---|---|---|---|---|---|---|---|")
    print(f"| {result['ok']} | {result['failed']} | {result['restarts']} | {wall_s:.0f} | "
          f"{result['simulated_s']:.0f} | {result['simulated_s'] / wall_s:.0f}x | {serial:.0f} | "
          f"{serial / wall_s:.2f}x | {result['dataset']['export_s']} |")
    print("\n(serial estimate: flights x the wall time of one lockstep flight above, "
          "process start included; the ratio is what two jobs gain on this machine's "
          f"{os.cpu_count()} cores)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    duration_s = 60.0 if args.quick else 300.0
    flights = 10 if args.quick else 100
    with tempfile.TemporaryDirectory(prefix="lockstep-bench-") as tmp:
        wall = part1(Path(tmp), duration_s)
        part2(Path(tmp), flights, duration_s, wall)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("lockstep", ["companion", "gcs_bridge", "legacy_protocol"], main))
