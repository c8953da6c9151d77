"""Tools that make the replay tests' log files from real ones: a MAVLink byte capture stamped
as a ground station's telemetry log, and the first seconds of a DataFlash log.

Used by `bench/replay_bench.py` and by hand to (re)make files under tests/data/replay/ (their
provenance is in tests/data/README.md); both are plain functions so a test can check them.
"""

from __future__ import annotations

import struct


def stamp_capture_as_tlog(capture: bytes, start_unix_us: int) -> bytes:
    """A raw MAVLink capture (frames back to back) as a tlog: each frame gets the 8-byte
    big-endian reception time a ground station writes. The capture has no reception times, so
    each frame is stamped with the vehicle's boot time of the last message that carried one
    (time_boot_ms or time_usec) plus `start_unix_us`, which is what a ground station on a
    latency-free link would have seen."""
    from pymavlink.dialects.v20 import ardupilotmega as dialect

    mav = dialect.MAVLink(None)
    mav.robust_parsing = True
    out = bytearray()
    boot_us = 0
    for m in mav.parse_buffer(capture) or []:
        if m.get_type() == "BAD_DATA":
            continue
        t_ms = getattr(m, "time_boot_ms", None)
        t_us = getattr(m, "time_usec", None)
        if isinstance(t_ms, int) and t_ms > 0:
            boot_us = max(boot_us, t_ms * 1000)
        elif isinstance(t_us, int) and 0 < t_us < 10**14:
            boot_us = max(boot_us, t_us)
        out += struct.pack(">Q", start_unix_us + boot_us) + bytes(m.get_msgbuf())
    return bytes(out)


def dataflash_head(data: bytes, seconds: float) -> bytes:
    """The first `seconds` of a DataFlash log by its messages' TimeUS/TimeMS, all FMT, PARM and
    other untimed messages kept, cut at a message boundary (walked by the log's own FMT table)."""
    from companion.estimation.replay.dfwalk import parse_fmt

    lengths = {0x80: 89}
    time_field: dict[int, tuple[int, str]] = {}
    off = 0
    t0: int | None = None
    while off + 3 <= len(data) and data[off:off + 2] == b"\xa3\x95":
        typ = data[off + 2]
        ln = lengths.get(typ)
        if ln is None or off + ln > len(data):
            break
        if typ == 0x80:
            f = parse_fmt(data[off + 3:off + ln])
            lengths[f.type_id] = f.length
            if f.letters[:1] in ("Q", "I") and f.columns[:1] in (("TimeUS",), ("TimeMS",)):
                time_field[f.type_id] = (1000 if f.columns[0] == "TimeMS" else 1, f.letters[0])
        elif typ in time_field:
            scale, letter = time_field[typ]
            t = struct.unpack_from("<" + letter, data, off + 3)[0] * scale
            t0 = t if t0 is None else t0
            if t - t0 > seconds * 1e6:
                return data[:off]
        off += ln
    return data[:off]


def repeat_dataflash(data: bytes, copies: int, period_us: int) -> bytes:
    """A long DataFlash log from a short real one: its records repeated `copies` times, each
    copy's TimeUS shifted by `period_us` more than the last (FMT records only in the first copy),
    so the result reads as one flight of `copies` x `period_us`. Only whole records are used
    (a cut-short last one is dropped); types without a leading TimeUS are copied unchanged."""
    from companion.estimation.replay.dfwalk import parse_fmt

    lengths = {0x80: 89}
    timed: set[int] = set()
    records: list[tuple[int, bytes]] = []
    off = 0
    while off + 3 <= len(data) and data[off:off + 2] == b"\xa3\x95":
        typ = data[off + 2]
        ln = lengths.get(typ)
        if ln is None or off + ln > len(data):
            break
        rec = data[off:off + ln]
        if typ == 0x80:
            f = parse_fmt(rec[3:])
            lengths[f.type_id] = f.length
            if f.letters[:1] == "Q" and f.columns[:1] == ("TimeUS",):
                timed.add(f.type_id)
        records.append((typ, rec))
        off += ln
    out = bytearray(b"".join(rec for _, rec in records))
    body = [(typ, rec) for typ, rec in records if typ != 0x80]
    for k in range(1, copies):
        shift = k * period_us
        for typ, rec in body:
            if typ in timed:
                t = struct.unpack_from("<Q", rec, 3)[0] + shift
                out += rec[:3] + struct.pack("<Q", t) + rec[11:]
            else:
                out += rec
    return bytes(out)
