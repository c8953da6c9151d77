"""Fault campaign: SITL flights, one fault each, and what the runtime did about it.

Run: `python bench/faults_bench.py [--quick]` (`make bench-faults`).

Every row is a `companion sim --fast` flight (5x real time, the `mixed` scenario) with one fault
from the devices, the network or the process, injected while the aircraft flies, and the same
figures: IMU and GPS rates held (in the flight's clock), restarts (none is intended in any row),
the events the supervisor reported, detection and recovery times where a device went quiet,
what a well-behaved ground station could still do, the runtime's peak memory, and for a kill,
which records survived. The baseline row is the same flight with nothing injected.

All of it runs on this machine, on loopback, against the project's own simulator: the figures
say what this runtime survives under these injected faults, not how a real device misbehaves.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import psutil
from pymavlink import mavutil

sys.path.insert(0, str(Path(__file__).resolve().parent))
from mavflood import flood  # noqa: E402
from mavlink_bench import free_port  # noqa: E402

from companion.drivers.imu import FMT_FAST  # noqa: E402
from companion.drivers.imu_protocol import CYCLE_FRAMES  # noqa: E402
from companion.logs import read_log  # noqa: E402
from legacy_protocol.codec import Decoded, decode  # noqa: E402
from legacy_protocol.messages import Imu  # noqa: E402

SCALE = 5.0  # --fast
GPS_HZ = 10.0


@dataclass
class Flight:
    """One `companion sim --fast` flight in a subprocess, with its ports and directories."""

    duration_s: float
    extra: list[str] = field(default_factory=list)
    root: Path = field(default_factory=lambda: Path(tempfile.mkdtemp(prefix="faults-")))
    mav_port: int = field(default_factory=free_port)
    legacy_port: int = field(default_factory=free_port)
    proc: subprocess.Popen[str] | None = None
    rss_mb: list[float] = field(default_factory=list)
    t_start: float = 0.0
    speed: float = SCALE
    key: bytes | None = None  # the MAVLink signing key, when the flight's link requires one

    def start(self) -> None:
        cmd = [sys.executable, "-m", "companion", "sim", "--speed", str(self.speed), "--duration",
               str(self.duration_s), "--mavlink", f"udpin:127.0.0.1:{self.mav_port}",
               "--legacy-listen", str(self.legacy_port), "--legacy-allow", "127.0.0.1/32",
               "--log-dir", str(self.root / "logs"), "--params-file",
               str(self.root / "params.parm"), "--json", *self.extra]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True)
        self.t_start = time.monotonic()

    def sample_rss(self) -> None:
        if self.proc is not None:
            try:
                self.rss_mb.append(psutil.Process(self.proc.pid).memory_info().rss / 1e6)
            except psutil.Error:
                pass

    def wait_ready(self, timeout_s: float = 60.0) -> bool:
        """Until the runtime answers a parameter read on its MAVLink port."""
        return param_read_s(self.mav_port, timeout_s, key=self.key) is not None

    def finish(self, timeout_s: float) -> tuple[dict[str, Any] | None, int]:
        assert self.proc is not None
        try:
            out, err = self.proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, err = self.proc.communicate()
        code = self.proc.returncode
        try:
            summary = json.loads(out[out.index("{"):])
        except ValueError:
            summary = None
            sys.stderr.write(err[-2000:])
        return summary, code

    def flight_dir(self) -> Path | None:
        dirs = sorted((self.root / "logs").glob("*/"))
        return dirs[-1] if dirs else None


def param_read_s(port: int, timeout_s: float, key: bytes | None = None) -> float | None:
    """Host seconds until a well-behaved ground station's PARAM_REQUEST_READ is answered
    (signed with `key` when given)."""
    conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=245)
    if key is not None:
        conn.setup_signing(key, sign_outgoing=True, link_id=1)
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < timeout_s:
            conn.mav.param_request_read_send(1, 1, b"IMU_WDG_MS", -1)
            if conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.3) is not None:
                return time.monotonic() - t0
        return None
    finally:
        conn.close()


def param_list_s(port: int, timeout_s: float) -> tuple[float | None, int, int]:
    """Host seconds to receive the whole parameter list (and how many of how many came)."""
    conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=244)
    t0 = time.monotonic()
    seen: set[int] = set()
    total = 0
    try:
        conn.mav.param_request_list_send(1, 1)
        while time.monotonic() - t0 < timeout_s:
            m = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.5)
            if m is None:
                conn.mav.param_request_list_send(1, 1)
                continue
            total = m.param_count
            seen.add(m.param_index)
            if total and len(seen) >= total:
                return time.monotonic() - t0, len(seen), total
        return None, len(seen), total
    finally:
        conn.close()


# ---------------------------------------------------------------------------------- analysis
def thread_of(summary: dict[str, Any], name: str) -> dict[str, Any]:
    return next((t for t in summary["threads"] if t["name"] == name), {})


def gap_figures(flight_dir: Path, summary: dict[str, Any], device: str) -> tuple[str, str]:
    """Detection (last sample -> SILENT event) and recovery (first sample again -> RECOVERED
    event), in the flight's clock, from the device's log and the supervisor's events."""
    log = read_log(flight_dir / f"{device}.bin", salvage=True)
    t = log.time_ns(1) / 1e9
    if len(t) < 2:
        return "-", "-"
    k = int(np.argmax(np.diff(t)))
    last, first = t[k], t[k + 1]
    events = [e for e in summary["events"] if e["thread"] == device]
    silent = next((e["t_s"] for e in events if e["kind"] == "silent" and e["t_s"] >= last), None)
    back = next((e["t_s"] for e in events if e["kind"] == "recovered" and e["t_s"] >= first), None)
    det = f"{(silent - last) * 1000:.0f} ms" if silent is not None else "not reported"
    rec = f"{(back - first) * 1000:.0f} ms" if back is not None else "not reported"
    return det, rec


