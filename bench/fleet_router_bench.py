"""K simulated aircraft, with and without MAVProxy as a router in front of them.

Run: `python bench/fleet_router_bench.py [--quick] [--vehicles 1 2 4 6 8 10] [--duration 30]`.

For each K, `companion sim --vehicles K` flies in real time for `--duration` simulated
seconds, twice:

- **direct**: the fleet sends MAVLink (`udpout`) straight to one ground-station port;
- **router**: the fleet sends to `mavproxy.py --master=udpin:...` (one master: `--vehicles`
  gives every aircraft the same endpoint), which forwards to two `--out=udpout:` ground-station
  ports, as in docs/ground-stations.md ("Several aircraft behind MAVProxy as a router").

The ground-station ports are drained by this process, which counts ATTITUDE frames per system
id from the raw bytes (no MAVLink parsing: the bench itself must cost little on two cores).

Per K and setup: each aircraft's device and control rates in the steady state, from its own
logs with sitl_bench's `periods_ms` (IMU 100 Hz, GPS 10 Hz, servo 50 Hz, control 100 Hz; held
= every aircraft within 1 % of nominal), the CPU of the runtimes and simulators per aircraft and
of MAVProxy (psutil, % of one core, in the window where every aircraft is flying), the ATTITUDE
rate each ground station receives per aircraft (20 Hz by default), and router / direct ratios
from the same run. Then the largest K with every rate held in each setup.
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
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import psutil

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sitl_bench import NOMINAL_MS, periods_ms  # noqa: E402  (the SITL bench's measurement)

MAVPROXY = Path(sys.executable).with_name("mavproxy.py")
RATES_MS = {**NOMINAL_MS, "control": 10.0}  # the control law runs with the IMU
ATTITUDE_ID = 30
HELD = 0.99  # a rate is held within 1 % of nominal


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Drain:
    """A ground station that only listens: counts ATTITUDE frames per system id."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.sock.setblocking(False)
        self.counts: Counter[int] = Counter()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if not select.select([self.sock], [], [], 0.1)[0]:
                continue
            while True:
                try:
                    buf = self.sock.recv(65536)
                except BlockingIOError:
                    break
                with self._lock:
                    self._count(buf)

    def snapshot(self) -> Counter[int]:
        with self._lock:
            return Counter(self.counts)

    def _count(self, buf: bytes) -> None:
        i = 0
        while i + 12 <= len(buf):
            if buf[i] != 0xFD:  # MAVLink 2 only (the bridge sends nothing else)
                i += 1
                continue
            plen, incompat = buf[i + 1], buf[i + 2]
            if buf[i + 7] | buf[i + 8] << 8 | buf[i + 9] << 16 == ATTITUDE_ID:
                self.counts[buf[i + 5]] += 1
            i += 12 + plen + (13 if incompat & 1 else 0)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.sock.close()


def tree_cpu_s(root: psutil.Process) -> dict[int, float]:
    """CPU seconds (user + system) of `root` and every descendant, by pid (with K = 1,
    `companion sim` is the runtime itself; with K > 1 it is run_fleet, idle, over K runtimes;
    each runtime's child is its simulator)."""
    out: dict[int, float] = {}
    for p in [root, *root.children(recursive=True)]:
        try:
            out[p.pid] = sum(p.cpu_times()[:2])
        except psutil.Error:
            pass
    return out


def window_cpu(first: dict[int, float], last: dict[int, float]) -> float:
    return sum(cpu - first.get(pid, 0.0) for pid, cpu in last.items())


