"""Flight-log benchmark: writer, reader and converter against pymavlink's DataFlash reader.

    python bench/logs_bench.py [--records N] [--quick]

Writer: records/s sustained through a LogService (one producer, default queue and flush
period) and the cost of one ``log()`` call. Reader: records/s and MB/s of `read_log` on a file of
5 formats, against pymavlink's ``DFReader_binary`` reading (indexing + iterating every message)
an ArduPilot DataFlash log with the same record count and similar record sizes. Converter: CSV
records/s against the same DFReader read rate. Sizes: binary against CSV for the same data.
"""

from __future__ import annotations

import argparse
import struct
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.result import Result  # noqa: E402
from companion.logs.convert import convert_file  # noqa: E402
from companion.logs.formats import parse_format  # noqa: E402
from companion.logs.reader import read_log  # noqa: E402
from companion.logs.records import (
    BEGIN,
    END,
    DataPacker,
    encode_comment,
    encode_definition,
    encode_marker,
)  # noqa: E402
from companion.logs.writer import LogService  # noqa: E402

# (our format, columns, DataFlash format after the TimeUS 'Q', DataFlash name): similar sizes.
FORMATS = [
    ("%f,%f,%f,%f,%f,%f", "gx,gy,gz,ax,ay,az", "ffffff", "IMU1"),
    ("%lf,%lf,%f,%hhu,%hhd,%u", "lat,lon,alt,fix,ns,fl", "ddfBbI", "GPS1"),
    ("%f,%f,%f", "roll,pitch,yaw", "fff", "ATT1"),
    ("%f,%hd", "alt,temp", "fh", "BAR1"),
    ("%hu,%hu,%hu,%hu", "c1,c2,c3,c4", "HHHH", "SRV1"),
]
VALUES = [
    (0.1, -0.2, 0.3, 0.01, -9.81, 0.02),
    (43.7, 10.4, 120.5, 3, 9, 0x1234),
    (0.05, -0.02, 1.57),
    (120.25, 2150),
    (1500, 1510, 1490, 1000),
]
T0 = 1_700_000_000 * 10**9


def make_our_log(path: Path, n: int) -> None:
    packers = [DataPacker(i + 1, parse_format(f)) for i, (f, _, _, _) in enumerate(FORMATS)]
    parts = [encode_marker(BEGIN, T0)]
    for i, (f, cols, _, _) in enumerate(FORMATS):
        parts += [encode_comment(i + 1, cols), encode_definition(i + 1, f)]
    for k in range(n):
        j = k % 5
        parts.append(packers[j].pack(T0 + k * 1000, VALUES[j]))
    parts.append(encode_marker(END, T0 + n * 1000))
    path.write_bytes(b"".join(parts))


def make_dataflash_log(path: Path, n: int) -> None:
    """An ArduPilot DataFlash log: FMT messages, then data messages, as pymavlink reads them."""
    head = b"\xa3\x95"
    parts = []
    structs = []
    for i, (_, cols, dfmt, name) in enumerate(FORMATS):
        mtype = 200 + i
        st = struct.Struct("<3sQ" + dfmt)
        parts.append(
            struct.pack(
                "<2sBBB4s16s64s",
                head,
                0x80,
                mtype,
                st.size,
                name.encode(),
                ("Q" + dfmt).encode(),
                ("TimeUS," + cols).encode(),
            )
        )
        structs.append((head + bytes([mtype]), st))
    for k in range(n):
        j = k % 5
        hdr, st = structs[j]
        parts.append(st.pack(hdr, k, *VALUES[j]))
    path.write_bytes(b"".join(parts))


