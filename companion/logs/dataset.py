"""A campaign of flights as one Parquet dataset, and SQL over it with DuckDB.

Why: the questions of a campaign cross flights ("restarts per thread across the campaign",
"inclination error per flight"), and one file per log per flight makes each such question a
script. Written once as one hive-partitioned dataset, every stream of every flight is one table
for DuckDB, pyarrow, Spark or Dask, with ``vehicle`` and ``flight`` columns from the paths::

    DIR/streams/vehicle=<id>/flight=<flight>/stream=<log>_fmt<index>[_<n>]/part-0.parquet
    DIR/flights/<flight>.parquet     one row per flight (start, duration, scenario, faults...)
    DIR/restarts/<flight>.parquet    one row per thread of the flight

Streams of different logs have different columns, so each stream is a partition of its own and
a reader picks one with a glob on ``stream=...``. The flight tables are one file per flight so
that re-exporting a flight replaces exactly its files (the flight's directory name is its key):
the new files are written in a staging directory inside DIR and renamed into place.

A damaged or incomplete flight (no summary.json, a cut log) is exported as far as it reads, and
what is missing is in `FlightExport.problems` and in the ``problems`` column of ``flights``.

Why the flight is read here and not with `companion.report.flight.load_flight`: the report is a
tool layer above the logs (docs/architecture.md, tests/test_architecture.py), so this module
reads run.json, summary.json and the logs with the logs layer's own reader (salvaging damage);
a log that lost its Format Definitions is not restored here (the report can restore it).
"""

from __future__ import annotations

import csv
import glob
import io
import json
import logging
import os
import re
import shutil
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from decimal import Decimal
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pyarrow as pa
import pyarrow.parquet as pq

from companion.logs.convert import csv_name, input_files
from companion.logs.reader import read_log
from companion.logs.records import NS_PER_S
from companion.logs.streams import LogFile, LogFormatError, Stream

if TYPE_CHECKING:
    import duckdb

__all__ = [
    "FLIGHTS_SCHEMA",
    "RESTARTS_SCHEMA",
    "FlightExport",
    "QueryError",
    "connect",
    "export_flight",
    "flight_dirs",
    "query",
    "render",
    "stream_names",
    "stream_table",
]

log = logging.getLogger(__name__)

_SAFE_NAME = re.compile(r"[^A-Za-z0-9.+-]")  # hive values: no '=', '/', '%', spaces or '_'-start
_VEHICLE_SUFFIX = re.compile(r"-v(\d+)$")  # `companion sim --vehicles K` names: <time>-v<k>
_HIVE_TYPES = "{'vehicle': BIGINT, 'flight': VARCHAR, 'stream': VARCHAR}"
#: Options of `companion sim` that inject faults, keyed by their run.json field.
_FAULT_OPTIONS = {"faults": "fault", "vanish": "vanish", "thread_faults": "thread-fault",
                  "clock_steps": "clock-step"}

FLIGHTS_SCHEMA = pa.schema([
    ("vehicle", pa.int64()),
    ("flight", pa.string()),
    ("start_utc", pa.timestamp("us", tz="UTC")),
    ("duration_s", pa.float64()),
    ("scenario", pa.string()),
    ("seed", pa.int64()),
    ("aircraft", pa.string()),
    ("wind_ned_m_s", pa.list_(pa.float64())),
    ("config_json", pa.string()),
    ("stop_reason", pa.string()),
    ("complete", pa.bool_()),
    ("restarts", pa.int64()),
    ("restarts_by_thread", pa.map_(pa.string(), pa.int64())),
    ("faults", pa.list_(pa.string())),
    ("problems", pa.list_(pa.string())),
    ("streams", pa.int64()),
    ("records", pa.int64()),
])

RESTARTS_SCHEMA = pa.schema([
    ("vehicle", pa.int64()),
    ("flight", pa.string()),
    ("thread", pa.string()),
    ("restarts", pa.int64()),
    ("crashes", pa.int64()),
    ("source", pa.string()),  # "summary.json", or "log markers" when the flight has no summary
])


class QueryError(ValueError):
    """A query that DuckDB refused, or a directory that holds no dataset; one line of text."""


@dataclass
class FlightExport:
    """What `export_flight` wrote for one flight, and what it could not read."""

    flight: str
    vehicle: int
    partition: Path
    streams: int = 0
    records: int = 0
    problems: list[str] = field(default_factory=list)


def stream_table(stream: Stream) -> pa.Table:
    """One stream as an Arrow table: the reader's columns (Data Blocks get the exact ``time_ns``
    next to ``time_s``), with the format string and column names in the schema metadata."""
    frame = stream.to_pandas()
    if stream.kind == "block":
        frame.insert(1, "time_ns", stream.time_ns)
    table = pa.Table.from_pandas(frame, preserve_index=False)
    meta = dict(table.schema.metadata or {})
    meta[b"uavlog"] = json.dumps({"index": stream.index, "kind": stream.kind,
                                  "format": stream.format, "columns": list(stream.columns)}).encode()
    return table.replace_schema_metadata(meta)


