"""Whole-system SITL runs: the real `companion sim` command, JSBSim, pseudo-terminals, logs."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import free_udp_port

from companion.logs import read_log

SCENARIOS = ["level", "turns", "climb", "aerobatic", "mixed", "auto"]


def sim_cmd(tmp: Path, *extra: str) -> list[str]:
    params = tmp / "params.parm"
    if not params.exists():
        # the simple receiver's 50 ms latency is EST_GPS_LAG's default: told, as these accuracy
        # bounds were set for (estimated, it is unobservable in the level scenario's straight
        # flight, where position then follows the GPS to about 2 m: issue #15 bench)
        tmp.mkdir(parents=True, exist_ok=True)
        params.write_text("EST_GPS_LAGSD 0\n")
    return [sys.executable, "-m", "companion", "sim", "--log-dir", str(tmp / "flights"),
            "--params-file", str(tmp / "params.parm"), "--mavlink", "none",
            "--legacy-listen", str(free_udp_port()),
            "--legacy-dest", f"127.0.0.1:{free_udp_port()}", *SIMPLE_SENSORS, *extra]


# estimator accuracy under the realistic profile: see issue #15 bench (these flights also check
# exact rates, which the realistic receiver's latency jitter and outages would blur)
SIMPLE_SENSORS = ("--imu-profile", "simple", "--gps-profile", "simple", "--turbulence", "none")


def fly_json(tmp: Path, *args: str) -> dict[str, Any]:
    """A `--fast` flight with `args`; asserts a clean exit and returns its JSON summary."""
    proc = subprocess.run(sim_cmd(tmp, "--fast", *args, "--json"),
                          capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary: dict[str, Any] = json.loads(proc.stdout)
    return summary


def flight_dir(tmp: Path) -> Path:
    dirs = sorted((tmp / "flights").iterdir())
    assert len(dirs) == 1, dirs
    return dirs[0]


NOMINAL_HZ = {"imu": 100.0, "gps": 10.0, "servo": 50.0}
"""Each simulated device's record rate: the world's IMU and GPS frames, the servo driver's timer."""


def record_rate_hz(path: Path, index: int) -> float:
    log = read_log(path)
    t = log.data(index)["time_s"]
    assert len(t) > 10, f"{path.name}: only {len(t)} records of format {index}"
    # records per second over the middle 80 % of the flight's time (start-up and shutdown are
    # not steady state). A fixed window of time, not percentiles of the records: a host that
    # holds the world back for a moment makes it send those frames in a burst afterwards, and
    # percentiles of bunched times read that as a higher rate (102.7 Hz at 5x beside a busy
    # core), where a window of time still holds every frame unless the hold straddles its edge
    lo, hi = t[0] + 0.1 * (t[-1] - t[0]), t[0] + 0.9 * (t[-1] - t[0])
    n = np.count_nonzero((t >= lo) & (t < hi))
    return float(n / (hi - lo))


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_fast_flight_of_each_scenario(tmp_path: Path, scenario: str) -> None:
    duration = 60
    summary = fly_json(tmp_path, "--duration", str(duration), "--scenario", scenario,
                       "--seed", "1")
    threads = {t["name"]: t for t in summary["threads"]}
    for name in ("imu", "gps", "servo"):
        assert threads[name]["restarts"] == 0, threads[name]
        assert not threads[name]["failed"]
    fdir = flight_dir(tmp_path)
    rates = {"imu": record_rate_hz(fdir / "imu.bin", 1),
             "gps": record_rate_hz(fdir / "gps.bin", 1),
             "servo": record_rate_hz(fdir / "servo.bin", 1)}
    # the IMU's and GPS's records are the world's frames, each one decoded; at 5x a hold of
    # the host that straddles the window's edge moves its frames across it (a 0.25 s hold of
    # host time is 1.25 s of flight, 2.6 % of the window), so 3 %, which still fails a decoder
    # that loses or repeats one frame in ten; lockstep asserts them within 0.5 %.
    # The servo board's are its driver's 20 ms timer at 5x (a 4 ms period of host time): on a
    # busy or slow 2-core machine it misses some periods (it catches up 3, then drops them;
    # 47.45 Hz was seen on a slow VM, 44.47 Hz beside a busy core and a second test worker),
    # so 25 %, which still fails a board thread that stalls or runs at half its rate. Its
    # exact rate on a quiet machine is the benchmarks' business (bench/sim_bench.py), and in
    # lockstep (test_lockstep_flight_of_each_scenario) the host has no say
    tolerance = {"imu": 0.03, "gps": 0.03, "servo": 0.25}
    for name, rate in rates.items():
        assert abs(rate / NOMINAL_HZ[name] - 1) < tolerance[name], \
            f"{scenario}: {name} at {rate:.2f} Hz"
    truth = read_log(fdir / "truth.bin").data(1)
    assert np.all(np.isfinite(truth["roll_rad"]))
    assert truth["time_s"][-1] - truth["time_s"][0] > duration * 0.9
    sim = summary["simulator"]
    assert sim.get("real_time_factor", 0) > 4.0, sim
    # the estimator runs and tracks in real time; how well it tracks is asserted in lockstep
    # (test_lockstep_flight_of_each_scenario), where the host's load cannot move the figure
    check_estimator(fdir, scenario, loose=True)
    if scenario == "auto":
        # at 5x the control law's 20 ms period is 4 ms of host time, and a host that keeps it
        # from running for 50 ms (a busy machine) costs it a quarter second of flight: the
        # wings come back from the pilot's 30 deg here, the precision of the law is asserted
        # in lockstep (test_lockstep_flight_of_each_scenario), where the host has no say
        check_auto_levels_wings(fdir, max_deg=20.0, mean_deg=8.0, alt_m=20.0)