@dataclass
class Row:
    name: str
    fault: str
    figures: dict[str, str]


def common(summary: dict[str, Any] | None, flight: Flight, code: int) -> dict[str, str]:
    if summary is None:
        return {"exit": str(code), "IMU Hz": "-", "GPS Hz": "-", "restarts": "-",
                "events": "no summary", "peak RSS": "-"}
    restarts = {t["name"]: t["restarts"] for t in summary["threads"] if t["restarts"]}
    kinds: dict[str, int] = {}
    for e in summary["events"]:
        if e["kind"] not in ("started", "stopped"):
            key = f"{e['thread']} {e['kind']}"
            kinds[key] = kinds.get(key, 0) + 1
    return {
        "exit": str(code),
        "IMU Hz": f"{thread_of(summary, 'imu').get('rate_hz', 0):.2f}",
        "GPS Hz": f"{thread_of(summary, 'gps').get('rate_hz', 0):.2f}",
        "restarts": ", ".join(f"{k} {v}" for k, v in restarts.items()) or "0",
        "events": "; ".join(f"{k} x{v}" for k, v in kinds.items()) or "none",
        "peak RSS": f"{max(flight.rss_mb):.0f} MB" if flight.rss_mb else "-",
    }


def fly(duration_s: float, extra: list[str] | None = None,
        during: Callable[[Flight], dict[str, str]] | None = None,
        finish_timeout_s: float | None = None, speed: float = SCALE, key: bytes | None = None,
        ) -> tuple[Flight, dict[str, Any] | None, int, dict[str, str]]:
    flight = Flight(duration_s, list(extra or []), speed=speed, key=key)
    flight.start()
    found: dict[str, str] = {}
    if not flight.wait_ready():
        found["ready"] = "runtime never answered"
    flight.sample_rss()
    if during is not None and not found:
        found.update(during(flight))
    assert flight.proc is not None
    deadline = time.monotonic() + (finish_timeout_s or duration_s / speed + 60)
    while flight.proc.poll() is None and time.monotonic() < deadline:
        flight.sample_rss()
        time.sleep(0.5)
    summary, code = flight.finish(5.0)
    return flight, summary, code, found


# ---------------------------------------------------------------------------------- the rows
def row_baseline(d: float) -> Row:
    f, s, code, _ = fly(d)
    return Row("baseline", "nothing injected", common(s, f, code))


