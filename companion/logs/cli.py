"""``companion logs ...``: convert binary logs to CSV, describe them, export them.

Registered by the main CLI through `add_commands`; every handler returns the exit code:
0 success, 1 a file could not be read (or is damaged, with ``--strict``), 2 usage errors. Damage
is skipped and reported with its byte offsets by default; ``--salvage`` is accepted for older
scripts and changes nothing.

Every command also takes a flight archive (what a ground station downloads from the vehicle's
log list, saved as ``.bin``, ``.ulg`` or anything: see `companion.logs.archive`) where it takes
a log file or directory: the archive is unpacked once next to itself and the command works on
the flight's logs.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

# The main CLI imports this module to build its parser for every `companion ...` command, so
# the libraries a command needs are imported in the command (docs/architecture.md).
if TYPE_CHECKING:
    from companion.logs.streams import LogFile

__all__ = ["add_commands", "flight_of_archive", "main"]


def add_commands(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``convert``, ``info`` and ``export`` to the sub-parsers of the main CLI's ``logs``."""
    c = sub.add_parser("convert", help="binary logs -> one CSV per format index")
    c.add_argument(
        "paths", nargs="+", metavar="FILE_OR_DIR",
        help="log files, directories of *.bin, or downloaded flight archives",
    )
    c.add_argument(
        "-o", "--out-dir", type=Path, help="output directory (default: next to each input)"
    )
    _damage_flags(c)
    c.set_defaults(func=cmd_convert)

    i = sub.add_parser("info", help="formats, record counts, time span, markers, damage")
    i.add_argument("path", type=Path, metavar="FILE_OR_DIR",
                   help="a log file, a flight directory (every *.bin log in it, and a total) "
                   "or a flight archive (every log in it)")
    _damage_flags(i)
    i.add_argument("--json", action="store_true", help="machine-readable output")
    i.set_defaults(func=cmd_info)

    e = sub.add_parser("export", help="export to Parquet (one file per format) or one .npz; "
                       "--dataset: many flights as one Parquet dataset")
    e.add_argument("path", type=Path, metavar="FILE", nargs="+",
                   help="a log file, or a flight archive (every log in it); with --dataset: "
                   "flight directories, archives, or directories of flights")
    e.add_argument("--to", choices=("parquet", "npz"), help="required without --dataset")
    e.add_argument("--dataset", type=Path, metavar="DIR",
                   help="write every stream of every FLIGHT into the hive-partitioned Parquet "
                   "dataset DIR, with the tables flights and restarts (docs/logs.md)")
    e.add_argument(
        "-o",
        "--out",
        type=Path,
        help="npz: output file (a directory for an archive); parquet: output directory "
        "(default: next to FILE, in the unpacked flight for an archive)",
    )
    _damage_flags(e)
    e.set_defaults(func=cmd_export)

    q = sub.add_parser("query", help="SQL (DuckDB) over a dataset written by export --dataset")
    q.add_argument("dataset", type=Path, metavar="DIR")
    q.add_argument("sql", metavar="SQL",
                   help="views: flights, restarts, and one per stream (e.g. imu_fmt1)")
    how = q.add_mutually_exclusive_group()
    how.add_argument("--csv", action="store_true", help="CSV output (every row)")
    how.add_argument("--json", action="store_true", help="JSON output (every row)")
    q.set_defaults(func=cmd_query)


def flight_of_archive(path: Path) -> Path | None:
    """The flight directory of the archive `path`, unpacked next to it unless it already is;
    says where on stderr. None (after printing the error) when the archive is unusable."""
    from companion.logs.archive import ArchiveError, unpack

    try:
        done = unpack(path)
    except ArchiveError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None
    except OSError as exc:
        print(f"error: unpacking {path}: {exc.strerror or exc}", file=sys.stderr)
        return None
    verb = "already unpacked in" if done.reused else "unpacked into"
    print(f"{path}: flight archive {verb} {done.flight_dir}", file=sys.stderr)
    return done.flight_dir


