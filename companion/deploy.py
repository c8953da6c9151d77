"""`companion install` / `companion uninstall`: the runtime as a systemd service on the aircraft.

Install writes four things and says each one:

- ``/etc/systemd/system/companion.service``: ``Type=notify`` (the runtime says READY once its
  threads fly and pings the watchdog from the manager's loop, `companion.service`),
  ``Restart=on-failure`` within a start limit, ``WatchdogSec``; exit status 2 (a bad
  configuration) is not restarted, 70 (a flight thread escalated) is;
- ``/etc/companion/companion.toml``: the configuration the runtime reads, kept if it exists;
- ``/var/lib/companion/``: the working and data directory (flights, and the parameter file,
  which turns the disk policy on: LOG_MIN_FREE_MB 500);
- ``/etc/udev/rules.d/99-companion.rules``: example rules that give the IMU, GPS and servo
  board stable names (``/dev/companion-imu`` ...), to be filled in with the devices' serial
  numbers (docs/deploy.md says how), so they do nothing until edited.

Everything goes under ``--prefix`` (default ``/``), so a package build or a test can install
into a directory. What was created is listed in a manifest in the data directory, and
uninstall removes exactly that (flights and parameters only with ``--purge``). With the real
root and without ``--dry-run`` both call ``systemctl`` (daemon-reload, enable/disable).
"""

from __future__ import annotations

import argparse
import grp
import json
import os
import pwd
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import tomli_w

from companion.core.config import Config
from companion.vehicle import VEHICLE, fill_device_defaults
from companion.watchdog.manager import EXIT_ESCALATED

__all__ = ["InstallPlan", "add_commands", "plan_install", "unit_text"]

UNIT_NAME = "companion.service"
MANIFEST = ".install-manifest.json"
WATCHDOG_S = 10
"""The manager wakes every 20 ms and pings every 5 s; 10 s leaves room for a loaded CPU."""


def device_names() -> dict[str, str]:
    """The stable name udev gives each device of the vehicle table: ``/dev/companion-<name>``."""
    return {row.name: f"/dev/companion-{row.name}" for row in VEHICLE.devices()}


@dataclass
class InstallPlan:
    prefix: Path
    user: str
    group: str
    exec_start: list[str]
    unit: Path = field(init=False)
    config: Path = field(init=False)
    data_dir: Path = field(init=False)
    udev_rules: Path = field(init=False)

    def __post_init__(self) -> None:
        root = self.prefix
        self.unit = root / "etc/systemd/system" / UNIT_NAME
        self.config = root / "etc/companion/companion.toml"
        self.data_dir = root / "var/lib/companion"
        self.udev_rules = root / "etc/udev/rules.d/99-companion.rules"

    def installed_path(self, p: Path) -> Path:
        """Where `p` is on the running system (the unit names paths without the prefix)."""
        return Path("/") / p.relative_to(self.prefix)


PARAMS_TEXT = """\
# Parameters of the installed runtime (MAVProxy .parm format); ground stations change them.
LOG_MIN_FREE_MB 500
LOG_MAX_FLIGHTS 0
"""


def _exec_start() -> list[str]:
    """The `companion` of this installation (a venv's script), or this Python with -m."""
    script = Path(sys.executable).parent / "companion"
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script)]
    return [sys.executable, "-m", "companion"]


def plan_install(prefix: Path, user: str | None) -> InstallPlan:
    name = user or os.environ.get("SUDO_USER") or pwd.getpwuid(os.getuid()).pw_name
    try:
        entry = pwd.getpwnam(name)
    except KeyError:
        raise SystemExit(f"companion install: no user {name!r} on this system "
                         "(create it, or pass --user)") from None
    group = grp.getgrgid(entry.pw_gid).gr_name
    return InstallPlan(prefix=prefix, user=name, group=group, exec_start=_exec_start())


def unit_text(plan: InstallPlan) -> str:
    config = plan.installed_path(plan.config)
    data = plan.installed_path(plan.data_dir)
    exec_start = " ".join([*plan.exec_start, "run", "--config", str(config)])
    return f"""\
# Written by `companion install`; `companion uninstall` removes it.
[Unit]
Description=uav-companion on-board runtime (threads, watchdog, logs, MAVLink)
After=network-online.target
Wants=network-online.target
# More than 5 starts in 5 minutes: give up (a restart loop only wears the flight's logs)
StartLimitIntervalSec=300
StartLimitBurst=5

[Service]
Type=notify
NotifyAccess=main
ExecStart={exec_start}
WorkingDirectory={data}
User={plan.user}
Group={plan.group}
SupplementaryGroups=dialout
Restart=on-failure
RestartSec=2
# 2: a bad configuration, which a restart cannot fix; {EXIT_ESCALATED} (a flight thread failed and
# escalated) and crashes are restarted
RestartPreventExitStatus=2
WatchdogSec={WATCHDOG_S}
TimeoutStartSec=90
# closing the logs on a slow disk may take 30 s (the runtime extends this when it stops)
TimeoutStopSec=60
# the backstop for a thread that allocates without bound (the runtime has no per-thread limit)
MemoryMax=1G
Nice=-5

[Install]
WantedBy=multi-user.target
"""


def config_text(plan: InstallPlan) -> str:
    cfg = fill_device_defaults(Config(), VEHICLE)
    for dev, name in device_names().items():
        cfg.devices[dev].port = name
    data = plan.installed_path(plan.data_dir)
    cfg.logs.dir = str(data / "flights")
    cfg.params.file = str(data / "params.parm")
    body = tomli_w.dumps(cfg.to_dict())
    return ("# uav-companion configuration, written by `companion install`.\n"
            "# Devices use the stable names of /etc/udev/rules.d/99-companion.rules (or put\n"
            "# /dev/serial/by-id/... paths here). Set mavlink.endpoints to your radio or the\n"
            "# ground station's address; see docs/flying.md and docs/deploy.md.\n\n" + body)


