"""`companion sim --horizon-camera`: the camera flies with the aircraft and the estimator uses it.

Real parts only: the real `companion sim` command (JSBSim world in its own process, the
runtime's legacy adapter on a loopback port it picks itself, the detector on rendered frames),
and a lockstep flight where the same camera writes the estimator's slot inside the world's tick.
What could fail: fixes not sent, sent to the wrong port or vehicle, stamped on another clock (the
estimator would then reject or mis-time them), or the world refusing the GO line.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from conftest import free_udp_port

from companion.core.config import Config
from companion.sim.campaign import CampaignError, load_campaign
from companion.sim.lockstep import run_lockstep
from companion.sim.runner import SimOptions

DURATION_S = 40.0
SIMPLE = ("--imu-profile", "simple", "--gps-profile", "simple", "--turbulence", "none")


def sim(tmp: Path, *extra: str, timeout_s: float = 180.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "companion", "sim", "--log-dir", str(tmp / "flights"),
         "--params-file", str(tmp / "params.parm"), "--mavlink", "none",
         "--legacy-dest", f"127.0.0.1:{free_udp_port()}", *SIMPLE, *extra],
        capture_output=True, text=True, timeout=timeout_s)


def estimator(summary: dict[str, Any]) -> dict[str, Any]:
    thread: dict[str, Any] = next(t for t in summary["threads"] if t["name"] == "estimator")
    return thread


def test_a_fast_flight_sends_the_detectors_fixes_and_the_estimator_fuses_them(
        tmp_path: Path) -> None:
    # port 0: the runtime binds any free port and tells the world which in its GO line
    proc = sim(tmp_path, "--fast", "--duration", str(DURATION_S), "--scenario", "turns",
               "--seed", "3", "--horizon-camera", "thesis", "--legacy-listen", "0", "--json")
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    cam = summary["simulator"]["camera"]
    # 10 Hz of simulated time over the world's flight would be 10 x DURATION_S frames; the world
    # renders and detects each frame itself, 50 a host second at 5x, and on a slow 2-core VM it
    # managed 195 of 400 (the code before this change as well). How many a machine keeps up with
    # is a benchmark's figure; the behaviour is that frames are made, sent and fused (below)
    assert cam["frames"] >= 0.3 * 10 * DURATION_S, cam
    assert cam["sent"] >= 0.9 * (cam["frames"] - cam["failures"] - cam["dropped"]), cam
    assert cam["send_errors"] == 0, cam
    est = estimator(summary)
    assert est["restarts"] == 0, est
    # the fixes arrived on the runtime's clock, for this vehicle, and passed the filter's gate:
    # most of what was sent after the filter started (a few seconds in) was fused
    used = est["counters"]["horizon_used"]
    assert used >= 0.7 * (cam["sent"] - 10 * 10), (used, cam)
    # and the IMU's slow block (once a simulated second) gave the filter the part's
    # temperature: counted against the seconds the world flew, which lag the runtime's clock
    # when the host cannot render and detect 50 frames a second (28 readings in a 40 s flight
    # beside a busy core and a second test worker); 10 s for the filter's start
    flown_s = summary["simulator"]["sim_time_s"]
    assert flown_s > 0.5 * DURATION_S, summary["simulator"]
    assert est["counters"]["temperature_readings"] >= flown_s - 10, (est["counters"], flown_s)
    assert summary["sensors"]["imu_profile"] == "simple"


def test_without_the_camera_nothing_is_fused_and_no_camera_is_reported(tmp_path: Path) -> None:
    proc = sim(tmp_path, "--fast", "--duration", "10", "--scenario", "level",
               "--legacy-listen", str(free_udp_port()), "--json")
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    assert "camera" not in summary["simulator"]
    assert estimator(summary)["counters"]["horizon_used"] == 0


def test_the_camera_needs_the_legacy_port_and_says_so(tmp_path: Path) -> None:
    proc = sim(tmp_path, "--fast", "--duration", "5", "--horizon-camera", "thesis",
               "--no-legacy", timeout_s=60.0)
    assert proc.returncode == 2, proc.stderr
    assert "--horizon-camera" in proc.stderr and "--no-legacy" in proc.stderr
    assert "Traceback" not in proc.stderr
    proc = sim(tmp_path, "--fast", "--duration", "5", "--horizon-camera", "foggy",
               timeout_s=60.0)
    assert proc.returncode == 2 and "foggy" in proc.stderr, proc.stderr


def test_a_lockstep_flight_fuses_the_camera_and_repeats_byte_for_byte(tmp_path: Path) -> None:
    def fly(sub: str) -> tuple[dict[str, Any], bytes]:
        cfg = Config()
        cfg.logs.dir = str(tmp_path / sub)
        cfg.params.file = str(tmp_path / sub / "params.parm")
        opts = SimOptions(scenario="turns", seed=5, imu_profile="simple", gps_profile="simple",
                          turbulence="none", horizon_camera="thesis")
        summary = run_lockstep(cfg, opts, 30.0, handle_signals=False)
        return summary, (Path(summary["flight_dir"]) / "estimator.bin").read_bytes()

    first, log1 = fly("a")
    cam = first["simulator"]["camera"]
    assert cam["frames"] == pytest.approx(300, abs=2), cam
    assert estimator(first)["counters"]["horizon_used"] >= 0.7 * (cam["sent"] - 10 * 10), cam
    second, log2 = fly("b")
    counts = ("frames", "detections", "failures", "gross", "dropped", "sent")
    assert [second["simulator"]["camera"][k] for k in counts] == [cam[k] for k in counts]
    assert log1 == log2, "the camera made a lockstep flight irreproducible"


def test_a_campaign_flight_may_carry_the_camera(tmp_path: Path) -> None:
    spec = tmp_path / "c.toml"
    spec.write_text('[[flight]]\nseed = 1\nhorizon_camera = "thesis"\n')
    (flight,) = load_campaign(spec)
    assert flight.settings["horizon_camera"] == "thesis"
    spec.write_text('[[flight]]\nseed = 1\nhorizon_camera = "fog"\n')
    with pytest.raises(CampaignError, match="horizon_camera"):
        load_campaign(spec)


def test_after_a_reboot_the_camera_follows_the_runtimes_new_port(tmp_path: Path) -> None:
    """With `--legacy-listen 0` the rebooted runtime binds another port; the runner names it to
    the world (a DEST line), so the new estimator still gets the camera's fixes."""
    from pymavlink import mavutil

    port = free_udp_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255)
    proc = subprocess.Popen(
        [sys.executable, "-m", "companion", "sim", "--log-dir", str(tmp_path / "flights"),
         "--params-file", str(tmp_path / "params.parm"), "--mavlink", f"udpout:127.0.0.1:{port}",
         "--legacy-dest", f"127.0.0.1:{free_udp_port()}", *SIMPLE, "--fast", "--duration", "60",
         "--scenario", "turns", "--seed", "3", "--horizon-camera", "clean",
         "--legacy-listen", "0", "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    reboot = mavutil.mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN
    try:
        assert gcs.wait_heartbeat(timeout=60) is not None
        acked = False
        for _ in range(6):  # bounded: a loaded machine may lose the first command
            gcs.mav.command_long_send(gcs.target_system, 1, reboot, 0, 1, 0, 0, 0, 0, 0, 0)
            ack = gcs.recv_match(type="COMMAND_ACK", blocking=True, timeout=5)
            if ack is not None and ack.command == reboot:
                acked = ack.result == mavutil.mavlink.MAV_RESULT_ACCEPTED
                break
        assert acked
        out, err = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        gcs.close()
    assert proc.returncode == 0, err[-3000:]
    assert "reboot requested" in err
    summary = json.loads(out)
    # the summary is the rebooted runtime's: its estimator started after the reboot and fused
    # the camera's fixes, which reach it only if the world was told the new port
    assert estimator(summary)["counters"]["horizon_used"] > 100, estimator(summary)
