"""`companion`: the one command-line entry point (run, sim, params, logs, drivers, monitor, ...).

Thin by design: parse, build, call the library, print. Every subsystem adds its own
sub-commands through an `add_commands(subparsers)` function, so this file only routes.
"""

from __future__ import annotations

import argparse
import contextlib
import faulthandler
import logging
import os
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion import __version__
from companion.cli_common import add_runtime_arguments, config_from_args, print_summary
from companion.core.config import ConfigError
from companion.core.lazy import load
from companion.liveview import live_view_bridges
from companion.vehicle import VEHICLE, apply_device_ports, load_vehicle_config

log = logging.getLogger("companion")


# ---------------------------------------------------------------------------- shared helpers
def setup_logging(verbosity: int) -> None:
    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(asctime)s %(levelname).1s %(name)s: %(message)s",
                        datefmt="%H:%M:%S", stream=sys.stderr)


def cmd_params(args: argparse.Namespace) -> int:
    from companion.core.params import ParamError, format_value
    from companion.runtime import declared_registry

    cfg = load_vehicle_config(args.config)
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


def cmd_run(args: argparse.Namespace) -> int:
    from companion.core.clock import every
    from companion.runtime import Runtime, RuntimeOptions, status_line
    from companion.watchdog.manager import EXIT_ESCALATED

    cfg = config_from_args(args)
    apply_device_ports(cfg, {row.name: getattr(args, f"device_{row.name}", None)
                             for row in VEHICLE.devices()})
    while True:
        rt = Runtime(cfg, RuntimeOptions(extra_bridges=live_view_bridges(cfg)))
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
        if rt.manager.escalated is not None:
            print(f"error: thread {rt.manager.escalated} failed (restart intensity exceeded); "
                  f"exiting with {EXIT_ESCALATED} for the service manager to restart the runtime",
                  file=sys.stderr)
            return EXIT_ESCALATED
        if reason != "reboot":
            return 0
        print("reboot requested: restarting the runtime", file=sys.stderr)


def _provider(module: str, attr: str) -> Callable[..., Any]:
    """A sub-command provider, imported when the parser is built.

    Every provider is part of this package, so a failing import is a broken installation: it
    stops the CLI at start with the module's name, instead of a command that silently vanishes
    (or a runtime that flies without a thread)."""
    try:
        return load(f"{module}:{attr}")  # type: ignore[no-any-return]
    except LookupError as exc:
        raise SystemExit(f"companion: cannot load {module}.{attr}: {exc} (a broken installation: "
                         "reinstall with `pip install -e .` or `make test`)") from None


def _rerun_frames(**kwargs: Any) -> Any:
    """The live view's adapter for `companion horizon stream --rerun` (imports rerun on use)."""
    from companion.liveview.horizon_frames import RerunFrames

    return RerunFrames(**kwargs)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="companion", description="On-board runtime and ground toolkit for fixed-wing UAV research.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more console output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    run = sub.add_parser("run", help="run on real hardware")
    add_runtime_arguments(run)
    for row in VEHICLE.devices():  # --imu PORT, --gps PORT ...: one per device of the table
        run.add_argument(f"--{row.name}", dest=f"device_{row.name}", metavar="PORT",
                         help=f"{row.name} serial port, overrides the configuration "
                              f"({row.summary})")
    run.set_defaults(func=cmd_run, fast_exit=True)

    _provider("companion.sim.cli", "add_commands")(sub, add_runtime_arguments)

    _add_params(sub)

    logs = sub.add_parser("logs", help="convert, inspect, export, report and view flight logs")
    logs_sub = logs.add_subparsers(dest="logs_command", metavar="ACTION", required=True)
    for module in ("companion.logs.cli", "companion.report.cli", "companion.liveview.cli"):
        _provider(module, "add_commands")(logs_sub)

    drivers = sub.add_parser("drivers", help="device driver tools (replay a capture)")
    drivers_sub = drivers.add_subparsers(dest="drivers_command", metavar="ACTION", required=True)
    _provider("companion.drivers.cli", "add_commands")(drivers_sub)

    estimation = sub.add_parser("estimation", help="estimator tools (replay a PX4/ArduPilot log, carry a gyro calibration to the next flight)")
    estimation_sub = estimation.add_subparsers(dest="estimation_command", metavar="ACTION",
                                               required=True)
    _provider("companion.estimation.replay.cli", "add_commands")(estimation_sub)
    _provider("companion.estimation.calibration_cli", "add_commands")(estimation_sub)

    mon = sub.add_parser("monitor", help="the legacy ground monitor (terminal UI or --json)")
    _provider("legacy_protocol.cli", "add_monitor_arguments")(mon)
    mon.set_defaults(func=_provider("legacy_protocol.cli", "run_monitor"))

    horizon = sub.add_parser("horizon", help="horizon detection tools")
    horizon_sub = horizon.add_subparsers(dest="horizon_command", metavar="ACTION", required=True)
    _provider("horizon.cli", "add_commands")(horizon_sub, rerun_frames=_rerun_frames)

    _provider("gcs_bridge.cli", "add_commands")(sub)
    _provider("companion.deploy", "add_commands")(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    setup_logging(getattr(args, "verbose", 0))
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 2
    if getattr(args, "fast_exit", False):
        # the long-running commands (a flight, a simulation, a fleet): `kill -USR1 PID` writes
        # every thread's Python stack to stderr (the journal under systemd) and the process
        # flies on, which is how a process that will not stop is looked into in the field
        # (an stderr that is no file, such as a test's captured stream, goes without it)
        with contextlib.suppress(OSError, ValueError):
            faulthandler.register(signal.SIGUSR1, all_threads=True, chain=False)
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