def check_estimator(fdir: Path, scenario: str, loose: bool = False) -> None:
    """The on-board GPS/INS filter against JSBSim's truth, in the shared NED frame.

    `loose`: a real-time flight at 5x, whose samples reach the filter with the host's jitter
    (five times larger in flight time): beside a busy core and a second test worker the
    position RMSE reached 2.9 m where lockstep flies 0.75 m. Its bounds still fail a filter
    that does not track (tens of degrees, hundreds of metres); the tight ones are lockstep's."""
    scale = 4.0 if loose else 1.0
    est = read_log(fdir / "estimator.bin").data(1)
    truth = read_log(fdir / "truth.bin").data(1)
    assert len(est) > 1000
    for name in ("roll_rad", "north_m", "vn_m_s"):
        assert np.isfinite(est[name]).all()
    assert int(est["faults"][-1]) == 0, "estimator faults in a nominal flight"
    steady = est[est["time_s"] > est["time_s"][0] + 10]

    def rmse(col: str, wrap: bool = False) -> float:
        err = steady[col] - np.interp(steady["time_s"], truth["time_s"], truth[col])
        if wrap:
            err = (err + np.pi) % (2 * np.pi) - np.pi
        return float(np.sqrt(np.mean(err**2)))

    if scenario != "aerobatic":  # Euler angles are singular in the loop's vertical climb
        assert np.degrees(rmse("roll_rad", True)) < 1.0 * scale
        assert np.degrees(rmse("pitch_rad", True)) < 1.0 * scale
        # heading in straight level flight is seen only through the GPS course and the small
        # accelerations of holding it: 2.75-3.15 deg over ten of these 60 s flights on a quiet
        # machine, 4.18 deg once beside a second test worker (a real-time flight's samples
        # arrive with the host's jitter), so 5 deg: a heading that is not estimated is tens
        yaw_bound_deg = 5.0 if scenario == "level" else 3.0
        assert np.degrees(rmse("yaw_rad", True)) < yaw_bound_deg * scale
    assert np.hypot(rmse("north_m"), rmse("east_m")) < 2.0 * scale
    assert np.sqrt(rmse("vn_m_s") ** 2 + rmse("ve_m_s") ** 2 + rmse("vd_m_s") ** 2) < 0.5 * scale


