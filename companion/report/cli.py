"""``companion logs report`` (``companion logs view`` is in companion.liveview.cli).

Registered by the main CLI on the ``logs`` sub-parsers through `add_commands`. Exit codes: 0 a
report or replay was produced (possibly partial: what is missing is printed), 1 the flight
directory or the output could not be used, 2 usage errors (argparse).

FLIGHT_DIR may also be a flight archive downloaded from the vehicle (saved as ``.bin``, ``.ulg``
or anything): it is unpacked once next to itself and the report is made of the unpacked flight.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

__all__ = ["add_commands", "cmd_report", "main"]


def add_commands(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``report`` to the ``companion logs`` sub-parsers."""
    r = sub.add_parser("report", help="PNG figures and one self-contained HTML page of a flight")
    r.add_argument("flight_dir", type=Path, metavar="FLIGHT_DIR",
                   help="a flight directory, or a downloaded flight archive")
    r.add_argument("-o", "--out", type=Path, help="output directory (default: FLIGHT_DIR/report)")
    r.add_argument("--no-csv-size", action="store_true",
                   help="skip converting the logs to CSV to measure the CSV size")
    r.add_argument("--json", action="store_true", help="print the result as JSON")
    r.set_defaults(func=cmd_report)


def cmd_report(args: argparse.Namespace) -> int:
    from companion.logs.archive import is_archive
    from companion.logs.cli import flight_of_archive
    from companion.report import generate_report

    flight_dir: Path = args.flight_dir
    if is_archive(flight_dir):
        unpacked = flight_of_archive(flight_dir)
        if unpacked is None:
            return 1
        flight_dir = unpacked
    try:
        result = generate_report(flight_dir, args.out, measure_csv=not args.no_csv_size)
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"error: writing the report: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps({
            "html": str(result.html),
            "figures": [str(p) for p in result.figures],
            "missing": result.missing,
            "problems": result.problems,
        }, indent=2))
        return 0
    for problem in result.problems:
        print(f"warning: {problem}", file=sys.stderr)
    for item in result.missing:
        print(f"not drawn: {item}", file=sys.stderr)
    for p in result.figures:
        print(p)
    print(result.html)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry: ``python -m companion.report.cli report FLIGHT_DIR``."""
    parser = argparse.ArgumentParser(prog="companion logs")
    sub = parser.add_subparsers(dest="logs_command", required=True)
    add_commands(sub)
    args = parser.parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
