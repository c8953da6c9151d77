"""`companion estimation replay LOG...`: PX4 or ArduPilot logs through this project's estimator.

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
        "replay", help="run PX4, ArduPilot or MAVLink telemetry logs through our estimator",
        description="Feed a flight controller's IMU and GPS samples through the estimator "
                    "this runtime flies (GPS/INS ESKF; an IMU-only filter, VQF unless told, "
                    "when the log has no GPS fix or the ESKF cannot start) and compare its "
                    "attitude with every attitude the flight controller logged. Writes "
                    "estimate.bin, summary.json and replay.png per log, into "
                    "<DIR>/<log stem>-replay/.")
    p.add_argument("logs", type=Path, nargs="+", metavar="LOG",
                   help="PX4 .ulg, ArduPilot DataFlash .bin or MAVLink .tlog logs, or "
                        "directories searched recursively for .bin/.BIN/.ulg/.tlog")
    p.add_argument("-o", "--output", type=Path, metavar="DIR", default=Path("."),
                   help="where each log's <stem>-replay/ goes (default: the current directory)")
    p.add_argument("--table", type=Path, metavar="CSV",
                   help="also write one row per log (what ran, differences from each "
                        "reference, notes) to this CSV")
    p.add_argument("--estimator", choices=["auto", "eskf", "attitude"], default="auto",
                   help="auto: the ESKF when the log has GPS fixes and it starts, else IMU-only")
    p.add_argument("--imu-filter", default=None, metavar="NAME",
                   help="the IMU-only filter (default vqf; ours, ours_timed, madgwick)")
    p.add_argument("--heading-from", default="auto", metavar="REF",
                   help="where the ESKF's heading starts: auto (default: the GPS course if the "
                        "vehicle is already moving at the first fix, else the log's first "
                        "attitude), gps (the GPS course, as in flight) or a reference "
                        "(ref: the first; ATT, NKF1, vehicle_attitude...)")
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
    p.add_argument("--json", action="store_true", help="print each summary as JSON")
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


def _options(args: argparse.Namespace) -> Any:
    """The replay's options from the command line; ValueError names the bad one."""
    from companion.estimation.imu_filters import DEFAULT_FILTER, resolve
    from companion.estimation.replay.runner import ReplayOptions, replay_params

    options = ReplayOptions(estimator=args.estimator, skip_s=args.skip_s,
                            params=_params(args.param),
                            imu_filter=args.imu_filter or DEFAULT_FILTER,
                            heading_from=args.heading_from)
    replay_params(options.params)
    resolve(options.imu_filter)
    return options


def cmd_replay(args: argparse.Namespace) -> int:
    from companion.estimation.replay.batch import find_logs, output_dirs, table_row, write_table

    try:
        options = _options(args)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_LOG
    logs = find_logs(args.logs)
    if not logs:
        print(f"error: no logs (.bin, .ulg, .tlog) under {', '.join(map(str, args.logs))}",
              file=sys.stderr)
        return EXIT_BAD_LOG
    dirs = output_dirs(logs, args.output)
    status = 0
    rows = []
    for log in logs:
        code, summary, error = _replay_one(log, dirs[log], options, args)
        status = max(status, code)
        rows.append(table_row(summary, log, error))
    if args.table is not None:
        try:
            write_table(rows, args.table)
        except OSError as exc:
            print(f"error: cannot write {args.table}: {exc}", file=sys.stderr)
            return EXIT_OUTPUT
        print(f"wrote {args.table} ({len(rows)} log(s))")
    return status


def _replay_one(log: Path, out_dir: Path, options: Any, args: argparse.Namespace
                ) -> tuple[int, dict[str, Any] | None, str | None]:
    """One log: (exit status, its summary or None, the error line or None)."""
    from companion.core.files import dump_json, write_json_atomic
    from companion.estimation.replay.output import (
        estimator_label,
        summary_dict,
        write_estimate_log,
        write_figure,
    )
    from companion.estimation.replay.runner import replay
    from companion.estimation.replay.sources import LogReadError, read_flight_log

    try:
        flight = read_flight_log(log, strict=args.strict, imu_instance=args.imu_instance)
    except LogReadError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_LOG, None, str(exc)
    result = replay(flight, options)
    files: dict[str, str] = {}
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        files["log"] = str(write_estimate_log(result, out_dir))
        if not args.no_plot and len(result.estimate.t_us):
            files["figure"] = str(write_figure(result, out_dir / "replay.png"))
        files["summary"] = str(out_dir / "summary.json")
        summary = summary_dict(result, files)
        write_json_atomic(out_dir / "summary.json", summary)
    except OSError as exc:
        print(f"error: cannot write {out_dir}: {exc}", file=sys.stderr)
        return EXIT_OUTPUT, None, f"cannot write {out_dir}: {exc}"
    if args.json:
        print(dump_json(summary))
        return 0, summary, None
    imu = summary["timelines"]["imu"]
    gps = summary["timelines"].get("gps")
    print(f"{flight.path.name} ({flight.kind}): IMU {flight.imu.source}, "
          f"{imu['samples_used']} samples at {imu['rate_hz']} Hz, {imu['gaps']} gap(s), "
          f"{imu['clock_jumps']} clock jump(s), {imu['duplicates_dropped']} duplicate(s)"
          + (f"; GPS {flight.gps.source if flight.gps else ''} {gps['samples_used']} fixes"
             if gps else "; no GPS"))
    print(f"estimator: {estimator_label(result)} ({result.estimator_reason})")
    if result.start.started_at_s is not None:
        print(f"started at {result.start.started_at_s:.1f} s (first fix "
              f"{result.start.first_fix_s:.1f} s, heading from {result.start.heading_from})")
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
    return 0, summary, None
