"""MAVLink bridge benchmarks: parameter list and set, telemetry latency, bridge CPU.

Run: `python bench/mavlink_bench.py [--quick]` (or `make bench`) from the repository root.
Figures, each with what it is compared against in the same run:
- parameter list of every parameter: raw MAVLink client, MAVSDK 4.1 and MAVProxy 1.8.75;
- parameter set round trip (PARAM_SET -> PARAM_VALUE): raw client and MAVSDK;
- telemetry latency from an IMU frame written to the serial port (a pseudo-terminal read by
  the real IMU driver) to its HIGHRES_IMU arriving at a UDP ground station (target: p99 < 5 ms),
  against a competitor on the same path: a straight-through forwarder process (pyserial read,
  the same frame decoder, pymavlink's `mavutil` sending each sample as soon as it is decoded; no
  threads, slots or stream scheduling), which is the floor a Python bridge can reach on this
  path. A third row, an in-process reference without serial port or UDP, shows the sample age a
  free-running 100 Hz timer would add by itself;
- CPU of the bridge's threads at default rates and at typical ground-station rates.
"""

from __future__ import annotations

import argparse
import logging
import os
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil

from companion.core.clock import Clock
from companion.core.params import ParamRegistry, ParamSpec, float_param, int_param
from companion.vehicle import VEHICLE
from companion.watchdog import RuntimeContext, ThreadManager
from gcs_bridge.bridge import MavlinkBridge
from gcs_bridge.dialect import mavlink
from gcs_bridge.params import codec as param_codec

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # test support
from support.synthetic_vehicle import MiniGcs, SyntheticVehicle  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.result import Result, split_row  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def pct(values: list[float], q: float) -> float:
    v = sorted(values)
    return v[min(len(v) - 1, int(len(v) * q))] if v else float("nan")


def filler_params(n: int) -> list[ParamSpec]:
    """Extra parameters so the list is as long as a real aircraft's."""
    out: list[ParamSpec] = []
    for i in range(n):
        if i % 2:
            out.append(int_param(f"BEN_I{i:03d}", i, -(2**31), 2**31 - 1, "", "bench int"))
        else:
            out.append(float_param(f"BEN_F{i:03d}", i * 0.5, -1e6, 1e6, "", "bench float"))
    return out


# ----------------------------------------------------------------------------------- params
def bench_param_list(n_extra: int, repeats: int) -> list[str]:
    rows = []
    port = free_port()
    with SyntheticVehicle([f"udpout:127.0.0.1:{port}"], extra_params=filler_params(n_extra)) as v:
        count = len(v.params)
        gcs = MiniGcs(listen_port=port)
        try:
            assert gcs.recv(5.0, "HEARTBEAT") is not None
            times = []
            for _ in range(repeats):
                seen: set[int] = set()
                t0 = time.perf_counter()
                gcs.send(mavlink.MAVLink_param_request_list_message(1, 1))
                while len(seen) < count:
                    m = gcs.recv(5.0, "PARAM_VALUE")
                    if m is None:
                        break
                    seen.add(m.param_index)
                times.append(time.perf_counter() - t0)
                assert len(seen) == count, f"raw list got {len(seen)} of {count}"
            rows.append(f"| raw MAVLink (PARAM_REQUEST_LIST) | {count} | "
                        f"{statistics.median(times) * 1000:.0f} ms | {repeats} runs, median |")
            set_times = []
            spec_index = v.params.index_of("BEN_I001") if n_extra > 1 else 0
            for i in range(200 if repeats > 1 else 50):
                raw = struct.pack("<i", 1000 + i)
                msg = mavlink.MAVLink_param_set_message(1, 1, b"BEN_I001", 0.0,
                                                        param_codec.T_INT32)
                payload = struct.pack("<4sBB16sB", raw, 1, 1, b"BEN_I001", param_codec.T_INT32)
                frame = msg._pack(gcs.mav, msg.crc_extra, payload)
                gcs.mav.seq = (gcs.mav.seq + 1) & 0xFF
                t0 = time.perf_counter()
                gcs.send_raw(frame)
                m = gcs.recv(2.0, "PARAM_VALUE", lambda p: p.param_index == spec_index)
                set_times.append(time.perf_counter() - t0)
                assert m is not None and param_codec.raw_value_of(m) == raw
            rows.append(f"| raw MAVLink set round trip | 1 | p50 {pct(set_times, 0.5) * 1e3:.2f} ms, "
                        f"p99 {pct(set_times, 0.99) * 1e3:.2f} ms | {len(set_times)} sets |")
        finally:
            gcs.close()
        rows += _mavsdk_params(port, count, repeats)
    rows += _mavproxy_params(n_extra)
    return rows


