"""Ground-station transfers: log download and MAVLink FTP with MAVProxy, telemetry kept, CPU.

Run: `python bench/gcs_transfer_bench.py [--quick]` from the repository root (about 3 minutes,
under one with --quick). Everything runs on this machine over loopback and pseudo-terminals.

The vehicle is `support.synthetic_vehicle.SyntheticVehicle` (tests/support) recording flight
ROOT/20261124T120000Z; an older flight ROOT/20261123T100000Z holds one random file (4 MB,
--quick 400 kB, over UDP; 40 kB over the radio). MAVProxy 1.8.75
(`--default-modules=log,ftp --streamrate=-1`, so it leaves the bridge's default telemetry
schedule alone) fetches it, driven on stdin:

1. over UDP loopback (`udpout:127.0.0.1:PORT?identity=px4`): `log download 0 FILE` (the old flight
   as the bridge's tar archive, checked byte for byte against `FlightArchive.snapshot(old)`) and
   `ftp get /<old flight>/<file> FILE` (checked against the file). Figure: file kB/s (1 kB = 1000
   bytes) from the command to MAVProxy's "finished" line; baseline: the configured pacing limit
   MAV_BULK_KB_S, so the ratio is the fraction of it achieved (wire bytes include MAVLink framing:
   at most 90/109 of the limit is log data, 239/266 FTP data);
2. the same over a "radio": two pseudo-terminals joined by bench/serial_relay.py at 57600 baud
   (5760 bytes/s each way, a 2 kB buffer each way), the bridge on one
   (`/dev/pts/X,57600?identity=px4`), MAVProxy on the other. Baseline: the bridge's pacing on a
   serial line, baud/10 x (1 - MAV_RADIO_PCT/100) x 0.8; the notes give the share of the line
   the file took and the share of the line the relay carried towards the ground in that time;
3. ATTITUDE per second during each transfer: UDP from the bridge's own tlog
   (flight/mavlink-0.tlog, messages stamped within the transfer window), the radio at the
   ground end of the relay (what MAVProxy received), against the configured MAV_ATT_HZ = 20 Hz
   (on the radio the schedule is fitted to MAV_RADIO_PCT of the line; the note gives the rate
   the bridge's schedule was set to);
4. CPU of the bridge's link threads (mav0rx + mav0tx, utime+stime from
   /proc/self/task/<tid>/stat) per wall second, 10 s with a pymavlink listener on UDP (no tlog),
   default rates vs every MAV_*_HZ = 1 (the old 1 s defaults) in the same run.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import random
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from companion.logs.archive import FlightArchive
from gcs_bridge.bridge_params import BRIDGE_PARAMS
from gcs_bridge.dialect import mavlink
from gcs_bridge.link import RADIO_BULK_SHARE

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # test support
from serial_relay import SerialRelay  # noqa: E402
from support.synthetic_vehicle import SyntheticVehicle  # noqa: E402

MAVPROXY = Path(sys.executable).with_name("mavproxy.py")
CURRENT = "20261124T120000Z"
OLD = "20261123T100000Z"
DATA_NAME = "data.bin"  # a .bin makes the directory a flight for the log server
BAUD = 57600
RADIO_BUFFER = 2048
ATT_HZ_CONFIGURED = 20.0
LOG_WIRE = 90 / (97 + 12)  # LOG_DATA: 90 data bytes in a 97-byte payload + framing
FTP_WIRE = 239 / (254 + 12)  # FILE_TRANSFER_PROTOCOL: 239 data bytes in a 254-byte payload
HZ_PARAMS = [p.name for p in BRIDGE_PARAMS if p.name.startswith("MAV_") and p.name.endswith("_HZ")]


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def param_default(name: str) -> float:
    return float(next(p.default for p in BRIDGE_PARAMS if p.name == name))


# ----------------------------------------------------------------------------------- MAVProxy
class MavProxy:
    """MAVProxy with commands on stdin, its output collected with arrival times."""

    def __init__(self, master_args: list[str], cwd: Path) -> None:
        self.lines: list[tuple[float, str]] = []
        self._lock = threading.Lock()
        self.proc = subprocess.Popen(
            [sys.executable, "-u", str(MAVPROXY), *master_args, "--no-state",
             "--default-modules=log,ftp", "--streamrate=-1", "--state-basedir", str(cwd)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            cwd=cwd)
        self._reader = threading.Thread(target=self._read, name="mavproxy-out", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            t = time.monotonic()
            with self._lock:
                self.lines.append((t, line.rstrip()))

    def cmd(self, text: str) -> float:
        assert self.proc.stdin is not None
        t = time.monotonic()
        self.proc.stdin.write(text + "\n")
        self.proc.stdin.flush()
        return t

    def mark(self) -> int:
        with self._lock:
            return len(self.lines)

    def wait_line(self, cond: Callable[[str], bool], timeout_s: float,
                  start: int = 0) -> tuple[float, str] | None:
        deadline = time.monotonic() + timeout_s
        seen = start
        while True:
            with self._lock:
                new = self.lines[seen:]
            for t, line in new:
                if cond(line):
                    return t, line
            seen += len(new)
            if time.monotonic() >= deadline or self.proc.poll() is not None and not new:
                return None
            time.sleep(0.02)

    def tail(self, n: int = 8) -> str:
        with self._lock:
            return " / ".join(line for _t, line in self.lines[-n:])

    def close(self) -> None:
        try:
            if self.proc.stdin is not None and self.proc.poll() is None:
                self.proc.stdin.write("exit\n")
                self.proc.stdin.flush()
                self.proc.stdin.close()  # EOF on stdin ends MAVProxy too
        except OSError:
            pass
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
        self._reader.join(5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


# ----------------------------------------------------------------------------------- transfers
@dataclass
class Transfer:
    what: str
    nbytes: int = 0
    seconds: float = float("nan")
    ok: bool = False
    error: str = ""
    window: tuple[float, float] = (0.0, 0.0)  # monotonic
    wall_window: tuple[float, float] = (0.0, 0.0)  # time.time(), for the tlog stamps
    line_bytes: int = 0  # radio: bytes the relay carried towards the ground in the window
    att_hz: float = float("nan")
    att_hz_tlog: float = float("nan")

    @property
    def kb_s(self) -> float:
        return self.nbytes / self.seconds / 1000.0 if self.ok else float("nan")


def make_root(base: Path, size: int) -> tuple[Path, bytes, bytes]:
    """The logs root with the old flight and an empty current one; (root, file, archive)."""
    root = base
    old = root / OLD
    old.mkdir(parents=True)
    (root / CURRENT).mkdir()
    data = random.Random(size).randbytes(size)
    (old / DATA_NAME).write_bytes(data)
    snap = FlightArchive.snapshot(old)
    return root, data, snap.read(0, snap.size)


def wait_file(path: Path, expected: bytes, timeout_s: float) -> bool:
    """The file holds exactly `expected` (MAVProxy may still be closing it)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            if path.stat().st_size == len(expected) and path.read_bytes() == expected:
                return True
        except OSError:
            pass
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.05)


