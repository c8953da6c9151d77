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

SPEED = 20.0
DURATION_S = 80  # simulated: 4 s of flight at 20x, plus start-up


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
