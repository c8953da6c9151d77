"""A campaign as one Parquet dataset: two real SITL flights of two vehicles, queried with DuckDB.

The flights are flown by the real `companion sim` (8 s, 5x faster than real time, one process,
two vehicles, a GPS thread fault at 3 s so that there is a restart to count); every figure the
queries give is checked against the logs read with `read_log` or against the flight's JSON.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.logs import cli, read_log
from companion.logs.archive import FlightArchive
from companion.logs.dataset import QueryError, query

SIM_TIMEOUT_S = 120
INCLINATION_SQL = """
SELECT e.vehicle, e.flight,
       avg(degrees(abs(acos(cos(e.roll_rad) * cos(e.pitch_rad))
                       - acos(cos(t.roll_rad) * cos(t.pitch_rad))))) AS incl_err_deg
FROM estimator_fmt1 e ASOF JOIN truth_fmt1 t ON e.flight = t.flight AND e.time_ns >= t.time_ns
WHERE e.aligned = 1
GROUP BY ALL ORDER BY e.flight
"""


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two 8 s flights (vehicles 1 and 2) of one `companion sim --vehicles 2` run."""
    work = tmp_path_factory.mktemp("sim")
    cmd = [sys.executable, "-m", "companion", "sim", "--duration", "8", "--fast", "--vehicles", "2",
           "--mavlink", "none", "--no-legacy", "--thread-fault", "gps:raise:3",
           "--log-dir", str(work / "flights"), "--params-file", str(work / "p.parm")]
    done = subprocess.run(cmd, cwd=work, capture_output=True, text=True, timeout=SIM_TIMEOUT_S)
    assert done.returncode == 0, done.stderr[-2000:]
    # vehicle 1 first: by the "-v<id>" suffix, not by name (the two aircraft may start in
    # different seconds on a busy machine, and a name sorts by its time stamp first)
    dirs = sorted((work / "flights").iterdir(),
                  key=lambda d: int(d.name.rpartition("-v")[2]) if "-v" in d.name else 1)
    assert len(dirs) == 2, dirs
    return dirs