def check_auto_levels_wings(fdir: Path, max_deg: float, mean_deg: float, alt_m: float) -> None:
    """The pilot banks to 30 deg, then engages automatic mode: the law levels and holds height
    (bounds on |roll| from 10 s after engagement and on the height change from engagement)."""
    truth = read_log(fdir / "truth.bin")
    state, surfaces = truth.data(1), truth.data(2)
    engaged = surfaces["time_s"][np.argmax(surfaces["auto_active"] == 1)]
    assert surfaces["auto_active"].any(), "automatic mode never engaged"
    before = state[(state["time_s"] > engaged - 2) & (state["time_s"] < engaged)]
    assert np.degrees(np.abs(before["roll_rad"])).mean() > 20, "the pilot was not banked"
    # judged while the law ran: at the stop the control thread ends before the world does,
    # and on a busy machine the world flew on for seconds, its pilot's 30 deg bank back
    # (32 deg in the last records of a 5x flight beside a busy core and a second worker)
    control = read_log(fdir / "control.bin").data(1)
    assert control["enabled"].any()
    flown = state["time_s"] < control["time_s"][-1]
    after = state[(state["time_s"] > engaged + 10) & flown]
    assert len(after) > 100
    roll_deg = np.degrees(np.abs(after["roll_rad"]))
    assert roll_deg.max() < max_deg, f"max |roll| {roll_deg.max():.2f} deg"
    assert roll_deg.mean() < mean_deg, f"mean |roll| {roll_deg.mean():.2f} deg"
    alt0 = float(np.interp(engaged, state["time_s"], state["alt_m"]))
    assert np.abs(after["alt_m"] - alt0).max() < alt_m


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_lockstep_flight_of_each_scenario(tmp_path: Path, scenario: str) -> None:
    """The whole loop (the IMU and GPS threads, the estimator, the control law, the servo
    board, JSBSim) in lockstep: how well the filter tracks and the law flies, whatever else the
    host does. Flown here (seed 1): roll RMSE 0.18-0.91 deg, heading 0.55-2.92 deg, position
    0.75 m, velocity 0.10-0.13 m/s; in `auto`, |roll| at most 0.77 deg (mean 0.21) and the
    height within 2.2 m. The bounds leave room for a retune, not for a law that does not level
    (the pilot's 30 deg bank stays: 12.5 deg with CTL_ROLL_KP 0) or a filter that does not
    track."""
    proc = subprocess.run(sim_cmd(tmp_path, "--lockstep", "--duration", "60", "--scenario",
                                  scenario, "--seed", "1", "--json"),
                          capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-2000:]
    fdir = flight_dir(tmp_path)
    # every device at its nominal rate: in lockstep no host can make a driver miss a period
    # (measured: 100.02, 10.015 and 49.98 Hz: a record either side of the window's edges is
    # 0.2 % of the GPS's 480, so 0.5 %; one frame in ten lost or repeated is 10 %)
    for name, nominal_hz in NOMINAL_HZ.items():
        rate = record_rate_hz(fdir / f"{name}.bin", 1)
        assert abs(rate / nominal_hz - 1) < 0.005, f"{scenario}: {name} at {rate:.3f} Hz"
    check_estimator(fdir, scenario)
    if scenario == "auto":
        check_auto_levels_wings(fdir, max_deg=3.0, mean_deg=1.0, alt_m=5.0)


