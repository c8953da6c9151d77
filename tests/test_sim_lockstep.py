"""Lockstep SITL: the scheduler on its own, then whole flights (`companion sim --lockstep`)."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.core.config import Config
from companion.core.lockstep import LockstepClock, LockstepDeadlock, LockstepError
from companion.core.sync import MessageQueue, WaitableSlot
from companion.logs import read_log
from companion.sim.lockstep import run_lockstep
from companion.sim.runner import SimOptions
from companion.watchdog.thread import ThreadInterrupted

# ----------------------------------------------------------------------------- the scheduler


def test_tasks_due_at_one_instant_run_in_priority_order_and_time_jumps() -> None:
    clock = LockstepClock()
    t0 = clock.monotonic_ns()
    trace: list[tuple[str, int]] = []
    stop = threading.Event()

    def ticker(name: str, period_s: float) -> None:
        next_ns = clock.monotonic_ns()
        for _ in range(3):
            trace.append((name, clock.monotonic_ns() - t0))
            next_ns += int(period_s * 1e9)
            if clock.wait_until_ns(next_ns, stop):
                return

    def main() -> int:
        workers = [clock.start_thread(ticker, ("slow", 0.02), "slow", priority=5),
                   clock.start_thread(ticker, ("fast", 0.01), "fast", priority=1)]
        for w in workers:
            w.join(1.0)
        return clock.monotonic_ns() - t0

    elapsed_ns = clock.run(main)
    assert trace == [("fast", 0), ("slow", 0), ("fast", 10_000_000), ("fast", 20_000_000),
                     ("slow", 20_000_000), ("slow", 40_000_000)]
    assert elapsed_ns == 60_000_000  # the last wait of "slow" ends at 60 ms: nothing is real


def test_queue_and_slot_waits_follow_the_producer_or_time_out_in_simulated_time() -> None:
    clock = LockstepClock()
    queue: MessageQueue[int] = MessageQueue(8)
    slot: WaitableSlot[int] = WaitableSlot()
    got: list[tuple[str, object, float]] = []
    stop = threading.Event()

    def producer() -> None:
        clock.sleep(0.5, stop)
        queue.put(7)
        slot.write(9)

    def consumer() -> None:
        t0 = clock.monotonic()
        got.append(("timeout", queue.get(0.1, clock), round(clock.monotonic() - t0, 6)))
        got.append(("queue", queue.get(1.0, clock), round(clock.monotonic() - t0, 6)))
        got.append(("slot", slot.wait_newer(1, 1.0, clock), round(clock.monotonic() - t0, 6)))

    def main() -> None:
        for w in (clock.start_thread(producer, (), "producer", 1),
                  clock.start_thread(consumer, (), "consumer", 2)):
            w.join(5.0)

    clock.run(main)
    assert got == [("timeout", None, 0.1), ("queue", 7, 0.5), ("slot", None, 1.5)]


def test_a_flight_where_every_task_waits_forever_is_reported_not_hung() -> None:
    clock = LockstepClock()
    event = threading.Event()

    def main() -> None:
        worker = clock.start_thread(lambda: clock._wait(event.is_set, None, None), (), "w", 1)
        worker.join()

    with pytest.raises(LockstepDeadlock, match="without a deadline"):
        clock.run(main)


def test_interrupt_reaches_a_waiting_task_and_waits_outside_a_task_are_refused() -> None:
    clock = LockstepClock()
    outcome: list[str] = []
    stop = threading.Event()

    def stubborn() -> None:
        try:
            while True:  # ignores its stop event, but waits: the interrupt lands in the wait
                clock.sleep(1.0, stop)
        except ThreadInterrupted:
            outcome.append("interrupted")

    def main() -> None:
        worker = clock.start_thread(stubborn, (), "stubborn", 1)
        clock.sleep(0.5, threading.Event())
        assert clock.interrupt_thread(worker, ThreadInterrupted)
        worker.join(1.0)
        assert not worker.is_alive()

    clock.run(main)
    assert outcome == ["interrupted"]
    with pytest.raises(LockstepError):
        clock.sleep(0.1, stop)  # not inside a task


# ----------------------------------------------------------------------------- flights


def fly(tmp: Path, duration_s: float = 30.0, **sim: Any) -> tuple[dict[str, Any], Path]:
    cfg = Config()
    cfg.logs.dir = str(tmp / "flights")
    cfg.params.file = str(tmp / "params.parm")
    # rates and determinism, not sensor realism: the original sensors (fixed GPS latency, so
    # every rate is exact) and calm air unless a test asks otherwise
    sim = {"imu_profile": "simple", "gps_profile": "simple", "turbulence": "none", **sim}
    summary = run_lockstep(cfg, SimOptions(**sim), duration_s, handle_signals=False)
    return summary, Path(summary["flight_dir"])


def logs_of(fdir: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(fdir.glob("*.bin"))}


def test_the_same_seed_flies_byte_identical_logs_and_every_rate_is_exact(tmp_path: Path) -> None:
    sim = {"scenario": "turns", "seed": 4, "faults": ["imu:garbage=0.01"]}
    first, dir1 = fly(tmp_path / "a", **sim)
    second, dir2 = fly(tmp_path / "b", **sim)
    logs1, logs2 = logs_of(dir1), logs_of(dir2)
    assert set(logs1) == {"control.bin", "estimator.bin", "gps.bin", "imu.bin", "servo.bin",
                          "truth.bin"}
    for name in logs1:
        assert logs1[name] == logs2[name], f"{name} differs between two lockstep flights"
    threads = {t["name"]: t for t in first["threads"]}
    nominal = {"imu": 100.0, "gps": 10.0, "servo": 50.0, "estimator": 100.0, "control": 100.0}
    for name, hz in nominal.items():
        assert threads[name]["restarts"] == 0 and threads[name]["stalls"] == 0, threads[name]
        assert threads[name]["rate_hz"] == pytest.approx(hz, rel=1e-6), threads[name]
    # every IMU frame the world sent was decoded, timestamped on the 10 ms grid
    t = read_log(dir1 / "imu.bin").data(1)["time_s"]
    assert np.allclose(np.diff(t), 0.01, atol=1e-6)
    assert threads["imu"]["counters"]["bytes_discarded"] > 0  # the garbage reached the decoder
    # the GPS thread wakes for its epochs, not on 20 ms read timeouts (1,300 in 30 s before)
    assert threads["gps"]["counters"]["timeouts"] <= 30, threads["gps"]["counters"]
    assert first["lockstep"]["sim_seconds"] == pytest.approx(30.0, abs=0.1)
    # another seed flies another flight: the comparison above can fail
    _, dir3 = fly(tmp_path / "c", **{**sim, "seed": 5})
    assert logs_of(dir3)["truth.bin"] != logs1["truth.bin"]


def test_supervision_runs_on_simulated_time(tmp_path: Path) -> None:
    """A crash is restarted, a vanished port is reported silent and recovers: the same
    supervisor, on the lockstep clock."""
    summary, _ = fly(tmp_path, 20.0, scenario="level", seed=1,
                     thread_faults=["control:raise:6"], vanish=["gps:8:3"])
    threads = {t["name"]: t for t in summary["threads"]}
    assert threads["control"]["crashes"] == 1 and threads["control"]["restarts"] == 1
    assert threads["gps"]["restarts"] == 0 and threads["gps"]["counters"]["reconnects"] == 1
    kinds = [(e["kind"], e["thread"]) for e in summary["events"]]
    assert ("silent", "gps") in kinds and ("recovered", "gps") in kinds
    for name in ("imu", "servo", "estimator"):
        assert threads[name]["restarts"] == 0, threads[name]


def test_a_dual_antenna_receiver_reaches_the_estimator(tmp_path: Path) -> None:
    """The profile's HDT goes through the driver (GPS_HDT set, as a user would) into the fix,
    the log and the estimator's heading update."""
    summary, fdir = fly(tmp_path, 20.0, scenario="turns", seed=2, gps_profile="dual-antenna")
    threads = {t["name"]: t for t in summary["threads"]}
    gps = threads["gps"]["counters"]
    assert gps["malformed"] == 0 and gps["epochs"] >= 190
    assert gps["sentences_good"] == 6 * gps["epochs"]  # HDT with each epoch, in the epoch
    est = threads["estimator"]["counters"]
    assert est["heading_used"] >= 0.9 * est["gps_accepted"] > 0 and est["heading_rejected"] == 0
    heading = read_log(fdir / "gps.bin").data(1)["heading_deg"]
    assert np.isfinite(heading).all() and ((heading >= 0.0) & (heading < 360.0)).all()