@pytest.fixture(scope="module")
def dataset(flights: list[Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("campaign") / "ds"
    assert cli.main(["export", "--dataset", str(out), str(flights[0].parent)]) == 0
    return out


def _run(flight: Path) -> dict:  # type: ignore[type-arg]
    return json.loads((flight / "run.json").read_text())


def _files(root: Path) -> dict[str, int]:
    return {str(p.relative_to(root)): p.stat().st_size for p in sorted(root.rglob("*")) if p.is_file()}


def test_every_record_of_every_stream_is_a_row_with_its_vehicle_and_flight(
        flights: list[Path], dataset: Path) -> None:
    expected_pairs = {(_run(f)["config"]["vehicle"]["id"], f.name) for f in flights}
    assert {v for v, _ in expected_pairs} == {1, 2}
    for flight in flights:
        for log_path in sorted(flight.glob("*.bin")):
            lf = read_log(log_path)
            for s in lf.streams:
                stream = f"{log_path.stem}_fmt{s.index}" + (f"_{s.number}" if s.number > 1 else "")
                _, rows = query(dataset, f"SELECT count(*) FROM {stream} WHERE flight = '{flight.name}'")
                assert rows[0][0] == s.data.size > 0, (flight.name, stream)
    _, pairs = query(dataset, "SELECT DISTINCT vehicle, flight FROM imu_fmt1")
    assert set(pairs) == expected_pairs
    _, pairs = query(dataset, "SELECT vehicle, flight FROM flights")
    assert set(pairs) == expected_pairs
    cols, rows = query(dataset, "SELECT * FROM gps_fmt1 LIMIT 1")
    assert cols[:2] == ["time_s", "time_ns"] and "lat_deg" in cols and "vehicle" in cols


def test_flights_and_restarts_tables_hold_the_runs_json(flights: list[Path], dataset: Path) -> None:
    _, rows = query(dataset, "SELECT thread, sum(restarts) FROM restarts GROUP BY thread ORDER BY thread")
    per_thread = dict(rows)
    summaries = [json.loads((f / "summary.json").read_text()) for f in flights]
    for name in per_thread:
        assert per_thread[name] == sum(t["restarts"] for s in summaries for t in s["threads"]
                                       if t["name"] == name)
    assert per_thread["gps"] == 2 and per_thread["imu"] == 0
    cols, rows = query(dataset, "SELECT flight, start_utc, seed, scenario, faults, restarts, "
                                "restarts_by_thread['gps'], complete, problems, duration_s "
                                "FROM flights ORDER BY flight")
    by_name = sorted(flights, key=lambda f: f.name)  # the query's order, not the vehicles'
    for flight, row in zip(by_name, rows, strict=True):
        run = _run(flight)
        assert row[0] == flight.name
        assert row[1].isoformat() == run["started_utc"]
        assert row[2] == run["simulation"]["seed"] and row[3] == run["simulation"]["scenario"]
        assert row[4] == ["thread-fault=gps:raise:3"]
        assert row[5] == 1 and row[6] == 1 and row[7] is True and row[8] == []
        assert 7.0 < row[9] < 10.0


def test_inclination_error_per_flight_matches_numpy(flights: list[Path], dataset: Path) -> None:
    _, rows = query(dataset, INCLINATION_SQL)
    by_name = sorted(flights, key=lambda f: f.name)  # the query's order, not the vehicles'
    assert [r[1] for r in rows] == [f.name for f in by_name]
    for flight, (_, _, got) in zip(by_name, rows, strict=True):
        est, truth = read_log(flight / "estimator.bin"), read_log(flight / "truth.bin")
        e, e_ns = est.data(1), est.time_ns(1)
        t, t_ns = truth.data(1), truth.time_ns(1)
        k = np.searchsorted(t_ns, e_ns, side="right") - 1  # the last truth at or before
        keep = (k >= 0) & (e["aligned"] == 1)
        e, k = e[keep], k[keep]

        def incl(r: np.ndarray, p: np.ndarray) -> np.ndarray:
            r, p = r.astype(np.float64), p.astype(np.float64)  # SQL computes in DOUBLE
            return np.arccos(np.cos(r) * np.cos(p))

        want = np.degrees(np.abs(incl(e["roll_rad"], e["pitch_rad"])
                                 - incl(t["roll_rad"][k], t["pitch_rad"][k]))).mean()
        assert got == pytest.approx(want, rel=1e-9)
        assert 0.0 < got < 5.0


def test_reexport_replaces_the_flight(flights: list[Path], dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "ds"
    shutil.copytree(dataset, out)
    before = _files(out / "streams")
    assert cli.main(["export", "--dataset", str(out), *map(str, flights)]) == 0
    assert _files(out / "streams") == before
    _, rows = query(out, "SELECT count(*), count(DISTINCT flight) FROM flights")
    assert rows == [(2, 2)]
    _, rows = query(out, "SELECT count(*) FROM restarts")
    assert rows == [(10, )]
    # a replacement, not a merge: a stream gone from the flight is gone from the dataset
    copy = shutil.copytree(flights[1], tmp_path / flights[1].name)
    (copy / "truth.bin").unlink()
    assert cli.main(["export", "--dataset", str(out), str(copy)]) == 0
    _, rows = query(out, "SELECT flight, count(*) FROM truth_fmt1 GROUP BY flight")
    assert [r[0] for r in rows] == [flights[0].name]


def test_a_cut_flight_is_exported_as_far_as_it_reads(
        flights: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cut = shutil.copytree(flights[0], tmp_path / "cut-flight")
    (cut / "summary.json").unlink()
    imu = cut / "imu.bin"
    offsets = read_log(imu).streams_of(1)[0].offsets
    imu.write_bytes(imu.read_bytes()[: int(offsets[offsets.size // 2]) + 3])  # inside a record
    out = tmp_path / "ds"
    assert cli.main(["export", "--dataset", str(out), str(cut)]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "summary.json is missing" in err and "imu.bin: cut short" in err
    salvaged = read_log(imu, salvage=True).data(1).size
    assert 0 < salvaged < read_log(flights[0] / "imu.bin").data(1).size
    _, rows = query(out, "SELECT count(*) FROM imu_fmt1")
    assert rows == [(salvaged, )]
    _, rows = query(out, "SELECT vehicle, complete, len(problems) > 0, stop_reason FROM flights")
    assert rows == [(1, False, True, None)]
    # without a summary, restarts come from the Begin Data records of each thread's log
    _, rows = query(out, "SELECT thread, restarts, source FROM restarts ORDER BY thread")
    assert ("gps", 1, "log markers") in rows and ("imu", 0, "log markers") in rows
    assert all(r[0] != "truth" for r in rows)  # the simulator's log is no thread


def test_a_flight_archive_is_a_flight(flights: list[Path], tmp_path: Path) -> None:
    saved = FlightArchive.snapshot(flights[1]).write_to(tmp_path / "log_2_2026-1-1.bin")
    out = tmp_path / "ds"
    assert cli.main(["export", "--dataset", str(out), str(saved)]) == 0
    _, rows = query(out, "SELECT DISTINCT vehicle, flight FROM servo_fmt1")
    assert rows == [(2, flights[1].name)]


def test_bad_sql_is_one_clear_line(dataset: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["query", str(dataset), "SELEC count(*) FROM flights"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: Parser Error") and "\n" not in err
    assert cli.main(["query", str(dataset), "SELECT nope FROM flights"]) == 1
    err = capsys.readouterr().err.strip()
    assert "nope" in err and "\n" not in err
    assert cli.main(["query", str(dataset.parent / "absent"), "SELECT 1"]) == 1
    assert "not a dataset" in capsys.readouterr().err
    with pytest.raises(QueryError):
        query(dataset, "SELECT * FROM no_such_stream")


def test_query_output_forms(dataset: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sql = "SELECT thread, sum(restarts) AS n FROM restarts GROUP BY thread ORDER BY thread"
    assert cli.main(["query", str(dataset), sql, "--csv"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "thread,n" and "gps,2" in lines
    assert cli.main(["query", str(dataset), sql, "--json"]) == 0
    assert {"thread": "gps", "n": 2} in json.loads(capsys.readouterr().out)
    assert cli.main(["query", str(dataset), sql]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].split() == ["thread", "n"] and table[-1] == "(5 rows)"
