"""`companion`: the one command-line entry point (run, sim, params, logs, drivers, monitor, ...).

Thin by design: parse, build, call the library, print. Every subsystem adds its own
sub-commands through an `add_commands(subparsers)` function, so this file only routes.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion import __version__
from companion.config import Config, ConfigError, apply_override, load_config

log = logging.getLogger("companion")


# ---------------------------------------------------------------------------- shared helpers
def setup_logging(verbosity: int) -> None:
    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(asctime)s %(levelname).1s %(name)s: %(message)s",
                        datefmt="%H:%M:%S", stream=sys.stderr)


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
    cfg = load_config(args.config)
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
def cmd_run(args: argparse.Namespace) -> int:
    from companion.runtime import Runtime, RuntimeOptions, every, status_line

    cfg = config_from_args(args)
    if args.imu:
        cfg.devices.imu.port = args.imu
    if args.gps:
        cfg.devices.gps.port = args.gps
    if args.servo:
        cfg.devices.servo.port = args.servo
    while True:
        rt = Runtime(cfg, RuntimeOptions())
        for issue in rt.param_issues:
            print(f"warning: {issue} (default used)", file=sys.stderr)
        if sys.stderr.isatty() and args.verbose == 0:
            mgr = rt.manager
            mgr.on_tick.append(every(1.0, lambda m=mgr: print(  # type: ignore[misc]
                "\r" + status_line(m)[:200], end="", file=sys.stderr, flush=True)))
        reason = rt.run(args.duration)
        if sys.stderr.isatty():
            print(file=sys.stderr)
        print_summary(rt.summary(), args.json)
        if reason != "reboot":
            return 0
        print("reboot requested: restarting the runtime", file=sys.stderr)


def cmd_params(args: argparse.Namespace) -> int:
    from companion.params import ParamError, format_value
    from companion.runtime import declared_registry

    cfg = load_config(args.config)
    reg = declared_registry(cfg)
    path = Path(args.file or cfg.params.file)
    issues = reg.attach_file(path)
    for issue in issues:
        print(f"warning: {issue} (default used)", file=sys.stderr)
    action = args.params_action or "show"
    if action == "show":
        for spec in reg.specs():
            value = reg.get(spec.name)
            flag = "" if value == spec.default else " *"
            print(f"{spec.name:<17}{format_value(spec.ptype, value):>12} {spec.unit:<6}"
                  f"[{format_value(spec.ptype, spec.min)}..{format_value(spec.ptype, spec.max)}]"
                  f"{flag}  {spec.description if args.long else ''}".rstrip())
        return 0
    if action == "get":
        try:
            spec = reg.spec(args.name)
        except ParamError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        print(format_value(spec.ptype, reg.get(args.name)))
        return 0
    if action == "set":
        try:
            value = float(args.value)
            new = reg.set(args.name, value)
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        if not reg.flush():
            reg.save(path)
        print(f"{args.name} = {format_value(reg.spec(args.name).ptype, new)} (saved to {path})")
        return 0
    if action == "export":
        fmt = args.format or ("params" if str(args.out).endswith(".params") else "parm")
        reg.save(Path(args.out), fmt=fmt, sysid=cfg.vehicle.id, compid=1)
        print(f"exported {len(reg)} parameters to {args.out} ({fmt})")
        return 0
    if action == "import":
        bad = reg.load(Path(args.source))
        for issue in bad:
            print(f"warning: {issue} (not applied)", file=sys.stderr)
        reg.save(path)
        print(f"imported {args.source} into {path}; {len(bad)} line(s) refused")
        return 1 if bad else 0
    return 2


def _add_params(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("params", help="show, get, set, export or import parameters")
    p.add_argument("--config", type=Path)
    p.add_argument("--file", type=Path, help="parameter file (default from the configuration)")
    ps = p.add_subparsers(dest="params_action")
    show = ps.add_parser("show", help="list every parameter (* = changed from default)")
    show.add_argument("--long", action="store_true", help="with descriptions")
    p.set_defaults(long=False)
    g = ps.add_parser("get")
    g.add_argument("name")
    s = ps.add_parser("set")
    s.add_argument("name")
    s.add_argument("value")
    e = ps.add_parser("export", help="write a QGroundControl .params or MAVProxy .parm file")
    e.add_argument("out", type=Path)
    e.add_argument("--format", choices=["params", "parm"])
    i = ps.add_parser("import", help="apply a .params or .parm file")
    i.add_argument("source", type=Path)
    p.set_defaults(func=cmd_params)


def _optional(module: str, attr: str) -> Callable[..., Any] | None:
    """Sub-command providers are imported lazily so one broken extra cannot stop the CLI."""
    try:
        return getattr(importlib.import_module(module), attr)  # type: ignore[no-any-return]
    except (ImportError, AttributeError) as exc:
        log.debug("%s.%s unavailable: %s", module, attr, exc)
        return None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="companion", description="On-board runtime and ground toolkit for fixed-wing UAV research.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more console output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    run = sub.add_parser("run", help="run on real hardware")
    add_runtime_arguments(run)
    run.add_argument("--imu", metavar="PORT", help="IMU serial port (overrides the configuration)")
    run.add_argument("--gps", metavar="PORT", help="GPS serial port")
    run.add_argument("--servo", metavar="PORT", help="servo-board serial port")
    run.set_defaults(func=cmd_run, fast_exit=True)

    sim_add = _optional("companion.sim.cli", "add_commands")
    if sim_add is not None:
        sim_add(sub, add_runtime_arguments)

    _add_params(sub)

    logs = sub.add_parser("logs", help="convert, inspect, export, report and view flight logs")
    logs_sub = logs.add_subparsers(dest="logs_command", metavar="ACTION", required=True)
    for module in ("companion.logs.cli", "companion.report.cli"):
        add = _optional(module, "add_commands")
        if add is not None:
            add(logs_sub)

    drivers = sub.add_parser("drivers", help="device driver tools (replay a capture)")
    drivers_sub = drivers.add_subparsers(dest="drivers_command", metavar="ACTION", required=True)
    add = _optional("companion.drivers.cli", "add_commands")
    if add is not None:
        add(drivers_sub)

    monitor_args = _optional("legacy_protocol.cli", "add_monitor_arguments")
    monitor_run = _optional("legacy_protocol.cli", "run_monitor")
    if monitor_args is not None and monitor_run is not None:
        mon = sub.add_parser("monitor", help="the legacy ground monitor (terminal UI or --json)")
        monitor_args(mon)
        mon.set_defaults(func=monitor_run)

    horizon = sub.add_parser("horizon", help="horizon detection tools")
    horizon_sub = horizon.add_subparsers(dest="horizon_command", metavar="ACTION", required=True)
    add = _optional("horizon.cli", "add_commands")
    if add is not None:
        add(horizon_sub)

    add = _optional("gcs_bridge.cli", "add_commands")
    if add is not None:
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    setup_logging(getattr(args, "verbose", 0))
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 2
    try:
        rc = int(func(args) or 0)
    except ConfigError as exc:
        print(f"companion: configuration error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    if getattr(args, "fast_exit", False):
        # Every thread is stopped and every log closed by now; skip the interpreter's teardown
        # of numpy/scipy modules (over half a second), so a SIGTERM ends the process promptly.
        sys.stdout.flush()
        sys.stderr.flush()
        logging.shutdown()
        os._exit(rc)
    return rc


if __name__ == "__main__":
    sys.exit(main())