def _mavsdk_params(port: int, count: int, repeats: int) -> list[str]:
    from mavsdk import ComponentType, Configuration, Mavsdk, log_subscribe, log_unsubscribe
    from mavsdk.plugins.param.param import Param

    log_subscribe(lambda *a: True)
    sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    rows = []
    try:
        sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = sdk.first_autopilot(5.0)
        if system is None:
            return ["| MAVSDK | - | not discovered | |"]
        param = Param(system)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            allp = param.get_all_params()
            times.append(time.perf_counter() - t0)
            got = len(allp.int_params) + len(allp.float_params)
            assert got == count, f"MAVSDK listed {got} of {count}"
        rows.append(f"| MAVSDK get_all_params | {count} | {statistics.median(times) * 1000:.0f} ms "
                    f"| {repeats} runs, median |")
        set_times = []
        for i in range(50):
            t0 = time.perf_counter()
            param.set_param_int("BEN_I001", 5000 + i)
            set_times.append(time.perf_counter() - t0)
        rows.append(f"| MAVSDK set_param_int round trip | 1 | p50 {pct(set_times, 0.5) * 1e3:.2f} ms, "
                    f"p99 {pct(set_times, 0.99) * 1e3:.2f} ms | 50 sets |")
    finally:
        sdk.destroy()
        log_unsubscribe()
    return rows


