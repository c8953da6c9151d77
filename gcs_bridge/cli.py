"""`companion keys`: create and show the MAVLink 2 signing key file."""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

DEFAULT_KEY_FILE = Path.home() / ".uav-companion" / "mavlink.key"


def cmd_keys_new(args: argparse.Namespace) -> int:
    # imported here: every `companion` command builds this parser, and pymavlink (which the
    # signing module's dialect loads) is for the commands that use it
    from gcs_bridge.signing import KeyFileError, new_key_file

    path = Path(args.file)
    try:
        passphrase = new_key_file(path, force=args.force)
    except KeyFileError as exc:
        print(f"companion keys new: {exc}", file=sys.stderr)
        return 1
    key = hashlib.sha256(passphrase.encode("utf-8")).digest()
    print(f"signing key file: {path} (mode 600)")
    print(f"passphrase:       {passphrase}")
    print(f"key (hex):        {key.hex()}")
    print(f'aircraft:  [mavlink] key_file = "{path}" in the configuration file')
    print(f"MAVProxy:  signing key {passphrase}")
    print("QGroundControl: Application Settings > MAVLink > signing key: the passphrase above")
    return 0


def cmd_keys_show(args: argparse.Namespace) -> int:
    from gcs_bridge.signing import KeyFileError, read_key_file

    path = Path(args.file)
    try:
        key, passphrase = read_key_file(path)
    except KeyFileError as exc:
        print(f"companion keys show: {exc}", file=sys.stderr)
        return 1
    print(f"signing key file: {path}")
    print(f"passphrase:       {passphrase}")
    print(f"key (hex):        {key.hex()}")
    print(f"MAVProxy:  signing key {passphrase}")
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:
    keys = sub.add_parser("keys", help="MAVLink 2 signing key file (create, show)")
    keys_sub = keys.add_subparsers(dest="keys_command", metavar="ACTION", required=True)
    new = keys_sub.add_parser("new", help="create a key file with a random passphrase (mode 600)")
    new.add_argument("--file", default=str(DEFAULT_KEY_FILE),
                     help=f"key file to create (default {DEFAULT_KEY_FILE})")
    new.add_argument("--force", action="store_true", help="replace an existing key file")
    new.set_defaults(func=cmd_keys_new)
    show = keys_sub.add_parser("show", help="print the passphrase and key of a key file")
    show.add_argument("--file", default=str(DEFAULT_KEY_FILE),
                      help=f"key file to read (default {DEFAULT_KEY_FILE})")
    show.set_defaults(func=cmd_keys_show)
