"""A real ArduPlane SITL beside the companion: ArduPilot's autopilot run as a process and wired to
the companion by serial cables made of pseudo-terminals.

The project's own simulator (`companion.sim.world`) plays the devices; this module plays the
flight controller with the real thing, for users who fly the companion beside an autopilot and
for the tests of that link. Nothing of ArduPilot is in the repository and nothing is downloaded:
the binary is given (`--autopilot-binary PATH` or `ARDUPILOT_SITL=PATH`; README: "Testing against
a real autopilot"), and ArduPilot's default parameters for the model (`plane.parm`) are read from
beside it unless a file is named (`--autopilot-defaults`).

`ArduPlaneSitl` starts `arduplane --model plane --speedup S --defaults FILE -I N` in a fresh
working directory (it writes eeprom.bin, logs/ and terrain/ there). Its SERIAL0 is a `PtyCable`:
the autopilot opens one pseudo-terminal, the companion the other (`companion_url`), and a pump
thread copies bytes between them both ways, as a cable would (no pacing, nothing measured).
SERIAL1 is a second cable for a scripted ground station (`ground_url`,
`companion.sim.ardupilot_mission`), or none. Where the machine allows it (`unshare`, user
namespaces), the autopilot runs in a private network namespace, so the UDP port it always opens
for RC input is reachable from nowhere; several instances (`instance`, `-I`) run side by side.
`stop` sends SIGTERM, then SIGKILL after `STOP_TIMEOUT_S`, and closes every descriptor it opened;
if this process dies first, the kernel kills the autopilot (`setpriv --pdeathsig`).
"""

from __future__ import annotations

import functools
import logging
import os
import select
import shutil
import signal
import subprocess
import tempfile
import threading
import time
import tty
from pathlib import Path
from types import TracebackType

log = logging.getLogger(__name__)

SITL_ENV = "ARDUPILOT_SITL"
DEFAULTS_NAME = "plane.parm"
CABLE_BAUD = 921600
OPEN_TIMEOUT_S = 20.0
"""Host seconds the autopilot may take to open its serial ports after it is started."""
STOP_TIMEOUT_S = 5.0
"""Host seconds between SIGTERM and SIGKILL."""
CABLE_BUFFER_BYTES = 65536
"""Bytes a cable holds for a side that does not read; the oldest go first beyond that."""
_PUMP_JOIN_S = 2.0


class SitlError(RuntimeError):
    """The autopilot could not be started, or stopped before it opened its ports."""


class SitlNotFound(SitlError):
    """No ArduPlane SITL binary: the message is one line saying how to give one."""


def find_binary(binary: str | os.PathLike[str] | None = None) -> Path:
    """The ArduPlane SITL binary: `binary`, else the one `ARDUPILOT_SITL` names."""
    given = os.fspath(binary) if binary is not None else os.environ.get(SITL_ENV, "")
    how = (f"give one with --autopilot-binary PATH or {SITL_ENV}=PATH "
           "(README: Testing against a real autopilot; nothing is downloaded)")
    if not given:
        raise SitlNotFound(f"no ArduPlane SITL binary: {how}")
    path = Path(given).expanduser()
    if not path.is_file() or not os.access(path, os.X_OK):
        raise SitlNotFound(f"ArduPlane SITL binary {str(path)!r} is not an executable file: {how}")
    return path.resolve()


def find_defaults(binary: Path, defaults: str | os.PathLike[str] | None = None) -> Path:
    """The default parameter file: `defaults`, else `plane.parm` beside the binary."""
    path = Path(defaults).expanduser() if defaults is not None else binary.parent / DEFAULTS_NAME
    if not path.is_file():
        where = "given" if defaults is not None else "beside the binary"
        raise SitlNotFound(f"ArduPlane default parameters {str(path)!r} ({where}) not found: give "
                           "a file with --autopilot-defaults PATH (ArduPilot's "
                           "Tools/autotest/models/plane.parm)")
    return path.resolve()


@functools.cache
def network_namespaces() -> bool:
    """True when this machine lets an unprivileged user run a program in a private network
    namespace (`unshare --user --map-root-user --net`)."""
    if shutil.which("unshare") is None:
        return False
    try:
        return subprocess.run(["unshare", "--user", "--map-root-user", "--net", "true"],
                              capture_output=True, timeout=10).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