def _mavproxy_params(n_extra: int) -> list[str]:
    port = free_port()
    mavproxy = Path(sys.executable).with_name("mavproxy.py")
    with SyntheticVehicle([f"udpout:127.0.0.1:{port}"], extra_params=filler_params(n_extra)) as v, \
            tempfile.TemporaryDirectory(prefix="mavproxy-bench-") as workdir:
        count = len(v.params)
        t0 = time.perf_counter()
        proc = subprocess.Popen(
            [sys.executable, "-u", str(mavproxy), f"--master=udpin:127.0.0.1:{port}", "--no-state",
             "--default-modules=param,ftp"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            cwd=workdir)
        detected = received = None
        deadline = time.monotonic() + 40
        assert proc.stdout is not None
        try:
            while time.monotonic() < deadline:
                line = proc.stdout.readline()
                if not line:
                    break
                if "Detected vehicle" in line and detected is None:
                    detected = time.perf_counter() - t0
                if "Received" in line and "parameters" in line:
                    received = time.perf_counter() - t0
                    break
        finally:
            if proc.stdin is not None:
                proc.stdin.close()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            proc.stdout.close()
    if received is None or detected is None:
        return [f"| MAVProxy param fetch | {count} | failed | |"]
    return [f"| MAVProxy param fetch (incl. refused FTP try) | {count} | "
            f"{(received - detected) * 1000:.0f} ms after detecting the vehicle | "
            f"{received:.1f} s from process start |"]


# ----------------------------------------------------------------------------------- latency
def serve_imu(pty_path: str, port: int, duration_s: float) -> int:
    """Child process: the real IMU driver on `pty_path` and a bridge sending HIGHRES_IMU at
    100 Hz to `port`; prints the bridge's own latency figures as one line of JSON."""
    import json

    from companion.drivers.imu import ImuDriver

    ctx = RuntimeContext(clock=Clock(), params=ParamRegistry())
    manager = ThreadManager(ctx, [ImuDriver(pty_path, 115200, task=VEHICLE["imu"].task)])
    ctx.params.set("MGR_WDG_GRAN_MS", 10)
    bridge = MavlinkBridge(ctx, manager, [f"udpout:127.0.0.1:{port}?HIGHRES_IMU=100"])
    manager.start()
    manager.run(duration_s)
    manager.shutdown()
    bridge.close()
    st = bridge.stats()[0]
    print(json.dumps({"p50_us": st["latency_us_p50"], "p99_us": st["latency_us_p99"]}))
    return 0


def serve_direct(pty_path: str, port: int, duration_s: float) -> int:
    """Child process, the competitor: read the pty, decode, send HIGHRES_IMU at once.

    The simplest forwarder on the same path (same pseudo-terminal, same decoder, UDP to the same
    ground station): one loop, no managed threads, no shared slots, no stream scheduler. It
    prints nothing; its latency is measured at the ground station like the bridge's."""
    import serial
    from pymavlink import mavutil

    from companion.drivers.imu_protocol import ImuDecoder, ImuFast

    ser = serial.serial_for_url(pty_path, 115200, timeout=0.05)
    conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1,
                                      source_component=1)
    dec = ImuDecoder()
    nan = float("nan")
    t_start = time.monotonic()
    next_hb = t_start
    try:
        while time.monotonic() - t_start < duration_s:
            if time.monotonic() >= next_hb:
                conn.mav.heartbeat_send(mavlink.MAV_TYPE_FIXED_WING, mavlink.MAV_AUTOPILOT_GENERIC,
                                        0, 0, mavlink.MAV_STATE_ACTIVE)
                next_hb += 1.0
            data = ser.read(ser.in_waiting or 1)
            if not data:
                continue
            for item in dec.feed(data, time.monotonic_ns()):
                if isinstance(item, ImuFast):
                    (p, q, r), (ax, ay, az) = item.rates_rad_s, item.accel_m_s2
                    conn.mav.highres_imu_send(item.t_ns // 1000, ax, ay, az, p, q, r, nan, nan,
                                              nan, nan, nan, nan, nan, 0b111111)
    finally:
        ser.close()
        conn.close()
    return 0


def bench_latency(duration_s: float) -> list[str]:
    """IMU frame -> pty -> (bridge process | direct forwarder process) -> UDP -> ground station."""
    ours = _path_latency("--serve-imu", duration_s)
    direct = _path_latency("--serve-direct", duration_s)
    base = _naive_latency(duration_s)

    def row(label: str, lat: list[float]) -> str:
        return (f"| {label} | {len(lat)} | p50 {pct(lat, 0.5):.2f} ms, p99 {pct(lat, 0.99):.2f} ms, "
                f"max {max(lat):.2f} ms | p99 {pct(lat, 0.99) / pct(direct[0], 0.99):.2f}x |")

    inner = ours[1] or {}
    return [
        row("bridge (the runtime's IMU driver, slot, MAVLink sender)", ours[0]),
        f"| (bridge's own measure: sample stamped by the driver -> message built) | | p50 "
        f"{(inner.get('p50_us') or 0) / 1e3:.2f} ms, p99 {(inner.get('p99_us') or 0) / 1e3:.2f} ms | |",
        row("competitor, same path: direct forwarder (pyserial + decoder + mavutil, one loop)",
            direct[0]),
        f"| in-process reference, no serial port and no UDP: age of the newest sample when a "
        f"free-running 100 Hz timer sends it | {base[0]} | p50 {base[1]:.2f} ms, "
        f"p99 {base[2]:.2f} ms | |",
    ]