def fly(tmp: Path, k: int, duration_s: float, router: bool) -> dict[str, Any]:
    flights = tmp / "flights"
    tmp.mkdir(parents=True)
    gcs_ports = [free_udp_port(), free_udp_port()] if router else [free_udp_port()]
    master = free_udp_port() if router else gcs_ports[0]
    drains = [Drain(p) for p in gcs_ports]
    mp: subprocess.Popen[bytes] | None = None
    fleet: subprocess.Popen[bytes] | None = None
    try:
        if router:
            state = tmp / "mavproxy"
            state.mkdir()
            mp = subprocess.Popen(
                [sys.executable, str(MAVPROXY), f"--master=udpin:127.0.0.1:{master}",
                 *(f"--out=udpout:127.0.0.1:{p}" for p in gcs_ports), "--daemon",
                 "--non-interactive", "--no-state", "--state-basedir", str(state),
                 "--default-modules=", "--streamrate=-1"],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                cwd=state)
        legacy = free_udp_port()
        fleet = subprocess.Popen(
            [sys.executable, "-m", "companion", "sim", "--vehicles", str(k),
             "--duration", str(duration_s), "--scenario", "mixed", "--log-dir", str(flights),
             "--mavlink", f"udpout:127.0.0.1:{master}", "--legacy-listen", str(legacy),
             "--legacy-dest", f"127.0.0.1:{free_udp_port()}"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            cwd=tmp, start_new_session=True)
        root = psutil.Process(fleet.pid)
        mp_ps = psutil.Process(mp.pid) if mp is not None else None
        # the window: every aircraft flying (its run.json written) plus 2 s, until one ends
        deadline = time.monotonic() + 120.0 + 10 * k
        while len(list(flights.glob("*/run.json"))) < k:
            if fleet.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"K={k}: the fleet did not start (exit {fleet.poll()})")
            time.sleep(0.2)
        time.sleep(2.0)
        t0, cpu0, att0 = time.monotonic(), tree_cpu_s(root), [d.snapshot() for d in drains]
        mp0 = sum(mp_ps.cpu_times()[:2]) if mp_ps else 0.0
        t1, cpu1, mp1, att1 = t0, cpu0, mp0, att0
        while fleet.poll() is None and not list(flights.glob("*/summary.json")):
            t1, cpu1 = time.monotonic(), tree_cpu_s(root)
            att1 = [d.snapshot() for d in drains]
            mp1 = sum(mp_ps.cpu_times()[:2]) if mp_ps else 0.0
            time.sleep(0.5)
        span = t1 - t0
        if fleet.wait(60) != 0:
            raise RuntimeError(f"K={k}: the fleet exited with {fleet.returncode}")
        if mp is not None and mp.poll() is not None:
            raise RuntimeError(f"K={k}: MAVProxy died (exit {mp.returncode})")
        rates: dict[str, list[float]] = {name: [] for name in RATES_MS}
        for fdir in sorted(p.parent for p in flights.glob("*/summary.json")):
            for name in RATES_MS:
                rates[name].append(1000.0 / float(periods_ms(fdir, name).mean()))
        att = [(a1[i] - a0[i]) / span for a0, a1 in zip(att0, att1, strict=True)
               for i in range(1, k + 1)]
        return {
            "k": k, "router": router, "span_s": span,
            "rates": {n: min(v) for n, v in rates.items()},
            "held": all(min(v) >= HELD * 1000.0 / RATES_MS[n] for n, v in rates.items()),
            "cpu_per_aircraft": window_cpu(cpu0, cpu1) / span / k * 100,
            "mavproxy_cpu": (mp1 - mp0) / span * 100 if mp_ps else 0.0,
            "gcs_attitude_hz": min(att),
        }
    finally:
        for proc in (fleet, mp):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGINT if proc is fleet else signal.SIGTERM)
                try:
                    proc.wait(15)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(5)
        if fleet is not None:
            try:
                os.killpg(fleet.pid, signal.SIGKILL)  # any runtime or world left behind
            except ProcessLookupError:
                pass
        for d in drains:
            d.close()


def rate_cell(r: dict[str, Any], base: dict[str, Any], name: str) -> str:
    nominal = 1000.0 / RATES_MS[name]
    return f"{r['rates'][name]:.2f} ({r['rates'][name] / base['rates'][name]:.3f})" \
        if r is not base else f"{r['rates'][name]:.2f} ({r['rates'][name] / nominal:.3f} nom)"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="K = 1, 2 and 20 s flights")
    ap.add_argument("--vehicles", type=int, nargs="+", default=None)
    ap.add_argument("--duration", type=float, default=None, help="simulated (= real) seconds")
    args = ap.parse_args()
    ks = args.vehicles or ([1, 2] if args.quick else [1, 2, 4, 6, 8, 10])
    duration = args.duration or (20.0 if args.quick else 30.0)
    if not MAVPROXY.is_file():
        print(f"no {MAVPROXY.name} next to {sys.executable}: install MAVProxy", file=sys.stderr)
        return 2
    load0 = os.getloadavg()
    results: list[tuple[dict[str, Any], dict[str, Any]]] = []
    with tempfile.TemporaryDirectory(prefix="fleet-router-") as tmp:
        for k in ks:
            direct = fly(Path(tmp) / f"k{k}-direct", k, duration, router=False)
            routed = fly(Path(tmp) / f"k{k}-router", k, duration, router=True)
            results.append((direct, routed))
            print(f"K={k} done", file=sys.stderr, flush=True)
    load1 = os.getloadavg()
    print(f"## {len(ks)} fleet sizes, {duration:.0f} s real-time flights, scenario mixed, "
          f"{os.cpu_count()} cores (load average {load0[0]:.2f} before, {load1[0]:.2f} after)\n")
    print("Rates: the slowest aircraft's steady-state rate in Hz (direct: its ratio to nominal; "
          "router: its ratio to direct in the same run). CPU: % of one core. GCS ATTITUDE: the "
          "slowest aircraft as seen by the slowest ground station (nominal 20 Hz).\n")
    print("| K | setup | IMU Hz | GPS Hz | servo Hz | control Hz | rates held | "
          "CPU / aircraft | MAVProxy CPU | GCS ATTITUDE Hz |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for direct, routed in results:
        for r in (direct, routed):
            cpu = f"{r['cpu_per_aircraft']:.1f}"
            att = f"{r['gcs_attitude_hz']:.1f}"
            if r is routed:
                cpu += f" ({r['cpu_per_aircraft'] / direct['cpu_per_aircraft']:.2f}x)"
                att += f" ({r['gcs_attitude_hz'] / max(direct['gcs_attitude_hz'], 1e-9):.2f}x)"
            print(f"| {r['k']} | {'router' if r['router'] else 'direct'} | "
                  + " | ".join(rate_cell(r, direct, n) for n in RATES_MS)
                  + f" | {'yes' if r['held'] else 'no'} | {cpu} | "
                  + (f"{r['mavproxy_cpu']:.1f}" if r["router"] else "-") + f" | {att} |")
    for setup in ("direct", "router"):
        held = [r["k"] for pair in results for r in pair
                if r["held"] and ("router" if r["router"] else "direct") == setup]
        print(f"\nlargest K with every rate held, {setup}: {max(held) if held else 'none'}")
    print("\n" + json.dumps([r for pair in results for r in pair]))
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("fleet_router", ["gcs_bridge", "bench/sitl_bench.py"], main))