def run_transfers(mp: MavProxy, workdir: Path, archive: bytes, data: bytes, bulk_bytes_s: float,
                  line_counter: Callable[[], int] | None) -> list[Transfer]:
    """`log list`, `log download 0`, then `ftp get` of the old flight's file, each timed."""
    out = []
    mark = mp.mark()
    mp.cmd("log list")
    found = mp.wait_line(lambda s: "Log 0 " in s and "numLogs" in s, 30.0, mark)
    log_t = Transfer("log download (tar of the flight)", len(archive))
    if found is None:
        log_t.error = f"no log list: {mp.tail()}"
    elif f"size {len(archive)}" not in found[1]:
        log_t.error = f"listed size differs: {found[1]!r} (archive {len(archive)} bytes)"
    jobs: list[tuple[Transfer, str, str, Path, bytes, float]] = [
        (log_t, "log download 0 {}", "Finished downloading", workdir / "log0.tar", archive,
         LOG_WIRE),
        (Transfer("FTP get (the file)", len(data)), f"ftp get /{OLD}/{DATA_NAME} {{}}", "Wrote ",
         workdir / "ftp.bin", data, FTP_WIRE),
    ]
    for t, command, done, local, expected, wire in jobs:
        out.append(t)
        if t.error:
            continue
        timeout_s = 30.0 + 4.0 * len(expected) / (bulk_bytes_s * wire)
        mark = mp.mark()
        n0 = line_counter() if line_counter else 0
        w0 = time.time()
        t0 = mp.cmd(command.format(local))
        got = mp.wait_line(lambda s, d=done: d in s, timeout_s, mark)
        w1 = time.time()
        n1 = line_counter() if line_counter else 0
        if got is None:
            t.error = f"not finished in {timeout_s:.0f} s: {mp.tail()}"
            mp.cmd("log cancel" if command.startswith("log") else "ftp cancel")
            time.sleep(1.0)
            continue
        t1 = got[0]
        t.seconds = t1 - t0
        t.window = (t0, t1)
        t.wall_window = (w0, w1)
        t.line_bytes = n1 - n0
        t.ok = wait_file(local, expected, 10.0)
        if not t.ok:
            size = local.stat().st_size if local.exists() else -1
            t.error = f"file differs ({size} of {len(expected)} bytes)"
        time.sleep(0.5)  # let the bridge see the end of the transfer
    return out


