"""Real flight logs through `companion estimation replay`: our estimate against each log's own.

    python bench/replay_logs_bench.py                      # tests/data/replay, tests/data/px4-ulog
    python bench/replay_logs_bench.py DIR... [--limit N]   # any logs (directories searched)
    python bench/replay_logs_bench.py --quick              # the first two logs
    python bench/replay_logs_bench.py erlerobot-logs --result replay_logs_public
        # a checkout of github.com/erlerobot/logs beside the current directory: public logs
        # with no licence, so not in the repository; docs/benchmarks.md names its commit

For every log (the replay's `find_logs`: .bin/.BIN/.ulg/.tlog, recursively) four replays, all
through `companion.estimation.replay.runner.replay`:

* ``auto``: what the command runs by default (the GPS/INS filter when the log has a fix inside
  its IMU span and it starts, its heading from the log's attitude unless the vehicle already
  moves at the first fix; else IMU-only VQF);
* ``eskf gps``: the same with the flight's heading rule (``--heading-from gps``: the GPS
  course only), only where the ESKF ran;
* ``vqf`` and ``ours``: the IMU-only filters of the registry (``--estimator attitude``).

The figure is the inclination difference (RMSE, degrees) from each reference the log has
(ArduPilot ATT, AHR2, NKF1/XKF1; PX4 vehicle_attitude), at our output instants against the
nearest reference sample, from 2 s after our start. A reference is the autopilot's estimate,
not truth: on a vibrating copter it can be the worse of the two, so a difference is an
agreement, and the IMU-only filters' rows are only comparable among themselves.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.estimation.replay.batch import find_logs  # noqa: E402
from companion.estimation.replay.runner import ReplayOptions, replay  # noqa: E402
from companion.estimation.replay.sources import LogReadError, read_flight_log  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DIRS = (REPO / "tests" / "data" / "replay", REPO / "tests" / "data" / "px4-ulog")
CONFIGS = {
    "auto": ReplayOptions(),
    "eskf gps": ReplayOptions(estimator="eskf", heading_from="gps"),
    "vqf": ReplayOptions(estimator="attitude", imu_filter="vqf"),
    "ours": ReplayOptions(estimator="attitude", imu_filter="ours"),
}


def _incl(result: Any) -> dict[str, float]:
    out = {}
    for c in result.comparisons:
        m = c.metrics.get("inclination_deg") or {}
        if m.get("rmse") is not None:
            out[c.name] = float(m["rmse"])
    return out


def _cell(x: float | None) -> str:
    return "" if x is None or not math.isfinite(x) else f"{x:.2f}"


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="*", type=Path, help="logs or directories")
    ap.add_argument("--limit", type=int, default=0, help="at most this many logs")
    ap.add_argument("--quick", action="store_true", help="the first two logs only")
    args = ap.parse_args(argv)
    if args.quick:
        args.limit = 2
    logging.disable(logging.WARNING)  # the ESKF's fault warnings: counted in the table
    logs = find_logs([p for p in (args.paths or DEFAULT_DIRS) if p.exists()])
    if args.limit:
        logs = logs[: args.limit]
    t0 = time.monotonic()
    rows: list[dict[str, Any]] = []
    for path in logs:
        try:
            flight = read_flight_log(path)
        except LogReadError as exc:
            rows.append({"log": path, "error": str(exc).replace(str(path), path.name)})
            continue
        row: dict[str, Any] = {"log": path, "flight": flight, "res": {}}
        for name, opts in CONFIGS.items():
            if name == "eskf gps" and row["res"]["auto"].estimator != "eskf":
                continue
            if not len(flight.imu.t_us):
                continue
            row["res"][name] = replay(flight, opts)
        rows.append(row)
    print(f"## Inclination difference from each log's references, RMSE in degrees "
          f"({len(logs)} logs, {time.monotonic() - t0:.0f} s)\n")
    print("| log | kind | s | IMU Hz | ran (auto) | start s | reference | auto | eskf gps "
          "| vqf | ours |")
    print("| --- | --- | ---: | ---: | --- | ---: | --- | ---: | ---: | ---: | ---: |")
    per_config: dict[str, list[float]] = {k: [] for k in CONFIGS}
    pairs: list[tuple[float, float]] = []  # (vqf, ours) per log, first reference
    for row in rows:
        name = Path(row["log"]).name
        if "error" in row:
            print(f"| {name} | unread | | | {row['error']} | | | | | | |")
            continue
        res = row["res"]
        if not res:
            print(f"| {name} | {row['flight'].kind} | | | no IMU | | | | | | |")
            continue
        auto = res["auto"]
        span = (int(auto.flight.imu.t_us[-1]) - int(auto.flight.imu.t_us[0])) / 1e6
        ran = "ESKF" if auto.estimator == "eskf" else f"IMU-only {auto.imu_filter}"
        start = auto.start.started_at_s
        incl = {k: _incl(r) for k, r in res.items()}
        refs = list(incl["auto"]) or ["(none)"]
        for i, ref in enumerate(refs):
            cells = [_cell(incl.get(k, {}).get(ref)) for k in CONFIGS]
            head = (f"| {name} | {auto.flight.kind} | {span:.0f} | "
                    f"{auto.timelines['imu'].rate_hz or 0:.0f} | {ran} | {_cell(start)} "
                    if i == 0 else "| | | | | | ")
            print(f"{head}| {ref} | " + " | ".join(cells) + " |")
        first = refs[0]
        for k in CONFIGS:
            v = incl.get(k, {}).get(first)
            if v is not None and (k != "auto" or auto.estimator == "eskf"):
                per_config[k].append(v)
        v, o = incl["vqf"].get(first), incl["ours"].get(first)
        if v is not None and o is not None:
            pairs.append((v, o))
    print("\n## Summary over logs (first reference of each log)\n")
    print("| replay | logs | median RMSE | mean RMSE |")
    print("| --- | ---: | ---: | ---: |")
    labels = {"auto": "ESKF, default heading (where it ran)",
              "eskf gps": "ESKF, heading from the GPS course only",
              "vqf": "IMU-only VQF", "ours": "IMU-only ours"}
    for k, vals in per_config.items():
        if vals:
            print(f"| {labels[k]} | {len(vals)} | {np.median(vals):.2f} | {np.mean(vals):.2f} |")
    if pairs:
        a = np.array(pairs)
        better = int((a[:, 0] < a[:, 1]).sum())
        print(f"\nIMU-only, per log: VQF closer to the reference on {better} of {len(a)} logs; "
              f"median ours / VQF = {np.median(a[:, 1] / a[:, 0]):.2f}")
    eskf_ran = sum(1 for r in rows if r.get("res") and r["res"]["auto"].estimator == "eskf")
    with_gps = sum(1 for r in rows if r.get("res") and r["flight"].gps is not None)
    print(f"\nESKF ran on {eskf_ran} of {with_gps} logs with GPS messages; "
          f"{time.monotonic() - t0:.0f} s in all")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("replay_logs", ["companion/estimation"],
                          lambda: main(sys.argv[1:])))