def udev_text() -> str:
    lines = [
        "# Stable device names for uav-companion, written by `companion install`.",
        "# Fill in each device's values from `udevadm info --attribute-walk /dev/ttyUSB0`",
        "# (idVendor, idProduct and serial of the USB-serial adapter), uncomment the line,",
        "# then `sudo udevadm control --reload && sudo udevadm trigger`.",
        "# A board UART (Raspberry Pi: ttyAMA0 / serial0) needs no rule: name it in the config.",
    ]
    for dev, name in device_names().items():
        lines.append(f'#SUBSYSTEM=="tty", ATTRS{{idVendor}}=="0403", ATTRS{{idProduct}}=="6001", '
                     f'ATTRS{{serial}}=="SERIAL-OF-{dev.upper()}", SYMLINK+="{name[5:]}", '
                     'GROUP="dialout", MODE="0660"')
    return "\n".join(lines) + "\n"


def _write(path: Path, text: str, created: list[str], dry: bool, *, keep: bool = False) -> None:
    if keep and path.exists():
        print(f"kept     {path} (exists)")
        return
    print(f"{'would write' if dry else 'wrote'}    {path}")
    if dry:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    existed = path.exists()
    path.write_text(text, encoding="utf-8")
    if not existed:
        created.append(str(path))


def _systemctl(*args: str) -> None:
    if shutil.which("systemctl") is None:
        print("systemctl not found: enable the unit by hand")
        return
    cmd = ["systemctl", *args]
    print("run     ", " ".join(cmd))
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)
    if done.returncode != 0:
        print(f"         failed ({done.returncode}): {done.stderr.strip()}")


def cmd_install(args: argparse.Namespace) -> int:
    plan = plan_install(Path(args.prefix), args.user)
    dry = bool(args.dry_run)
    created: list[str] = []
    _write(plan.unit, unit_text(plan), created, dry)
    _write(plan.config, config_text(plan), created, dry, keep=True)
    _write(plan.udev_rules, udev_text(), created, dry, keep=True)
    for d in (plan.data_dir, plan.data_dir / "flights"):
        print(f"{'would create' if dry else 'created'}  {d}/")
        if not dry and not d.exists():
            d.mkdir(parents=True)
            created.append(str(d) + "/")
        if not dry and os.getuid() == 0:
            entry = pwd.getpwnam(plan.user)
            os.chown(d, entry.pw_uid, entry.pw_gid)
    # the disk policy on: an aircraft's card must not fill up over a season
    _write(plan.data_dir / "params.parm", PARAMS_TEXT, created, dry, keep=True)
    if not dry:
        if os.getuid() == 0:
            entry = pwd.getpwnam(plan.user)
            os.chown(plan.data_dir / "params.parm", entry.pw_uid, entry.pw_gid)
        manifest = plan.data_dir / MANIFEST
        old = json.loads(manifest.read_text()) if manifest.exists() else []
        manifest.write_text(json.dumps(sorted(set(old) | set(created)), indent=1) + "\n")
    if plan.prefix == Path("/") and not dry:
        _systemctl("daemon-reload")
        if args.enable:
            _systemctl("enable", UNIT_NAME)
            print(f"start it now with: sudo systemctl start {UNIT_NAME}")
    return 0


def cmd_uninstall(args: argparse.Namespace) -> int:
    plan = plan_install(Path(args.prefix), args.user)
    dry = bool(args.dry_run)
    manifest = plan.data_dir / MANIFEST
    if not manifest.exists():
        print(f"companion uninstall: no {manifest}: nothing this tool installed", file=sys.stderr)
        return 1
    if plan.prefix == Path("/") and not dry:
        _systemctl("disable", "--now", UNIT_NAME)
    entries: list[str] = json.loads(manifest.read_text())
    keep_data = not args.purge
    for entry in sorted(entries, key=len, reverse=True):  # files before their directories
        path = Path(entry.rstrip("/"))
        if entry.endswith("/"):
            if keep_data and path.is_relative_to(plan.data_dir):
                continue
            print(f"{'would remove' if dry else 'removed'}  {path}/")
            if not dry:
                shutil.rmtree(path, ignore_errors=True)
        elif path.exists():
            if keep_data and path.is_relative_to(plan.data_dir):
                continue  # the parameters, with the flights
            print(f"{'would remove' if dry else 'removed'}  {path}")
            if not dry:
                path.unlink()
    if not dry:
        if keep_data:
            manifest.unlink()
            print(f"kept     {plan.data_dir}/ (flights, parameters; --purge removes them)")
        elif plan.data_dir.exists():
            shutil.rmtree(plan.data_dir)
            print(f"removed  {plan.data_dir}/")
        if plan.prefix == Path("/"):
            _systemctl("daemon-reload")
    return 0


def add_commands(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    for name, func, text in (("install", cmd_install, "install the runtime as a systemd service"),
                             ("uninstall", cmd_uninstall, "remove what `install` wrote")):
        p = sub.add_parser(name, help=text)
        p.add_argument("--user", help="the account the service runs as (default: the one "
                       "calling sudo, else the current one)")
        p.add_argument("--prefix", default="/", help="install under this directory (default /)")
        p.add_argument("--dry-run", action="store_true", help="say what would be done, do nothing")
        if name == "install":
            p.add_argument("--no-enable", dest="enable", action="store_false",
                           help="do not enable the unit at boot")
        else:
            p.add_argument("--purge", action="store_true",
                           help="also remove the data directory (flights, parameters)")
        p.set_defaults(func=func)
