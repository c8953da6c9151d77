"""One flight directory read into memory, tolerant of whatever is missing or damaged.

The report and the rerun replay both start here, so a flight that can be plotted can also be
replayed, and both say the same thing about what is missing. Nothing in this module raises for
bad data: every log that cannot be read becomes a line in `FlightData.problems` and the rest of
the flight is still usable.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.logs import LogFile, LogFormatError, read_log_bytes
from companion.report.headers import definition_records, known_header

__all__ = [
    "FLIGHT_LOGS",
    "MAX_LOG_BYTES",
    "OPTIONAL_LOGS",
    "FlightData",
    "LogStatus",
    "load_flight",
]

log = logging.getLogger(__name__)

#: Logs the runtime and the simulator write, with what each one is for (used in messages).
FLIGHT_LOGS: dict[str, str] = {
    "imu": "IMU rates and specific force",
    "gps": "GPS solutions",
    "servo": "servo-board exchanges (pilot commands, batteries)",
    "control": "control law outputs",
    "estimator": "on-board state estimate",
    "truth": "SITL ground truth",
}

#: Logs only some flights have: read when present (as every ``*.bin`` is), never reported missing.
OPTIONAL_LOGS: dict[str, str] = {
    "autopilot": "the flight controller's own estimate, clock sync and GUIDED targets",
}

#: Larger files are refused rather than read whole into memory (a 10-minute flight is ~10 MB).
MAX_LOG_BYTES = 1 << 30


@dataclass
class LogStatus:
    """What happened when one log file was read."""

    name: str
    path: Path
    present: bool
    size_bytes: int = 0
    log: LogFile | None = None
    problems: list[str] = field(default_factory=list)
    header_restored: bool = False
    header_bytes: int = 0  # prepended by a restoration (offsets in messages exclude it)

    @property
    def usable(self) -> bool:
        return self.log is not None and any(s.n_records for s in self.log.streams)

    @property
    def begins(self) -> int:
        return sum(1 for m in self.log.markers if m.kind == "begin") if self.log else 0

    @property
    def ends(self) -> int:
        return sum(1 for m in self.log.markers if m.kind == "end") if self.log else 0

    @property
    def restarts(self) -> int:
        """Every (re)start of a thread writes one Begin Data: restarts are the extra ones."""
        return max(0, self.begins - 1)


@dataclass
class FlightData:
    """Everything a report or a replay needs from one flight directory."""

    flight_dir: Path
    run_info: dict[str, Any] | None
    run_summary: dict[str, Any] | None
    logs: dict[str, LogStatus]
    t0_ns: int  # common time origin: the earliest Begin Data (else the earliest record)
    problems: list[str] = field(default_factory=list)

    def status(self, name: str) -> LogStatus | None:
        return self.logs.get(name)

    def block(self, name: str, index: int, required: tuple[str, ...] = ()) -> np.ndarray | None:
        """The Data Block array of `name`.bin, format `index`; None when absent, empty, a byte
        array, or lacking one of the `required` columns."""
        st = self.logs.get(name)
        if st is None or st.log is None or index not in st.log.indexes:
            return None
        try:
            data = st.log.data(index)
        except ValueError as exc:
            log.debug("%s", exc)
            return None
        names = data.dtype.names or ()
        if "record" in names and "element" in names:  # a byte array, not a block
            return None
        if data.size == 0 or any(c not in names for c in required):
            return None
        return data

    def rel_s(self, time_s: np.ndarray) -> np.ndarray:
        """Seconds since the start of the flight (float64)."""
        return np.asarray(time_s, dtype=np.float64) - self.t0_ns / 1e9

    def why_missing(self, name: str, index: int | None = None, columns: tuple[str, ...] = ()) -> str:
        """A one-line reason, naming the file, why `name`.bin cannot give the data asked for."""
        st = self.logs.get(name)
        what = FLIGHT_LOGS.get(name) or OPTIONAL_LOGS.get(name, name)
        if st is None or not st.present:
            return f"{name}.bin is missing ({what})"
        if st.log is None:
            return f"{name}.bin could not be read: " + ("; ".join(st.problems) or "unknown error")
        if index is not None and index not in st.log.indexes:
            return f"{name}.bin has no format {index} ({what})"
        if index is not None:
            data = self.block(name, index)
            if data is None:
                return f"{name}.bin format {index} has no records"
            absent = [c for c in columns if c not in (data.dtype.names or ())]
            if absent:
                return f"{name}.bin format {index} lacks column(s) {', '.join(absent)}"
        return f"{name}.bin has no usable records"

    @property
    def duration_s(self) -> float:
        end = self.t0_ns
        for st in self.logs.values():
            if st.log is None:
                continue
            for s in st.log.streams:
                if s.n_records:
                    end = max(end, int(s.time_ns.max()))
            for m in st.log.markers:
                end = max(end, m.time_ns)
        return (end - self.t0_ns) / 1e9


def _read_json(path: Path, problems: list[str]) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    try:
        value = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        problems.append(f"{path.name}: cannot read: {exc}")
        return None
    except json.JSONDecodeError as exc:
        problems.append(f"{path.name}: line {exc.lineno} column {exc.colno}: invalid JSON ({exc.msg})")
        return None
    if not isinstance(value, dict):
        problems.append(f"{path.name}: expected a JSON object, found {type(value).__name__}")
        return None
    return value


def _read_one(name: str, path: Path) -> LogStatus:
    st = LogStatus(name=name, path=path, present=path.is_file())
    if not st.present:
        return st
    try:
        st.size_bytes = path.stat().st_size
    except OSError as exc:
        st.problems.append(f"cannot stat: {exc.strerror or exc}")
        return st
    if st.size_bytes > MAX_LOG_BYTES:
        st.problems.append(f"{st.size_bytes} bytes is more than the {MAX_LOG_BYTES} bytes a report reads")
        return st
    try:
        raw = path.read_bytes()
    except OSError as exc:
        st.problems.append(f"cannot read: {exc.strerror or exc}")
        return st
    try:
        st.log = read_log_bytes(raw, name=str(path), strict=True)  # damage: try restoring first
    except LogFormatError as exc:
        st.log = _restored(st, raw, exc) or read_log_bytes(raw, name=str(path), salvage=True)
    lf = st.log
    for d in lf.damage:
        st.problems.append(f"byte offset {d.offset - st.header_bytes}: {d.message}; "
                           f"{d.skipped_bytes} bytes skipped")
    if lf.truncated_bytes:
        st.problems.append(f"last record cut short ({lf.truncated_bytes} bytes dropped)")
    if not lf.closed_cleanly:
        st.problems.append("not closed cleanly (no End Data at the end)")
    return st


def _restored(st: LogStatus, raw: bytes, exc: LogFormatError) -> LogFile | None:
    """A log whose Format Definitions never reached the disk is unreadable although every data
    record is intact; when the producer is one of ours and the file defined nothing before the
    first record that needed a definition, the producer's current definitions are put back."""
    if exc.kind != "undefined_index" or definition_records(raw[: exc.offset]):
        return None
    header = known_header(st.name)
    if header is None:
        return None
    try:
        lf = read_log_bytes(header + raw, name=str(st.path), strict=True)
    except LogFormatError:
        lf = read_log_bytes(header + raw, name=str(st.path), salvage=True)
    if not any(s.n_records for s in lf.streams):
        return None
    st.header_restored = True
    st.header_bytes = len(header)
    st.problems.append(
        f"no Format Definitions before byte offset {exc.offset} (they were never written); "
        f"read with the {st.name} thread's current definitions"
    )
    return lf