def row_device(d: float, dev: str, spec: str, label: str, gap: bool = False) -> Row:
    f, s, code, _ = fly(d, ["--fault", f"{dev}:{spec}"])
    figs = common(s, f, code)
    if s is not None:
        counters = thread_of(s, dev).get("counters", {})
        figs["driver counters"] = ", ".join(
            f"{k} {v}" for k, v in counters.items()
            if v and k in ("bad_checksum", "bad_field", "resyncs", "bytes_discarded", "cut",
                           "malformed", "frames_good", "sentences_good", "epochs", "repeated",
                           "utc_jumps", "late_epochs", "missed_answers"))
        injected = s.get("simulator", {}).get("faults", {}).get(dev, {})
        figs["injected"] = ", ".join(f"{k} {v}" for k, v in injected.items()
                                     if v and k != "chunks") or "-"
        reports = [f"{e['kind']}: {e['detail']}" for e in s["events"]
                   if e["thread"] == dev and e["kind"] in ("silent", "notice")]
        figs["reported"] = "; ".join(dict.fromkeys(reports)) or "nothing"
        fd = f.flight_dir()
        if gap and fd is not None:
            figs["detected after"], figs["recovered after"] = gap_figures(fd, s, dev)
    return Row(f"{dev} {label}", f"--fault {dev}:{spec}", figs)


def row_vanish(d: float, dev: str, start: float, dur: float, renamed: bool = False) -> Row:
    spec = f"{dev}:{start}:{dur}" + (":renamed" if renamed else "")
    f, s, code, _ = fly(d, ["--vanish", spec])
    figs = common(s, f, code)
    if s is not None:
        c = thread_of(s, dev).get("counters", {})
        figs["driver counters"] = f"reconnects {c.get('reconnects', 0)}"
        fd = f.flight_dir()
        if fd is not None:
            figs["detected after"], figs["recovered after"] = gap_figures(fd, s, dev)
    what = ", returns under another kernel name" if renamed else ""
    return Row(f"{dev} port vanishes {dur:g} s{what}", f"--vanish {spec}", figs)


def row_clock_step(d: float) -> Row:
    """The wall clock stepped an hour forward, then two back, in real time (scale 1, where the
    runtime's timestamps once followed the wall clock): the logs' time must not jump."""
    def during(f: Flight) -> dict[str, str]:
        out = {}
        for at in (d / 3 + 2, 2 * d / 3 + 2):
            while time.monotonic() - f.t_start < at + 3 and f.proc and f.proc.poll() is None:
                time.sleep(0.2)
            t = param_read_s(f.mav_port, 5.0)
            out[f"GCS at {at:.0f} s"] = f"answered in {t:.2f} s" if t else "no answer"
        return out

    steps = [f"{d / 3:g}:3600", f"{2 * d / 3:g}:-7200"]
    f, s, code, found = fly(d, [a for st in steps for a in ("--clock-step", st)], during,
                            speed=1.0)
    figs = common(s, f, code)
    figs.update(found)
    fd = f.flight_dir()
    if fd is not None:
        worst = []
        for p in sorted(fd.glob("*.bin")):
            log = read_log(p, salvage=True)
            for idx in log.indexes:
                t = log.time_ns(idx)
                if len(t) > 1:
                    worst.append((float(np.diff(t).min()) / 1e6, float(np.diff(t).max()) / 1e6,
                                  f"{p.stem}/{idx}"))
        if worst:
            small = min(worst)
            figs["log time steps, smallest"] = f"{small[0]:.3f} ms ({small[2]})"
            big = max(worst, key=lambda w: w[1])
            figs["log time steps, largest"] = f"{big[1]:.0f} ms ({big[2]})"
    return Row("wall clock stepped +1 h, then -2 h", " ".join(f"--clock-step {x}" for x in steps)
               + " (real time)", figs)


