"""`companion sim --vehicles K` stops every aircraft cleanly on SIGINT or SIGTERM, also when
it was started with SIGINT ignored (`nohup ... &`, a CI job's background step)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import free_udp_port

K = 2
START_TIMEOUT_S = 40.0
STOP_TIMEOUT_S = 20.0


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_fleet_started_with_sigint_ignored_still_stops_every_aircraft(
        tmp_path: Path, sig: signal.Signals) -> None:
    flights = tmp_path / "flights"
    cmd = [sys.executable, "-m", "companion", "sim", "--vehicles", str(K), "--duration", "300",
           "--scenario", "level", "--mavlink", "none", "--legacy-listen", str(free_udp_port()),
           "--legacy-dest", f"127.0.0.1:{free_udp_port()}", "--log-dir", str(flights)]
    with open(tmp_path / "fleet.err", "w") as err:
        proc = subprocess.Popen(cmd, cwd=tmp_path, stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=err,
                                preexec_fn=_ignore_sigint, start_new_session=True)
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while len(list(flights.glob("*/imu.bin"))) < K:
            assert proc.poll() is None, (tmp_path / "fleet.err").read_text()[-2000:]
            assert time.monotonic() < deadline, "the fleet's aircraft did not start"
            time.sleep(0.1)
        proc.send_signal(sig)
        try:
            rc = proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"the fleet still runs {STOP_TIMEOUT_S} s after {sig.name}")
        assert rc == 0, (tmp_path / "fleet.err").read_text()[-2000:]
        summaries = [json.loads(p.read_text()) for p in flights.glob("*/summary.json")]
        assert len(summaries) == K  # every aircraft ended and wrote its summary
        assert all(s["stop_reason"] == "signal SIGINT" for s in summaries)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
