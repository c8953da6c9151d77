"""Command-line pieces shared by `companion run` (companion.cli) and `companion sim`
(companion.sim.cli): the runtime's options, the configuration they build, the final summary.

It sits in the application layer, under both commands, so the simulator's CLI does not import the
main CLI that dispatches to it (see docs/architecture.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from companion.core.config import Config, apply_override
from companion.vehicle import load_vehicle_config

__all__ = ["add_runtime_arguments", "config_from_args", "print_summary"]


def add_runtime_arguments(p: argparse.ArgumentParser) -> None:
    """Options shared by `run` and `sim`: configuration, endpoints, duration."""
    p.add_argument("--config", type=Path, help="TOML configuration file")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a configuration value, e.g. devices.imu.port=/dev/ttyUSB0")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="programmed execution time in seconds (default: MGR_EXEC_TIME_S, 0 = until stopped)")
    p.add_argument("--mavlink", action="append", default=None, metavar="URL",
                   help="MAVLink endpoint as a pymavlink connection string (repeatable; "
                        "default udpout:127.0.0.1:14550); 'none' disables MAVLink")
    p.add_argument("--legacy-dest", metavar="HOST:PORT", help="where legacy UDP messages go")
    p.add_argument("--legacy-listen", type=int, metavar="PORT", help="legacy UDP command port")
    p.add_argument("--legacy-allow", action="append", default=None, metavar="CIDR",
                   help="networks allowed to send legacy commands (repeatable)")
    p.add_argument("--no-legacy", action="store_true", help="disable the legacy UDP protocol")
    p.add_argument("--log-dir", type=Path, help="root directory of flight directories")
    p.add_argument("--params-file", type=Path, help="parameter file (persisted changes)")
    p.add_argument("--vehicle-id", type=int, help="MAVLink system id / legacy vehicle id")
    p.add_argument("--rerun", action="store_true", help="stream to a rerun viewer")
    p.add_argument("--rerun-save", type=Path, metavar="PATH", help="write the rerun stream to a .rrd")
    p.add_argument("--json", action="store_true", help="print the final summary as JSON")


def config_from_args(args: argparse.Namespace) -> Config:
    cfg = load_vehicle_config(args.config)
    for item in args.overrides:
        apply_override(cfg, item)
    if args.mavlink is not None:
        cfg.mavlink.endpoints = [] if args.mavlink == ["none"] else list(args.mavlink)
    if args.legacy_dest:
        cfg.legacy.dest = args.legacy_dest
    if args.legacy_listen is not None:
        cfg.legacy.listen = args.legacy_listen
    if args.legacy_allow:
        cfg.legacy.allow = list(args.legacy_allow)
    if args.no_legacy:
        cfg.legacy.enabled = False
    if args.log_dir is not None:
        cfg.logs.dir = str(args.log_dir)
    if args.params_file is not None:
        cfg.params.file = str(args.params_file)
    if args.vehicle_id is not None:
        cfg.vehicle.id = args.vehicle_id
    if getattr(args, "rerun", False):
        cfg.rerun.enabled = True
    if getattr(args, "rerun_save", None):
        cfg.rerun.save = str(args.rerun_save)
    return cfg


def print_summary(summary: dict[str, Any], as_json: bool) -> None:
    import json

    if as_json:
        print(json.dumps(summary, indent=2, default=str))
        return
    print(f"flight directory: {summary['flight_dir']}")
    print(f"stopped: {summary.get('stop_reason')}")
    print(f"{'thread':<12}{'cycles':>9}{'rate Hz':>9}{'restarts':>9}{'stalls':>7}"
          f"{'step us':>9}{'missed':>7}{'log drop':>9}")
    for t in summary["threads"]:
        print(f"{t['name']:<12}{t['cycles']:>9}{t['rate_hz']:>9.2f}{t['restarts']:>9}"
              f"{t['stalls']:>7}{t['mean_step_us']:>9.1f}{t['missed_deadlines']:>7}"
              f"{t['log_dropped']:>9}")
    for link in summary.get("messages", []):
        counts = ", ".join(f"{k}={v}" for k, v in link.items()
                           if k != "link" and isinstance(v, int | float) and v)
        print(f"link {link.get('link') or 'mavlink ' + str(link.get('endpoint', '?'))}: {counts}")
    if "simulator" in summary:
        sim = summary["simulator"]
        print(f"simulator: {sim.get('sim_time_s')} s flown, real-time factor "
              f"{sim.get('real_time_factor')}, stop: {sim.get('stop')}")
    files = summary.get("files", {})
    if files:
        total = sum(files.values())
        print(f"files: {len(files)}, {total / 1e6:.2f} MB: " + ", ".join(
            f"{n} {s / 1e3:.0f} kB" for n, s in files.items()))
    print("convert logs with: companion logs convert " + summary["flight_dir"])


# ---------------------------------------------------------------------------- commands