def row_thread(d: float, thread: str, kind: str, at_s: float, label: str) -> Row:
    f, s, code, _ = fly(d, ["--thread-fault", f"{thread}:{kind}:{at_s:g}"])
    figs = common(s, f, code)
    if s is not None:
        t = thread_of(s, thread)
        figs[thread] = (f"crashes {t.get('crashes')}, interrupted {t.get('interrupted')}, "
                        f"abandoned {t.get('abandoned')}, failed {t.get('failed')}, "
                        f"rate {t.get('rate_hz')} Hz at the end")
        armed = s.get("thread_faults", [])
        ev = [e for e in s["events"] if e["thread"] == thread and e["kind"] in
              ("crash", "stall", "restarted", "failed")]
        if armed and ev:
            t0 = armed[0]["t_ns"] / 1e9
            first = next((e for e in ev if e["kind"] in ("crash", "stall")), None)
            last = ev[-1]
            if first is not None:
                figs["detected after"] = f"{(first['t_s'] - t0) * 1000:.0f} ms ({first['kind']})"
            figs[f"{last['kind']} after"] = f"{(last['t_s'] - t0) * 1000:.0f} ms"
        if f.rss_mb:
            figs["RSS first / peak"] = f"{f.rss_mb[0]:.0f} / {max(f.rss_mb):.0f} MB"
    return Row(f"{thread}: {label}", f"--thread-fault {thread}:{kind}:{at_s:g}", figs)


def row_mavlink_flood(d: float, flood_s: float, rate: float) -> Row:
    def during(f: Flight) -> dict[str, str]:
        out: dict[str, str] = {}
        t0 = time.monotonic()
        sent = flood("127.0.0.1", f.mav_port, flood_s, seed=7, rate_per_s=rate)
        out["flood"] = f"{sum(sent.values())} datagrams in {time.monotonic() - t0:.1f} s"
        f.sample_rss()
        t_list, got, total = param_list_s(f.mav_port, 10.0)
        out["GCS after"] = (f"{got}/{total} parameters in {t_list:.2f} s" if t_list is not None
                            else f"DEAF: {got}/{total} parameters in 10 s")
        return out

    f, s, code, found = fly(d, [], during)
    figs = common(s, f, code)
    figs.update(found)
    if s is not None and s.get("messages"):
        m = s["messages"][0]
        figs["link"] = (f"rx_frames {m['rx_frames']}, parse_errors {m['parse_errors']}, "
                        f"refused {m['refused']}, bytes_in {m['transport']['bytes_in']}")
    return Row("MAVLink flood (udpin)", f"bench/mavflood.py, {rate:g} datagrams/s", figs)


def row_signed_flood(d: float, flood_s: float, rate: float) -> Row:
    """A link that requires signing, flooded with signed-looking garbage (valid CRCs, random
    signatures, link ids and timestamps): refused and counted, the signed GCS still served."""
    from signed_flood import signed_garbage_flood

    from gcs_bridge.signing import key_from_text, new_key_file

    key_path = Path(tempfile.mkdtemp(prefix="faults-key-")) / "mavlink.key"
    key = key_from_text(new_key_file(key_path))

    def during(f: Flight) -> dict[str, str]:
        t0 = time.monotonic()
        sent = signed_garbage_flood("127.0.0.1", f.mav_port, flood_s, seed=5, rate_per_s=rate)
        out = {"flood": f"{sum(v for k, v in sent.items() if k != 'send_failed')} frames in "
                        f"{time.monotonic() - t0:.1f} s"}
        t = param_read_s(f.mav_port, 10.0, key=key)
        out["signed GCS after"] = f"answered in {t:.3f} s" if t is not None else "no answer"
        return out

    f, s, code, found = fly(d, ["--set", f"mavlink.key_file={key_path}"], during, key=key)
    figs = common(s, f, code)
    figs.update(found)
    if s is not None and s.get("messages"):
        m = s["messages"][0]
        figs["link"] = (f"rx_frames {m['rx_frames']}, refused {m['refused']}, "
                        f"refusals {m.get('refusals', {})}")
    return Row("signed link: flood of signed-looking garbage", f"bench/signed_flood.py, "
               f"{rate:g} frames/s for {flood_s:g} s", figs)


