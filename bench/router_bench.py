"""Routing beside an autopilot: ours, mavlink-router and MAVProxy between a flight
controller's serial line and a ground station, on the same bytes in one run.

Run: `MAVLINK_ROUTER=/path/to/mavlink-routerd python bench/router_bench.py [--quick]
[--json OUT] [--routers ours mavlink-router mavproxy] [--profile-ours]` (without
MAVLINK_ROUTER the C++ reference is left out and said so; `--profile-ours` runs ours once more
under cProfile, per thread, for where its CPU goes; ROUTER_BENCH_DUMP=DIR keeps each router's
send times and datagrams, to look into odd frames).

The autopilot is this process: it writes a real ArduPlane's TELEM stream
(`tests/data/autopilot/arduplane-sitl-telem.bin`, 17,240 MAVLink 2 frames, 40 s) into the
master of a pseudo-terminal; the router under test opens the slave at 921600 baud and routes
to one ground station, `udpout` to a UDP socket on 127.0.0.1 that a forked receiver process
drains (a separate process, so neither side waits for the other's GIL). Every wait is bounded,
every process is stopped at the end and every temporary directory removed.

The routers, each as its users run it as a router:

- **ours**: `companion.runtime.Runtime` with the autopilot device on the pty and one MAVLink
  link, driven by this file's own small driver (`--serve-ours`) with `RuntimeOptions(
  legacy=False, estimator=False, control=False)`: `companion run` has no switch for the
  estimator and the control law, which a router does not need. The autopilot link still
  decodes what it uses and writes its logs (imu.bin, gps.bin, servo.bin, autopilot.bin,
  truth.bin): that is part of what ours does beside an autopilot, and part of its CPU.
- **mavlink-router**: `UartEndpoint` on the pty at 921600, one `UdpEndpoint` in normal mode
  to the receiver, `TcpServerPort = 0`.
- **MAVProxy** 1.8.75: `--master=PTY --baudrate 921600 --out=udpout:... --daemon
  --non-interactive --default-modules= --streamrate=-1` (no modules, no stream requests).

The stream: frame i is the recording's frame i mod 17,240, its time fields (time_boot_ms,
time_usec, time_unix_usec) moved on by one recording length per loop (so the autopilot's clock
never runs back), and a 16-bit frame number in the header: its sequence byte (i mod 256) and
its compat_flags byte (i / 256 mod 256), CRC recomputed. compat_flags are "flags a receiver
may ignore if it does not understand them": every router forwards them untouched; no real
autopilot sets them. The receiver finds frame i from the frame number, the latest frame with
that number written before the datagram came, and checks its bytes.

Phases, for each router in turn (warm-up until the ground station hears it, then):

- **idle**: 2 s of silence (the router's CPU with nothing to do);
- **flight**: the recording's own byte rate (590 KB in 40 s = 14.7 KB/s, 431 frames/s),
  spread evenly by bytes (the recording has no arrival times);
- **line**: 921600 baud 8N1 = 92,160 B/s, the most a UART at that rate can deliver
  (about 2,700 frames/s), each frame written when its last byte would have arrived;
- **bursts**: 2,000 frames written back to back as fast as the pty takes them (a USB link is
  not held to a baud rate), then 1 s to drain, several times; its "frames/s written" is the
  median rate within a burst, i.e. how fast the router took them off the pty.

A frame's latency runs from the start of the `write` of its last byte into the pty to the
return of the `recv` of the UDP datagram holding it (the start, not the return: the router,
woken by the write, often runs before the writer does; how long the writes took until the
writer ran again is reported, `write_call_us`, as the bound on that choice). CPU: the router's process (and children)
user + system time from psutil, from the phase's first write to the end of its drain, per 1,000
frames received; loss: frames written in the phase that never arrived. The receiver's socket
drops (from /proc/net/udp) are reported apart: they would not be the router's loss.
"""

from __future__ import annotations

import argparse
import bisect
import json
import multiprocessing as mp
import os
import pickle
import select
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pymavlink.dialects.v20 import ardupilotmega as apm  # noqa: E402
from pymavlink.generator.mavcrc import x25crc  # noqa: E402

