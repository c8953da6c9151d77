"""MAVSDK 4.1 and MAVProxy 1.8.75 against a real `companion sim` flight, not a synthetic vehicle.

tests/test_gcs_mavsdk.py and tests/test_gcs_mavproxy.py talk to the MAVLink bridge on a
`SyntheticVehicle` (synthetic state, no drivers, no simulator). Here the whole runtime runs as
`companion sim --fast` in a subprocess: the JSBSim world, the device simulators on
pseudo-terminals, the drivers, the estimator, the control law, the logs and the bridge. What the
clients receive is then checked against the flight's own logs (estimator.bin, truth.bin), and
what they set against the runtime's parameter file and final summary.

Each test flies its own flight, about 5 s of host time on two cores (start-up about 1.5 s).
The flight is programmed for FLIGHT_S simulated seconds as a safety net and stopped with SIGINT
once the client is done, so its summary must say it was still flying ("signal SIGINT"). The
`turns` scenario (8 s level, 20 s banked 30 degrees, 8 s level, 20 s banked the other way, ...)
makes the attitude change within a few seconds of host time at --fast.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import free_udp_port, quiet_mavsdk, wait_for
from mavsdk import ComponentType, Configuration, Mavsdk
from mavsdk.plugins.param.param import Param, ParamError, ParamResult
from mavsdk.plugins.telemetry.telemetry import Telemetry

# the MAVProxy driver (commands on stdin, output collected line by line) is shared
from test_gcs_mavproxy import MavProxy, words

from companion.core.params import parse_param_file, to_float32
from companion.logs import read_log

FLIGHT_S = 300  # programmed duration, simulated seconds (60 s of host time at --fast)
START_TIMEOUT_S = 60.0  # JSBSim and the runtime start in about 1.5 s; a loaded machine is slower
STOP_TIMEOUT_S = 15.0  # SIGINT to exit: under a second normally
MAVSDK_SYSID = (245, 190)  # MAVSDK's default ground-station system and component ids
MAVPROXY_SYSID = (255, 230)


@pytest.fixture(scope="module", autouse=True)
def _mavsdk_quiet() -> Iterator[None]:
    with quiet_mavsdk():
        yield


# ---------------------------------------------------------------------------- the flight
class SimFlight:
    """`companion sim` in its own session, output in files, everything under `root`."""

    def __init__(self, root: Path, endpoint: str) -> None:
        root.mkdir(parents=True, exist_ok=True)
        self.root = root
        self.params_file = root / "params.parm"
        self.flights = root / "flights"
        self.out_path = root / "sim.stdout"
        self.err_path = root / "sim.stderr"
        cmd = [sys.executable, "-m", "companion", "sim", "--fast", "--duration", str(FLIGHT_S),
               "--scenario", "turns", "--seed", "1", "--json",
               # the MAVLink path is under test, compared with the truth within a few degrees
               # from the first seconds: sensors whose errors the estimator has converged on
               # (estimator accuracy under the realistic profile: see issue #15 bench)
               "--imu-profile", "simple", "--gps-profile", "simple", "--turbulence", "none",
               "--log-dir", str(self.flights), "--params-file", str(self.params_file),
               "--mavlink", endpoint,
               # the legacy protocol binds a fixed port (5500) by default: move it
               "--legacy-listen", str(free_udp_port()),
               "--legacy-dest", f"127.0.0.1:{free_udp_port()}"]
        with open(self.out_path, "w") as out, open(self.err_path, "w") as err:
            # a session of its own: a last-resort SIGKILL reaches the simulator process too
            self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=err,
                                         cwd=root, start_new_session=True)
        self.world_pid: int | None = None

    def stderr_tail(self) -> str:
        try:
            return self.err_path.read_text(errors="replace")[-3000:]
        except OSError:
            return ""

    def check_alive(self) -> None:
        """Fail at once (with its stderr) if the flight ended before the test was done."""
        if self.proc.poll() is not None:
            pytest.fail(f"companion sim exited early with {self.proc.returncode}:\n"
                        f"{self.stderr_tail()}", pytrace=False)

    def flight_dir(self) -> Path:
        found: list[Path] = []

        def started() -> bool:
            self.check_alive()
            found[:] = list(self.flights.glob("*/run.json")) if self.flights.is_dir() else []
            return bool(found)

        assert wait_for(started, START_TIMEOUT_S, 0.05), "no run.json: the flight did not start"
        assert len(found) == 1, found
        return found[0].parent

    def run_info(self) -> dict[str, Any]:
        info: dict[str, Any] = json.loads((self.flight_dir() / "run.json").read_text())
        self.world_pid = int(info["simulation"]["pid"])
        return info

    def saved_params(self) -> dict[str, float]:
        if not self.params_file.exists():
            return {}
        return {name: value for _, name, _, value, problem in parse_param_file(self.params_file)
                if name is not None and problem is None}

    def stop(self) -> dict[str, Any]:
        """SIGINT, as Ctrl-C would; the flight must end cleanly and print its JSON summary."""
        self.check_alive()
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGINT)
        try:
            rc = self.proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"companion sim still running {STOP_TIMEOUT_S} s after SIGINT")
        stop_s = time.monotonic() - t0
        assert rc == 0, self.stderr_tail()
        print(f"companion sim stopped {stop_s:.2f} s after SIGINT")
        summary: dict[str, Any] = json.loads(self.out_path.read_text())
        return summary

    def world_gone(self) -> bool:
        """The simulator process (the runtime's child) has exited."""
        if self.world_pid is None:
            return True
        try:
            cmdline = Path(f"/proc/{self.world_pid}/cmdline").read_bytes()
            state = Path(f"/proc/{self.world_pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            return True
        return b"companion.sim.world" not in cmdline or state in ("Z", "X")

    def close(self) -> None:
        """Make sure nothing is left running, whatever the test did (idempotent)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                pass
        if self.proc.poll() is None or not wait_for(self.world_gone, 10.0, 0.05):
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)  # the group this test started
            except ProcessLookupError:
                pass
            self.proc.wait(10)


@contextmanager
def sim_flight(root: Path, endpoint: str) -> Iterator[SimFlight]:
    flight = SimFlight(root, endpoint)
    try:
        yield flight
    finally:
        flight.close()


def check_clean_end(flight: SimFlight, summary: dict[str, Any]) -> None:
    """Stopped by the test (not by the duration), no thread in trouble, simulator gone."""
    assert summary["stop_reason"] == "signal SIGINT", summary["stop_reason"]
    threads = {t["name"]: t for t in summary["threads"]}
    for name in ("imu", "gps", "servo", "estimator", "control", "mav0rx", "mav0tx"):
        assert threads[name]["restarts"] == 0 and not threads[name]["failed"], threads[name]
    assert summary["simulator"]["sim_time_s"] > 0, summary["simulator"]
    assert wait_for(flight.world_gone, 10.0, 0.05), f"simulator pid {flight.world_pid} left running"


# ---------------------------------------------------------------------------- MAVSDK
@contextmanager
def mavsdk_on(port: int, flight: SimFlight) -> Iterator[Any]:
    sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = None
        deadline = time.monotonic() + START_TIMEOUT_S
        while system is None and time.monotonic() < deadline:
            flight.check_alive()
            system = sdk.first_autopilot(1.0)
        assert system is not None, "MAVSDK did not discover the simulated vehicle"
        yield system
    finally:
        sdk.destroy()


class Recorder:
    """Thread-safe lists of what MAVSDK's subscriptions deliver (from its own threads)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._data: dict[str, list[Any]] = {}

    def callback(self, kind: str) -> Any:
        store = self._data.setdefault(kind, [])

        def cb(value: Any, *_: Any) -> None:
            with self._lock:
                store.append(value)
        return cb

    def get(self, kind: str) -> list[Any]:
        with self._lock:
            return list(self._data.get(kind, []))


def roll_span_deg(rec: Recorder) -> float:
    rolls = [a.roll_deg for a in rec.get("attitude")]
    return max(rolls) - min(rolls) if rolls else 0.0


def test_mavsdk_telemetry_and_parameters_on_a_simulated_flight(tmp_path: Path) -> None:
    port = free_udp_port()
    with sim_flight(tmp_path / "sim", f"udpout:127.0.0.1:{port}") as flight:
        with mavsdk_on(port, flight) as system:
            assert system.get_system_id() == 1 and system.has_autopilot()
            run = flight.run_info()
            telemetry = Telemetry(system)
            rec = Recorder()
            telemetry.subscribe_attitude_euler(rec.callback("attitude"))
            telemetry.subscribe_position(rec.callback("position"))
            telemetry.subscribe_velocity_ned(rec.callback("velocity"))

            # "turns": 8 s level, 20 s banked 30 deg right, 8 s level, 20 s banked left, ...
            def turning() -> bool:
                flight.check_alive()
                return (roll_span_deg(rec) > 20.0 and len(rec.get("position")) >= 10
                        and len(rec.get("velocity")) >= 10)

            assert wait_for(turning, 30.0, 0.05), \
                f"no turn seen: rolls {[round(a.roll_deg, 1) for a in rec.get('attitude')]}"

            # every parameter of this runtime (run.json has them as the flight started)
            param = Param(system)
            everything = param.get_all_params()
            ints = {p.name: p.value for p in everything.int_params}
            floats = {p.name: p.value for p in everything.float_params}
            expected = run["parameters"]
            assert len(ints) + len(floats) == len(expected)
            assert set(ints) | set(floats) == set(expected)
            for name, value in ints.items():
                assert value == expected[name], name
            for name, value in floats.items():
                assert value == to_float32(expected[name]), name

            # an integer (the estimator's message period, which paces the legacy protocol)
            assert ints["EST_MSG_MS"] == 1000
            param.set_param_int("EST_MSG_MS", 100)
            assert param.get_param_int("EST_MSG_MS") == 100
            # a float with a visible effect: the HUD's attitude rate, 20 Hz of flight time by
            # default (no rate was requested), now 10 Hz
            assert floats["MAV_ATT_HZ"] == 20.0
            mark = len(rec.get("attitude"))
            param.set_param_float("MAV_ATT_HZ", 10.0)
            assert param.get_param_float("MAV_ATT_HZ") == 10.0
            # and a float; then a refused value changes nothing
            assert floats["CTL_ROLL_MAX"] == 35.0
            param.set_param_float("CTL_ROLL_MAX", 30.5)
            assert param.get_param_float("CTL_ROLL_MAX") == 30.5
            with pytest.raises(ParamError) as info:
                param.set_param_float("CTL_ROLL_MAX", 75.0)  # range 5..60
            assert info.value.result == ParamResult.VALUE_OUT_OF_RANGE
            assert param.get_param_float("CTL_ROLL_MAX") == 30.5

            # the runtime acts on it: ATTITUDE now every 100 ms of flight time (time_boot_ms)
            assert wait_for(lambda: len(rec.get("attitude")) - mark >= 40, 15.0, 0.05)
            stamps = [a.timestamp_us for a in rec.get("attitude")]
            before = np.diff(stamps[:mark])
            after = np.diff(stamps[mark + 5:])  # a few in flight while the set was answered
            assert 47_500 <= np.median(before) <= 52_500, before
            assert 95_000 <= np.median(after) <= 105_000, after
            # and persists it (saved once the changes pause)
            assert wait_for(lambda: flight.saved_params().get("EST_MSG_MS") == 100
                            and flight.saved_params().get("MAV_ATT_HZ") == 10.0
                            and flight.saved_params().get("CTL_ROLL_MAX") == 30.5, 10.0, 0.05), \
                flight.saved_params()
        summary = flight.stop()
    check_clean_end(flight, summary)
    link = summary["messages"][0]
    assert link["endpoint"] == f"udpout:127.0.0.1:{port}"
    assert MAVSDK_SYSID in [tuple(p) for p in link["peers"]], link["peers"]
    assert link["rx_frames"] > 0 and link["streams_sent"]["ATTITUDE"] >= len(stamps)
    saved = flight.saved_params()  # still there after the shutdown
    assert saved["EST_MSG_MS"] == 100 and saved["CTL_ROLL_MAX"] == 30.5

    check_attitude_against_logs(Path(summary["flight_dir"]), rec.get("attitude"))
    check_position_against_truth(Path(summary["flight_dir"]), rec.get("position"),
                                 rec.get("velocity"))


def check_attitude_against_logs(fdir: Path, attitude: list[Any]) -> None:
    """Each sample is one of the estimator's states, at a fixed time offset, near the truth."""
    est = read_log(fdir / "estimator.bin").data(1)
    truth = read_log(fdir / "truth.bin").data(1)
    est_roll, est_pitch = np.degrees(est["roll_rad"]), np.degrees(est["pitch_rad"])
    offsets = []
    unmatched = []
    for a in attitude:
        diff = np.abs(est_roll - a.roll_deg) + np.abs(est_pitch - a.pitch_deg)
        i = int(np.argmin(diff))
        if diff[i] < 1e-4:  # the same float32 values
            offsets.append(float(est["time_s"][i]) - a.timestamp_us / 1e6)
        else:
            unmatched.append((a.timestamp_us, a.roll_deg, a.pitch_deg))
    assert len(unmatched) <= len(attitude) // 20, f"not in estimator.bin: {unmatched[:10]}"
    # time_boot_ms counts from the bridge's start: one offset for every sample (ms resolution)
    assert max(offsets) - min(offsets) < 0.005, (min(offsets), max(offsets))
    offset = float(np.median(offsets))
    t = np.array([a.timestamp_us / 1e6 + offset for a in attitude])
    assert t[0] >= truth["time_s"][0] and t[-1] <= truth["time_s"][-1]
    roll = np.array([a.roll_deg for a in attitude])
    pitch = np.array([a.pitch_deg for a in attitude])
    yaw = np.array([a.yaw_deg for a in attitude])
    true_roll = np.degrees(np.interp(t, truth["time_s"], truth["roll_rad"]))
    true_pitch = np.degrees(np.interp(t, truth["time_s"], truth["pitch_rad"]))
    true_yaw = np.degrees(np.interp(t, truth["time_s"], np.unwrap(truth["yaw_rad"])))
    yaw_err = (yaw - true_yaw + 180.0) % 360.0 - 180.0
    assert np.abs(roll - true_roll).max() < 3.0, np.abs(roll - true_roll).max()
    assert np.abs(pitch - true_pitch).max() < 3.0, np.abs(pitch - true_pitch).max()
    assert np.abs(yaw_err).max() < 5.0, np.abs(yaw_err).max()
    # plausible for a light aircraft in 30 degree turns
    assert np.abs(roll).max() < 45.0 and np.abs(pitch).max() < 20.0
    assert 25.0 < np.abs(roll).max() and np.ptp(roll) > 20.0


def check_position_against_truth(fdir: Path, position: list[Any], velocity: list[Any]) -> None:
    """Positions inside the truth's track (plus a margin), moving at the truth's speeds."""
    truth = read_log(fdir / "truth.bin").data(1)
    lat = np.array([p.latitude_deg for p in position])
    lon = np.array([p.longitude_deg for p in position])
    alt = np.array([p.absolute_altitude_m for p in position])
    margin_deg = 30.0 / 111_000.0  # 30 m
    assert truth["lat_deg"].min() - margin_deg < lat.min() and lat.max() < truth["lat_deg"].max() + margin_deg
    lon_margin = margin_deg / math.cos(math.radians(float(lat[0])))
    assert truth["lon_deg"].min() - lon_margin < lon.min() and lon.max() < truth["lon_deg"].max() + lon_margin
    assert truth["alt_m"].min() - 10.0 < alt.min() and alt.max() < truth["alt_m"].max() + 10.0
    north = (lat[-1] - lat[0]) * 111_000.0
    east = (lon[-1] - lon[0]) * 111_000.0 * math.cos(math.radians(float(lat[0])))
    assert math.hypot(north, east) > 100.0, "the aircraft did not move"
    speed = np.array([math.hypot(v.north_m_s, v.east_m_s) for v in velocity])
    true_speed = np.hypot(truth["vn_m_s"], truth["ve_m_s"])
    assert true_speed.min() - 3.0 < speed.min() and speed.max() < true_speed.max() + 3.0
    assert 20.0 < speed.min() and speed.max() < 90.0  # a C172 in cruise: about 50 m/s


# ---------------------------------------------------------------------------- MAVProxy
def test_mavproxy_fetches_and_sets_parameters_on_a_simulated_flight(tmp_path: Path) -> None:
    port = free_udp_port()
    # MAVProxy reads integer parameters bytewise only from a PX4: the link claims one
    with sim_flight(tmp_path / "sim", f"udpout:127.0.0.1:{port}?identity=px4") as flight:
        mp_dir = tmp_path / "mavproxy"
        mp_dir.mkdir()
        mp = MavProxy(port, mp_dir)
        try:
            run = flight.run_info()
            count = len(run["parameters"])
            t0 = time.monotonic()
            line = mp.wait_line("Received", START_TIMEOUT_S)
            flight.check_alive()
            assert line is not None, "\n".join(mp.lines[-40:])
            assert line.strip().endswith(f"Received {count} parameters"), line
            print(f"MAVProxy: {count} parameters in {time.monotonic() - t0:.2f} s")

            mark = mp.mark()
            mp.cmd("param show MAV_B_LOW_PCT")
            mp.cmd("param show CTL_PTCH_MAX")
            assert words(mp.wait_line("MAV_B_LOW_PCT", 5.0, mark)) == ["MAV_B_LOW_PCT", "20"]
            name, value = words(mp.wait_line("CTL_PTCH_MAX", 5.0, mark))
            assert name == "CTL_PTCH_MAX" and float(value) == 15.0

            mp.cmd("param set MAV_B_LOW_PCT 25")
            mp.cmd("param set CTL_PTCH_MAX 12.5")
            assert wait_for(lambda: flight.saved_params().get("MAV_B_LOW_PCT") == 25
                            and flight.saved_params().get("CTL_PTCH_MAX") == 12.5, 10.0, 0.05), \
                (flight.saved_params(), mp.lines[-20:])
            # MAVProxy's own copy was updated from the runtime's PARAM_VALUE answers
            mark = mp.mark()
            mp.cmd("param show MAV_B_LOW_PCT")
            mp.cmd("param show CTL_PTCH_MAX")
            assert words(mp.wait_line("MAV_B_LOW_PCT", 5.0, mark)) == ["MAV_B_LOW_PCT", "25"]
            name, value = words(mp.wait_line("CTL_PTCH_MAX", 5.0, mark))
            assert float(value) == 12.5

            # and it receives the flight's attitude, which changes
            def attitude_line() -> tuple[int, float] | None:
                mark = mp.mark()
                mp.cmd("status ATTITUDE")
                line = mp.wait_line("ATTITUDE {", 2.0, mark)
                if line is None:
                    return None
                fields = dict(f.split(" : ") for f in line.split("{", 1)[1].rstrip("}").split(", "))
                return int(fields["time_boot_ms"]), float(fields["roll"])

            seen: list[tuple[int, float]] = []

            def attitude_moves() -> bool:
                flight.check_alive()
                sample = attitude_line()
                if sample is not None:
                    seen.append(sample)
                rolls = [math.degrees(r) for _, r in seen]
                return len({t for t, _ in seen}) >= 3 and max(rolls) - min(rolls) > 10.0

            # the same turns as above: within one level-bank-level cycle the roll changes
            assert wait_for(attitude_moves, 20.0, 0.2), seen
            assert all(abs(math.degrees(r)) < 45.0 for _, r in seen), seen
            assert [t for t, _ in seen] == sorted(t for t, _ in seen), seen
        finally:
            mp.close()
        # EOF on stdin ended it (not the kill in close()); MAVProxy 1.8.75's main() always
        # ends with sys.exit(1), clean quit or not
        assert mp.proc.returncode == 1, "\n".join(mp.lines[-20:])
        summary = flight.stop()
    check_clean_end(flight, summary)
    link = summary["messages"][0]
    assert MAVPROXY_SYSID in [tuple(p) for p in link["peers"]], link["peers"]
    saved = flight.saved_params()
    assert saved["MAV_B_LOW_PCT"] == 25 and saved["CTL_PTCH_MAX"] == 12.5