def flight_dirs(path: Path) -> list[Path]:
    """`path` when it is a flight directory; its flight sub-directories when it holds flights
    (a ``--log-dir`` of many runs) and no log of its own."""
    if _is_flight(path) or not path.is_dir():
        return [path]
    subs = sorted(p for p in path.iterdir() if p.is_dir() and _is_flight(p))
    return subs or [path]


def _is_flight(path: Path) -> bool:
    return (path / "run.json").is_file() or (path / "summary.json").is_file() or bool(
        input_files([path]) if path.is_dir() else False)


def _json_object(path: Path, problems: list[str]) -> dict[str, Any] | None:
    try:
        value = json.loads(path.read_bytes())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        problems.append(f"{path.name}: unreadable, ignored ({exc})")
        return None
    if isinstance(value, dict):
        return value
    problems.append(f"{path.name}: not a JSON object, ignored")
    return None


def _read_logs(flight_dir: Path, problems: list[str]) -> dict[str, LogFile]:
    """Every log of the flight, read past damage; what was skipped goes to `problems`."""
    out: dict[str, LogFile] = {}
    for path in input_files([flight_dir]):
        try:
            lf = read_log(path, salvage=True)
        except (OSError, LogFormatError) as exc:
            problems.append(f"{path.name}: not exported ({exc})")
            continue
        lost = [f"{len(lf.damage)} damaged region(s), {lf.skipped_bytes} bytes skipped"] if lf.damage else []
        if lf.truncated_bytes:
            lost.append(f"cut short ({lf.truncated_bytes} bytes at the end dropped)")
        if not lf.closed_cleanly:
            lost.append("not closed cleanly")
        if lost:
            problems.append(f"{path.name}: " + ", ".join(lost))
        out[path.stem] = lf
    return out


def _vehicle(run: dict[str, Any] | None, name: str, problems: list[str]) -> int:
    """The vehicle id: run.json's configuration, else its SYS_VEHICLE_ID, else the ``-v<k>``
    of the directory name; 0 (never a vehicle: MAVLink's broadcast id) when nothing says."""
    run = run or {}
    for value in ((run.get("config") or {}).get("vehicle", {}).get("id"),
                  (run.get("parameters") or {}).get("SYS_VEHICLE_ID")):
        if isinstance(value, int | float):
            return int(value)
    match = _VEHICLE_SUFFIX.search(name)
    if match:
        return int(match.group(1))
    problems.append("vehicle id unknown (no run.json): exported as vehicle=0")
    return 0


def _start(run: dict[str, Any] | None, logs: dict[str, LogFile]) -> tuple[datetime | None, float]:
    """Start (run.json's ``started_utc``, else the first Begin Data) and the seconds from the
    first Begin Data (else the first record) to the last record or marker of any log."""
    begins = [m.time_ns for name, lf in logs.items() if name != "truth"
              for m in lf.markers if m.kind == "begin"]
    times = [t for lf in logs.values() for s in lf.streams if s.n_records
             for t in (int(s.time_ns.min()), int(s.time_ns.max()))]
    times += [m.time_ns for lf in logs.values() for m in lf.markers]
    t0 = min(begins) if begins else min(times, default=0)
    duration_s = (max(times) - t0) / NS_PER_S if times else 0.0
    start = None
    if run and isinstance(run.get("started_utc"), str):
        try:
            start = datetime.fromisoformat(run["started_utc"])
        except ValueError:
            start = None
    if start is None and (begins or times):
        start = datetime.fromtimestamp(t0 / NS_PER_S, tz=UTC)
    return start, duration_s


def _faults(run: dict[str, Any] | None, summary: dict[str, Any] | None) -> list[str]:
    """Injected faults as the `companion sim` options that injected them."""
    sim = (run or {}).get("simulation") or {}
    out = [f"{option}={spec}" for key, option in _FAULT_OPTIONS.items()
           for spec in sim.get(key) or ()]
    if not sim and summary:  # no run.json: the summary still lists the thread faults
        out += [f"thread-fault={f.get('thread')}:{f.get('kind')}:{f.get('at_s')}"
                for f in summary.get("thread_faults") or () if isinstance(f, dict)]
    return out