from bench.result import Result, machine  # noqa: E402
from gcs_bridge.framing import FrameSplitter  # noqa: E402
from gcs_bridge.msg_targets import field_offsets  # noqa: E402

RECORDING = ROOT / "tests" / "data" / "autopilot" / "arduplane-sitl-telem.bin"
MAVPROXY = Path(sys.executable).with_name("mavproxy.py")
BAUD = 921600
LINE_BYTES_S = BAUD / 10.0  # 8N1: ten bit times a byte
BURST_FRAMES = 2000
TIME_FIELDS = {"time_boot_ms": (4, 1), "time_usec": (8, 1000), "time_unix_usec": (8, 1000)}
"""field -> (size in bytes, units per millisecond)."""
WRITE_STALL_S = 10.0
"""A router that takes no byte from the pty for this long has stopped: the run fails."""
ROUTERS = ("ours", "mavlink-router", "mavproxy")
"""Measured by default; `ours-profiled` (ours under cProfile, one profile per thread: where
its CPU goes, its figures not comparable) runs after them with --profile-ours."""


# ---------------------------------------------------------------------------- the stream
@dataclass
class Recording:
    frames: list[bytes]
    patches: list[list[tuple[int, int, int]]]
    """Per frame: (offset in the payload, size, units per ms) of each time field it carries."""
    span_ms: int
    total_bytes: int


def load_recording() -> Recording:
    frames = [f.data for f in FrameSplitter().feed(RECORDING.read_bytes())]
    offsets = {mid: field_offsets(cls) for mid, cls in apm.mavlink_map.items()}
    patches: list[list[tuple[int, int, int]]] = []
    boot_ms: list[int] = []
    for data in frames:
        assert data[0] == 0xFD and not data[2] & 1, "MAVLink 2, unsigned"
        msg_id = data[7] | data[8] << 8 | data[9] << 16
        payload = data[10:10 + data[1]]
        mine = []
        for name, (size, per_ms) in TIME_FIELDS.items():
            off = offsets.get(msg_id, {}).get(name)
            if off is not None:
                mine.append((off, size, per_ms))
                if name == "time_boot_ms":
                    boot_ms.append(int.from_bytes(payload[off:off + size], "little"))
        patches.append(mine)
    span_ms = max(boot_ms) - min(boot_ms) + 20  # the last frame's tick, and one more
    return Recording(frames, patches, span_ms, sum(len(f) for f in frames))


def make_frame(rec: Recording, i: int) -> bytes:
    """Frame i of the looped stream: numbered, its clock moved on by whole loops (a time
    field that MAVLink 2 truncated away, its high bytes being zero, is put back first and the
    payload truncated again after: on the ground, AOA_SSA is its time stamp alone)."""
    n = len(rec.frames)
    loop, src = divmod(i, n)
    data = rec.frames[src]
    payload = bytearray(data[10:10 + data[1]])
    if loop:
        for off, size, per_ms in rec.patches[src]:
            if len(payload) < off + size:
                payload.extend(bytes(off + size - len(payload)))
            value = int.from_bytes(payload[off:off + size], "little") + loop * rec.span_ms * per_ms
            payload[off:off + size] = (value % (1 << (8 * size))).to_bytes(size, "little")
        while len(payload) > 1 and payload[-1] == 0:
            del payload[-1]
    buf = bytearray(data[:10]) + payload
    buf[1] = len(payload)
    buf[3] = (i >> 8) & 0xFF  # compat_flags: the frame number's high byte
    buf[4] = i & 0xFF  # sequence: its low byte
    crc = x25crc(bytes(buf[1:]))
    msg_id = buf[7] | buf[8] << 8 | buf[9] << 16
    crc.accumulate(bytes((apm.mavlink_map[msg_id].crc_extra,)))  # type: ignore[arg-type]
    return bytes(buf) + crc.crc.to_bytes(2, "little")


def frame_number(data: bytes) -> int:
    return data[4] | data[3] << 8


# ---------------------------------------------------------------------------- the receiver
def receive(sock: socket.socket, stop: Any, count: Any, out_path: str) -> None:
    """The ground station, in its own process: every datagram with its arrival time."""
    got: list[tuple[int, bytes]] = []
    sock.settimeout(0.1)
    while not stop.is_set():
        try:
            data = sock.recv(65536)
        except TimeoutError:
            continue
        got.append((time.monotonic_ns(), data))
        count.value += 1
    with open(out_path, "wb") as f:
        pickle.dump(got, f)


