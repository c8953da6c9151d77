"""`companion estimation replay LOG`: a PX4 or ArduPilot log through this project's estimator.

Registering the command imports nothing but argparse; the readers, the estimator, numpy and
matplotlib load when the command runs, so `companion --help` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

EXIT_BAD_LOG = 2
EXIT_OUTPUT = 1


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay", help="run a PX4, ArduPilot or MAVLink telemetry log through our estimator",
        description="Feed a flight controller's IMU and GPS samples through the estimator "
                    "this runtime flies (GPS/INS ESKF; IMU-only attitude when the log has no "
                    "GPS fix) and compare its attitude with the flight controller's own. "
                    "Writes estimate.bin, summary.json and replay.png.")
    p.add_argument("log", type=Path, help="a PX4 .ulg, an ArduPilot DataFlash .bin or a MAVLink .tlog")
    p.add_argument("-o", "--output", type=Path, metavar="DIR",
                   help="output directory (default: <log stem>-replay/ next to the log)")
    p.add_argument("--estimator", choices=["auto", "eskf", "attitude"], default="auto",
                   help="auto: the ESKF when the log has GPS fixes, else IMU-only")
    p.add_argument("--skip-s", type=float, default=2.0, metavar="S",
                   help="seconds after our estimator starts that are not scored (default 2)")
    p.add_argument("--imu-instance", type=int, metavar="N",
                   help="ArduPilot IMU instance to use (default: the first logged)")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="an estimator parameter (EST_GPS_LAG=0.1 or GPS_LAG=0.1); repeatable")
    p.add_argument("--strict", action="store_true",
                   help="refuse a log with a damaged or cut-short message (default: read what "
                        "is whole, skip damage and report it with byte offsets)")
    p.add_argument("--salvage", action="store_true",
                   help="accepted for older scripts: reading what is whole is the default")
    p.add_argument("--no-plot", action="store_true", help="do not draw replay.png")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=cmd_replay)


def _params(items: list[str]) -> dict[str, float]:
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--param {item!r}: use NAME=VALUE")
        out[name.strip()] = float(value)
    return out


def _fmt(m: dict[str, Any] | None) -> str:
    if not m or m.get("rmse") is None:
        return "-"
    return f"{m['rmse']:.2f}/{m['p95']:.2f}/{m['max']:.2f}"


def cmd_replay(args: argparse.Namespace) -> int:
    from companion.core.files import dump_json, write_json_atomic
    from companion.estimation.replay.output import (
        ESTIMATOR_LABELS,
        summary_dict,
        write_estimate_log,
        write_figure,
    )
    from companion.estimation.replay.runner import ReplayOptions, replay
    from companion.estimation.replay.sources import LogReadError, read_flight_log

    try:
        options = ReplayOptions(estimator=args.estimator, skip_s=args.skip_s,
                                params=_params(args.param))
        from companion.estimation.replay.runner import replay_params

        replay_params(options.params)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_LOG
    try:
        flight = read_flight_log(args.log, strict=args.strict, imu_instance=args.imu_instance)
    except LogReadError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_LOG
    if len(flight.imu.t_us) < 2:
        print(f"error: {args.log}: fewer than 2 IMU samples", file=sys.stderr)
        return EXIT_BAD_LOG
    result = replay(flight, options)
    out_dir = args.output or args.log.with_name(f"{args.log.stem}-replay")
    files: dict[str, str] = {}
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        files["log"] = str(write_estimate_log(result, out_dir))
        if not args.no_plot:
            files["figure"] = str(write_figure(result, out_dir / "replay.png"))
        files["summary"] = str(out_dir / "summary.json")
        summary = summary_dict(result, files)
        write_json_atomic(out_dir / "summary.json", summary)
    except OSError as exc:
        print(f"error: cannot write {out_dir}: {exc}", file=sys.stderr)
        return EXIT_OUTPUT
    if args.json:
        print(dump_json(summary))
        return 0
    imu = summary["timelines"]["imu"]
    gps = summary["timelines"].get("gps")
    print(f"{flight.path.name} ({flight.kind}): IMU {flight.imu.source}, "
          f"{imu['samples_used']} samples at {imu['rate_hz']} Hz, {imu['gaps']} gap(s), "
          f"{imu['clock_jumps']} clock jump(s), {imu['duplicates_dropped']} duplicate(s)"
          + (f"; GPS {flight.gps.source if flight.gps else ''} {gps['samples_used']} fixes"
             if gps else "; no GPS"))
    print(f"estimator: {ESTIMATOR_LABELS[result.estimator]} ({result.estimator_reason})")
    if flight.damage:
        print(f"warning: damaged log: {flight.damage}")
    for note in result.notes:
        print(f"note: {note}")
    if result.comparisons:
        print(f"difference from the flight controller, from {options.skip_s:g} s after our "
              "start (deg, RMSE/p95/max):")
        print(f"  {'reference':<24}{'samples':>8} {'roll':>19}{'pitch':>19}{'yaw':>19}"
              f"{'inclination':>19}")
        for c in result.comparisons:
            m = c.metrics
            print(f"  {c.name:<24}{m.get('samples_compared', 0):>8} "
                  f"{_fmt(m.get('roll_deg')):>19}{_fmt(m.get('pitch_deg')):>19}"
                  f"{_fmt(m.get('yaw_deg')):>19}{_fmt(m.get('inclination_deg')):>19}")
    print(f"wrote {', '.join(files.values())} (replay {result.run_time_s:.1f} s)")
    return 0
