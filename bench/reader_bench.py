"""Log reader and log-tool start-up benchmark: `read_log` against `numpy.fromfile` of the same bytes.

    python bench/reader_bench.py [--minutes M] [--flight DIR] [--repeat N] [--quick]

The input is a 20-minute flight (``--quick``: 2 minutes) made from a real one: unless --flight
names a flight directory, `companion sim --fast --duration 30` flies 30 s in a temporary
directory; the data records of each of its binary logs (IMU 100 Hz with its raw bytes as Byte
Arrays, GPS 10 Hz with raw NMEA, servo 50 Hz, estimator, control, SITL truth) are then repeated,
with their times shifted by the flight's length, until the flight lasts M minutes. Headers,
definitions and Begin/End markers stay as the runtime wrote them, so every file reads like the
runtime's own (interleaved formats, variable-length Byte Arrays).

Reader: MB/s of `read_log` (every stream decoded to its numpy arrays) over all the flight's logs,
against `numpy.fromfile` reading the same files in the same run (best of N, warm page cache), and
the ratio. Target: at least 1 GB/s.

Start-up: wall time of `companion logs info FILE` (the smallest log) and `companion logs info
DIR` on the 30-second flight, and of `companion params show`, run as subprocesses (median of N),
against `python -c pass`: what a user waits for before a tool does anything. Target: under 0.3 s
each.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.result import Cell, Result  # noqa: E402
from companion.logs.reader import read_log  # noqa: E402
from companion.logs.records import ARRAY, ARRAY_ALT, DATA, END  # noqa: E402


def fly(root: Path, seconds: float) -> Path:
    """A real flight: `companion sim --fast` in `root` (it writes ./flights/<stamp>/)."""
    subprocess.run(
        [sys.executable, "-m", "companion", "sim", "--fast", "--duration", str(seconds),
         "--mavlink", "none", "--no-legacy"],
        cwd=root, check=True, stdout=subprocess.DEVNULL, timeout=600,
    )
    flights = sorted((root / "flights").iterdir())
    if not flights:
        raise SystemExit("reader_bench: the simulated flight wrote no flight directory")
    return flights[-1]


def _records(buf: bytes) -> list[tuple[int, int]]:
    """(start, end) of every record of a whole log (the reader's framing pass)."""
    from companion.logs.framing import _scan

    offs, stop, _ = _scan(buf, 0, len(buf))
    starts = list(offs)
    return list(zip(starts, starts[1:] + [stop], strict=True))


def lengthen(src: Path, dst: Path, minutes: float) -> Path:
    """`dst`: the logs of the flight `src` with their data records repeated to last `minutes`."""
    dst.mkdir(parents=True, exist_ok=True)
    for f in sorted(src.glob("*.bin")):
        buf = f.read_bytes()
        head: list[bytes] = []
        data: list[bytes] = []
        tail: list[bytes] = []
        for a, b in _records(buf):
            rec = buf[a:b]
            if rec[0] in (DATA, ARRAY, ARRAY_ALT):
                data.append(rec)
            elif rec[0] == END or data:
                tail.append(rec)
            else:
                head.append(rec)
        if not data:
            (dst / f.name).write_bytes(buf)
            continue
        blob = np.frombuffer(b"".join(data), dtype=np.uint8).copy()
        starts = np.cumsum([0] + [len(r) for r in data[:-1]])
        sec = blob[(starts[:, None] + 4 + np.arange(4)).ravel()].view("<i4")
        span = int(sec.max() - sec.min()) + 1
        copies = max(1, int(np.ceil(minutes * 60.0 / span)))
        parts = [b"".join(head)]
        for c in range(copies):
            piece = blob.copy()
            shifted = (sec + c * span).astype("<i4").view(np.uint8).reshape(-1, 4)
            piece[(starts[:, None] + 4 + np.arange(4))] = shifted
            parts.append(piece.tobytes())
        for rec in tail:  # End Data after the last copy
            if rec[0] == END:
                t = int.from_bytes(rec[4:8], "little", signed=True) + (copies - 1) * span
                rec = rec[:4] + t.to_bytes(4, "little", signed=True) + rec[8:]
            parts.append(rec)
        (dst / f.name).write_bytes(b"".join(parts))
    return dst


def bench_reader(flight: Path, repeat: int) -> tuple[int, float, float, float, int]:
    """Total bytes; best seconds of numpy.fromfile, of read_log (every stream decoded: Data
    Blocks as structured arrays, Byte Arrays as element values, lengths and times) and of
    read_log plus the long table of every Byte Array stream; records."""
    files = sorted(flight.glob("*.bin"))
    size = sum(f.stat().st_size for f in files)
    best_np = best_rd = best_long = float("inf")
    records = 0
    for _ in range(repeat):
        t0 = time.perf_counter()
        for f in files:
            np.fromfile(f, dtype=np.uint8)
        best_np = min(best_np, time.perf_counter() - t0)
        t0 = time.perf_counter()
        for f in files:
            read_log(f)
        best_rd = min(best_rd, time.perf_counter() - t0)
        t0 = time.perf_counter()
        records = 0
        for f in files:
            lf = read_log(f)
            records += lf.record_count
            for s in lf.streams:
                s.data  # noqa: B018 (builds the long table of a Byte Array stream)
        best_long = min(best_long, time.perf_counter() - t0)
    return size, best_np, best_rd, best_long, records


def _wall(cmd: list[str], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run(cmd, check=False, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                       timeout=120)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_startup(flight: Path, repeat: int) -> list[tuple[str, float]]:
    one = sorted(flight.glob("*.bin"), key=lambda f: f.stat().st_size)[0]
    py = [sys.executable]
    return [
        ("python -c pass (baseline)", _wall([*py, "-c", "pass"], repeat)),
        (f"companion logs info {one.name}", _wall([*py, "-m", "companion", "logs", "info",
                                                   str(one)], repeat)),
        ("companion logs info FLIGHT_DIR", _wall([*py, "-m", "companion", "logs", "info",
                                                  str(flight)], repeat)),
        ("companion params show", _wall([*py, "-m", "companion", "params", "show"], repeat)),
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=20.0)
    ap.add_argument("--flight", type=Path, help="a flight directory to lengthen (default: fly one)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="a 2-minute flight, 3 repeats")
    args = ap.parse_args(argv)
    if args.quick:
        args.minutes, args.repeat = 2.0, 3
    res = Result("reader", ["companion/logs", "companion/cli.py", "companion/__main__.py"],
                 quick=args.quick)
    with tempfile.TemporaryDirectory(prefix="reader-bench-") as tmp:
        root = Path(tmp)
        src = args.flight or fly(root, 30.0)
        flight = lengthen(src, root / "long", args.minutes)
        n_logs = len(list(flight.glob("*.bin")))
        size, t_np, t_rd, t_long, records = bench_reader(flight, args.repeat)
        startup = bench_startup(src, args.repeat)  # the short flight: start-up, not reading
    mb = size / 1e6
    res.figure("read_log_mb_s", round(mb / t_rd), "MB/s", "read_log, every stream decoded")
    rows: list[list[Cell]] = [["numpy.fromfile (baseline)", round(t_np, 4), round(mb / t_np), "1"]]
    for label, t in (("read_log, every stream decoded", t_rd),
                     ("read_log + Byte Arrays' long tables (`Stream.data`)", t_long)):
        rows.append([label, round(t, 4), round(mb / t),
                     f"{t_np / t:.3f} ({t / t_np:.1f}x slower)"])
    res.table(f"Log reader: a {args.minutes:g}-minute flight ({mb:.1f} MB in {n_logs} logs, "
              f"{records:,} records; best of {args.repeat})",
              ["reader", "s", "MB/s", "vs numpy.fromfile"], rows)
    base = startup[0][1]
    res.table(f"Start-up of the log tools (median of {args.repeat}, wall time)",
              ["command", "s", "over python -c pass"],
              [[label, f"{s:.3f}", f"{s - base:+.3f}"] for label, s in startup])
    res.write()
    return 0


if __name__ == "__main__":
    sys.exit(main())