def udp_drops(port: int) -> int:
    """The kernel's drop count of the UDP socket bound to 127.0.0.1:`port`."""
    want = f"0100007F:{port:04X}"
    for line in Path("/proc/net/udp").read_text().splitlines()[1:]:
        cols = line.split()
        if cols[1] == want:
            return int(cols[-1])
    return -1


def split_v2(data: bytes) -> list[bytes]:
    out = []
    i = 0
    while i + 12 <= len(data):
        if data[i] != 0xFD:
            i += 1
            continue
        n = 12 + data[i + 1] + (13 if data[i + 2] & 1 else 0)
        out.append(data[i:i + n])
        i += n
    return out


# ---------------------------------------------------------------------------- the writer
class PtyWriter:
    """The autopilot's side of the pty: writes frames, reads (and drops) what the router
    sends back (heartbeats, stream requests), so its writes never block on us."""

    def __init__(self, frames: list[bytes]) -> None:
        self.frames = frames
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # held open: the master never sees EIO while nobody has it
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        self.sent_ns: list[int] = []
        """Per frame: when the write of its last byte began (monotonic ns)."""
        self.write_ns: list[int] = []
        """Per frame: how long that write took (until the writer ran again)."""
        self.bytes_back = 0

    def _drain(self) -> None:
        try:
            while True:
                got = os.read(self.master, 65536)
                if not got:
                    return
                self.bytes_back += len(got)
        except (BlockingIOError, OSError):
            return

    def wait(self, seconds: float) -> None:
        """Sleep `seconds`, draining what the router writes."""
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            if select.select([self.master], [], [], left)[0]:
                self._drain()

    def write_next(self) -> None:
        """Write the next frame whole; note when the write of its last byte began (a reader
        woken by the write can run before the writer returns from it: on two cores the
        router often pre-empts the writer, and a time taken after the write came up to
        0.6 ms after the router had already forwarded the frame) and how long it took."""
        data = memoryview(self.frames[len(self.sent_ns)])
        stall_end = time.monotonic() + WRITE_STALL_S
        while True:
            t_ns = time.monotonic_ns()
            try:
                n = os.write(self.master, data)
            except BlockingIOError:
                n = 0
            if n == len(data):
                break
            if n:
                data = data[n:]
                stall_end = time.monotonic() + WRITE_STALL_S
                continue
            left = stall_end - time.monotonic()
            if left <= 0:
                raise RuntimeError("the router took nothing from the pty for "
                                   f"{WRITE_STALL_S:.0f} s")
            r, _w, _x = select.select([self.master], [self.master], [], min(left, 0.1))
            if r:
                self._drain()
        self.write_ns.append(time.monotonic_ns() - t_ns)
        self.sent_ns.append(t_ns)

    def paced(self, rate_bytes_s: float, duration_s: float,
              until: Any = None) -> None:
        """Frames at `rate_bytes_s`, each when its last byte would have arrived on the
        line, for `duration_s` (or until `until()` is true, checked ten times a second)."""
        t0 = time.monotonic()
        cum = 0
        next_check = t0
        while True:
            cum += len(self.frames[len(self.sent_ns)])
            due = t0 + cum / rate_bytes_s
            if due - t0 > duration_s:
                return
            while (left := due - time.monotonic()) > 0:
                if select.select([self.master], [], [], left)[0]:
                    self._drain()
            self.write_next()
            if until is not None and time.monotonic() >= next_check:
                next_check = time.monotonic() + 0.1
                if until():
                    return

    def burst(self, n: int) -> None:
        for _ in range(n):
            self.write_next()

    def close(self) -> None:
        os.close(self.master)
        os.close(self.slave)