def row_transfer_flood(d: float, flood_s: float) -> Row:
    """LOG and FTP requests for huge ranges from several fake ground stations, then a ground
    station that vanishes mid-download while another downloads after it."""
    from transfer_flood import transfer_flood, vanishing_download

    def during(f: Flight) -> dict[str, str]:
        sent = transfer_flood("127.0.0.1", f.mav_port, flood_s, seed=3)
        out = {"requests": f"{sum(sent.values())} of {len(sent)} kinds"}
        f.sample_rss()
        t = param_read_s(f.mav_port, 5.0)
        out["GCS after"] = f"answered in {t:.3f} s" if t is not None else "no answer"
        out.update({f"vanishing GCS: {k}": v for k, v in
                    vanishing_download("127.0.0.1", f.mav_port, 20.0).items()})
        return out

    f, s, code, found = fly(d, [], during)
    figs = common(s, f, code)
    figs.update(found)
    return Row("LOG and FTP request floods, a GCS vanishing mid-transfer",
               f"bench/transfer_flood.py for {flood_s:g} s", figs)


def row_legacy_flood(d: float, flood_s: float, rate: float) -> Row:
    def during(f: Flight) -> dict[str, str]:
        rng = np.random.default_rng(3)
        n = [0]

        def datagram() -> bytes:
            payload = rng.integers(0, 256, int(rng.integers(1, 1400)), dtype=np.uint8).tobytes()
            n[0] += 1
            # every third one starts like a command, so the parser goes past the first byte
            return bytes([0x81, 0x00]) + payload if n[0] % 3 == 1 else payload

        sent = flood("127.0.0.1", f.legacy_port, flood_s, rate_per_s=rate, datagram=datagram)
        t = param_read_s(f.mav_port, 5.0)
        return {"flood": f"{sent['datagram']} datagrams",
                "GCS after": f"answered in {t:.2f} s" if t else "no answer"}

    f, s, code, found = fly(d, [], during)
    figs = common(s, f, code)
    figs.update(found)
    return Row("legacy UDP flood (allowed source)", f"random datagrams, {rate:g}/s", figs)


def row_disk_full(d: float, size_kb: int) -> Row:
    """The flight's log directory on a size-limited tmpfs (needs root to mount it; without root
    the row says so instead of pretending)."""
    mnt = Path(tempfile.mkdtemp(prefix="faults-disk-"))
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kb}k", "tmpfs",
                              str(mnt)], capture_output=True, text=True)
    if mounted.returncode != 0:
        return Row("disk full while logging", f"tmpfs of {size_kb} kB",
                   {"skipped": "cannot mount a tmpfs here (needs root): "
                               + mounted.stderr.strip()[:80]})
    try:
        flight, s, code, found = fly(d, ["--log-dir", str(mnt)])  # the last --log-dir wins
        figs = common(s, flight, code)
        figs.update(found)
        if s is not None:
            figs["records dropped (logging off)"] = ", ".join(
                f"{t['name']} {t['log_dropped']}" for t in s["threads"] if t["log_dropped"])
            figs["summary.json"] = ("written" if any(p.name == "summary.json"
                                                     for p in mnt.glob("*/summary.json"))
                                    else "not written (disk full); printed with --json")
        return Row("disk full while logging", f"--log-dir on a tmpfs of {size_kb} kB", figs)
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


def row_sigstop(d: float, stop_s: float) -> Row:
    def during(f: Flight) -> dict[str, str]:
        assert f.proc is not None
        time.sleep(2.0)
        os.kill(f.proc.pid, signal.SIGSTOP)
        time.sleep(stop_s)
        os.kill(f.proc.pid, signal.SIGCONT)
        t = param_read_s(f.mav_port, 10.0)
        return {"GCS after": f"answered in {t:.2f} s" if t else "no answer"}

    f, s, code, found = fly(d, [], during)
    figs = common(s, f, code)
    figs.update(found)
    return Row(f"SIGSTOP {stop_s:g} s, SIGCONT", "the runtime's process", figs)


def row_sigterm(d: float) -> Row:
    stop_t: list[float] = []

    def during(f: Flight) -> dict[str, str]:
        assert f.proc is not None
        time.sleep(2.0)
        stop_t.append(time.monotonic())
        f.proc.send_signal(signal.SIGTERM)
        f.proc.wait(30)
        return {"exit after": f"{time.monotonic() - stop_t[0]:.2f} s"}

    f, s, code, found = fly(d, [], during)
    figs = common(s, f, code)
    figs.update(found)
    fd = f.flight_dir()
    if fd is not None:
        closed = [p.name for p in sorted(fd.glob("*.bin"))
                  if read_log(p, salvage=True).closed_cleanly]
        figs["logs closed cleanly"] = f"{len(closed)}/{len(list(fd.glob('*.bin')))}"
    return Row("SIGTERM", "stop mid-flight", figs)