def test_sigterm_stops_cleanly_within_one_second(tmp_path: Path) -> None:
    proc = subprocess.Popen(sim_cmd(tmp_path, "--fast"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        imu = None
        while time.monotonic() < deadline:
            dirs = list((tmp_path / "flights").glob("*/imu.bin")) if (tmp_path / "flights").exists() else []
            if dirs and dirs[0].stat().st_size > 20_000:
                imu = dirs[0]
                break
            assert proc.poll() is None, proc.communicate()[1][-2000:]
            time.sleep(0.05)
        assert imu is not None, "the flight never started logging"
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(10)
        elapsed = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()  # type: ignore[union-attr]
        proc.stderr.close()  # type: ignore[union-attr]
    assert proc.returncode == 0
    assert elapsed < 1.0, f"shutdown took {elapsed:.2f} s"
    fdir = imu.parent
    for name in ("imu", "gps", "servo", "truth"):
        log = read_log(fdir / f"{name}.bin")
        assert log.closed_cleanly, f"{name}.bin has no final End Data"
    run = json.loads((fdir / "run.json").read_text())
    assert run["software"]["name"] == "uav-companion"
    assert "IMU_WDG_MS" in run["parameters"]


def test_runtime_killed_mid_write_leaves_readable_logs(tmp_path: Path) -> None:
    # real time, so log timestamps and the host clock agree
    proc = subprocess.Popen(sim_cmd(tmp_path), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            found = list((tmp_path / "flights").glob("*/imu.bin")) if (tmp_path / "flights").exists() else []
            if found and found[0].stat().st_size > 30_000:
                break
            time.sleep(0.05)
        killed_at_ns = time.time_ns()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        subprocess.run(["pkill", "-f", f"companion.sim.world.*{tmp_path}"], check=False)
    fdir = flight_dir(tmp_path)
    log = read_log(fdir / "imu.bin")
    assert not log.closed_cleanly
    t = log.data(1)["time_s"]
    # every record older than 0.5 s before the kill is on disk and readable
    assert len(t) > 100 and t[-1] > killed_at_ns / 1e9 - 0.5


def test_injected_faults_are_survived_and_counted(tmp_path: Path) -> None:
    """Garbage, cut frames, bad checksums, a silent GPS and a servo port that vanishes."""
    summary = fly_json(tmp_path, "--duration", "30", "--scenario", "level",
                       "--fault", "imu:garbage=0.05,cut=0.02,badsum=0.02",
                       "--fault", "gps:silence=10-13,badsum=0.05",
                       "--vanish", "servo:15:2")
    threads = {t["name"]: t for t in summary["threads"]}
    for name in ("imu", "gps", "servo", "estimator"):
        assert threads[name]["restarts"] == 0, threads[name]
    imu, gps, servo = (threads[n]["counters"] for n in ("imu", "gps", "servo"))
    assert imu["bad_checksum"] + imu["resyncs"] > 10 and imu["bytes_discarded"] > 0
    assert gps["bad_checksum"] > 0
    assert servo["reconnects"] >= 1
    kinds = {(e["kind"], e["thread"]) for e in summary["events"]}
    assert ("silent", "gps") in kinds and ("recovered", "gps") in kinds
    assert ("silent", "servo") in kinds and ("recovered", "servo") in kinds
    faults = summary["simulator"]["faults"]
    assert faults["imu"]["garbage_bursts"] > 0 and faults["gps"]["silenced"] > 0
    est = read_log(flight_dir(tmp_path) / "estimator.bin").data(1)
    assert np.isfinite(est["roll_rad"]).all()


def test_babbling_misconfigured_and_renamed_devices(tmp_path: Path) -> None:
    """An IMU at twice the expected baud rate, then flooding copies; a GPS whose UTC jumps an
    hour and that floods; a servo board whose port returns under another kernel name."""
    summary = fly_json(tmp_path, "--duration", "30", "--scenario", "level",
                       "--fault", "imu:wrongbaud=8-10,flood=14-16",
                       "--fault", "gps:utcstep=12:3600,flood=18-20",
                       "--vanish", "servo:22:1:renamed")
    threads = {t["name"]: t for t in summary["threads"]}
    for name in ("imu", "gps", "servo", "estimator", "control"):
        assert threads[name]["restarts"] == 0, threads[name]
    imu, gps, servo = (threads[n]["counters"] for n in ("imu", "gps", "servo"))
    events = [(e["kind"], e["thread"], e["detail"]) for e in summary["events"]]
    # wrong baud rate: bytes keep coming, nothing decodes, and the report says so
    assert ("silent", "imu", "bytes arrive, none decode") in events, events
    assert ("recovered", "imu", "data again") in events
    # copies are dropped, counted and reported, not integrated as samples
    faults = summary["simulator"]["faults"]
    assert imu["repeated"] >= 0.9 * faults["imu"]["flooded"] > 0
    assert gps["repeated"] >= 0.8 * faults["gps"]["flooded"] > 0
    assert gps["utc_jumps"] == 1
    notices = [d for k, t, d in events if k == "notice"]
    assert any("receiver UTC jumped +3600.0 s" in d for d in notices), notices
    assert any("repeated frames" in d for d in notices)
    assert servo["reconnects"] >= 1 and ("recovered", "servo", "data again") in events
    est = read_log(flight_dir(tmp_path) / "estimator.bin").data(1)
    assert np.isfinite(est["roll_rad"]).all() and np.abs(est["roll_rad"]).max() < 1.0
    # the flight's report shows each injected fault next to what the runtime said about it
    out = tmp_path / "report"
    done = subprocess.run([sys.executable, "-m", "companion", "logs", "report",
                           str(flight_dir(tmp_path)), "-o", str(out), "--no-csv-size"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    html = (out / "report.html").read_text(encoding="utf-8")
    for text in ("Faults and events", "--fault imu:wrongbaud=8-10,flood=14-16",
                 "--vanish servo:22:1:renamed", "receiver UTC jumped +3600.0 s",
                 "bytes arrive, none decode", "imu: the simulator injected flooded"):
        assert text in html, text
    import re

    # the wrong baud rate (8-10 s of flight time) is in the report as the IMU's silence; on a
    # busy machine a late start can add an earlier silence of its own, so any one will do
    silences = [float(t) for t in
                re.findall(r"<td>([\d.]+)</td><td>imu</td><td>silent</td>", html)]
    assert any(8.0 < t_s < 11.0 for t_s in silences), silences


def test_faults_injected_into_the_runtime_threads_are_survived(tmp_path: Path) -> None:
    """A crash, a Python loop that ignores its stop event and a block inside C, each in a real
    flight; and a thread that crashes at every step is left down while the others fly on."""
    summary = fly_json(tmp_path, "--duration", "40", "--scenario", "level",
                       "--thread-fault", "estimator:raise:8", "--thread-fault", "gps:pyloop:12",
                       "--thread-fault", "estimator:cblock:20",
                       "--thread-fault", "control:crash-loop:10")
    threads = {t["name"]: t for t in summary["threads"]}
    assert [f["kind"] for f in summary["thread_faults"]] == ["raise", "crash-loop", "pyloop",
                                                             "cblock"]
    est, gps, ctl = threads["estimator"], threads["gps"], threads["control"]
    assert est["crashes"] == 1 and est["abandoned"] == 1 and est["restarts"] == 2
    assert gps["interrupted"] == 1 and gps["restarts"] == 1
    assert ctl["failed"] and not est["failed"]
    assert threads["imu"]["restarts"] == threads["servo"]["restarts"] == 0
    kinds = [(e["kind"], e["thread"]) for e in summary["events"]]
    assert ("failed", "control") in kinds and ("abandoned", "estimator") in kinds
    assert ("resumed", "manager") not in kinds  # the manager's own joins are not a suspension
    # the estimator came back after each fault: its log runs to the end of the flight
    t = read_log(flight_dir(tmp_path) / "estimator.bin").data(1)["time_s"]
    assert t[-1] - t[0] > 0.8 * 40
    assert threads["imu"]["rate_hz"] > 95


def test_a_bad_thread_fault_is_refused_by_name(tmp_path: Path) -> None:
    proc = subprocess.run(sim_cmd(tmp_path, "--thread-fault", "estimator:explode:3"),
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "estimator:explode:3" in proc.stderr and "crash-loop" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_several_vehicles(tmp_path: Path) -> None:
    base = free_udp_port()
    proc = subprocess.run(
        [sys.executable, "-m", "companion", "sim", "--vehicles", "2", "--fast", "--duration", "8",
         "--log-dir", str(tmp_path / "flights"), "--mavlink", "none",
         "--legacy-listen", str(base), "--legacy-dest", f"127.0.0.1:{free_udp_port()}"],
        capture_output=True, text=True, timeout=240, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    dirs = sorted((tmp_path / "flights").iterdir())
    assert len(dirs) == 2
    configs = [json.loads((d / "run.json").read_text())["config"] for d in dirs]
    assert sorted(c["vehicle"]["id"] for c in configs) == [1, 2]
    for d in dirs:
        assert read_log(d / "imu.bin").closed_cleanly
    # each aircraft keeps its parameters in a file of its own: one shared file would have the
    # two overwrite each other's vehicle id and trims
    for c in configs:
        vid = c["vehicle"]["id"]
        assert c["params"]["file"] == f"params-v{vid}.parm"
        text = (tmp_path / f"params-v{vid}.parm").read_text()
        assert re.search(rf"^SYS_VEHICLE_ID\s+{vid}$", text, re.M), text[:300]
