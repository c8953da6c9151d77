"""Disk policy: the oldest finished flights go first, never the current one, never one another
runtime is writing (a real lock held by another process), never a directory that is not a
flight; and in a real flight, with the deletions reported."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from test_sim_runtime import sim_cmd

from companion.logs.retention import FlightLock, enforce, finished_flights

NAMES = ["20260101T000000Z", "20260102T000000Z", "20260103T000000Z-v2", "20260104T000000Z",
         "20260105T000000Z"]


def make_flights(root: Path, sizes_kb: list[int]) -> list[Path]:
    out = []
    for name, kb in zip(NAMES, sizes_kb, strict=False):
        d = root / name
        d.mkdir(parents=True)
        (d / "imu.bin").write_bytes(b"\0" * kb * 1000)
        out.append(d)
    return out


def hold_lock_in_another_process(path: Path) -> subprocess.Popen[str]:
    code = ("import sys, time; from pathlib import Path; from companion.logs.retention import "
            "FlightLock; FlightLock(Path(sys.argv[1])); print('locked', flush=True); "
            "sys.stdin.read()")
    proc = subprocess.Popen([sys.executable, "-c", code, str(path)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "locked"
    return proc


def test_at_most_m_flights_oldest_first_skipping_live_and_foreign_ones(tmp_path: Path) -> None:
    flights = make_flights(tmp_path, [1, 1, 1, 1, 1])
    (tmp_path / "notes").mkdir()  # not a flight
    (tmp_path / "notes" / "x.txt").write_text("mine")
    current = flights[-1]
    other = hold_lock_in_another_process(flights[0])  # another aircraft still writing it
    try:
        assert finished_flights(tmp_path, current) == flights[1:4]
        done = enforce(tmp_path, current, min_free_mb=0, max_flights=3)
    finally:
        assert other.stdin is not None
        other.stdin.close()
        other.wait(10)
        assert other.stdout is not None
        other.stdout.close()
    # 5 flights, at most 3: the two oldest finished ones go (the locked oldest stays)
    assert [d.path.name for d in done] == [NAMES[1], NAMES[2]]
    assert all(d.reason == "more than 3 flights" for d in done)
    assert sorted(p.name for p in tmp_path.iterdir()) == [NAMES[0], NAMES[3], NAMES[4], "notes"]
    assert enforce(tmp_path, current, min_free_mb=0, max_flights=0) == []  # off


def test_min_free_deletes_until_enough_is_free_and_stops_there(tmp_path: Path) -> None:
    flights = make_flights(tmp_path, [300, 200, 100, 50, 10])
    capacity_mb = 1.0

    def free_mb(root: Path) -> float:  # a 1 MB disk holding what is really under root
        used = sum(f.stat().st_size for f in root.rglob("*") if f.is_file())
        return capacity_mb - used / 1e6

    lock = FlightLock(flights[-1])
    try:
        done = enforce(tmp_path, flights[-1], min_free_mb=0.7, max_flights=0, free_mb=free_mb)
    finally:
        lock.release()
    # 0.34 MB free; deleting 0.3 MB gives 0.64, then 0.2 MB gives 0.84 >= 0.7: two, no more
    assert [d.path.name for d in done] == NAMES[:2]
    assert [round(d.size_mb, 1) for d in done] == [0.3, 0.2]
    assert done[0].reason == "less than 0.7 MB free"
    assert (tmp_path / NAMES[2]).exists()


def test_a_flight_deletes_the_oldest_and_says_so(tmp_path: Path) -> None:
    root = tmp_path / "flights"
    make_flights(root, [20, 20, 20])
    (tmp_path / "params.parm").write_text("LOG_MAX_FLIGHTS 2\n")
    proc = subprocess.run(sim_cmd(tmp_path, "--fast", "--duration", "3", "--json"),
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads(proc.stdout)
    deleted = [d["flight"] for d in summary["disk_policy_deleted"]]
    assert deleted == NAMES[:2]
    left = sorted(p.name for p in root.iterdir())
    assert left[0] == NAMES[2] and len(left) == 2  # the newest old one and this flight
    notices = [e["detail"] for e in summary["events"] if e["kind"] == "notice"]
    assert any(f"deleted flight {NAMES[0]}" in n and "more than 2 flights" in n for n in notices)
    assert "disk policy: deleted flight" in proc.stderr