def _log_inputs(paths: list[Path]) -> tuple[list[Path], bool]:
    """Log files named by `paths` (directories expanded), archives replaced by the logs of
    their unpacked flight; and whether every archive could be unpacked."""
    from companion.logs.archive import is_archive
    from companion.logs.convert import input_files

    out: list[Path] = []
    ok = True
    for p in input_files(paths):
        if not is_archive(p):
            out.append(p)
            continue
        flight = flight_of_archive(p)
        if flight is None:
            ok = False
        else:
            out.extend(input_files([flight]))
    return out, ok


def _damage_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--strict", action="store_true",
                   help="fail on a damaged file (default: skip damaged regions and report them)")
    p.add_argument("--salvage", action="store_true",
                   help="accepted for older scripts: skipping damage is the default")


def _read(path: Path, strict: bool) -> LogFile | None:
    from companion.logs.reader import read_log
    from companion.logs.streams import LogFormatError

    try:
        lf = read_log(path, strict=strict)
    except LogFormatError as exc:
        print(f"error: {exc} (without --strict the damaged regions are skipped)",
              file=sys.stderr)
        return None
    except OSError as exc:
        print(f"error: cannot read {path}: {exc.strerror or exc}", file=sys.stderr)
        return None
    for w in lf.warnings:
        print(f"warning: {w}", file=sys.stderr)
    for d in lf.damage:
        print(
            f"warning: {path}: byte offset {d.offset}: {d.message}; skipped {d.skipped_bytes} bytes",
            file=sys.stderr,
        )
    return lf


class _Progress:
    """A one-line progress counter on stderr, shown only on a terminal, at most 10 times/s."""

    def __init__(self, label: str) -> None:
        self.label = label
        self.enabled = sys.stderr.isatty()
        self.last = 0.0
        self.shown = False

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if not self.enabled or (now - self.last < 0.1 and done < total):
            return
        self.last = now
        pct = 100.0 * done / total if total else 100.0
        print(
            f"\r{self.label}: {pct:5.1f}% ({done}/{total} records)",
            end="",
            file=sys.stderr,
            flush=True,
        )
        self.shown = True

    def done(self) -> None:
        if self.shown:
            print(file=sys.stderr)


def cmd_convert(args: argparse.Namespace) -> int:
    from companion.logs.convert import convert_file

    files, ok = _log_inputs([Path(p) for p in args.paths])
    if not files:
        if ok:
            print("error: no .bin/.uavlog files found in the given directories", file=sys.stderr)
        return 1
    status = 0 if ok else 1
    for path in files:
        lf = _read(path, args.strict)
        if lf is None:
            status = 1
            continue
        progress = _Progress(f"converting {path.name}")
        try:
            out = convert_file(path, args.out_dir, progress=progress, log_file=lf)
        except OSError as exc:
            progress.done()
            print(f"error: writing CSV for {path}: {exc}", file=sys.stderr)
            status = 1
            continue
        progress.done()
        for p in out:
            print(p)
    return status


def _info_dict(lf: LogFile) -> dict[str, Any]:
    from companion.logs.convert import format_time

    times = [int(s.time_ns.min()) for s in lf.streams if s.n_records] + [
        m.time_ns for m in lf.markers
    ]
    times_end = [int(s.time_ns.max()) for s in lf.streams if s.n_records] + [
        m.time_ns for m in lf.markers
    ]
    return {
        "file": lf.path,
        "size_bytes": lf.size_bytes,
        "records": lf.record_count,
        "closed_cleanly": lf.closed_cleanly,
        "start": format_time(min(times)) if times else None,
        "end": format_time(max(times_end)) if times_end else None,
        "span_s": (max(times_end) - min(times)) / 1e9 if times else None,
        "formats": [
            {
                "index": s.index,
                "stream": s.number,
                "kind": s.kind,
                "format": s.format,
                "columns": list(s.columns),
                "records": s.n_records,
                "first": format_time(int(s.time_ns.min())) if s.n_records else None,
                "last": format_time(int(s.time_ns.max())) if s.n_records else None,
                "defined_at": s.definition_offset,
            }
            for s in lf.streams
        ],
        "begin_end": [
            {
                "begin": format_time(b.time_ns) if b else None,
                "end": format_time(e.time_ns) if e else None,
            }
            for b, e in lf.begin_end_pairs()
        ],
        "truncated_bytes": lf.truncated_bytes,
        "damage": [
            {
                "offset": d.offset,
                "kind": d.kind,
                "message": d.message,
                "skipped_bytes": d.skipped_bytes,
            }
            for d in lf.damage
        ],
    }