def _path_latency(mode: str, duration_s: float) -> tuple[list[float], dict | None]:
    """Latency over one path; the forwarding process is `mode` of this script.

    The forwarder runs in its own process, as in flight; this process plays the IMU (writes a
    frame every 10 ms, each with a distinct rate value) and the ground station, and timestamps
    both ends with one clock.
    """
    import json

    from companion.drivers.imu_protocol import RATE_LSB_RAD_S, encode_fast_frame

    master, slave = os.openpty()
    path = os.ttyname(slave)
    port = free_port()
    gcs = MiniGcs(listen_port=port)
    child = subprocess.Popen([sys.executable, __file__, mode, path, str(port),
                              str(duration_s + 4.0)], stdout=subprocess.PIPE, text=True,
                             cwd=ROOT)
    os.close(slave)
    written: dict[int, int] = {}
    stop = threading.Event()

    def writer() -> None:
        k = 0
        next_t = time.perf_counter()
        while not stop.is_set():
            k += 1
            code = k % 5000 + 1
            frame = encode_fast_frame(k % 100, 3, (code * RATE_LSB_RAD_S, 0.0, 0.0),
                                      (0.0, 0.0, -9.8), 0)
            written[code] = time.perf_counter_ns()
            os.write(master, frame)
            next_t += 0.01
            stop.wait(max(0.0, next_t - time.perf_counter()))

    wt = threading.Thread(target=writer, daemon=True)
    lat_ms: list[float] = []
    try:
        assert gcs.recv(10.0, "HEARTBEAT") is not None, "runtime did not start"
        wt.start()
        gcs.collect(1.0)
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            m = gcs.recv(0.5, "HIGHRES_IMU")
            now = time.perf_counter_ns()
            if m is None:
                continue
            t_w = written.get(round(m.xgyro / RATE_LSB_RAD_S))
            if t_w is not None:
                lat_ms.append((now - t_w) / 1e6)
    finally:
        stop.set()
        if wt.is_alive():
            wt.join(2)
        out, _ = child.communicate(timeout=30)
        gcs.close()
        os.close(master)
    lines = out.strip().splitlines()
    inner = json.loads(lines[-1]) if lines else None
    if not lat_ms:
        raise SystemExit(f"{mode}: no HIGHRES_IMU reached the ground station")
    return lat_ms, inner


def _naive_latency(duration_s: float) -> tuple[int, float, float]:
    """Sample age when a plain 100 Hz timer sends the newest 100 Hz sample (no alignment)."""
    latest = [0]
    stop = threading.Event()

    def producer() -> None:
        next_t = time.perf_counter()
        while not stop.is_set():
            latest[0] = time.perf_counter_ns()
            next_t += 0.01
            stop.wait(max(0.0, next_t - time.perf_counter()))

    th = threading.Thread(target=producer, daemon=True)
    th.start()
    ages = []
    # the sender's clock is not the device's: 0.1 % apart, their phase sweeps every 10 s
    next_t = time.perf_counter()
    end = time.perf_counter() + duration_s
    while time.perf_counter() < end:
        time.sleep(max(0.0, next_t - time.perf_counter()))
        ages.append((time.perf_counter_ns() - latest[0]) / 1e6)
        next_t += 0.01001
    stop.set()
    th.join(1)
    return len(ages), pct(ages, 0.5), pct(ages, 0.99)


# ----------------------------------------------------------------------------------- CPU
def thread_cpu_s() -> dict[int, float]:
    """CPU seconds used so far by each thread of this process, by native thread id."""
    return {t.id: t.user_time + t.system_time for t in psutil.Process().threads()}