def _restarts(run: dict[str, Any] | None, summary: dict[str, Any] | None,
              logs: dict[str, LogFile]) -> list[tuple[str, int, int | None, str]]:
    """(thread, restarts, crashes, source): the summary's counts, or, for a flight that never
    wrote one, one per Begin Data after the first in the thread's log (each start writes one)."""
    threads = [t for t in (summary or {}).get("threads") or () if isinstance(t, dict)]
    if threads:
        return [(str(t.get("name")), int(t.get("restarts") or 0), int(t.get("crashes") or 0),
                 "summary.json") for t in threads]
    names = [str(t.get("name")) for t in (run or {}).get("threads") or () if isinstance(t, dict)]
    return [(name, max(0, sum(m.kind == "begin" for m in lf.markers) - 1), None, "log markers")
            for name, lf in logs.items() if not names or name in names]


def export_flight(flight_dir: Path, dataset_dir: Path) -> FlightExport:
    """Write every stream of the flight in `flight_dir` into the dataset `dataset_dir`, with its
    rows of ``flights`` and ``restarts``, replacing what an earlier export of it wrote.

    Reading never raises: what could not be read is in the result's `problems`. Writing raises
    OSError (a full disk, no permission); the dataset then still holds the flight's old files.
    """
    problems: list[str] = []
    name = _SAFE_NAME.sub("_", flight_dir.resolve().name)
    if name != flight_dir.resolve().name:
        problems.append(f"directory name {flight_dir.resolve().name!r} exported as flight={name}")
    run = _json_object(flight_dir / "run.json", problems)
    summary = _json_object(flight_dir / "summary.json", problems)
    if run is None and not (flight_dir / "run.json").exists():
        problems.append("run.json is missing (no configuration or scenario)")
    if summary is None and not (flight_dir / "summary.json").exists():
        problems.append("summary.json is missing (the flight did not end normally)")
    logs = _read_logs(flight_dir, problems)
    if not logs:
        problems.append("no .bin/.uavlog log in the flight")
    vehicle = _vehicle(run, name, problems)
    result = FlightExport(name, vehicle, dataset_dir / "streams" / f"vehicle={vehicle}" / f"flight={name}")

    dataset_dir.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".staging-", dir=dataset_dir))
    try:
        part = staging / "part"
        part.mkdir()
        for log_name, lf in logs.items():
            for s in lf.streams:
                stream_dir = part / f"stream={_SAFE_NAME.sub('_', log_name)}_{_fmt_key(s)}"
                stream_dir.mkdir()
                table = stream_table(s)
                pq.write_table(table, stream_dir / "part-0.parquet")
                result.streams += 1
                result.records += table.num_rows
        restarts = _restarts(run, summary, logs)
        start, duration_s = _start(run, logs)
        sim = (run or {}).get("simulation") or {}
        wind = sim.get("wind_ned_m_s")
        row = {
            "vehicle": vehicle, "flight": name, "start_utc": start, "duration_s": duration_s,
            "scenario": sim.get("scenario"), "seed": sim.get("seed"), "aircraft": sim.get("aircraft"),
            "wind_ned_m_s": [float(w) for w in wind] if isinstance(wind, list) else None,
            "config_json": json.dumps(run["config"], sort_keys=True) if run and "config" in run else None,
            "stop_reason": (summary or {}).get("stop_reason"),
            "complete": summary is not None and not problems,
            "restarts": sum(r[1] for r in restarts),
            "restarts_by_thread": [(r[0], r[1]) for r in restarts],
            "faults": _faults(run, summary), "problems": problems,
            "streams": result.streams, "records": result.records,
        }
        pq.write_table(pa.Table.from_pylist([row], schema=FLIGHTS_SCHEMA), staging / "flights.parquet")
        rows = [dict(zip(RESTARTS_SCHEMA.names, (vehicle, name, *r), strict=True)) for r in restarts]
        pq.write_table(pa.Table.from_pylist(rows, schema=RESTARTS_SCHEMA), staging / "restarts.parquet")
        _replace(dataset_dir, name, staging, result.partition)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    result.problems = problems
    log.info("%s: %d streams, %d rows into %s", name, result.streams, result.records, result.partition)
    return result


def _fmt_key(stream: Stream) -> str:
    return csv_name("", stream.index, stream.number)[1:].removesuffix(".csv")


def _replace(dataset_dir: Path, name: str, staging: Path, partition: Path) -> None:
    """Swap the staged files in: the flight's old partition (under any vehicle id an earlier
    export gave it) moves into the staging directory, which the caller removes."""
    old = staging / "old"
    old.mkdir()
    for k, previous in enumerate((dataset_dir / "streams").glob(f"vehicle=*/flight={glob.escape(name)}")):
        os.rename(previous, old / str(k))
        if previous.parent != partition.parent:
            try:
                previous.parent.rmdir()  # a vehicle directory left empty
            except OSError:
                pass
    partition.parent.mkdir(parents=True, exist_ok=True)
    os.rename(staging / "part", partition)
    for table in ("flights", "restarts"):
        (dataset_dir / table).mkdir(exist_ok=True)
        os.replace(staging / f"{table}.parquet", dataset_dir / table / f"{name}.parquet")


