"""The simulator subprocess's stop: its figures are collected, and a world that gives none
(died, or hung past the wait) still yields a reason instead of an empty dictionary."""

from __future__ import annotations

import os
import signal
from pathlib import Path

from companion.core.clock import Clock
from companion.sim.runner import SimOptions, WorldProcess


def start_world(tmp_path: Path) -> WorldProcess:
    (tmp_path / "dev").mkdir()
    (tmp_path / "flight").mkdir()
    return WorldProcess(SimOptions(scenario="level", seed=1), Clock(5.0), tmp_path / "dev",
                        tmp_path / "flight", 30.0)


def test_a_flown_world_reports_its_figures(tmp_path: Path) -> None:
    world = start_world(tmp_path)
    world.go()
    stats = world.stop()
    assert stats["stop"] == "signal", stats
    assert "real_time_factor" in stats and "exit_code" not in stats


def test_a_world_that_died_says_so(tmp_path: Path) -> None:
    world = start_world(tmp_path)
    world.proc.kill()
    world.proc.wait(10)
    stats = world.stop()
    assert stats["stop"] == "simulator exited with code -9 without a report", stats
    assert stats["exit_code"] == -9


def test_a_hung_world_is_killed_after_the_wait(tmp_path: Path) -> None:
    world = start_world(tmp_path)
    world.go()
    os.kill(world.proc.pid, signal.SIGSTOP)  # a world that cannot answer SIGTERM
    stats = world.stop(timeout_s=1.0)
    assert stats["stop"] == "simulator killed after 1 s without a report", stats
    assert stats["exit_code"] == -9
    assert 1.0 <= stats["stop_wait_s"] < 10.0