# ---------------------------------------------------------------------------- the routers
def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_router(name: str, pty: str, port: int, tmp: Path) -> subprocess.Popen[bytes]:
    quiet: dict[str, Any] = {"stdin": subprocess.DEVNULL, "stdout": subprocess.DEVNULL,
                             "stderr": open(tmp / "stderr.txt", "wb"),
                             "cwd": tmp, "start_new_session": True}
    if name in ("ours", "ours-profiled"):
        return subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--serve-ours",
                                 pty, str(port), str(tmp),
                                 *(["profile"] if name == "ours-profiled" else [])], **quiet)
    if name == "mavlink-router":
        conf = tmp / "main.conf"
        conf.write_text("[General]\nTcpServerPort = 0\nReportStats = false\n"
                        "DebugLogLevel = error\n\n"
                        f"[UartEndpoint autopilot]\nDevice = {pty}\nBaud = {BAUD}\n\n"
                        f"[UdpEndpoint gcs]\nMode = Normal\nAddress = 127.0.0.1\nPort = {port}\n")
        confd = tmp / "conf.d"
        confd.mkdir()
        return subprocess.Popen([os.environ["MAVLINK_ROUTER"], "-c", str(conf),
                                 "-d", str(confd)], **quiet)
    if name == "mavproxy":
        state = tmp / "mavproxy"
        state.mkdir()
        return subprocess.Popen([sys.executable, str(MAVPROXY), f"--master={pty}",
                                 f"--baudrate={BAUD}", f"--out=udpout:127.0.0.1:{port}",
                                 "--daemon", "--non-interactive", "--no-state",
                                 "--state-basedir", str(state), "--default-modules=",
                                 "--streamrate=-1"], **quiet)
    raise ValueError(name)


