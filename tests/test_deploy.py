"""`companion install` / `uninstall` into a prefix: the unit passes `systemd-analyze verify`, the
configuration it writes is the one the unit's command runs with (up to READY under a real
notification socket), and uninstall removes exactly what install created."""

from __future__ import annotations

import json
import os
import pwd
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import free_udp_port
from test_service import NotifySocket

from companion.core.config import load_config

USER = pwd.getpwuid(os.getuid()).pw_name


def companion(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion", *args], capture_output=True,
                          text=True, timeout=60, cwd=cwd)


def install(prefix: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    done = companion("install", "--prefix", str(prefix), "--user", USER, *extra)
    assert done.returncode == 0, done.stderr
    return done


def files_under(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")} if root.exists() else set()


def unit_fields(unit: Path) -> dict[str, str]:
    return dict(line.split("=", 1) for line in unit.read_text().splitlines()
                if "=" in line and not line.startswith("#"))


def test_install_writes_a_verified_unit_a_config_and_a_data_directory(tmp_path: Path) -> None:
    prefix = tmp_path / "root"
    out = install(prefix).stdout
    unit = prefix / "etc/systemd/system/companion.service"
    for what in (unit, prefix / "etc/companion/companion.toml",
                 prefix / "etc/udev/rules.d/99-companion.rules", prefix / "var/lib/companion/flights"):
        assert what.exists() and str(what) in out  # and it said so
    f = unit_fields(unit)
    assert f["Type"] == "notify" and f["Restart"] == "on-failure" and f["User"] == USER
    assert int(f["WatchdogSec"]) > 0 and int(f["StartLimitBurst"]) > 0
    assert f["RestartPreventExitStatus"] == "2"  # a bad configuration is not retried
    assert f["WorkingDirectory"] == "/var/lib/companion"  # paths as on the running system
    assert "--config /etc/companion/companion.toml" in f["ExecStart"]
    cfg = load_config(prefix / "etc/companion/companion.toml")
    assert cfg.devices["imu"].port == "/dev/companion-imu"
    assert cfg.logs.dir == "/var/lib/companion/flights"
    # every rule is commented out until the user fills in the devices' serial numbers
    rules = (prefix / "etc/udev/rules.d/99-companion.rules").read_text().splitlines()
    assert all(line.startswith("#") for line in rules)
    # one stable name per device of the vehicle's table (the autopilot's TELEM adapter too)
    assert sum("SYMLINK+=" in line for line in rules) == 4
    assert any("companion-autopilot" in line for line in rules)
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not on this machine: the unit was not verified")
    check = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True,
                           timeout=60)
    assert check.returncode == 0, check.stderr
    assert "companion.service" not in check.stderr  # no warning about our unit


def test_dry_run_writes_nothing_and_an_existing_config_is_kept(tmp_path: Path) -> None:
    prefix = tmp_path / "root"
    out = install(prefix, "--dry-run").stdout
    assert "would write" in out and not prefix.exists()
    mine = prefix / "etc/companion/companion.toml"
    mine.parent.mkdir(parents=True)
    mine.write_text("[vehicle]\nid = 7\n")
    out = install(prefix).stdout
    assert "kept" in out and mine.read_text() == "[vehicle]\nid = 7\n"


def test_uninstall_removes_what_install_created_and_keeps_flights(tmp_path: Path) -> None:
    prefix = tmp_path / "root"
    (prefix / "etc").mkdir(parents=True)
    (prefix / "etc/hostname").write_text("aircraft\n")  # not ours: must survive
    before = files_under(prefix)
    install(prefix)
    flight = prefix / "var/lib/companion/flights/20261124T100000Z"
    flight.mkdir()
    (flight / "imu.bin").write_bytes(b"x")
    dry = companion("uninstall", "--prefix", str(prefix), "--user", USER, "--dry-run")
    assert dry.returncode == 0 and "would remove" in dry.stdout
    assert (prefix / "etc/systemd/system/companion.service").exists()
    done = companion("uninstall", "--prefix", str(prefix), "--user", USER)
    assert done.returncode == 0, done.stderr
    assert not (prefix / "etc/systemd/system/companion.service").exists()
    assert not (prefix / "etc/companion/companion.toml").exists()
    assert (flight / "imu.bin").exists()  # flights are kept without --purge
    assert (prefix / "etc/hostname").read_text() == "aircraft\n"
    again = companion("uninstall", "--prefix", str(prefix), "--user", USER)
    assert again.returncode == 1 and "nothing this tool installed" in again.stderr
    install(prefix)
    purge = companion("uninstall", "--prefix", str(prefix), "--user", USER, "--purge")
    assert purge.returncode == 0, purge.stderr
    left = files_under(prefix) - before
    assert all((prefix / p).is_dir() and not any((prefix / p).iterdir()) or
               all((prefix / p / q).is_dir() for q in os.listdir(prefix / p))
               for p in left), left  # only empty parent directories remain
    assert not (prefix / "var/lib/companion").exists()


def test_the_units_command_runs_to_ready_and_stops_on_sigterm(tmp_path: Path) -> None:
    """The unit's ExecStart with the installed configuration, as systemd would start it (with
    the data paths and the network moved into the test's directory and loopback): no device
    is connected, so the estimator never gets past its start; READY comes after MGR_READY_S
    anyway, naming what is still starting; SIGTERM (systemctl stop) ends it with STOPPING and
    exit 0."""
    prefix = tmp_path / "root"
    install(prefix)
    f = unit_fields(prefix / "etc/systemd/system/companion.service")
    argv = shlex.split(f["ExecStart"])
    config = prefix / "etc/companion/companion.toml"
    argv[argv.index("--config") + 1] = str(config)
    (tmp_path / "p.parm").write_text("MGR_READY_S 2\n")
    argv += ["--log-dir", str(tmp_path / "flights"), "--params-file", str(tmp_path / "p.parm"),
             "--mavlink", f"udpout:127.0.0.1:{free_udp_port()}",
             "--legacy-listen", str(free_udp_port()),
             "--legacy-dest", f"127.0.0.1:{free_udp_port()}", "--set", "legacy.bind=127.0.0.1"]
    ns = NotifySocket(tmp_path / "notify.sock")
    env = {**os.environ, "NOTIFY_SOCKET": str(ns.path), "WATCHDOG_USEC": "10000000"}
    proc = subprocess.Popen(argv, env=env, cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while not ns.with_key("READY") and time.monotonic() < deadline and proc.poll() is None:
            ns.drain()
        assert ns.with_key("READY"), proc.stderr.read() if proc.poll() is not None else "no READY"
        status = ns.with_key("READY")[0][1]["STATUS"]
        assert "starting: estimator" in status and "silent: imu" in status
        proc.send_signal(signal.SIGTERM)
        _out, err = proc.communicate(timeout=30)
        ns.drain()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        ns.close()
    assert proc.returncode == 0, err[-2000:]
    stopping = ns.with_key("STOPPING")
    assert stopping and "signal SIGTERM" in stopping[0][1]["STATUS"]
    flights = list((tmp_path / "flights").iterdir())
    assert len(flights) == 1 and (flights[0] / "summary.json").exists()
    summary = json.loads((flights[0] / "summary.json").read_text())
    assert summary["stop_reason"] == "signal SIGTERM" and summary["escalated"] is None