def _time_origin(logs: dict[str, LogStatus]) -> int:
    begins = [m.time_ns for name, st in logs.items() if st.log is not None and name != "truth"
              for m in st.log.markers if m.kind == "begin"]
    if begins:
        return min(begins)
    firsts = [int(s.time_ns.min()) for st in logs.values() if st.log is not None
              for s in st.log.streams if s.n_records]
    if firsts:
        return min(firsts)
    markers = [m.time_ns for st in logs.values() if st.log is not None for m in st.log.markers]
    return min(markers) if markers else 0


def load_flight(flight_dir: str | Path) -> FlightData:
    """Read run.json, summary.json (when the runtime wrote one) and every ``*.bin``.

    Raises FileNotFoundError only when `flight_dir` is not a directory; everything else is
    reported in `problems` and the `LogStatus` of each file.
    """
    root = Path(flight_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: not a flight directory")
    problems: list[str] = []
    run_info = _read_json(root / "run.json", problems)
    if run_info is None and not (root / "run.json").exists():
        problems.append("run.json is missing (configuration and thread list unknown)")
    run_summary = _read_json(root / "summary.json", problems)
    names = list(FLIGHT_LOGS) + sorted(p.stem for p in root.glob("*.bin") if p.stem not in FLIGHT_LOGS)
    logs = {name: _read_one(name, root / f"{name}.bin") for name in names}
    for name, st in logs.items():
        for p in st.problems:
            problems.append(f"{name}.bin: {p}")
    return FlightData(root, run_info, run_summary, logs, _time_origin(logs), problems)

