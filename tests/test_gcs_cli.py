"""`companion keys`: the sub-commands the bridge adds to the companion CLI."""

from __future__ import annotations

import argparse
import os
import stat
from pathlib import Path

import pytest

from gcs_bridge.cli import add_commands
from gcs_bridge.signing import key_from_text, read_key_file


def run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="companion")
    sub = parser.add_subparsers(dest="command", required=True)
    add_commands(sub)
    args = parser.parse_args(argv)
    return int(args.func(args))


def test_keys_new_and_show(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "k" / "mavlink.key"
    assert run(["keys", "new", "--file", str(path)]) == 0
    out = capsys.readouterr().out
    key, passphrase = read_key_file(path)
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert passphrase in out and key.hex() in out and f"signing key {passphrase}" in out
    assert key == key_from_text(passphrase)
    assert run(["keys", "new", "--file", str(path)]) == 1  # never overwritten by accident
    assert "exists already" in capsys.readouterr().err
    assert read_key_file(path)[1] == passphrase
    assert run(["keys", "show", "--file", str(path)]) == 0
    assert key.hex() in capsys.readouterr().out
    assert run(["keys", "new", "--file", str(path), "--force"]) == 0
    assert read_key_file(path)[1] != passphrase


def test_keys_show_reports_a_bad_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.key"
    bad.write_text("one\ntwo\n")
    assert run(["keys", "show", "--file", str(bad)]) == 1
    err = capsys.readouterr().err
    assert str(bad) in err and "exactly one" in err
    assert run(["keys", "show", "--file", str(tmp_path / "none.key")]) == 1
    assert "cannot read" in capsys.readouterr().err