KILL_SETTLE_S = 0.5
"""Host seconds between the last IMU count the bench heard and the SIGKILL: five of the log
writer's 100 ms flush periods, so every record counted had been handed to the kernel."""


def imu_samples_reported(sock: socket.socket, listen_s: float) -> int | None:
    """The IMU thread's sample count in the last legacy IMU message heard on `sock` within
    `listen_s` host seconds (None: none heard).

    The driver publishes each IMU sample as one fast record (`FMT_FAST`) handed to imu.bin's
    writer, then counts it as a cycle; the legacy IMU message carries that count. Heard from
    outside while the process runs, it survives the kill, unlike anything the runtime keeps."""
    count = None
    deadline = time.monotonic() + listen_s
    while (left := deadline - time.monotonic()) > 0:
        if not select.select([sock], [], [], left)[0]:
            break
        decoded = decode(sock.recv(65536))
        if isinstance(decoded, Decoded) and isinstance(decoded.payload, Imu):
            count = decoded.payload.frame_count
    return count


def row_sigkill(d: float) -> Row:
    """SIGKILL mid-flight: of the IMU records the writer had accepted `KILL_SETTLE_S` before
    the kill (counted from outside, `imu_samples_reported`), how many read back. The count
    comes from the runtime, not from the file: loss at the file's tail shows as missing."""
    reported: list[int] = []
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))

    def during(f: Flight) -> dict[str, str]:
        assert f.proc is not None
        time.sleep(3.0)
        count = imu_samples_reported(sock, 1.0)  # the IMU message comes every 200 ms at 5x
        if count is not None:
            reported.append(count)
        time.sleep(KILL_SETTLE_S)
        f.proc.kill()
        f.proc.wait(10)
        return {}

    try:
        f, s, code, found = fly(d, ["--legacy-dest", f"127.0.0.1:{sock.getsockname()[1]}"],
                                during)
    finally:
        sock.close()
    figs = common(s, f, code)
    figs.update(found)
    fd = f.flight_dir()
    if fd is not None and (fd / "imu.bin").exists():
        log = read_log(fd / "imu.bin", salvage=True)
        counter = log.data(FMT_FAST)["counter"].astype(np.int64)
        # the device's sample counter (0..CYCLE_FRAMES-1): a record missing between two read back
        gaps = int(np.sum((np.diff(counter) - 1) % CYCLE_FRAMES)) if len(counter) > 1 else 0
        if reported:
            accepted = reported[-1]
            lost = max(0, accepted - len(counter))
            figs[f"IMU records accepted {KILL_SETTLE_S:g} s before the kill"] = (
                f"{accepted} (the IMU thread's count, heard on the legacy link)")
            figs["of those, read back"] = (
                f"{accepted - lost} of {accepted} ({lost} lost at the tail); "
                f"{len(counter) - accepted + lost} later ones too")
        else:
            figs["IMU records accepted before the kill"] = "no IMU message heard"
        figs["gaps in the device counter"] = f"{gaps} samples"
        figs["damage"] = f"{log.skipped_bytes} bytes skipped"
    return Row("SIGKILL", f"{KILL_SETTLE_S:g} s after the IMU count was heard, about 4 s "
               "after the runtime answered", figs)


