"""`companion monitor`: the legacy-protocol ground monitor, as a TUI or as JSON lines.

The main ``companion`` CLI calls :func:`add_monitor_arguments` on its ``monitor`` sub-parser and
dispatches to :func:`run_monitor`; :func:`add_commands` does both for CLIs following the project's
sub-command convention, and :func:`main` runs the monitor on its own
(``python -m legacy_protocol.cli``).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import time
from typing import Any

from legacy_protocol.codec import Decoded, as_dict
from legacy_protocol.messages import DEFAULT_COMMAND_PORT, DEFAULT_MONITOR_PORT
from legacy_protocol.monitor_link import CommandSender, LinkError, MonitorLink, Received

__all__ = ["add_commands", "add_monitor_arguments", "main", "record_json", "run_monitor"]


def _port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"port '{text}' is not a number") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"port {value} outside 0..65535")
    return value


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port_text = text.rpartition(":")
    if not sep or not host:
        raise argparse.ArgumentTypeError(f"'{text}' is not HOST:PORT")
    port = _port(port_text)
    if port == 0:
        raise argparse.ArgumentTypeError(f"'{text}': port 0 cannot receive commands")
    return host, port


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} must be at least 1")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
    if not value > 0:  # also rejects NaN
        raise argparse.ArgumentTypeError(f"{text} must be above 0")
    return value


def add_monitor_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the monitor's options to ``parser``."""
    parser.add_argument(
        "--listen",
        type=_port,
        default=DEFAULT_MONITOR_PORT,
        metavar="PORT",
        help=f"UDP port the aircraft's messages arrive on (default {DEFAULT_MONITOR_PORT});"
        " several monitors on one host may share it",
    )
    parser.add_argument(
        "--vehicle",
        type=_host_port,
        default=("127.0.0.1", DEFAULT_COMMAND_PORT),
        metavar="HOST:PORT",
        help=f"where commands are sent (default 127.0.0.1:{DEFAULT_COMMAND_PORT})",
    )
    parser.add_argument(
        "--json",
        action="store_true",
        help="no TUI: print every decoded datagram as one JSON line on stdout",
    )
    parser.add_argument(
        "--count",
        type=_positive_int,
        metavar="N",
        help="with --json: stop after N decoded datagrams",
    )
    parser.add_argument(
        "--duration",
        type=_positive_float,
        metavar="S",
        help="with --json: stop after S seconds",
    )


def record_json(rx: Received) -> dict[str, Any]:
    """One decoded datagram as a JSON-ready dict (the shape ``--json`` prints)."""
    if not isinstance(rx.result, Decoded):
        raise ValueError(f"datagram from {rx.source} was not decoded: {rx.result}")
    h = rx.result.header
    return {
        "rx_time": round(rx.rx_wall_s, 6),
        "source": f"{rx.source[0]}:{rx.source[1]}",
        "type": rx.result.name,
        "vehicle": h.vehicle_id,
        "seq": h.seq,
        "time_ns": h.t_ns,
        "fields": as_dict(rx.result.payload),
    }


def _run_json(link: MonitorLink, count: int | None, duration_s: float | None) -> int:
    printed = 0
    deadline = None if duration_s is None else time.monotonic() + duration_s
    while True:
        wait_s = 0.5
        if deadline is not None:
            wait_s = deadline - time.monotonic()
            if wait_s <= 0:
                return 0
        if not link.wait(min(wait_s, 0.5)):
            continue
        for rx in link.poll():
            if not isinstance(rx.result, Decoded):
                print(
                    f"malformed datagram from {rx.source[0]}:{rx.source[1]}"
                    f" ({rx.size} bytes): {rx.result}",
                    file=sys.stderr,
                )
                continue
            print(json.dumps(record_json(rx), separators=(",", ":")), flush=True)
            printed += 1
            if count is not None and printed >= count:
                return 0


def run_monitor(args: argparse.Namespace) -> int:
    """Run ``companion monitor`` with parsed arguments; returns the exit code."""
    if not args.json and (args.count is not None or args.duration is not None):
        print("monitor: --count and --duration only apply with --json", file=sys.stderr)
        return 2
    host, port = args.vehicle
    try:
        target = (socket.gethostbyname(host), port)
    except OSError as exc:
        print(f"monitor: --vehicle: cannot resolve host '{host}': {exc}", file=sys.stderr)
        return 2
    try:
        link = MonitorLink(args.listen)
    except LinkError as exc:
        print(f"monitor: {exc}", file=sys.stderr)
        return 1
    try:
        if args.json:
            try:
                return _run_json(link, args.count, args.duration)
            except BrokenPipeError:
                # The reader (e.g. `head`) went away: a normal way for a pipeline to end.  Point
                # stdout at /dev/null so the interpreter's final flush does not fail again.
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, sys.stdout.fileno())
                os.close(devnull)
                return 0
            except KeyboardInterrupt:
                return 130
        from legacy_protocol.monitor_app import MonitorApp  # Textual is slow to import

        try:
            sender = CommandSender(target)
        except LinkError as exc:
            print(f"monitor: {exc}", file=sys.stderr)
            return 1
        with sender:
            result = MonitorApp(link, sender).run()
        return int(result or 0)
    finally:
        link.close()


def add_commands(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add the ``monitor`` sub-command to a ``companion``-style sub-parser set."""
    parser = sub.add_parser(
        "monitor",
        help="watch and command aircraft speaking the legacy UDP protocol",
        description="Ground monitor for the legacy UDP protocol: a terminal UI, or JSON lines"
        " with --json.",
    )
    add_monitor_arguments(parser)
    parser.set_defaults(func=run_monitor)


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry point, equivalent to ``companion monitor``."""
    parser = argparse.ArgumentParser(prog="monitor", description="legacy UDP ground monitor")
    add_monitor_arguments(parser)
    return run_monitor(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
