"""MAVProxy 1.8.75, as a separate non-interactive process, against the bridge on a SyntheticVehicle.

Every test runs the MAVLink bridge on a `support.synthetic_vehicle.SyntheticVehicle`: synthetic
vehicle state (an aircraft in a steady banked circle) under a real ThreadManager, in this
process. No drivers, estimator, control law or simulator run, and the parameters are only
the manager's, the synthetic threads' and the bridge's (not the runtime's set) plus the
test's.

MAVProxy against a whole `companion sim` flight is in test_gcs_clients_sim.py.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

from conftest import free_udp_port, wait_for
from support.synthetic_vehicle import SyntheticVehicle

from companion.core.params import float_param, int_param
from gcs_bridge.signing import new_key_file

EXTRA = [
    int_param("TST_BIG", 0, -(2**31), 2**31 - 1, "", "full int32 range"),
    float_param("TST_F", 1.5, -10.0, 10.0, "m", "a float"),
]
MAVPROXY = Path(sys.executable).with_name("mavproxy.py")


class MavProxy:
    """MAVProxy with commands on stdin and its output collected line by line."""

    def __init__(self, port: int, cwd: Path,
                 modules: str = "param,ftp,cmdlong,signing") -> None:
        self.lines: list[str] = []
        self._lock = threading.Lock()
        self.proc = subprocess.Popen(
            [sys.executable, "-u", str(MAVPROXY), f"--master=udpin:127.0.0.1:{port}", "--no-state",
             f"--default-modules={modules}", "--state-basedir", str(cwd)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            cwd=cwd)
        self._reader = threading.Thread(target=self._read, name="mavproxy-out", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._lock:
                self.lines.append(line.rstrip())

    def cmd(self, text: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(text + "\n")
        self.proc.stdin.flush()

    def wait_line(self, fragment: str, timeout_s: float, start: int = 0) -> str | None:
        found: list[str] = []

        def check() -> bool:
            with self._lock:
                found[:] = [ln for ln in self.lines[start:] if fragment in ln]
            return bool(found)

        return found[0] if wait_for(check, timeout_s, 0.02) else None

    def mark(self) -> int:
        with self._lock:
            return len(self.lines)

    def close(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()  # EOF on stdin ends MAVProxy
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
        self._reader.join(5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


def words(line: str | None) -> list[str]:
    """The last two words of a MAVProxy output line (it may start with the prompt)."""
    assert line is not None
    return line.split()[-2:]


def test_fetch_show_and_set(tmp_path: Path) -> None:
    port = free_udp_port()
    # MAVProxy reads integers bytewise only from a PX4: the link claims one (docs/ground-stations.md)
    with SyntheticVehicle([f"udpout:127.0.0.1:{port}?identity=px4"], extra_params=EXTRA) as v:
        mp = MavProxy(port, tmp_path)
        try:
            t0 = time.monotonic()
            line = mp.wait_line("Received", 25.0)
            fetch_s = time.monotonic() - t0
            assert line is not None, "\n".join(mp.lines)
            assert line.strip().endswith(f"Received {len(v.params)} parameters"), line
            print(f"MAVProxy: {len(v.params)} parameters in {fetch_s:.2f} s from start")
            assert fetch_s < 9.0  # FTP refused at once: a silent vehicle alone costs 11 s
            mark = mp.mark()
            mp.cmd("param show TST_*")
            assert words(mp.wait_line("TST_BIG", 5.0, mark)) == ["TST_BIG", "0"]
            assert words(mp.wait_line("TST_F", 5.0, mark)) == ["TST_F", "1.5"]
            # an integer beyond 2**24 only survives the bytewise encoding
            mp.cmd("param set TST_BIG 123456789")
            mp.cmd("param set TST_F -2.75")
            assert wait_for(lambda: v.params.get("TST_BIG") == 123456789
                            and v.params.get("TST_F") == -2.75, 10.0)
            mark = mp.mark()
            mp.cmd("param show TST_BIG")
            assert words(mp.wait_line("TST_BIG", 5.0, mark)) == ["TST_BIG", "123456789"]
            # a value set on the aircraft side shows up in MAVProxy (PARAM_VALUE broadcast)
            v.params.set("TST_BIG", -42)

            def shows_new_value() -> bool:
                mark = mp.mark()
                mp.cmd("param show TST_BIG")
                line = mp.wait_line("TST_BIG", 2.0, mark)
                return line is not None and words(line) == ["TST_BIG", "-42"]

            assert wait_for(shows_new_value, 10.0, 0.1)
        finally:
            mp.close()


def test_signed_link_with_mavproxy(tmp_path: Path) -> None:
    port = free_udp_port()
    key_file = tmp_path / "mavlink.key"
    passphrase = new_key_file(key_file)
    with SyntheticVehicle([f"udpout:127.0.0.1:{port}?identity=px4"], extra_params=EXTRA,
                          key_file=key_file) as v:
        mp = MavProxy(port, tmp_path)
        try:
            assert mp.wait_line("Received", 25.0) is not None, "\n".join(mp.lines)  # unsigned reads
            mp.cmd("param set TST_F 3.5")
            assert wait_for(lambda: v.bridge.stats()[0]["refused"] >= 1, 5.0)
            assert v.params.get("TST_F") == 1.5
            mp.cmd(f"signing key {passphrase}")
            assert mp.wait_line("Setup signing key", 5.0) is not None
            mp.cmd("param set TST_F 4.5")
            assert wait_for(lambda: v.params.get("TST_F") == 4.5, 10.0)
        finally:
            mp.close()