def row_nominal_starts(n: int, duration_s: float, parallel: int = 2) -> Row:
    """`n` nominal flights, `parallel` at a time on this 2-core machine (so each start meets a
    loaded machine): how many restarted anything. The start-up restart the issue measured (one
    flight in five restarted the estimator about 1 s in) is what this row would catch."""
    restarted: list[str] = []
    done = 0
    t0 = time.monotonic()
    while done < n:
        batch = [Flight(duration_s) for _ in range(min(parallel, n - done))]
        for f in batch:
            f.start()
        for f in batch:
            s, code = f.finish(duration_s / SCALE + 90)
            done += 1
            if s is None or code != 0:
                restarted.append(f"exit {code}")
                continue
            r = {t["name"]: t["restarts"] for t in s["threads"] if t["restarts"]}
            if r:
                restarted.append(", ".join(f"{k} {v}" for k, v in r.items()))
    return Row(f"{n} nominal starts, {parallel} flights at a time",
               f"nothing injected, {duration_s:g} s each",
               {"flights with a restart": f"{len(restarted)} of {n}",
                "which": "; ".join(restarted) or "none",
                "wall time": f"{time.monotonic() - t0:.0f} s"})


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="shorter flights, fewer rows")
    args = ap.parse_args()
    d = 30.0 if args.quick else 60.0
    rows: list[Row] = [row_baseline(d)]
    rows.append(row_device(d, "imu", "silence=20-23", "silent 3 s", gap=True))
    rows.append(row_device(d, "imu", "garbage=0.02,cut=0.02,badsum=0.02", "garbage, cut frames, "
                           "bad checksums (2 % each)"))
    if not args.quick:
        rows.append(row_device(d, "gps", "garbage=0.05,cut=0.05,badsum=0.05", "garbage, cut "
                               "sentences, bad checksums (5 % each)"))
        rows.append(row_device(d, "servo", "badsum=0.05,cut=0.05", "cut frames, bad checksums "
                               "(5 % each)"))
        rows.append(row_vanish(d, "gps", 20.0, 5.0))
    rows.append(row_thread(d, "estimator", "raise", 20, "an exception in step"))
    rows.append(row_thread(d, "control", "crash-loop", 20, "an exception in every step "
                           "(restart intensity exceeded)"))
    if not args.quick:
        rows.append(row_thread(d, "gps", "pyloop", 20, "a Python loop ignoring its stop event"))
        rows.append(row_thread(d, "estimator", "cblock", 20, "stuck inside C"))
        rows.append(row_thread(d, "estimator", "alloc", 20, "allocates 1 MiB per step for 10 s"))
    rows.append(row_device(d, "imu", "wrongbaud=20-23", "at twice the expected baud rate for 3 s",
                           gap=True))
    rows.append(row_device(d, "imu", "flood=20-25", "floods copies (10x its rate) for 5 s"))
    rows.append(row_device(d, "gps", "utcstep=20:3600", "UTC jumps +1 h"))
    if not args.quick:
        rows.append(row_device(d, "gps", "flood=20-25", "floods copies (10x its rate) for 5 s"))
        rows.append(row_vanish(d, "servo", 20.0, 3.0, renamed=True))
        rows.append(row_clock_step(d))
    rows.append(row_mavlink_flood(d, 5.0 if args.quick else 8.0, 3000.0))
    rows.append(row_signed_flood(d, 5.0 if args.quick else 8.0, 4000.0))
    rows.append(row_transfer_flood(d, 5.0 if args.quick else 8.0))
    if not args.quick:
        rows.append(row_legacy_flood(d, 8.0, 2000.0))
    rows.append(row_disk_full(d, 1500))
    from faults_disk import row_readonly, row_slow_fsync, row_slow_write

    rows.append(row_readonly(d, 5.0))
    rows.append(row_slow_fsync(d))
    if not args.quick:
        rows.append(row_slow_write(d))
    rows.append(row_sigstop(d, 5.0))
    rows.append(row_nominal_starts(4 if args.quick else 20, 15.0))
    if not args.quick:
        rows.append(row_sigterm(d))
        rows.append(row_sigkill(d))

    print(f"## Fault campaign: {len(rows)} SITL flights of {d:g} s at 5x (companion sim --fast)\n")
    print("Nominal rates: IMU 100 Hz, GPS 10 Hz (flight clock). No restart is intended in any "
          "row. Figures measured on the project's own simulator on loopback.\n")
    for r in rows:
        print(f"### {r.name}\n\nfault: {r.fault}\n")
        print("| figure | value |\n|---|---|")
        for k, v in r.figures.items():
            print(f"| {k} | {v} |")
        print()
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("faults", ["companion", "gcs_bridge", "legacy_protocol", "bench/faultfs.py", "bench/faults_disk.py"], main))
