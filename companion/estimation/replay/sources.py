"""Flight-controller logs of three kinds into one `FlightLog`: PX4 ULog (`ulog`), ArduPilot
DataFlash (`dataflash`) and MAVLink telemetry logs (`tlog`), recognised by their first bytes.

Every reader reads what is whole by default: a log that ends inside its last message (how
DataFlash and ULog files end when the power goes) is read to its last whole message with a
note, and damage in the middle is skipped by resynchronising on the next plausible record and
reported with byte offsets (`FlightLog.notes`, `.damage`, `.skipped`). `strict=True` refuses
any damage instead. What cannot be read at all is a `LogReadError` naming the file. The types
the runner consumes live in `series`; they are re-exported here for older imports.
"""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path
from typing import Any

from companion.estimation.replay.series import (
    AttitudeSeries,
    FlightLog,
    GpsSeries,
    ImuSeries,
    LogReadError,
    SkippedRegion,
    TemperatureSeries,
)

__all__ = ["AttitudeSeries", "FlightLog", "GpsSeries", "ImuSeries", "LogReadError",
           "SkippedRegion", "TemperatureSeries", "close_dfreader", "read_flight_log"]

log = logging.getLogger(__name__)

HEAD_BYTES = 32
ULOG_MAGIC = b"ULog\x01\x12\x35"
DF_HEAD = b"\xa3\x95"


def read_flight_log(path: Path | str, *, strict: bool = False, salvage: bool = False,
                    imu_instance: int | None = None) -> FlightLog:
    """Read a PX4 ULog, an ArduPilot DataFlash log or a MAVLink telemetry log.

    `strict`: refuse a log with any damaged or cut-short message (`LogReadError` at its byte
    offset). `salvage` is accepted for older callers and changes nothing: reading what is
    whole is the default. `imu_instance` picks an ArduPilot DataFlash IMU (default: the first
    one logged at the full rate).
    """
    del salvage  # the default behaviour now
    from companion.estimation.replay.tlog import looks_like_tlog

    p = Path(path)
    try:
        with p.open("rb") as fh:
            head = fh.read(HEAD_BYTES)
    except OSError as exc:
        raise LogReadError(p, f"cannot read: {exc.strerror or exc}") from None
    if not head:
        raise LogReadError(p, "empty file")
    if head.startswith(ULOG_MAGIC):
        from companion.estimation.replay.ulog import read_ulog

        return read_ulog(p, strict=strict)
    if head.startswith(DF_HEAD):
        from companion.estimation.replay.dataflash import read_dataflash

        return read_dataflash(p, strict=strict, imu_instance=imu_instance)
    if looks_like_tlog(head):
        from companion.estimation.replay.tlog import read_tlog

        return read_tlog(p, strict=strict)
    raise LogReadError(p, "not a PX4 ULog (no 'ULog' magic), an ArduPilot DataFlash log (no "
                          "0xA3 0x95 header) nor a MAVLink telemetry log (no 8-byte time then "
                          "0xFE/0xFD frame)", 0)


def close_dfreader(reader: Any) -> None:
    """Release a pymavlink DFReader's file: it keeps an mmap and the file open until
    collected (the tests compare our reading with DFReader's)."""
    for name in ("data_map", "filehandle"):
        handle = getattr(reader, name, None)
        if handle is not None:
            with contextlib.suppress(Exception):
                handle.close()