def bench_cpu(duration_s: float) -> list[str]:
    rows = []
    one_hz = {name: 1.0 for name in ("MAV_ATT_HZ", "MAV_POS_HZ", "MAV_HUD_HZ", "MAV_GPS_HZ",
                                     "MAV_STAT_HZ", "MAV_IMU_HZ", "MAV_RC_HZ")}
    for label, rates, params in [
            ("every stream at 1 Hz (the defaults before the ground-station rates)", "", one_hz),
            ("default rates (ATTITUDE 20 Hz, position and HUD 5 Hz, IMU 10 Hz, RC 4 Hz, "
             "GPS and status 2 Hz)", "", {}),
            ("high GCS rates (ATTITUDE 50 Hz, position 10 Hz, IMU 20 Hz, GPS 5 Hz, "
             "RC/servo 10 Hz)", "?ATTITUDE=50&ATTITUDE_QUATERNION=50&"
             "GLOBAL_POSITION_INT=10&LOCAL_POSITION_NED=10&HIGHRES_IMU=20&"
             "GPS_RAW_INT=5&RC_CHANNELS=10&SERVO_OUTPUT_RAW=10&VFR_HUD=10", {})]:
        port = free_port()
        gcs = MiniGcs(listen_port=port)
        with SyntheticVehicle([f"udpout:127.0.0.1:{port}{rates}"]) as v:
            for name, value in params.items():
                v.params.set(name, value)
            gcs.collect(1.0)
            ids = {t.name: t.native_id or 0 for t in v.bridge.threads if t.native_id}
            src_ids = [t.native_id or 0 for t in v.sources if t.native_id]
            c0, w0 = thread_cpu_s(), time.perf_counter()
            n0 = v.bridge.stats()[0]["tx_frames"]
            gcs.collect(duration_s)
            c1, w1 = thread_cpu_s(), time.perf_counter()
            n1 = v.bridge.stats()[0]["tx_frames"]
            wall = w1 - w0
            parts = {name: (c1.get(tid, 0) - c0.get(tid, 0)) / wall * 100 for name, tid in ids.items()}
            total = sum(parts.values())
            src = sum((c1.get(tid, 0.0) - c0.get(tid, 0.0)) / wall * 100 for tid in src_ids)
            rows.append(f"| {label} | {(n1 - n0) / wall:.0f} msg/s | bridge {total:.2f} % of a core "
                        f"({', '.join(f'{k} {p:.2f} %' for k, p in parts.items())}) | "
                        f"baseline: the 4 synthetic sources {src:.2f} % |")
        gcs.close()
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short runs (smoke test)")
    ap.add_argument("--serve-imu", nargs=3, metavar=("PTY", "PORT", "SECONDS"),
                    help=argparse.SUPPRESS)  # the latency benchmark's runtime process
    ap.add_argument("--serve-direct", nargs=3, metavar=("PTY", "PORT", "SECONDS"),
                    help=argparse.SUPPRESS)  # the same path's competitor process
    args = ap.parse_args()
    if args.serve_imu:
        return serve_imu(args.serve_imu[0], int(args.serve_imu[1]), float(args.serve_imu[2]))
    if args.serve_direct:
        return serve_direct(args.serve_direct[0], int(args.serve_direct[1]),
                            float(args.serve_direct[2]))
    logging.basicConfig(level=logging.WARNING)
    quick = args.quick
    res = Result("mavlink", ["gcs_bridge", "companion/runtime.py", "companion/drivers"],
                 quick=quick)
    print("## MAVLink bridge\n", flush=True)
    res.table("Parameters", ["what", "params", "time", "notes"],
              [split_row(r) for r in bench_param_list(20 if quick else 270, 1 if quick else 5)])
    res.table("Telemetry latency, IMU frame on the serial port -> HIGHRES_IMU at the GCS",
              ["path", "samples", "result", "p99 vs the direct forwarder"],
              [split_row(r) for r in bench_latency(3.0 if quick else 20.0)])
    res.table("Bridge CPU", ["bridge", "sent", "CPU", "baseline"],
              [split_row(r) for r in bench_cpu(3.0 if quick else 20.0)])
    res.write()
    return 0


if __name__ == "__main__":
    sys.exit(main())