def bench_writer(tmp: Path, n: int) -> dict[str, float]:
    svc = LogService(tmp / "writer", clock_ns=time.time_ns)
    svc.start()
    lg = svc.open("bench")
    for i, (f, cols, _, _) in enumerate(FORMATS):
        lg.define(i + 1, f, cols.split(","))
    lg.begin()
    timed = min(n, 200_000)
    costs = np.empty(timed, dtype=np.int64)
    clock = time.perf_counter_ns
    log = lg.log
    start = time.perf_counter()
    for k in range(timed):
        j = k % 5
        t = clock()
        log(j + 1, *VALUES[j])
        costs[k] = clock() - t
    for k in range(timed, n):
        j = k % 5
        log(j + 1, *VALUES[j])
    lg.end()
    svc.close(timeout_s=60)
    elapsed = time.perf_counter() - start
    stats = svc.stats()
    return {
        "written": stats["written"],
        "dropped": stats["dropped"],
        "rate": stats["written"] / elapsed,
        "median_us": float(np.median(costs)) / 1000,
        "p99_us": float(np.percentile(costs, 99)) / 1000,
    }


def timed(fn, repeat: int = 3) -> float:  # type: ignore[no-untyped-def]
    best = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best.append(time.perf_counter() - t)
    return min(best)


def read_dataflash(path: Path) -> int:
    from pymavlink.DFReader import DFReader_binary

    r = DFReader_binary(str(path))
    count = 0
    while r.recv_msg() is not None:
        count += 1
    return count


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--records", type=int, default=1_000_000)
    ap.add_argument("--quick", action="store_true", help="100,000 records, one repetition")
    args = ap.parse_args(argv)
    n = 100_000 if args.quick else args.records
    repeat = 1 if args.quick else 3
    res = Result("logs", ["companion/logs"], quick=args.quick)
    with tempfile.TemporaryDirectory(prefix="logs-bench-") as d:
        tmp = Path(d)
        ours, df = tmp / "bench.bin", tmp / "bench_df.bin"
        make_our_log(ours, n)
        make_dataflash_log(df, n)
        w = bench_writer(tmp, n)

        t_read = timed(lambda: read_log(ours), repeat)
        lf = read_log(ours)
        n_ours = sum(s.n_records for s in lf.streams)
        t_df = timed(lambda: read_dataflash(df), 1)
        out = tmp / "csv"
        t_csv = timed(lambda: convert_file(ours, out), 1)
        csv_bytes = sum(p.stat().st_size for p in out.iterdir())

        size_ours, size_df = ours.stat().st_size, df.stat().st_size
        r_read, r_df, r_csv = n_ours / t_read, n / t_df, n_ours / t_csv
        mb_read, mb_df = size_ours / t_read / 1e6, size_df / t_df / 1e6
        res.figure("read_mb_s", round(mb_read, 1), "MB/s", "read_log")
        res.figure("read_vs_dfreader", round(r_read / r_df, 1), "x", "read_log / DFReader")
        res.table(
            f"{n:,} records, 5 formats", ["measure", "value"], [
                ["writer: records written/s (1 producer, default queue)",
                 f"{w['rate']:,.0f} ({w['dropped']:,} dropped)"],
                ["writer: log() cost median / p99",
                 f"{w['median_us']:.2f} us / {w['p99_us']:.2f} us"],
                ["reader: read_log records/s", f"{r_read:,.0f} ({mb_read:,.1f} MB/s)"],
                ["pymavlink DFReader_binary records/s (index + recv_msg)",
                 f"{r_df:,.0f} ({mb_df:,.1f} MB/s)"],
                ["reader speed-up vs DFReader", f"{r_read / r_df:,.1f}x"],
                ["CSV conversion records/s",
                 f"{r_csv:,.0f} ({csv_bytes / t_csv / 1e6:,.1f} MB/s of CSV)"],
                ["CSV conversion vs DFReader read rate", f"{r_csv / r_df:,.1f}x"],
                ["size: binary / CSV / DataFlash",
                 f"{size_ours / 1e6:,.1f} MB / {csv_bytes / 1e6:,.1f} MB / {size_df / 1e6:,.1f} MB"],
                ["binary saves vs CSV", f"{100 * (1 - size_ours / csv_bytes):.0f}%"],
            ])
    res.write()
    return 0


if __name__ == "__main__":
    sys.exit(main())