def test_a_warming_imu_has_its_temperature_coefficient_learnt_and_logged(tmp_path: Path) -> None:
    """The consumer part warms up (20 -> 40 C): its temperature travels from the simulated
    IMU's slow block through the driver to the estimator, whose coefficient moves off its
    prior's zero and is logged with every fix; a part that does not warm moves nothing."""
    summary, fdir = fly(tmp_path / "warm", 40.0, scenario="turns", seed=3,
                        imu_profile="consumer")
    est = {t["name"]: t for t in summary["threads"]}["estimator"]["counters"]
    assert est["temperature_readings"] >= 30
    fixes = read_log(fdir / "estimator.bin").data(2)
    coeff = np.stack([fixes[f"gyro_temp_{a}"] for a in "xyz"], axis=1)
    assert np.isfinite(coeff).all() and len(coeff) > 100
    assert np.abs(coeff[-1]).max() > 1e-5  # learnt from the warm-up (prior: 1.5e-3 1-sigma)
    assert np.abs(coeff).max() < 0.01
    _, still = fly(tmp_path / "simple", 20.0, scenario="turns", seed=3)  # no temperature drift
    assert not read_log(still / "estimator.bin").data(2)["gyro_temp_x"].any()


def test_cli_lockstep_flight_and_what_it_refuses(tmp_path: Path) -> None:
    base = [sys.executable, "-m", "companion", "sim", "--lockstep",
            "--log-dir", str(tmp_path / "flights"), "--params-file", str(tmp_path / "p.parm")]
    proc = subprocess.run([*base, "--duration", "10", "--json"], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads(proc.stdout)
    assert summary["stop_reason"] == "duration"
    assert summary["messages"] == []  # no ground links in lockstep
    assert summary["lockstep"]["speed"] > 1.0
    for bad, word in ((["--thread-fault", "imu:pyloop:5"], "pyloop"),
                      (["--clock-step", "5:3600"], "clock-step")):
        proc = subprocess.run([*base, "--duration", "5", *bad], capture_output=True,
                              text=True, timeout=60)
        assert proc.returncode == 2, proc.stderr
        assert word in proc.stderr and "Traceback" not in proc.stderr
