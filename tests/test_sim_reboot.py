"""MAVLink reboot restarts the flight program while the (simulated) aircraft flies on."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from conftest import free_udp_port
from pymavlink import mavutil

from companion.logs import read_log


def test_reboot_then_shutdown_over_mavlink(tmp_path: Path) -> None:
    port = free_udp_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255)
    proc = subprocess.Popen(
        [sys.executable, "-m", "companion", "-v", "sim", "--fast", "--log-dir", str(tmp_path / "f"),
         "--params-file", str(tmp_path / "p.parm"), "--mavlink", f"udpout:127.0.0.1:{port}",
         "--legacy-listen", str(free_udp_port()), "--legacy-dest", f"127.0.0.1:{free_udp_port()}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        hb = gcs.wait_heartbeat(timeout=60)
        assert hb is not None
        reboot = mavutil.mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN

        def drain() -> None:
            """Drop whatever is queued, so a late ACK of an earlier command is not read as ours."""
            while gcs.recv_match(blocking=False) is not None:
                pass

        def command(param1: float) -> int:
            # A retransmission reaching the restarted runtime would be a second reboot: wait long
            # for the ACK (a loaded machine is slow) before sending again.
            drain()
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                gcs.mav.command_long_send(gcs.target_system, 1, reboot, 0, param1, 0, 0, 0, 0, 0, 0)
                ack = gcs.recv_match(type="COMMAND_ACK", blocking=True, timeout=5)
                if ack is not None and ack.command == reboot:
                    return int(ack.result)
            proc.terminate()
            _out, err = proc.communicate(timeout=30)
            raise AssertionError(f"no ACK to command {param1:g} in 30 s; runtime log:\n{err[-6000:]}")

        assert command(1) == mavutil.mavlink.MAV_RESULT_ACCEPTED
        # the runtime comes back: heartbeats again after the restart
        time.sleep(0.5)  # let the old incarnation go quiet before looking for the new one
        gcs.recv_match(type="HEARTBEAT", blocking=False)
        assert gcs.wait_heartbeat(timeout=30) is not None
        assert proc.poll() is None
        assert command(2) == mavutil.mavlink.MAV_RESULT_ACCEPTED
        _out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
        if proc.returncode is None or not (proc.stdout is None or proc.stdout.closed):
            proc.communicate()  # reaps it and closes its pipes, whichever way it ended
        gcs.close()
    fdir = next((tmp_path / "f").iterdir())
    imu = read_log(fdir / "imu.bin")
    begins = [m for m in imu.markers if m.kind == "begin"]
    assert len(begins) >= 2 and imu.closed_cleanly