def cmd_info(args: argparse.Namespace) -> int:
    """A log file, a flight directory (each log, then a total) or a flight archive."""
    from companion.logs.archive import is_archive
    from companion.logs.convert import input_files

    path: Path = args.path
    if not path.exists():
        print(f"error: cannot read {path}: no such file or directory", file=sys.stderr)
        return 1
    if path.is_dir():
        try:
            files = input_files([path])
        except OSError as exc:
            print(f"error: cannot list {path}: {exc.strerror or exc}", file=sys.stderr)
            return 1
        if not files:
            print(f"error: {path}: no .bin/.uavlog log in this directory", file=sys.stderr)
            return 1
        return _info_many(files, args.strict, args.json, total=True)
    if not is_archive(path):
        return _info_one(path, args.strict, args.json, None)
    files, ok = _log_inputs([path])
    if not ok:
        return 1
    if not files:
        print(f"error: {path}: the flight holds no .bin/.uavlog file", file=sys.stderr)
        return 1
    return _info_many(files, args.strict, args.json, total=False)


def _info_many(files: list[Path], strict: bool, as_json: bool, *, total: bool) -> int:
    """One block per log (a JSON list with --json); with `total`, a last line adding them up.
    A log that cannot be read is its error line, and the exit status is 1."""
    infos: list[dict[str, Any]] = []
    status = 0
    for k, path in enumerate(files):
        if k and not as_json:
            print()
        status |= _info_one(path, strict, as_json, infos)
    if as_json:
        print(json.dumps(infos, indent=2))  # one list: one JSON document
    elif total:
        size = sum(i["size_bytes"] for i in infos)
        records = sum(i["records"] for i in infos)
        failed = len(files) - len(infos)
        print(f"\ntotal: {len(infos)} log(s), {size} bytes ({size / 1e6:.1f} MB), {records} records"
              + (f"; {failed} log(s) unreadable" if failed else ""))
    return status


def _info_one(path: Path, strict: bool, as_json: bool,
              collect: list[dict[str, Any]] | None) -> int:
    """Describe one log; with `collect`, append the JSON dict to it instead of printing."""
    lf = _read(path, strict)
    if lf is None:
        return 1
    info = _info_dict(lf)
    if collect is not None:
        collect.append(info)
        if as_json:
            return 0
    elif as_json:
        print(json.dumps(info, indent=2))
        return 0
    print(
        f"file:            {info['file']} ({info['size_bytes']} bytes, {info['records']} records)"
    )
    print(f"closed cleanly:  {'yes' if info['closed_cleanly'] else 'no'}")
    if info["start"] is not None:
        print(f"time span:       {info['start']} .. {info['end']} s ({info['span_s']:.3f} s)")
    print(f"begin/end pairs: {len(info['begin_end'])}")
    for k, pair in enumerate(info["begin_end"], 1):
        print(f"  {k}: {pair['begin'] or '(none)'} .. {pair['end'] or '(not ended)'}")
    print("formats:")
    for f in info["formats"]:
        tag = f"{f['index']}" + (f".{f['stream']}" if f["stream"] > 1 else "")
        print(f"  [{tag}] {f['kind']:5s} {f['records']:>9d} records  format {f['format']!r}")
        print(f"        columns: {','.join(f['columns'])}")
        if f["first"] is not None:
            print(f"        time: {f['first']} .. {f['last']}")
    if lf.truncated_bytes:
        print(f"truncated tail:  {lf.truncated_bytes} bytes dropped")
    if info["damage"]:
        print(f"damage:          {len(info['damage'])} region(s), {lf.skipped_bytes} bytes skipped")
        for d in info["damage"]:
            print(
                f"  byte offset {d['offset']}: {d['message']} ({d['skipped_bytes']} bytes skipped)"
            )
    else:
        print("damage:          none")
    return 0