# --------------------------------------------------------------------------------- query
def stream_names(dataset_dir: Path) -> list[str]:
    """Every stream name found in the dataset (each becomes a view of `connect`)."""
    found = {p.name.partition("=")[2]
             for p in (dataset_dir / "streams").glob("vehicle=*/flight=*/stream=*")}
    return sorted(found)


def _literal(text: str) -> str:
    return "'" + text.replace("'", "''") + "'"


def _identifier(text: str) -> str:
    return '"' + text.replace('"', '""') + '"'


def connect(dataset_dir: Path) -> duckdb.DuckDBPyConnection:
    """An in-memory DuckDB connection with the views ``flights``, ``restarts`` and one per stream
    (e.g. ``imu_fmt1``) over every flight, with ``vehicle`` and ``flight`` from the paths."""
    import duckdb

    if not (dataset_dir / "flights").is_dir():
        raise QueryError(f"{dataset_dir}: not a dataset (no flights/ in it: "
                         "write one with companion logs export --dataset)")
    con = duckdb.connect()
    con.execute("SET TimeZone = 'UTC'")  # start_utc prints as UTC whatever the machine's zone
    root = dataset_dir.resolve()
    for table in ("flights", "restarts"):
        files = _literal(str(root / table / "*.parquet"))
        con.execute(f"CREATE VIEW {table} AS SELECT * FROM read_parquet({files}, union_by_name=true)")
    for stream in stream_names(dataset_dir):
        files = _literal(str(root / "streams" / "*" / "*" / f"stream={stream}" / "*.parquet"))
        con.execute(f"CREATE VIEW {_identifier(stream)} AS SELECT * FROM read_parquet({files}, "
                    f"hive_partitioning=true, hive_types={_HIVE_TYPES}, union_by_name=true)")
    return con


def query(dataset_dir: Path, sql: str) -> tuple[list[str], list[tuple[Any, ...]]]:
    """Column names and rows of `sql` run over the dataset; QueryError (one line) if refused."""
    import duckdb

    try:
        con = connect(dataset_dir)
    except duckdb.Error as exc:
        raise QueryError(_first_line(exc)) from exc
    try:
        rel = con.sql(sql)
        if rel is None:  # a statement without a result (SET, CREATE ...)
            return [], []
        # through Arrow: DuckDB's own conversion of TIMESTAMPTZ to Python needs pytz
        to_arrow = getattr(rel, "to_arrow_table", None) or rel.fetch_arrow_table  # DuckDB < 1.4
        table = to_arrow()
        return table.column_names, [tuple(r.values()) for r in table.to_pylist()]
    except duckdb.Error as exc:
        raise QueryError(_first_line(exc)) from exc
    finally:
        con.close()


def _first_line(exc: Exception) -> str:
    return next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)


def render(columns: Sequence[str], rows: Iterable[Sequence[Any]], how: str = "table",
           max_rows: int = 100) -> str:
    """Rows as an aligned text table (at most `max_rows`, saying how many were left out),
    ``csv`` or ``json`` (a list of objects; timestamps and other non-JSON values as text)."""
    rows = list(rows)
    if how == "json":
        return json.dumps([dict(zip(columns, r, strict=True)) for r in rows], default=_json_value,
                          indent=1)
    if how == "csv":
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(columns)
        writer.writerows(rows)
        return buf.getvalue().rstrip("\n")
    shown = [[_cell(v) for v in r] for r in rows[:max_rows]]
    widths = [max([len(c), *(len(r[k]) for r in shown)]) for k, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths, strict=True)),
             "  ".join("-" * w for w in widths)]
    right = [all(isinstance(r[k], int | float | Decimal) for r in rows[:max_rows] if r[k] is not None)
             for k in range(len(columns))]  # numbers right-aligned, text left-aligned
    lines += ["  ".join(v.rjust(w) if ra else v.ljust(w)
                        for v, w, ra in zip(r, widths, right, strict=True)) for r in shown]
    more = len(rows) - len(shown)
    lines.append(f"({len(rows)} rows" + (f", {more} not shown: use --csv or --json)" if more else ")"))
    return "\n".join(lines)


def _json_value(value: Any) -> Any:
    """What `json` cannot write: DuckDB's sums (Decimal) as numbers, timestamps as ISO text."""
    if isinstance(value, Decimal):
        return int(value) if value == value.to_integral_value() else float(value)
    if isinstance(value, datetime):
        return value.isoformat()
    return str(value)


def _cell(value: Any) -> str:
    if value is None:
        return "NULL"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)