def tlog_attitude_times(path: Path) -> list[float]:
    from pymavlink import mavutil

    times: list[float] = []
    if not path.exists():
        return times
    conn = mavutil.mavlink_connection(str(path), dialect="common")
    try:
        while (m := conn.recv_match(type="ATTITUDE")) is not None:
            times.append(float(m._timestamp))
    finally:
        conn.close()
    return times


def rate_in(times: list[float], window: tuple[float, float]) -> float:
    a, b = window
    if b <= a:
        return float("nan")
    return sum(1 for x in times if a <= x <= b) / (b - a)


def bench_udp(size: int, base: Path) -> tuple[list[Transfer], float]:
    root, data, archive = make_root(base / "udp", size)
    port = free_port()
    workdir = base / "mavproxy-udp"
    workdir.mkdir()
    with SyntheticVehicle([f"udpout:127.0.0.1:{port}?identity=px4"],
                          flight_dir=root / CURRENT) as v, contextlib.ExitStack() as stack:
        limit = float(v.params.get("MAV_BULK_KB_S")) * 1000.0
        mp = MavProxy([f"--master=udpin:127.0.0.1:{port}"], workdir)
        stack.callback(mp.close)
        if mp.wait_line(lambda s: "Detected vehicle" in s or "online system" in s, 30.0) is None:
            raise RuntimeError(f"MAVProxy saw no vehicle over UDP: {mp.tail()}")
        results = run_transfers(mp, workdir, archive, data, limit, None)
    times = tlog_attitude_times(root / CURRENT / "mavlink-0.tlog")
    for t in results:
        if t.ok:
            t.att_hz_tlog = rate_in(times, t.wall_window)
            t.att_hz = t.att_hz_tlog
    return results, limit


def bench_radio(size: int, base: Path) -> tuple[list[Transfer], float, float]:
    root, data, archive = make_root(base / "radio", size)
    workdir = base / "mavproxy-radio"
    workdir.mkdir()
    att_ground: list[float] = []
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True

    def tap(chunk: bytes, t: float) -> None:
        for m in parser.parse_buffer(chunk) or []:
            if m.get_type() == "ATTITUDE":
                att_ground.append(t)

    scheduled_hz = float("nan")
    with SerialRelay(BAUD, buffer_bytes=RADIO_BUFFER) as relay, contextlib.ExitStack() as stack:
        relay.taps[0] = tap
        v = SyntheticVehicle([f"{relay.path_a},{BAUD}?identity=px4"], flight_dir=root / CURRENT)
        stack.callback(v.stop)
        v.start()
        link = v.bridge.links[0]
        pct = float(v.params.get("MAV_RADIO_PCT"))
        limit = BAUD / 10.0 * (1.0 - pct / 100.0) * RADIO_BULK_SHARE
        mp = MavProxy([f"--master={relay.path_b}", "--baudrate", str(BAUD)], workdir)
        stack.callback(mp.close)
        if mp.wait_line(lambda s: "Detected vehicle" in s or "online system" in s, 30.0) is None:
            raise RuntimeError(f"MAVProxy saw no vehicle over the radio: {mp.tail()}")
        results = run_transfers(mp, workdir, archive, data, limit, lambda: relay.delivered[0])
        interval = link.interval_us(mavlink.MAVLINK_MSG_ID_ATTITUDE)
        scheduled_hz = 1e6 / interval if interval > 0 else 0.0
    times = tlog_attitude_times(root / CURRENT / "mavlink-0.tlog")
    for t in results:
        if t.ok:
            t.att_hz = rate_in(att_ground, t.window)
            t.att_hz_tlog = rate_in(times, t.wall_window)
    return results, limit, scheduled_hz