def _key(index: int, number: int) -> str:
    return f"fmt{index}" if number == 1 else f"fmt{index}_{number}"


def cmd_export(args: argparse.Namespace) -> int:
    from companion.logs.archive import is_archive

    if args.dataset is not None:
        return _export_dataset(args.path, args.dataset)
    if args.to is None or len(args.path) != 1:
        print("error: export takes one FILE and --to, or FLIGHT... and --dataset", file=sys.stderr)
        return 2
    path: Path = args.path[0]
    if not is_archive(path):
        return _export_one(path, args.to, args.out, args.strict)
    files, ok = _log_inputs([path])
    if not ok:
        return 1
    if not files:
        print(f"error: {path}: the flight holds no .bin/.uavlog file", file=sys.stderr)
        return 1
    # several logs: -o names a directory for npz too (one <log>.npz in it per log)
    npz_dir: Path | None = args.out if args.out is not None and args.to == "npz" else None
    if npz_dir is not None:
        try:
            npz_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            print(f"error: export of {path}: {exc}", file=sys.stderr)
            return 1
    status = 0
    for path in files:
        out = npz_dir / f"{path.stem}.npz" if npz_dir is not None else args.out
        status |= _export_one(path, args.to, out, args.strict)
    return status


def _export_one(path: Path, to: str, out_arg: Path | None, strict: bool) -> int:
    import numpy as np

    from companion.logs.convert import csv_name

    lf = _read(path, strict)
    if lf is None:
        return 1
    stem = path.stem
    try:
        if to == "npz":
            out = out_arg or path.with_suffix(".npz")
            arrays: dict[str, np.ndarray] = {}
            for s in lf.streams:
                arrays[_key(s.index, s.number)] = s.data
                arrays[_key(s.index, s.number) + "_time_ns"] = s.time_ns
            arrays["markers"] = np.array(
                [(m.kind, m.time_ns, m.offset) for m in lf.markers],
                dtype=[("kind", "U5"), ("time_ns", "<i8"), ("offset", "<i8")],
            )
            np.savez(out, **arrays)  # type: ignore[arg-type]
            print(out)
            return 0
        import pyarrow.parquet as pq

        from companion.logs.dataset import stream_table

        out_dir = out_arg or path.parent
        out_dir.mkdir(parents=True, exist_ok=True)
        for s in lf.streams:
            target = out_dir / csv_name(stem, s.index, s.number).replace(".csv", ".parquet")
            pq.write_table(stream_table(s), target)
            print(target)
    except OSError as exc:
        print(f"error: export of {path}: {exc}", file=sys.stderr)
        return 1
    return 0


def _export_dataset(paths: list[Path], dataset: Path) -> int:
    """``export --dataset``: each flight as far as it reads; exit 1 when one had problems."""
    from companion.logs.archive import is_archive
    from companion.logs.dataset import export_flight, flight_dirs

    status = 0
    for given in paths:
        flight = flight_of_archive(given) if is_archive(given) else given
        if flight is None or not flight.is_dir():
            if flight is not None:
                print(f"error: {given}: not a flight directory or archive", file=sys.stderr)
            status = 1
            continue
        for d in flight_dirs(flight):
            try:
                done = export_flight(d, dataset)
            except OSError as exc:
                print(f"error: export of {d} into {dataset}: {exc}", file=sys.stderr)
                status = 1
                continue
            print(f"{done.partition} ({done.streams} streams, {done.records} rows)")
            for p in done.problems:
                print(f"warning: {d}: {p}", file=sys.stderr)
            status |= 1 if done.problems else 0
    return status


def cmd_query(args: argparse.Namespace) -> int:
    from companion.logs.dataset import QueryError, query, render

    try:
        columns, rows = query(args.dataset, args.sql)
    except QueryError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(render(columns, rows, "csv" if args.csv else "json" if args.json else "table"))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry: ``python -m companion.logs.cli info FILE`` = ``companion logs info FILE``."""
    parser = argparse.ArgumentParser(prog="companion logs", description=__doc__)
    add_commands(parser.add_subparsers(metavar="ACTION", required=True))
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
