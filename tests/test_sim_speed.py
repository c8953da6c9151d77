"""A simulated flight at 20x with both ground links on: no thread is restarted or stalls.

At 20x a watchdog window of 2000 ms is 100 ms of host time. A bridge thread whose wait is fixed
in host time (a 0.1 s socket timeout) can let a whole window pass without a completed cycle and
be restarted for nothing; every bridge wait is therefore in the runtime's clock and a quarter
of the thread's watchdog period at most (see legacy_protocol.adapter and
gcs_bridge.link_threads). The IMU's 500 ms window would be 25 ms of host time, shorter than a
busy machine may keep a healthy thread waiting: a window lasts at least `MIN_WINDOW_HOST_S` of
host time (companion.watchdog.manager).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from conftest import free_udp_port

from companion.drivers.gps import FMT_SOLUTION
from companion.drivers.imu import FMT_FAST
from companion.logs import read_log

SPEED = 20.0
DURATION_S = 80  # simulated: 4 s of flight at 20x, plus start-up


def achieved(tmp: Path) -> tuple[float, float, float]:
    """(flight-clock seconds of IMU samples per host second, IMU Hz, GPS Hz in the flight's
    clock) of the flight in `tmp`. The host window runs from run.json (written as the runtime
    starts) to summary.json (written once it has shut down), so the interpreter's start-up is
    not counted against the runtime; its shutdown is, which only lowers the figure."""
    flight = sorted((tmp / "flights").glob("*/"))[-1]
    host_s = (flight / "summary.json").stat().st_mtime - (flight / "run.json").stat().st_mtime
    imu_t = read_log(flight / "imu.bin").time_ns(FMT_FAST) / 1e9
    gps_t = read_log(flight / "gps.bin").time_ns(FMT_SOLUTION) / 1e9
    span_s = float(imu_t[-1] - imu_t[0])
    gps_span_s = float(gps_t[-1] - gps_t[0])
    return span_s / host_s, (len(imu_t) - 1) / span_s, (len(gps_t) - 1) / gps_span_s


def fly_at_speed(tmp: Path, speed: float, duration_s: int) -> dict[str, Any]:
    """A flight at `speed` with MAVLink (to a UDP port nobody reads) and the legacy protocol."""
    cmd = [sys.executable, "-m", "companion", "sim", "--speed", str(speed),
           "--duration", str(duration_s), "--json",
           "--log-dir", str(tmp / "flights"), "--params-file", str(tmp / "params.parm"),
           "--mavlink", f"udpout:127.0.0.1:{free_udp_port()}",
           "--legacy-listen", str(free_udp_port()),
           "--legacy-dest", f"127.0.0.1:{free_udp_port()}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary: dict[str, Any] = json.loads(proc.stdout)
    return summary


def test_twenty_times_real_time_restarts_no_thread(tmp_path: Path) -> None:
    summary = fly_at_speed(tmp_path, SPEED, DURATION_S)
    assert summary["clock_scale"] == SPEED
    # The flight really ran faster than real time. On this 2-core machine, shared with other
    # jobs, 20x is not reliably reached (17x measured with the machine's load average near 8):
    # more than 5 flight seconds per host second tells a real speed-up from a flight paced
    # at real time under a 20x label; the exact figure belongs to a benchmark.
    speedup, imu_hz, gps_hz = achieved(tmp_path)
    assert speedup > 5.0, f"{speedup:.1f} flight seconds per host second at --speed {SPEED:g}"
    # ... and the devices delivered in the flight's clock: IMU 100 Hz and GPS 10 Hz nominal,
    # measured 81-96 Hz and 8-10 Hz at 20x on this loaded machine (a device thread that cannot
    # keep up at 2,000 host frames a second loses frames, it does not slow the clock); half the
    # nominal rate tells a device running at its host-time rate (5 Hz, 0.5 Hz) from a busy one
    assert imu_hz > 50.0 and gps_hz > 5.0, f"IMU {imu_hz:.1f} Hz, GPS {gps_hz:.1f} Hz"
    threads = {t["name"]: t for t in summary["threads"]}
    for name in ("mav0rx", "mav0tx", "legacy-rx", "legacy-tx"):
        assert name in threads, sorted(threads)
    # what this test is about: the threads whose waits face the host (the ground links) and
    # the devices. The estimator's 100 Hz filter at 20x is 2,000 cycles a host second: whether
    # a 2-core machine keeps up with that is a throughput figure for the benchmarks, not
    # behaviour (on a slow VM it stalls at 10x and 20x on the code before this change as well)
    judged = {name: t for name, t in threads.items() if name not in ("estimator", "control")}
    troubled = {name: {k: t[k] for k in ("restarts", "stalls", "crashes", "failed")}
                for name, t in judged.items()
                if t["restarts"] or t["stalls"] or t["crashes"] or t["failed"]}
    bad_events = [(e["kind"], e["thread"], e["detail"]) for e in summary["events"]
                  if e["thread"] in judged
                  and e["kind"] in ("stall", "restarted", "crash", "failed", "escalated",
                                    "exited", "interrupted", "abandoned")]
    assert not troubled, troubled
    assert not bad_events, bad_events
    # the links did their work at that speed, not only survived it
    assert threads["mav0tx"]["cycles"] > 0 and threads["legacy-tx"]["cycles"] > 0
