"""Fault campaign, disk rows: the log disk turns slow or read-only under a real SITL flight.

Run one row: ``python -c "import sys; sys.path.insert(0, 'bench'); import faults_disk as f;
print(f.row_slow_fsync(30.0)); print(f.row_readonly(30.0, 5.0))"`` (as root, with FUSE).

The flight is a `companion sim --fast` flight of `faults_bench` whose ``--log-dir`` is a
`faultfs.FaultFs` mount (a FUSE passthrough in its own process) over a temporary directory.
The fault is switched on `at_s` flight seconds after the runtime first answers a ground
station, and the row reports what the issue asks of a degraded log disk: the IMU and GPS
rates held, restarts (none intended), records dropped per log, whether the runtime said so
(supervisor events, STATUSTEXT seen by a ground station, warnings on stderr, summary.json),
how long after the flight's end the process took to exit (a slow disk must not hang the
shutdown), and which logs read back from the backing directory afterwards.

Why these: the runtime's log writer never fsyncs its logs (it leaves them to the kernel),
but run.json and summary.json are written atomically with two fsyncs each, so a slow disk
shows up in the shutdown; a read-only disk fails every write of files that are already open,
which the writer must turn into "logging off", not a crash or a restart.

`row_slow_write` (every write request slow) is the third: every thread that wrote to the disk
itself waited for it (the MAVLink threads wrote the .tlog and missed their watchdog; the
.tlog now goes through the log writer), and the log writer's close shows whether a slow disk
still gets every record written.

Without FUSE (no /dev/fuse, no mfusepy, no libfuse, no permission) a row says "skipped: ...".
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import tempfile
import threading
import time
from datetime import datetime
from pathlib import Path
from typing import Any

from faultfs import FaultFs, FaultFsUnavailable, unavailable_reason
from faults_bench import SCALE, Flight, Row, common, fly
from pymavlink import mavutil

from companion.logs import read_log

_REPORT_WORDS = re.compile(r"log|disk|summary|tlog|fsync|read-only|no space|errno", re.I)


class _Observer:
    """Everything the `during` callback sees: switches the fault, listens like a ground station,
    keeps the runtime's stdout/stderr (faults_bench's `Flight.finish` would drop stderr) and
    notes when the process exits, to the tenth of a second."""

    def __init__(self, fs: FaultFs, faults: dict[str, Any], at_s: float, duration_s: float):
        self.fs = fs
        self.faults = faults
        self.at_s = at_s
        self.duration_s = duration_s
        self.out: list[str] = []
        self.err: list[str] = []
        self.readers: list[threading.Thread] = []
        self.chunks: list[tuple[int, int, int, str]] = []  # STATUSTEXT (severity, id, seq, text)
        self.t_ready = 0.0
        self.t_switch: float | None = None
        self.t_exit: float | None = None
        self.wall_exit: float | None = None
        self.last_heartbeat: float | None = None
        self.max_hb_gap = 0.0  # longest silence of the vehicle's HEARTBEAT after the switch

    # -- stdout/stderr, read all along (a full pipe would block the runtime's logging)
    def _capture(self, flight: Flight) -> None:
        proc = flight.proc
        assert proc is not None and proc.stdout is not None and proc.stderr is not None
        for stream, sink in ((proc.stdout, self.out), (proc.stderr, self.err)):
            t = threading.Thread(target=lambda s=stream, k=sink: k.extend(iter(s.readline, "")),
                                 daemon=True)
            t.start()
            self.readers.append(t)

        def finish(timeout_s: float) -> tuple[dict[str, Any] | None, int]:
            """`Flight.finish`, reading from the capture instead of communicate()."""
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            for r in self.readers:
                r.join(5.0)
            out = "".join(self.out)
            try:
                return json.loads(out[out.index("{"):]), proc.returncode
            except ValueError:
                return None, proc.returncode

        flight.finish = finish  # type: ignore[method-assign]  # this flight only

    def statustext(self) -> list[tuple[int, str]]:
        """STATUSTEXT received after the switch, chunked ones (id != 0) put back together."""
        out: list[tuple[int, str]] = []
        parts: dict[int, list[tuple[int, str]]] = {}
        for sev, ident, seq, text in self.chunks:
            if ident == 0:
                out.append((sev, text))
                continue
            if ident not in parts:
                parts[ident] = []
                out.append((sev, f"\0{ident}"))  # placeholder keeps the order of arrival
            parts[ident].append((seq, text))
        return [(sev, "".join(t for _, t in sorted(parts[int(text[1:])]))
                 if text.startswith("\0") else text) for sev, text in out]

    def during(self, flight: Flight) -> dict[str, str]:
        assert flight.proc is not None
        self._capture(flight)
        self.t_ready = time.monotonic()
        found: dict[str, str] = {}
        conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{flight.mav_port}",
                                          source_system=243)
        switch_at = self.t_ready + self.at_s / SCALE
        deadline = self.t_ready + self.duration_s / SCALE + 60.0
        next_hb = next_rss = 0.0
        try:
            while time.monotonic() < deadline:
                now = time.monotonic()
                if now >= next_hb:  # a ground station the runtime keeps answering (udpin)
                    conn.mav.heartbeat_send(6, 8, 0, 0, 0)
                    next_hb = now + 0.5
                if now >= next_rss:
                    flight.sample_rss()
                    next_rss = now + 0.5
                if self.t_switch is None and now >= switch_at:
                    try:
                        self.fs.set(**self.faults)
                        self.t_switch = time.monotonic()
                        found["fault on after"] = (f"{self.at_s:g} s of flight (host "
                                                   f"{self.t_switch - self.t_ready:.2f} s after "
                                                   f"the first answer; applied in "
                                                   f"{(self.t_switch - now) * 1000:.0f} ms)")
                    except (TimeoutError, OSError) as exc:
                        found["fault on after"] = f"NOT SWITCHED: {exc}"
                        self.t_switch = time.monotonic()
                if flight.proc.poll() is not None:
                    self.t_exit, self.wall_exit = time.monotonic(), time.time()
                    break
                m = conn.recv_match(type=["STATUSTEXT", "HEARTBEAT"], blocking=True, timeout=0.1)
                if m is None or m.get_srcSystem() == 243:
                    continue
                if m.get_type() == "HEARTBEAT":
                    t = time.monotonic()
                    if self.t_switch is not None and self.last_heartbeat is not None:
                        self.max_hb_gap = max(self.max_hb_gap, t - self.last_heartbeat)
                    self.last_heartbeat = t
                elif self.t_switch is not None:
                    self.chunks.append((m.severity, getattr(m, "id", 0),
                                        getattr(m, "chunk_seq", 0), m.text.rstrip("\x00")))
        finally:
            conn.close()
        if self.t_exit is None:
            found["exit"] = f"still running {deadline - self.t_ready:.0f} s after the first answer"
        return found


def _started_wall(flight_dir: Path) -> float | None:
    """Host wall time the flight started (run.json, written just before take-off)."""
    try:
        info = json.loads((flight_dir / "run.json").read_text())
        return datetime.fromisoformat(info["started_utc"]).timestamp()
    except (OSError, ValueError, KeyError):
        return None


def _stderr_report(lines: list[str]) -> str:
    """The runtime's warnings and errors on stderr that concern the disk, per logger: how many,
    and the distinct messages once the log names and paths are taken out."""
    tracebacks = sum(1 for ln in lines if ln.startswith("Traceback"))
    by_logger: dict[str, list[str]] = {}
    for ln in lines:
        # the runtime's format is "HH:MM:SS W logger: ..."; the simulator's "sim: WARNING ..."
        m = (re.match(r"^\S+ [WEC] ([\w.]+): (.*)$", ln.strip())
             or re.match(r"^(\w+): (?:WARNING|ERROR|CRITICAL) (.*)$", ln.strip()))
        if m is None or not _REPORT_WORDS.search(m.group(2)):
            continue
        msg = re.sub(r"(/[^/\s:']+)+/?", "<path>", m.group(2))
        msg = re.sub(r"\b(for|watchdog:) [\w.-]+:", r"\1 <log>:", msg)
        by_logger.setdefault(m.group(1), []).append(msg)
    parts = [f"{tracebacks} TRACEBACK(S)"] if tracebacks else []
    for logger, msgs in by_logger.items():
        distinct = list(dict.fromkeys(msgs))
        shown = " | ".join(d[:70] for d in distinct[:2]) + (" | ..." if len(distinct) > 2 else "")
        parts.append(f"{logger} x{len(msgs)}: {shown}")
    return "; ".join(parts) or "nothing"


def _logs_read_back(flight_dir: Path) -> dict[str, str]:
    """Each binary log of the flight, read from the backing directory (what reached the disk)."""
    parts: list[str] = []
    bad: list[str] = []
    clean = 0
    bins = sorted(flight_dir.glob("*.bin"))
    for p in bins:
        try:
            lg = read_log(p, salvage=True)
        except Exception as exc:  # a log the reader cannot open at all is the finding
            bad.append(f"{p.stem}: {type(exc).__name__}: {str(exc)[:60]}")
            continue
        clean += lg.closed_cleanly
        if lg.skipped_bytes or lg.truncated_bytes:
            bad.append(f"{p.stem}: {lg.skipped_bytes} B skipped, {lg.truncated_bytes} B cut")
        if p.stem in ("imu", "gps", "truth"):
            t = lg.time_ns(1) / 1e9
            span = f", {t[-1] - t[0]:.1f} s of flight" if len(t) > 1 else ""
            parts.append(f"{p.stem} {lg.record_count} records{span}")
    out = {"logs read back": (f"{len(bins) - len(bad)}/{len(bins)} readable, {clean} closed "
                              f"cleanly; " + ", ".join(parts))}
    if bad:
        out["log damage"] = "; ".join(bad)
    return out


def _disk_row(d: float, name: str, fault: str, faults: dict[str, Any], at_s: float) -> Row:
    """One flight with its log directory on a FaultFs, `faults` switched on at `at_s`."""
    reason = unavailable_reason()
    if reason:
        return Row(name, fault, {"skipped": reason})
    backing = Path(tempfile.mkdtemp(prefix="faults-disk-backing-"))
    mount = Path(tempfile.mkdtemp(prefix="faults-disk-mnt-"))
    try:
        with FaultFs(backing, mount) as fs:
            obs = _Observer(fs, faults, at_s, d)
            flight, s, code, found = fly(d, ["--log-dir", str(mount)], obs.during)  # last wins
            fs_stats = fs.stats()
    except FaultFsUnavailable as exc:
        return Row(name, fault, {"skipped": str(exc)})
    try:
        figs = common(s, flight, code)
        figs.update(found)
        dirs = sorted(p for p in backing.iterdir() if p.is_dir())
        fdir = dirs[-1] if dirs else None
        if s is not None:
            figs["records dropped"] = ", ".join(
                f"{t['name']} {t['log_dropped']}" for t in s["threads"] if t["log_dropped"]
            ) or "none"
            off = [e for e in s["events"] if e["kind"] == "logging off"]
            figs["'logging off' events"] = (", ".join(f"{e['thread']} ({e['detail']})"
                                                      for e in off[:8])
                                            + (f" ... {len(off)} in all" if len(off) > 8 else "")
                                            ) or "none"
            figs["stop reason"] = str(s.get("stop_reason"))
        texts: dict[str, int] = {}
        for sev, text in obs.statustext():
            if sev > 4:  # warnings and worse: not the threads' "stopped (shutdown)" notices
                continue
            texts[f"[{sev}] {text}"] = texts.get(f"[{sev}] {text}", 0) + 1
        figs["STATUSTEXT (warning or worse) after the switch"] = "; ".join(
            f"{k} (x{v})" if v > 1 else k for k, v in list(texts.items())[:8]) or "none"
        figs["stderr (disk-related warnings)"] = _stderr_report(obs.err)
        figs["summary.json"] = ("written" if fdir is not None and (fdir / "summary.json").exists()
                                else "not written" + (" (printed with --json)" if s else ""))
        # shutdown: the flight ends d/SCALE host seconds after take-off (run.json's stamp)
        start = _started_wall(fdir) if fdir is not None else None
        if obs.wall_exit is not None and start is not None:
            figs["exit after the flight's end"] = f"{obs.wall_exit - start - d / SCALE:.1f} s"
        if s is not None and "host_seconds" in s:
            figs["run() past the flight's end"] = (f"{max(0.0, s['host_seconds'] - d / SCALE):.1f} s "
                                                   "(Runtime.shutdown, first summary.json)")
        figs["longest HEARTBEAT gap after the switch"] = f"{obs.max_hb_gap:.2f} s (host)"
        if obs.last_heartbeat is not None and obs.t_exit is not None:
            figs["last HEARTBEAT before exit"] = f"{obs.t_exit - obs.last_heartbeat:.1f} s"
        c = fs_stats.get("counts", {})
        fsx = [f"fsyncs {c.get('fsyncs', 0):.0f} (delayed {c.get('fsyncs_delayed', 0):.0f}, "
               f"{c.get('fsync_delayed_s', 0):.1f} s)", f"writes {c.get('writes', 0):.0f}"]
        if c.get("erofs"):
            ops = ", ".join(f"{k[6:]} {v:.0f}" for k, v in sorted(c.items())
                            if k.startswith("erofs_"))
            fsx.append(f"EROFS {c['erofs']:.0f} ({ops})")
        if c.get("enospc"):
            fsx.append(f"ENOSPC {c['enospc']:.0f}")
        paths = fs_stats.get("fsync_paths", {})
        if paths:
            fsx.append("slow fsyncs on " + ", ".join(
                f"{re.sub(r'^/[^/]+/', '', p) or 'the flight directory'} x{n}"
                for p, n in sorted(paths.items())))
        figs["on the disk (faultfs)"] = "; ".join(fsx)
        if fdir is not None:
            figs.update(_logs_read_back(fdir))
        return Row(name, fault, figs)
    finally:
        shutil.rmtree(backing, ignore_errors=True)
        try:
            mount.rmdir()
        except OSError:
            pass


def row_slow_fsync(d: float, at_s: float = 5.0, delay_s: float = 1.0) -> Row:
    """Every fsync on the log disk takes `delay_s` from `at_s` (flight seconds) on."""
    return _disk_row(d, f"slow log disk (fsync {delay_s:g} s)",
                     f"--log-dir on faultfs, fsync_delay_s={delay_s:g} from {at_s:g} s",
                     {"fsync_delay_s": delay_s}, at_s)


def row_readonly(d: float, at_s: float) -> Row:
    """The log disk turns read-only at `at_s` (flight seconds), files open for writing."""
    return _disk_row(d, "log disk turns read-only", f"--log-dir on faultfs, readonly from "
                     f"{at_s:g} s (EROFS on every write, create, rename)",
                     {"readonly": True}, at_s)


def row_slow_write(d: float, at_s: float = 5.0, delay_s: float = 0.3) -> Row:
    """Every write request to the log disk takes `delay_s` from `at_s` (flight seconds) on: the
    disk every thread that writes to it directly (not through the log writer) waits for."""
    return _disk_row(d, f"slow log disk (write {delay_s:g} s)",
                     f"--log-dir on faultfs, write_delay_s={delay_s:g} from {at_s:g} s",
                     {"write_delay_s": delay_s}, at_s)


def print_row(r: Row) -> None:
    """The same Markdown table as faults_bench's main."""
    print(f"### {r.name}\n\nfault: {r.fault}\n")
    print("| figure | value |\n|---|---|")
    for k, v in r.figures.items():
        print(f"| {k} | {v} |")
    print()


if __name__ == "__main__":
    for row in (row_slow_fsync(30.0), row_readonly(30.0, 5.0)):
        print_row(row)
