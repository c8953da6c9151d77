"""`companion drivers replay DEVICE FILE`: decode a capture with the real driver.

A command of the tools layer (it reads the vehicle's table for the device names).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from companion.vehicle import VEHICLE


def cmd_replay(args: argparse.Namespace) -> int:
    from companion.drivers.replay import item_to_json, replay

    try:
        data = Path(args.file).read_bytes()
    except OSError as exc:
        print(f"companion drivers replay: cannot read {args.file}: {exc.strerror}", file=sys.stderr)
        return 2
    count = [0]

    def emit(item: object) -> None:
        count[0] += 1
        print(json.dumps(item_to_json(item)), flush=False)

    counters = replay(args.kind, data, emit)
    summary = {"file": str(args.file), "bytes": len(data), "items": count[0], **counters}
    if args.json:
        print(json.dumps({"summary": summary}))
    else:
        print(", ".join(f"{k}={v}" for k, v in summary.items()), file=sys.stderr)
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="feed a raw device capture through the real driver")
    p.add_argument("kind", choices=[row.name for row in VEHICLE.devices() if row.replay])
    p.add_argument("file", type=Path, help="raw bytes as the device sent them")
    p.add_argument("--json", action="store_true", help="print the counter summary as JSON too")
    p.set_defaults(func=cmd_replay)
