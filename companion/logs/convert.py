"""Binary log -> CSV text logs, one per format index, and the CSV layout shared with the writer.

Layout (the contract's text-log section): ``%`` comment lines first (source, columns, format),
then one line per record: the time in seconds with exactly 9 decimals (printed from the integer
seconds and nanoseconds, so it is exact), a comma, and the record rendered with its format string
as C's printf would. Byte Array records become one line each: time, then every element rendered
with the format's single conversion, comma separated. Begin/End markers become comment lines at
their place among the records. The text-mode writer produces files with the same layout.

If a format string ends with a newline, the record line ends there (no blank line is added).
A data line may contain bytes above 0x7F only through ``%c``; it is written byte for byte as C
would, so data lines are Latin-1 and comment lines UTF-8.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np

from companion.logs.formats import FormatSpec
from companion.logs.reader import read_log
from companion.logs.records import NS_PER_S
from companion.logs.streams import LogFile, Marker, Stream

__all__ = [
    "BATCH_RECORDS",
    "convert_file",
    "csv_header",
    "csv_name",
    "format_time",
    "marker_line",
    "render_array_lines",
    "render_block_lines",
    "write_stream_csv",
]

BATCH_RECORDS = 65536  # records rendered per batch: bounds the memory of a conversion

Progress = Callable[[int, int], None]


def format_time(t_ns: int) -> str:
    """Seconds with 9 decimals, exact (``tv_sec + tv_nsec/1e9`` without float rounding)."""
    sign = "-" if t_ns < 0 else ""
    sec, nsec = divmod(abs(t_ns), NS_PER_S)
    return f"{sign}{sec}.{nsec:09d}"


def csv_name(stem: str, index: int, number: int = 1) -> str:
    """``<stem>_fmt<index>.csv``; a later, different definition of the index gets ``_<number>``."""
    return f"{stem}_fmt{index}.csv" if number == 1 else f"{stem}_fmt{index}_{number}.csv"


def csv_header(spec: FormatSpec, columns: Sequence[str], kind: str, source: str = "") -> str:
    """The comment lines that open a CSV text log (free-form by the contract)."""
    lines = []
    if source:
        lines.append(f"% source: {source}")
    if kind == "array":
        lines.append(f"% columns: time_s,then one {columns[0]} column per element")
        lines.append(f"% format: {_one_line(spec.text)} (byte array)")
    else:
        lines.append("% columns: " + ",".join(["time_s", *columns]))
        lines.append(f"% format: {_one_line(spec.text)}")
    return "\n".join(lines) + "\n"


def _one_line(text: str) -> str:
    return text.replace("\r", "\\r").replace("\n", "\\n")


def marker_line(kind: str, t_ns: int) -> str:
    """The comment line standing for a Begin Data / End Data record."""
    return f"% {kind} data {format_time(t_ns)}\n"


def _line_end(spec: FormatSpec) -> str:
    return "" if spec.text.endswith("\n") else "\n"


def render_block_lines(
    spec: FormatSpec, time_ns: np.ndarray, columns: Sequence[np.ndarray]
) -> list[str]:
    """Lines (with their newline) of a batch of Data Blocks; columns are the field arrays."""
    template, lists = spec.batch(columns)
    end = _line_end(spec)
    t = np.asarray(time_ns, dtype=np.int64)
    if t.size and int(t.min()) >= 0:
        sec, nsec = np.divmod(t, NS_PER_S)
        line = "%d.%09d," + template + end
        return [line % row for row in zip(sec.tolist(), nsec.tolist(), *lists, strict=True)]
    times = [format_time(v) for v in t.tolist()]
    line = "%s," + template + end
    return [line % row for row in zip(times, *lists, strict=True)]


def render_array_lines(
    spec: FormatSpec, time_ns: np.ndarray, lengths: np.ndarray, values: np.ndarray
) -> list[str]:
    """Lines of a batch of Byte Arrays: time, then each element with the single conversion."""
    conv = spec.conversions[0]
    vals = np.asarray(values)
    py = conv.python_spec
    if py is not None and conv.conv == "c":
        texts = [py % v for v in vals.astype(np.uint8).tolist()]
    elif py == "%d":
        texts = list(map(str, vals.tolist()))
    elif py is not None and not conv.is_float:
        texts = [py % v for v in vals.tolist()]
    else:
        texts = [conv.render(v) for v in vals.tolist()]
    out: list[str] = []
    pos = 0
    for t_ns, n in zip(np.asarray(time_ns).tolist(), np.asarray(lengths).tolist(), strict=True):
        out.append(",".join([format_time(t_ns), *texts[pos : pos + n]]) + "\n")
        pos += n
    return out


def _marker_slots(stream: Stream, markers: Sequence[Marker]) -> list[tuple[int, Marker]]:
    """(row before which the marker goes, marker) for every marker, in file order."""
    if not markers:
        return []
    where = np.searchsorted(stream.offsets, np.array([m.offset for m in markers], dtype=np.int64))
    return list(zip(where.tolist(), markers, strict=True))


def write_stream_csv(
    stream: Stream,
    markers: Sequence[Marker],
    out_path: Path,
    *,
    source: str = "",
    progress: Callable[[int], None] | None = None,
) -> None:
    """Write one stream as a CSV text log, markers included, in bounded batches."""
    slots = _marker_slots(stream, markers)
    n = stream.n_records
    values_pos = 0
    with open(out_path, "wb") as f:
        f.write(csv_header(stream.spec, stream.columns, stream.kind, source).encode("utf-8"))
        k = 0
        start = 0
        while True:
            stop = min(n, start + BATCH_RECORDS)
            chunk: list[str] = []
            if stream.kind == "block":
                cols = [stream.data[c][start:stop] for c in stream.columns]
                lines = render_block_lines(stream.spec, stream.time_ns[start:stop], cols)
            else:
                assert stream.lengths is not None
                lens = stream.lengths[start:stop]
                count = int(lens.sum())
                vals = stream.data[stream.value_field][values_pos : values_pos + count]
                values_pos += count
                lines = render_array_lines(stream.spec, stream.time_ns[start:stop], lens, vals)
            row = start
            for line in lines:
                while k < len(slots) and slots[k][0] <= row:
                    chunk.append(marker_line(slots[k][1].kind, slots[k][1].time_ns))
                    k += 1
                chunk.append(line)
                row += 1
            if stop >= n:
                while k < len(slots):
                    chunk.append(marker_line(slots[k][1].kind, slots[k][1].time_ns))
                    k += 1
            f.write("".join(chunk).encode("latin-1"))
            if progress is not None:
                progress(stop - start)
            if stop >= n:
                break
            start = stop


def convert_file(
    path: str | os.PathLike[str],
    out_dir: str | os.PathLike[str] | None = None,
    *,
    salvage: bool | None = None,
    progress: Progress | None = None,
    log_file: LogFile | None = None,
    strict: bool = False,
) -> list[Path]:
    """Convert one binary log; returns the CSV files written (``<stem>_fmt<index>.csv``).

    Damage is skipped as `read_log` does; `strict` (or `salvage=False`) raises LogFormatError
    on a damaged file instead. `progress(done, total)` is called with record counts as batches
    are written.
    """
    src = Path(path)
    lf = log_file if log_file is not None else read_log(src, salvage=salvage, strict=strict)
    dest = Path(out_dir) if out_dir is not None else src.parent
    dest.mkdir(parents=True, exist_ok=True)
    total = sum(s.n_records for s in lf.streams)
    done = 0

    def step(n: int) -> None:
        nonlocal done
        done += n
        if progress is not None:
            progress(done, total)

    written: list[Path] = []
    for stream in lf.streams:
        out = dest / csv_name(src.stem, stream.index, stream.number)
        write_stream_csv(stream, lf.markers, out, source=src.name, progress=step)
        written.append(out)
    return written


def input_files(paths: Iterable[str | os.PathLike[str]]) -> list[Path]:
    """Expand directories into their ``*.bin`` / ``*.uavlog`` files (sorted, not recursive)."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out.extend(
                sorted(q for q in p.iterdir() if q.suffix in (".bin", ".uavlog") and q.is_file())
            )
        else:
            out.append(p)
    return out
