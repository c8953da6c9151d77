"""The summary table at the top of a report: what flew, for how long, and what the logs hold.

Per-thread watchdog events and step times are not in any log yet; when the runtime leaves a
``summary.json`` (the dictionary `Runtime.summary()` returns) they are taken from there, and
otherwise restarts are counted from the Begin Data records each (re)start writes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.report.analysis import counter_gaps, csv_size_bytes
from companion.report.autopilot import AutopilotSummary, summarise_autopilot
from companion.report.flight import FlightData

__all__ = ["EventRow", "LogRow", "Summary", "ThreadRow", "summarise"]

EVENT_ROWS_MAX = 400
"""Events listed one by one; an hour of injected faults makes thousands, counted per kind."""

IMU_COUNTER_MODULO = 100  # the IMU frame counter runs 0..99
SERVO_SEQ_MODULO = 256  # the servo exchange sequence number is one byte


@dataclass(frozen=True)
class LogRow:
    name: str
    present: bool
    size_bytes: int
    csv_bytes: int | None
    records: int
    formats: int
    begins: int
    closed_cleanly: bool
    span_s: float | None
    problems: tuple[str, ...]


@dataclass(frozen=True)
class ThreadRow:
    name: str
    restarts: int | None
    source: str  # where the figures come from: "summary.json", "log markers" or "no log"
    cycles: int | None = None
    rate_hz: float | None = None
    stalls: int | None = None
    mean_step_us: float | None = None
    worst_step_us: float | None = None
    missed_deadlines: int | None = None
    log_dropped: int | None = None


@dataclass(frozen=True)
class EventRow:
    t_s: float  # flight time: seconds from the report's time origin
    thread: str
    kind: str
    detail: str


@dataclass
class Summary:
    flight_dir: str
    duration_s: float
    software: str
    started_utc: str
    clock_scale: float | None
    simulation: str
    logs: list[LogRow]
    threads: list[ThreadRow]
    binary_bytes: int
    csv_bytes: int | None
    csv_estimated: bool = False  # long formats converted in part and scaled
    counters: dict[str, int] = field(default_factory=dict)
    events: list[EventRow] = field(default_factory=list)
    """What the supervisor and the threads reported (summary.json), in time order."""
    event_counts: dict[tuple[str, str], int] = field(default_factory=dict)
    """(thread, kind) -> events, over the whole flight (also those not listed)."""
    injected: list[str] = field(default_factory=list)
    """Faults a simulation injected on purpose (run.json and summary.json), one line each."""
    autopilot: AutopilotSummary | None = None
    """Our estimate against the autopilot's, its clock map, GUIDED targets: only for a flight
    with an autopilot.bin."""

    @property
    def restarts(self) -> int:
        return sum(t.restarts or 0 for t in self.threads)


def _span(fd: FlightData, name: str) -> float | None:
    st = fd.logs[name]
    if st.log is None:
        return None
    times = [int(s.time_ns.min()) for s in st.log.streams if s.n_records]
    times_end = [int(s.time_ns.max()) for s in st.log.streams if s.n_records]
    times += [m.time_ns for m in st.log.markers]
    times_end += [m.time_ns for m in st.log.markers]
    return (max(times_end) - min(times)) / 1e9 if times else None


def _thread_rows(fd: FlightData) -> list[ThreadRow]:
    from_summary: dict[str, dict[str, Any]] = {}
    if fd.run_summary and isinstance(fd.run_summary.get("threads"), list):
        for t in fd.run_summary["threads"]:
            if isinstance(t, dict) and "name" in t:
                from_summary[str(t["name"])] = t
    names: list[str] = []
    if fd.run_info and isinstance(fd.run_info.get("threads"), list):
        names = [str(t.get("name")) for t in fd.run_info["threads"] if isinstance(t, dict)]
    for n in list(from_summary) + [n for n, st in fd.logs.items() if st.present and n != "truth"]:
        if n not in names:
            names.append(n)
    rows = []
    for name in names:
        s = from_summary.get(name)
        st = fd.logs.get(name)
        if s is not None:
            rows.append(ThreadRow(
                name, int(s.get("restarts", 0) or 0), "summary.json",
                cycles=s.get("cycles"), rate_hz=s.get("rate_hz"), stalls=s.get("stalls"),
                mean_step_us=s.get("mean_step_us"), worst_step_us=s.get("worst_step_us"),
                missed_deadlines=s.get("missed_deadlines"), log_dropped=s.get("log_dropped")))
        elif st is not None and st.log is not None:
            rows.append(ThreadRow(name, st.restarts, "log markers"))
        else:
            rows.append(ThreadRow(name, None, "no log"))
    return rows


def _counters(fd: FlightData) -> dict[str, int]:
    out: dict[str, int] = {}
    imu = fd.block("imu", 1, ("counter",))
    if imu is not None:
        out["IMU frames missing (counter gaps)"] = counter_gaps(imu["counter"], IMU_COUNTER_MODULO)
    servo = fd.block("servo", 1, ("seq",))
    if servo is not None:
        out["servo exchanges missing (sequence gaps)"] = counter_gaps(servo["seq"], SERVO_SEQ_MODULO)
    gps = fd.block("gps", 1, ("fix",))
    if gps is not None:
        out["GPS epochs without a fix"] = int(np.sum(np.asarray(gps["fix"]) <= 0))
    return out


def _events(fd: FlightData) -> tuple[list[EventRow], dict[tuple[str, str], int]]:
    raw = (fd.run_summary or {}).get("events")
    rows: list[EventRow] = []
    counts: dict[tuple[str, str], int] = {}
    if not isinstance(raw, list):
        return rows, counts
    for e in raw:
        if not isinstance(e, dict) or e.get("kind") in ("started", "stopped", None):
            continue
        key = (str(e.get("thread", "?")), str(e["kind"]))
        counts[key] = counts.get(key, 0) + 1
        t = e.get("t_s")
        if len(rows) < EVENT_ROWS_MAX:
            rows.append(EventRow(float(t) - fd.t0_ns / 1e9 if isinstance(t, (int, float))
                                 else float("nan"), key[0], key[1], str(e.get("detail", ""))))
    return rows, counts


def _injected(fd: FlightData) -> list[str]:
    out: list[str] = []
    sim = (fd.run_info or {}).get("simulation")
    if isinstance(sim, dict):
        for key, flag in (("faults", "--fault"), ("vanish", "--vanish"),
                          ("thread_faults", "--thread-fault"), ("clock_steps", "--clock-step")):
            items = sim.get(key)
            if isinstance(items, list):
                out += [f"{flag} {item}" for item in items]
    counts = ((fd.run_summary or {}).get("simulator") or {}).get("faults")
    if isinstance(counts, dict):
        for dev, c in counts.items():
            if isinstance(c, dict):
                done = ", ".join(f"{k} {v}" for k, v in c.items() if v and k != "chunks")
                out.append(f"{dev}: the simulator injected {done or 'nothing'}")
    return out


def summarise(fd: FlightData, *, measure_csv: bool = True) -> Summary:
    rows = []
    estimated = False
    for name, st in fd.logs.items():
        lf = st.log
        csv = csv_size_bytes(st) if measure_csv and lf is not None else None
        estimated = estimated or bool(csv and csv[1])
        rows.append(LogRow(
            name=name,
            present=st.present,
            size_bytes=st.size_bytes,
            csv_bytes=csv[0] if csv else None,
            records=lf.record_count if lf else 0,
            formats=len(lf.streams) if lf else 0,
            begins=st.begins,
            closed_cleanly=bool(lf and lf.closed_cleanly),
            span_s=_span(fd, name),
            problems=tuple(st.problems),
        ))
    present = [r for r in rows if r.present]
    binary = sum(r.size_bytes for r in present)
    csv_total: int | None = None
    if measure_csv and present and all(r.csv_bytes is not None for r in present):
        csv_total = sum(r.csv_bytes or 0 for r in present)
    info = fd.run_info or {}
    sw = info.get("software") if isinstance(info.get("software"), dict) else {}
    sim = info.get("simulation") if isinstance(info.get("simulation"), dict) else None
    sim_text = (f"SITL, scenario {sim.get('scenario')}, aircraft {sim.get('aircraft')}, "
                f"seed {sim.get('seed')}" if sim else "real flight (no simulation in run.json)")
    scale = info.get("clock_scale")
    events, event_counts = _events(fd)
    return Summary(
        flight_dir=str(fd.flight_dir),
        duration_s=fd.duration_s,
        software=f"{sw.get('name', '?')} {sw.get('version', '?')}" if sw else "unknown",
        started_utc=str(info.get("started_utc", "unknown")),
        clock_scale=float(scale) if isinstance(scale, (int, float)) else None,
        simulation=sim_text,
        logs=rows,
        threads=_thread_rows(fd),
        binary_bytes=binary,
        csv_bytes=csv_total,
        csv_estimated=estimated,
        counters=_counters(fd),
        events=events,
        event_counts=event_counts,
        injected=_injected(fd),
        autopilot=summarise_autopilot(fd),
    )