def stop_process(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    try:
        os.killpg(proc.pid, signal.SIGKILL)  # anything it left behind (its own group)
    except ProcessLookupError:
        pass


def opened(proc: psutil.Process, path: str, limit_s: float) -> None:
    """Wait until `proc` (or a child) has `path` open (bounded): before that, the pty would
    only buffer what the autopilot writes."""
    end = time.monotonic() + limit_s
    while time.monotonic() < end and proc.is_running():
        for p in [proc, *proc.children(recursive=True)]:
            try:
                fds = Path(f"/proc/{p.pid}/fd").iterdir()
                if any(os.readlink(fd) == path for fd in fds):
                    return
            except OSError:
                continue
        time.sleep(0.05)


def cpu_s(proc: psutil.Process) -> float:
    total = 0.0
    for p in [proc, *proc.children(recursive=True)]:
        try:
            t = p.cpu_times()
            total += t.user + t.system
        except psutil.Error:
            pass
    return total


def thread_cpu_s(pid: int) -> dict[int, float]:
    """CPU seconds of each thread of `pid`, by native thread id (/proc)."""
    out: dict[int, float] = {}
    tick = os.sysconf("SC_CLK_TCK")
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            stat = (task / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        out[int(task.name)] = (int(fields[11]) + int(fields[12])) / tick
    return out


# ---------------------------------------------------------------------------- one router
@dataclass
class Phase:
    name: str
    first: int
    end: int
    t0: float
    t1: float
    cpu_s: float
    threads_s: dict[int, float] = field(default_factory=dict)


def run_router(name: str, frames: list[bytes], rec: Recording, phase_s: float, bursts: int,
               base: Path) -> dict[str, Any]:
    tmp = base / name
    tmp.mkdir()
    port = free_udp_port()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    sock.bind(("127.0.0.1", port))
    ctx = mp.get_context("fork")
    stop, count = ctx.Event(), ctx.RawValue("q", 0)
    got_path = tmp / "received.pickle"
    receiver = ctx.Process(target=receive, args=(sock, stop, count, str(got_path)), daemon=True)
    receiver.start()
    writer = PtyWriter(frames)
    proc = start_router(name, writer.path, port, tmp)
    ps = psutil.Process(proc.pid)
    opened(ps, writer.path, 30.0)
    phases: list[Phase] = []
    error = None

    def threads() -> dict[int, float]:
        return thread_cpu_s(proc.pid) if name.startswith("ours") else {}

    def drained(limit_s: float = 5.0) -> None:
        """Until nothing came for 0.5 s (bounded)."""
        end = time.monotonic() + limit_s
        last = -1
        while time.monotonic() < end and count.value != last:
            last = count.value
            writer.wait(0.5)

    def phase(pname: str, body: Any) -> None:
        first, t0, c0, th0 = len(writer.sent_ns), time.monotonic(), cpu_s(ps), threads()
        body()
        drained()
        th1 = threads()
        phases.append(Phase(pname, first, len(writer.sent_ns), t0, time.monotonic(),
                            cpu_s(ps) - c0, {k: v - th0.get(k, 0.0) for k, v in th1.items()}))

    try:
        flight_rate = rec.total_bytes / (rec.span_ms / 1000.0)
        warm_start = time.monotonic()
        writer.paced(flight_rate, 30.0, until=lambda: count.value >= 50)
        if count.value < 50 or proc.poll() is not None:
            raise RuntimeError(f"{name}: the ground station heard nothing in 30 s "
                               f"(exit {proc.poll()})")
        writer.paced(flight_rate, 1.0)
        drained()
        warm = len(writer.sent_ns)
        warm_s = time.monotonic() - warm_start
        phase("idle", lambda: writer.wait(2.0))
        phase("flight", lambda: writer.paced(flight_rate, phase_s))
        phase("line", lambda: writer.paced(LINE_BYTES_S, phase_s))

        def burst_body() -> None:
            for k in range(bursts):
                writer.burst(BURST_FRAMES)
                if k + 1 < bursts:
                    writer.wait(1.0)

        phase("bursts", burst_body)
        if proc.poll() is not None:
            raise RuntimeError(f"{name} exited during the run ({proc.returncode})")
    except Exception as exc:  # reported in the results, the other routers still run
        error = f"{type(exc).__name__}: {exc}"
        warm = len(writer.sent_ns)
        warm_s = 0.0
    finally:
        names = {}
        if name.startswith("ours") and (tmp / "threads.json").exists():
            names = {int(k): v for k, v in json.loads((tmp / "threads.json").read_text()).items()}
        stop_process(proc)
        stop.set()
        receiver.join(10)
        if receiver.is_alive():
            receiver.kill()
            receiver.join(5)
        drops = udp_drops(port)
        sock.close()
        writer.close()
    got: list[tuple[int, bytes]] = []
    if got_path.exists():
        got = pickle.loads(got_path.read_bytes())
    result: dict[str, Any] = {"router": name, "error": error, "warmup_frames": warm,
                              "warmup_s": round(warm_s, 2), "datagrams": len(got),
                              "receiver_socket_drops": drops,
                              "bytes_router_wrote_to_pty": writer.bytes_back}
    if os.environ.get("ROUTER_BENCH_DUMP"):  # for looking into a router's odd frames
        Path(os.environ["ROUTER_BENCH_DUMP"], f"{name}.pickle").write_bytes(
            pickle.dumps((writer.sent_ns, got, [(p.name, p.first, p.end) for p in phases])))
    result.update(analyse(writer.sent_ns, writer.write_ns, frames, got, phases, names))
    if (tmp / "profile.json").exists():
        result["profile"] = json.loads((tmp / "profile.json").read_text())
    summary = tmp / "summary.json"
    if summary.exists():
        result["ours_counters"] = ours_counters(json.loads(summary.read_text()))
    err = (tmp / "stderr.txt").read_bytes().decode(errors="replace").strip()
    if err:
        result["stderr_tail"] = err[-600:]
    return result


def ours_counters(summary: dict[str, Any]) -> dict[str, Any]:
    """What our runtime counted: each thread's counters, each link's figures."""
    out: dict[str, Any] = {t["name"]: {k: v for k, v in t["counters"].items()
                                       if isinstance(v, int)}
                           for t in summary.get("threads", []) if t.get("counters")}
    out["links"] = [{k: v for k, v in m.items() if isinstance(v, int)}
                    for m in summary.get("messages", [])]
    return out


def analyse(sent_ns: list[int], write_ns: list[int], frames: list[bytes], got: list[tuple[int, bytes]],
            phases: list[Phase], names: dict[int, str]) -> dict[str, Any]:
    first_rx: dict[int, int] = {}
    dup = other = mismatch = 0
    examples: list[str] = []
    n_sent = len(sent_ns)
    for t, data in got:
        for fr in split_v2(data):
            if (fr[5], fr[6]) != (1, 1):
                other += 1  # the router's own frames (ours: the companion's heartbeat)
                continue
            hi = bisect.bisect_right(sent_ns, t) - 1
            idx = hi - ((hi - frame_number(fr)) % 65536)
            if idx < 0 or idx >= n_sent or fr != frames[idx]:
                mismatch += 1
                if len(examples) < 3:
                    examples.append(f"got {fr.hex()} for frame {idx}: "
                                    f"{frames[idx].hex() if 0 <= idx < n_sent else '-'}")
                continue
            if idx in first_rx:
                dup += 1
            else:
                first_rx[idx] = t
    out: dict[str, Any] = {"frames_not_from_the_autopilot": other,
                           "frames_unmatched": mismatch,
                           "unmatched_examples": examples, "duplicates": dup, "phases": {}}
    for ph in phases:
        lat = sorted((first_rx[i] - sent_ns[i]) / 1e3 for i in range(ph.first, ph.end)
                     if i in first_rx)
        sent = ph.end - ph.first
        span = ph.t1 - ph.t0
        rec: dict[str, Any] = {"frames_sent": sent, "frames_received": len(lat),
                               "lost": sent - len(lat), "wall_s": round(span, 3),
                               "cpu_s": round(ph.cpu_s, 4),
                               "cpu_pct_of_one_core": round(100 * ph.cpu_s / span, 2)}
        if sent:
            bytes_sent = sum(len(frames[i]) for i in range(ph.first, ph.end))
            rec["bytes_sent"] = bytes_sent
            # bursts: the rate within each burst (the pty took them as fast as the router
            # read), the median of the bursts; else over the phase
            chunk = BURST_FRAMES if ph.name == "bursts" else sent
            rates = []
            for a in range(ph.first, ph.end - 1, chunk):
                b = min(a + chunk, ph.end) - 1
                if b > a and sent_ns[b] > sent_ns[a]:
                    rates.append((b - a) / ((sent_ns[b] - sent_ns[a]) / 1e9))
            rec["write_rate_frames_s"] = round(statistics.median(rates), 1) if rates else None
            rec["loss_pct"] = round(100 * (sent - len(lat)) / sent, 3)
            calls = sorted(write_ns[ph.first:ph.end])
            rec["write_call_us"] = {"p50": round(calls[len(calls) // 2] / 1e3, 1),
                                    "p99": round(calls[int(0.99 * (len(calls) - 1))] / 1e3, 1),
                                    "max": round(calls[-1] / 1e3, 1)}
        if lat:
            rec["cpu_ms_per_1000"] = round(1e6 * ph.cpu_s / len(lat), 2)
            rec["latency_us"] = {"p50": round(statistics.median(lat), 1),
                                 "p99": round(lat[min(len(lat) - 1, int(0.99 * len(lat)))], 1),
                                 "max": round(lat[-1], 1), "mean": round(statistics.fmean(lat), 1)}
        if ph.threads_s:
            by_name: dict[str, float] = {}
            for tid, s in ph.threads_s.items():
                key = names.get(tid, "other")
                by_name[key] = by_name.get(key, 0.0) + s
            rec["threads_cpu_s"] = {k: round(v, 3) for k, v in sorted(
                by_name.items(), key=lambda kv: -kv[1]) if v > 0}
        out["phases"][ph.name] = rec
    return out


# ---------------------------------------------------------------------------- our driver
def serve_ours(pty: str, port: int, tmp: Path, profile: bool = False) -> int:
    """The bench's own driver of our runtime as a router: `companion run --autopilot PTY
    --mavlink udpout:127.0.0.1:PORT --no-legacy`, without the estimator and the control law
    (no command-line switch for those). Writes the summary and a thread-id -> name map."""
    from companion.core.config import Config
    from companion.runtime import Runtime, RuntimeOptions
    from companion.vehicle import VEHICLE, apply_device_ports, fill_device_defaults

    cfg = fill_device_defaults(Config(), VEHICLE)
    cfg.logs.dir = str(tmp / "flights")
    cfg.params.file = str(tmp / "params.parm")
    cfg.mavlink.endpoints = [f"udpout:127.0.0.1:{port}"]
    cfg.legacy.enabled = False
    apply_device_ports(cfg, {"autopilot": f"{pty},{BAUD}"})
    rt = Runtime(cfg, RuntimeOptions(legacy=False, estimator=False, control=False))
    done = threading.Event()

    def name_threads() -> None:  # Python does not name the OS threads: the bench reads this
        while not done.wait(0.5):
            names = {t.native_id: t.name for t in threading.enumerate()
                     if t.native_id is not None}
            (tmp / "threads.json.new").write_text(json.dumps(names))
            os.replace(tmp / "threads.json.new", tmp / "threads.json")

    threading.Thread(target=name_threads, name="bench-names", daemon=True).start()
    profiles: list[tuple[str, Any]] = []
    if profile:  # one cProfile per thread started from here on (the runtime's threads)
        import cProfile

        def per_thread(*_args: Any) -> None:
            prof = cProfile.Profile(time.thread_time)  # this thread's CPU, not waits
            profiles.append((threading.current_thread().name, prof))
            prof.enable()  # replaces this hook in this thread

        threading.setprofile(per_thread)
    rt.run()
    done.set()
    if profile:
        write_profile(profiles, tmp / "profile.json")
    (tmp / "summary.json").write_text(json.dumps(rt.summary(), default=str))
    return 0


def write_profile(profiles: list[tuple[str, Any]], path: Path) -> None:
    """Each thread's total, its 12 most costly functions (own CPU time) and its 15 most
    costly calls (with what they call), as JSON."""
    import pstats

    out = {}
    for name, prof in profiles:
        st = pstats.Stats(prof)
        rows = sorted(st.stats.items(), key=lambda kv: -kv[1][2])  # type: ignore[attr-defined]
        total = sum(v[2] for _k, v in rows)
        if total < 0.02:
            continue
        out[name] = {"own_s_total": round(total, 3), "top": [
            {"function": f"{Path(k[0]).name}:{k[1]}:{k[2]}", "calls": v[1],
             "own_s": round(v[2], 3), "cumulative_s": round(v[3], 3)} for k, v in rows[:12]],
            "top_cumulative": [
                {"function": f"{Path(k[0]).name}:{k[1]}:{k[2]}", "cumulative_s": round(v[3], 3)}
                for k, v in sorted(st.stats.items(),  # type: ignore[attr-defined]
                                   key=lambda kv: -kv[1][3])[:15]]}
    path.write_text(json.dumps(out, indent=1))


# ---------------------------------------------------------------------------- the report
def ratio(a: float | None, b: float | None) -> float | None:
    return round(a / b, 2) if a is not None and b else None


def report(results: dict[str, Any]) -> str:
    rows = results["routers"]
    lines = ["| router | phase | frames/s written | sent | lost | p50 us | p99 us | max us | "
             "CPU % of a core | CPU ms / 1000 |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r.get("error"):
            lines.append(f"| {r['router']} | failed: {r['error']} | | | | | | | | |")
        for pname, p in r.get("phases", {}).items():
            lat = p.get("latency_us", {})
            lines.append(
                f"| {r['router']} | {pname} | {p.get('write_rate_frames_s') or '-'} | "
                f"{p['frames_sent']} | {p['lost']} | {lat.get('p50', '-')} | "
                f"{lat.get('p99', '-')} | {lat.get('max', '-')} | {p['cpu_pct_of_one_core']} | "
                f"{p.get('cpu_ms_per_1000', '-')} |")
    lines.append("")
    for key, label in (("ours/mavlink-router", "ours / mavlink-router"),
                       ("ours/mavproxy", "ours / MAVProxy")):
        rat = results["ratios"].get(key)
        if not rat:
            continue
        lines.append(f"{label}: " + "; ".join(
            f"{pname} CPU {v['cpu_per_1000']}x, p50 {v['p50']}x, p99 {v['p99']}x"
            for pname, v in rat.items()))
    return "\n".join(lines)


def main() -> int:
    if len(sys.argv) in (5, 6) and sys.argv[1] == "--serve-ours":
        return serve_ours(sys.argv[2], int(sys.argv[3]), Path(sys.argv[4]),
                          profile=sys.argv[5:] == ["profile"])
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 s phases, one burst")
    ap.add_argument("--phase-s", type=float, default=None, help="flight and line phase length")
    ap.add_argument("--bursts", type=int, default=None)
    ap.add_argument("--routers", nargs="+", choices=ROUTERS, default=list(ROUTERS))
    ap.add_argument("--json", type=Path, help="write every figure here")
    ap.add_argument("--profile-ours", action="store_true",
                    help="then ours once more under cProfile: where its CPU goes")
    args = ap.parse_args()
    phase_s = args.phase_s or (3.0 if args.quick else 20.0)
    bursts = args.bursts or (1 if args.quick else 5)
    routers = list(args.routers) + (["ours-profiled"] if args.profile_ours else [])
    notes = []
    if "mavlink-router" in routers and not (
            os.environ.get("MAVLINK_ROUTER") and Path(os.environ["MAVLINK_ROUTER"]).is_file()):
        notes.append("mavlink-router left out: MAVLINK_ROUTER does not name its binary")
        routers.remove("mavlink-router")
    if "mavproxy" in routers and not MAVPROXY.is_file():
        notes.append(f"MAVProxy left out: no {MAVPROXY.name} beside {sys.executable}")
        routers.remove("mavproxy")
    for n in notes:
        print(n, file=sys.stderr)
    res = Result("router", ["companion", "gcs_bridge"], quick=args.quick)
    rec = load_recording()
    flight_rate = rec.total_bytes / (rec.span_ms / 1000.0)
    # enough frames for a warm-up of up to 31 s, both phases and the bursts
    n_frames = int((31 + phase_s) * flight_rate / 30 + phase_s * LINE_BYTES_S / 30
                   + bursts * BURST_FRAMES + 5000)
    frames = [make_frame(rec, i) for i in range(n_frames)]
    load0 = os.getloadavg()
    started = res.started.strftime("%Y-%m-%dT%H:%M:%SZ")
    out: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="router-bench-") as tmp:
        for name in routers:
            print(f"{name}...", file=sys.stderr, flush=True)
            out.append(run_router(name, frames, rec, phase_s, bursts, Path(tmp)))
    load1 = os.getloadavg()
    by = {r["router"]: r for r in out}
    ratios: dict[str, Any] = {}
    for peer in ("mavlink-router", "mavproxy"):
        if "ours" in by and peer in by:
            ratios[f"ours/{peer}"] = {
                pname: {"cpu_per_1000": ratio(p.get("cpu_ms_per_1000"),
                                              by[peer]["phases"].get(pname, {})
                                              .get("cpu_ms_per_1000")),
                        "p50": ratio(p.get("latency_us", {}).get("p50"),
                                     by[peer]["phases"].get(pname, {}).get("latency_us", {})
                                     .get("p50")),
                        "p99": ratio(p.get("latency_us", {}).get("p99"),
                                     by[peer]["phases"].get(pname, {}).get("latency_us", {})
                                     .get("p99"))}
                for pname, p in by["ours"].get("phases", {}).items() if pname != "idle"}
    results = {
        "command": "python bench/router_bench.py " + " ".join(sys.argv[1:]),
        "commit": res.commit, "date": started, "machine": machine(),
        "load_average_before": [round(x, 2) for x in load0],
        "load_average_after": [round(x, 2) for x in load1],
        "recording": {"file": str(RECORDING.relative_to(ROOT)), "frames": len(rec.frames),
                      "bytes": rec.total_bytes, "span_ms": rec.span_ms,
                      "flight_rate_bytes_s": round(flight_rate, 1)},
        "line_rate_bytes_s": LINE_BYTES_S, "phase_s": phase_s, "bursts": bursts,
        "burst_frames": BURST_FRAMES, "notes": notes, "routers": out, "ratios": ratios,
    }
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    print(f"## Routing beside an autopilot, {started}, {os.cpu_count()} cores, load "
          f"{load0[0]:.2f} before, {load1[0]:.2f} after\n")
    with res.capture():
        print(report(results))
    ok = all(r.get("error") is None for r in out)
    if ok:
        res.data = {k: v for k, v in results.items() if k not in ("command", "commit", "date")}
        res.write()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
