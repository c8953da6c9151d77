"""``companion logs view``: replay a flight's logs into the rerun viewer.

Registered by the main CLI on the ``logs`` sub-parsers through `add_commands`. Exit codes: 0 a
replay was produced (possibly partial: what is missing is printed), 1 the flight directory or the
viewer could not be used, 2 usage errors (argparse).
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path

__all__ = ["add_commands", "cmd_view"]


def add_commands(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``view`` to the ``companion logs`` sub-parsers."""
    v = sub.add_parser("view", help="replay a flight into the rerun viewer on the log timestamps")
    v.add_argument("flight_dir", type=Path, metavar="FLIGHT_DIR")
    dest = v.add_mutually_exclusive_group()
    dest.add_argument("--rerun-save", type=Path, metavar="PATH", help="write an .rrd file instead")
    dest.add_argument("--serve", action="store_true",
                      help="serve to web browsers (gRPC on --grpc-port, web viewer on --web-port) "
                           "until Ctrl-C")
    v.add_argument("--grpc-port", type=int, default=9876)
    v.add_argument("--web-port", type=int, default=9090)
    v.set_defaults(func=cmd_view)


def cmd_view(args: argparse.Namespace) -> int:
    from companion.liveview import ViewerError, replay_flight
    from companion.liveview.replay import replay_into
    from companion.liveview.sink import open_recording
    from companion.report.flight import load_flight

    try:
        if args.serve:
            fd = load_flight(args.flight_dir)
            rec = open_recording(serve=True, name=fd.flight_dir.name, grpc_port=args.grpc_port,
                                 web_port=args.web_port)
            try:
                result = replay_into(fd, rec.stream)
                rec.stream.flush()
                print(f"serving {sum(result.samples.values())} rows: open {rec.web_url} "
                      f"(or connect a viewer to {rec.url}); Ctrl-C to stop", file=sys.stderr)
                _wait_for_stop()
            except KeyboardInterrupt:
                pass
            finally:
                rec.close()
            return 0
        result = replay_flight(args.flight_dir, args.rerun_save, spawn=args.rerun_save is None)
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except ViewerError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    for problem in result.problems:
        print(f"warning: {problem}", file=sys.stderr)
    for item in result.missing:
        print(f"not shown: {item}", file=sys.stderr)
    total = sum(result.samples.values())
    where = args.rerun_save if args.rerun_save else "the rerun viewer"
    print(f"replayed {total} rows on {len(result.samples)} entities to {where}")
    return 0


def _wait_for_stop() -> None:
    """Block until Ctrl-C or SIGTERM (a service manager stopping the server)."""
    stop = threading.Event()
    old = None
    if threading.current_thread() is threading.main_thread():
        old = signal.signal(signal.SIGTERM, lambda _sig, _frame: stop.set())
    try:
        while not stop.wait(0.5):
            pass
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)