class PtyCable:
    """A serial cable between two programs that each open a device path: two pseudo-terminals
    whose masters a pump thread joins back to back. The autopilot opens `autopilot_path`, the
    companion `companion_path`. Both slaves stay open here too (raw: no echo, no line editing), so
    neither master reads EIO while a side is closed; a side that does not read loses the oldest
    bytes beyond `CABLE_BUFFER_BYTES` (`dropped_bytes`), and the writer is never held back."""

    def __init__(self, name: str, baud: int = CABLE_BAUD) -> None:
        self.name = name
        self.baud = baud
        self.dropped_bytes = 0
        self._fds: list[int] = []
        try:
            masters, paths = [], []
            for _ in range(2):
                master, slave = os.openpty()
                self._fds += [master, slave]
                tty.setraw(slave)
                os.set_blocking(master, False)
                masters.append(master)
                paths.append(os.ttyname(slave))
            self._wake_r, self._wake_w = os.pipe()
            self._fds += [self._wake_r, self._wake_w]
        except BaseException:
            self._close_fds()
            raise
        self._masters = masters
        self.autopilot_path, self.companion_path = paths
        self._thread = threading.Thread(target=self._pump, name=f"pty-cable-{name}", daemon=True)
        self._thread.start()

    @property
    def companion_url(self) -> str:
        """The companion's end as a port setting: ``/dev/pts/N,BAUD`` (as pymavlink takes it)."""
        return f"{self.companion_path},{self.baud}"

    def _pump(self) -> None:
        pending = [bytearray(), bytearray()]  # pending[i]: read from side i, for side 1 - i
        while True:
            wanted = [self._masters[1 - i] for i in range(2) if pending[i]]
            try:
                readable, writable, _ = select.select([self._wake_r, *self._masters], wanted, [])
            except (OSError, ValueError):
                return
            if self._wake_r in readable:
                return
            for i, master in enumerate(self._masters):
                if master in readable:
                    try:
                        pending[i] += os.read(master, CABLE_BUFFER_BYTES)
                    except BlockingIOError:
                        pass
                    except OSError as exc:
                        log.warning("cable %s: read failed (%s): the pump stops", self.name, exc)
                        return
                    excess = len(pending[i]) - CABLE_BUFFER_BYTES
                    if excess > 0:
                        del pending[i][:excess]
                        self.dropped_bytes += excess
                far = self._masters[1 - i]
                if pending[i] and (far in writable or master in readable):
                    try:
                        del pending[i][:os.write(far, pending[i])]
                    except BlockingIOError:
                        pass
                    except OSError as exc:
                        log.warning("cable %s: write failed (%s): the pump stops", self.name, exc)
                        return

    def close(self) -> None:
        if self._thread.is_alive():
            os.write(self._wake_w, b"x")
            self._thread.join(_PUMP_JOIN_S)
        self._close_fds()

    def _close_fds(self) -> None:
        for fd in self._fds:
            try:
                os.close(fd)
            except OSError:
                pass
        self._fds = []


