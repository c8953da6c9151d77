"""The wall clock stepped under a running runtime (NTP or GPS time setting it in flight).

Stepping the machine's real clock would disturb every other program on it, and libfaketime
cannot step CLOCK_REALTIME alone (its monotonic exemption makes `time.sleep` fail with EINVAL,
seen with 0.9.10), so these tests step Python's view of the wall clock (`time.time`,
`time.time_ns`) in the process under test, which is what the runtime reads.
"""

from __future__ import annotations

import time

import pytest

from companion.core.clock import Clock


@pytest.mark.parametrize("step_s", [3600.0, -3600.0, -0.5])
def test_timestamps_do_not_follow_a_wall_clock_step(monkeypatch: pytest.MonkeyPatch,
                                                    step_s: float) -> None:
    clock = Clock(1.0)
    before = [clock.realtime_ns() for _ in range(3)]
    real_time_ns = time.time_ns
    monkeypatch.setattr(time, "time_ns", lambda: real_time_ns() + int(step_s * 1e9))
    monkeypatch.setattr(time, "time", lambda: real_time_ns() / 1e9 + step_s)
    after = [clock.realtime_ns() for _ in range(3)]
    stamps = before + after
    assert all(b >= a for a, b in zip(stamps, stamps[1:], strict=False))  # never backwards
    assert after[0] - before[-1] < 50_000_000  # no jump: the time between two reads only