# ----------------------------------------------------------------------------------- CPU
def thread_cpu_s(native_id: int) -> float:
    """utime + stime of one thread of this process, in seconds."""
    with open(f"/proc/self/task/{native_id}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@dataclass
class CpuRun:
    label: str
    core_pct: float = float("nan")
    parts: dict[str, float] = field(default_factory=dict)
    msg_s: float = float("nan")
    precise_pct: float = float("nan")  # the same threads' CPU clocks (ns, not 10 ms ticks)


def bench_cpu(label: str, rates_hz: float | None, duration_s: float) -> CpuRun:
    from pymavlink import mavutil

    port = free_port()
    listener = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", dialect="common")
    count = [0]
    stop = threading.Event()

    def listen() -> None:
        while not stop.is_set():
            if listener.recv_match(blocking=True, timeout=0.2) is not None:
                count[0] += 1

    th = threading.Thread(target=listen, name="cpu-listener", daemon=True)
    run = CpuRun(label)
    v = SyntheticVehicle([f"udpout:127.0.0.1:{port}"])
    try:
        if rates_hz is not None:
            for name in HZ_PARAMS:
                v.params.set(name, rates_hz)
        th.start()
        v.start()
        time.sleep(2.0)  # links open, schedule running
        ids, clocks = {}, {}
        for name in ("mav0rx", "mav0tx"):
            t = v.manager.find(name)
            if t is None or not t.native_id:
                raise RuntimeError(f"no running thread {name}")
            ids[name] = int(t.native_id)
            worker = getattr(t, "_worker", None)  # its pthread: a ns-resolution CPU clock
            if worker is not None and worker.ident is not None:
                clocks[name] = time.pthread_getcpuclockid(worker.ident)
        c0 = {k: thread_cpu_s(i) for k, i in ids.items()}
        p0 = {k: time.clock_gettime(c) for k, c in clocks.items()}
        n0, w0 = count[0], time.perf_counter()
        time.sleep(duration_s)
        c1 = {k: thread_cpu_s(i) for k, i in ids.items()}
        p1 = {k: time.clock_gettime(c) for k, c in clocks.items()}
        n1, w1 = count[0], time.perf_counter()
        wall = w1 - w0
        run.parts = {k: (c1[k] - c0[k]) / wall * 100.0 for k in ids}
        run.core_pct = sum(run.parts.values())
        if len(p1) == len(ids):
            run.precise_pct = sum(p1[k] - p0[k] for k in p1) / wall * 100.0
        run.msg_s = (n1 - n0) / wall
    finally:
        v.stop()
        stop.set()
        if th.is_alive():
            th.join(2.0)
        listener.close()
    return run


# ----------------------------------------------------------------------------------- report
def fmt(x: float, spec: str = ".1f") -> str:
    return "n/a" if x != x else format(x, spec)


def transfer_rows(link: str, results: list[Transfer], limit_b_s: float,
                  line_b_s: float | None, scheduled_hz: float | None) -> list[str]:
    rows = []
    for t in results:
        if not t.ok:
            rows.append(f"| {link}: {t.what}, {t.nbytes} B | FAILED | - | {t.error} |")
            continue
        wire = LOG_WIRE if t.what.startswith("log") else FTP_WIRE
        note = (f"{t.seconds:.1f} s, byte-exact; limit {limit_b_s / 1000:.2f} kB/s on the wire, "
                f"of which file data at most {wire:.2f}x")
        if line_b_s:
            note += (f"; file = {t.kb_s * 1000 / line_b_s:.0%} of the line, relay carried "
                     f"{t.line_bytes / t.seconds / line_b_s:.0%} of the line to the ground")
        rows.append(f"| {link}: {t.what}, {t.nbytes} B | {t.kb_s:.2f} kB/s | "
                    f"{t.kb_s * 1000 / limit_b_s:.2f}x of the pacing limit | {note} |")
    for t in results:
        if not t.ok:
            continue
        note = "from the bridge's tlog"
        if line_b_s:
            note = (f"received at the ground end of the relay (bridge's tlog: "
                    f"{fmt(t.att_hz_tlog)} Hz); schedule fitted to the radio: "
                    f"{fmt(scheduled_hz or float('nan'))} Hz")
        rows.append(f"| {link}: ATTITUDE during {t.what.split(' (')[0]} | {fmt(t.att_hz)} Hz | "
                    f"{t.att_hz / ATT_HZ_CONFIGURED:.2f}x of the configured "
                    f"{ATT_HZ_CONFIGURED:.0f} Hz | {note} |")
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short runs (smoke test)")
    args = ap.parse_args()
    quick = args.quick
    udp_size = 400_000 if quick else 4_000_000
    radio_size = 40_000
    cpu_s = 3.0 if quick else 10.0
    if not MAVPROXY.exists():
        print(f"gcs_transfer_bench: {MAVPROXY} not found (MAVProxy 1.8.75 is a dev dependency)",
              file=sys.stderr)
        return 2
    print("## Ground-station transfers (log download, MAVLink FTP) with MAVProxy\n")
    print(f"machine: {os.cpu_count()} cores, Python {sys.version.split()[0]}, load average "
          f"{os.getloadavg()[0]:.2f}; {'--quick' if quick else 'full run'}\n")
    rows: list[str] = []
    failures = 0
    base = Path(tempfile.mkdtemp(prefix="gcs-transfer-bench-"))
    try:
        for name, job in [("UDP", lambda: bench_udp(udp_size, base)),
                          ("radio", lambda: bench_radio(radio_size, base))]:
            try:
                got = job()
            except Exception as exc:  # one failed part must not hide the others
                rows.append(f"| {name} transfers | FAILED | - | {type(exc).__name__}: {exc} |")
                failures += 1
                continue
            if name == "UDP":
                results, limit = got  # type: ignore[misc]
                rows += transfer_rows("UDP", results, limit, None, None)
            else:
                results, limit, sched = got  # type: ignore[misc]
                rows += transfer_rows(f"radio {BAUD} Bd", results, limit, BAUD / 10.0, sched)
            failures += sum(not t.ok for t in results)
            print(f"({name} done)", flush=True)
    finally:
        shutil.rmtree(base, ignore_errors=True)
    try:
        new = bench_cpu("defaults", None, cpu_s)
        old = bench_cpu("1 Hz", 1.0, cpu_s)
        tick_pct = 100.0 / os.sysconf("SC_CLK_TCK") / cpu_s
        for run, ratio in [(new, f"{new.core_pct / old.core_pct:.2f}x of the 1 Hz schedule"),
                           (old, "1.00x (baseline)")]:
            what = (f"default rates (MAV_ATT_HZ {param_default('MAV_ATT_HZ'):.0f} etc.)"
                    if run is new else "every MAV_*_HZ = 1 (the old 1 s defaults)")
            rows.append(
                f"| bridge link threads CPU, {what} | {run.core_pct:.2f} % of a core | {ratio} | "
                f"{cpu_s:.0f} s, {run.msg_s:.0f} msg/s received; "
                + ", ".join(f"{k} {p:.2f} %" for k, p in run.parts.items())
                + f" (/proc ticks: +-{tick_pct:.2f} %); thread CPU clocks: "
                f"{fmt(run.precise_pct, '.2f')} % |")
        if new.precise_pct == new.precise_pct and old.precise_pct:
            rows.append(f"| bridge link threads CPU by the thread CPU clocks | "
                        f"{new.precise_pct:.2f} % of a core | "
                        f"{new.precise_pct / old.precise_pct:.2f}x of the 1 Hz schedule | "
                        f"ns-resolution cross-check of the two rows above |")
    except Exception as exc:
        rows.append(f"| bridge CPU | FAILED | - | {type(exc).__name__}: {exc} |")
        failures += 1
    print("\n| measurement | value | ratio vs baseline | notes |\n|---|---|---|---|")
    for row in rows:
        print(row)
    print(f"\n(load average after: {os.getloadavg()[0]:.2f})")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("gcs_transfer", ["gcs_bridge", "companion/logs", "bench/serial_relay.py"], main))