class ArduPlaneSitl:
    """One ArduPlane SITL process with its cables (a context manager: `start`, `stop`).

    `binary` and `defaults` as `find_binary` / `find_defaults`; `speedup` scales simulated time
    (its clock runs `speedup` times the host's); `instance` is its `-I` (ports shifted by 10 N),
    `sysid` its MAVLink system id (default `instance + 1`); `ground` adds the SERIAL1 cable for a
    ground station. `workdir`: keep its eeprom, logs and terrain there (default: a temporary
    directory removed on stop). `isolate_network`: run it in a private network namespace (None:
    when `network_namespaces()` allows)."""

    def __init__(self, binary: str | os.PathLike[str] | None = None, *, speedup: float = 1.0,
                 defaults: str | os.PathLike[str] | None = None, instance: int = 0,
                 sysid: int | None = None, ground: bool = True, home: str | None = None,
                 workdir: str | os.PathLike[str] | None = None,
                 isolate_network: bool | None = None) -> None:
        self.binary = find_binary(binary)
        self.defaults = find_defaults(self.binary, defaults)
        if speedup <= 0:
            raise ValueError(f"speedup must be positive, not {speedup}")
        self.speedup = speedup
        self.instance = instance
        self.sysid = instance + 1 if sysid is None else sysid
        self.ground = ground
        self.home = home
        self._keep_dir = workdir is not None
        self.workdir = Path(workdir) if workdir is not None else None
        self.isolate_network = isolate_network
        self.proc: subprocess.Popen[bytes] | None = None
        self._cmd: list[str] = []
        self.companion_cable: PtyCable | None = None
        self.ground_cable: PtyCable | None = None
        self.started_at = 0.0
        """`time.monotonic()` when the process was started."""
        self.opened_s = 0.0
        """Host seconds from the start until the autopilot had opened all its cables."""

    @property
    def companion_url(self) -> str:
        """SERIAL0's companion end (``/dev/pts/N,921600``): the `[devices.autopilot] port`."""
        if self.companion_cable is None:
            raise SitlError("the autopilot is not started")
        return self.companion_cable.companion_url

    @property
    def ground_url(self) -> str:
        """SERIAL1's far end, for a ground station (`ground=True`)."""
        if self.ground_cable is None:
            raise SitlError("the autopilot is not started, or was started without a ground port")
        return self.ground_cable.companion_url

    @property
    def output_path(self) -> Path:
        """The autopilot's stdout and stderr."""
        if self.workdir is None:
            raise SitlError("the autopilot is not started")
        return self.workdir / "arduplane.out"

    def command(self) -> list[str]:
        assert self.companion_cable is not None
        serial1 = (f"uart:{self.ground_cable.autopilot_path}:{CABLE_BAUD}"
                   if self.ground_cable is not None else "none")
        cmd = [str(self.binary), "--model", "plane", "--speedup", f"{self.speedup:g}",
               "--defaults", str(self.defaults), "-I", str(self.instance),
               "--sysid", str(self.sysid),
               "--serial0", f"uart:{self.companion_cable.autopilot_path}:{CABLE_BAUD}",
               "--serial1", serial1, "--serial2", "none"]
        if self.home is not None:
            cmd += ["--home", self.home]
        # The autopilot dies with us, even when we are killed: the kernel signals it when the
        # thread that started it ends, so only the main thread (which lasts as long as the process)
        # asks for it. After unshare, whose change of credentials would clear it.
        if threading.current_thread() is threading.main_thread() and shutil.which("setpriv"):
            cmd = ["setpriv", "--pdeathsig", "KILL", *cmd]
        isolate = self.isolate_network
        if isolate is None:
            isolate = network_namespaces()
            if not isolate:
                log.warning("no private network namespace here (unshare): the autopilot's RC "
                            "input port (UDP %d) is open on every interface",
                            5501 + 10 * self.instance)
        if isolate:
            cmd = ["unshare", "--user", "--map-root-user", "--net", *cmd]
        return cmd

    def start(self) -> ArduPlaneSitl:
        """Start the process and wait (bounded) until it has opened its cables."""
        if self.proc is not None:
            raise SitlError("the autopilot is already started")
        try:
            if self.workdir is None:
                self.workdir = Path(tempfile.mkdtemp(prefix=f"arduplane-{self.instance}-"))
            else:
                self.workdir.mkdir(parents=True, exist_ok=True)
            self.companion_cable = PtyCable(f"serial0-{self.instance}")
            if self.ground:
                self.ground_cable = PtyCable(f"serial1-{self.instance}")
            self._launch()
        except BaseException:
            self.stop()
            raise
        return self

    def _launch(self) -> None:
        cmd = self._cmd = self.command()
        log.info("starting %s", " ".join(cmd))
        with open(self.output_path, "wb") as out:
            self.started_at = time.monotonic()
            self.proc = subprocess.Popen(cmd, cwd=self.workdir, stdin=subprocess.DEVNULL,
                                         stdout=out, stderr=subprocess.STDOUT)
        self._wait_open()

    def kill(self) -> int | None:
        """SIGKILL the autopilot and leave its cables in place: what a flight controller's loss
        of power or a crash looks like from the companion's side of the wire (the port stays,
        the bytes stop). Returns the exit code (None: it was not running)."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.kill()
        code = self.proc.wait()
        self.proc = None
        return code

    def restart(self) -> ArduPlaneSitl:
        """Start the autopilot again after `kill`, on the same cables and working directory (so
        with the parameters it had saved): a power cycle. Bounded as `start`."""
        if self.companion_cable is None:
            raise SitlError("the autopilot was never started: start, not restart")
        if self.running():
            raise SitlError("the autopilot is still running: kill it first")
        self.proc = None
        try:
            self._launch()
        except BaseException:
            self.stop()
            raise
        return self

    def _wait_open(self) -> None:
        paths = [c.autopilot_path for c in (self.companion_cable, self.ground_cable) if c]
        deadline = self.started_at + OPEN_TIMEOUT_S
        assert self.proc is not None
        while True:
            text = self.output()
            if all(f"Opened {path}" in text for path in paths):
                self.opened_s = time.monotonic() - self.started_at
                return
            code = self.proc.poll()
            if code is not None or time.monotonic() > deadline:
                why = (f"exited with code {code}" if code is not None
                       else f"did not open its serial ports within {OPEN_TIMEOUT_S:g} s")
                last = (text.strip().splitlines() or ["(no output)"])[-1]
                raise SitlError(f"ArduPlane SITL {why}: {last.strip()[:200]} "
                                f"(command: {' '.join(self._cmd)})")
            time.sleep(0.02)

    def output(self) -> str:
        """What the autopilot printed so far."""
        try:
            return self.output_path.read_text(errors="replace")
        except (OSError, SitlError):
            return ""

    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self) -> int | None:
        """SIGTERM, SIGKILL after `STOP_TIMEOUT_S`; close the cables; remove a temporary working
        directory. Returns the exit code (None: never started)."""
        code = None
        if self.proc is not None:
            if self.proc.poll() is None:
                self.proc.send_signal(signal.SIGTERM)
                try:
                    self.proc.wait(STOP_TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    log.warning("ArduPlane SITL ignored SIGTERM for %g s: killed", STOP_TIMEOUT_S)
                    self.proc.kill()
                    self.proc.wait()
            code = self.proc.returncode
            self.proc = None
        for cable in (self.companion_cable, self.ground_cable):
            if cable is not None:
                cable.close()
        self.companion_cable = self.ground_cable = None
        if self.workdir is not None and not self._keep_dir:
            shutil.rmtree(self.workdir, ignore_errors=True)
            self.workdir = None
        return code

    def __enter__(self) -> ArduPlaneSitl:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()
