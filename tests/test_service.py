"""The runtime under a service manager: sd_notify over a real datagram socket, and escalation
(a failed flight thread ends the process with EXIT_ESCALATED for systemd to restart it)."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import time
from pathlib import Path

from test_sim_runtime import sim_cmd

from companion.core.sdnotify import Notifier, supervised_by_service_manager
from companion.watchdog.manager import EXIT_ESCALATED


class NotifySocket:
    """What systemd listens on: a Unix datagram socket; keeps every message with its time."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.1)
        self.messages: list[tuple[float, dict[str, str]]] = []

    def drain(self) -> None:
        while True:
            try:
                data = self.sock.recv(4096)
            except (TimeoutError, BlockingIOError):
                return
            fields = dict(line.split("=", 1) for line in data.decode().splitlines() if "=" in line)
            self.messages.append((time.monotonic(), fields))

    def with_key(self, key: str) -> list[tuple[float, dict[str, str]]]:
        return [(t, m) for t, m in self.messages if key in m]

    def close(self) -> None:
        self.sock.close()


def fly_notified(tmp: Path, *args: str, watchdog_s: float = 1.0,
                 timeout_s: float = 120.0) -> tuple[subprocess.CompletedProcess[str], NotifySocket]:
    ns = NotifySocket(tmp / "notify.sock")
    env = {**os.environ, "NOTIFY_SOCKET": str(ns.path),
           "WATCHDOG_USEC": str(int(watchdog_s * 1e6))}
    proc = subprocess.Popen(sim_cmd(tmp, "--fast", "--json", *args), env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + timeout_s
    try:
        while proc.poll() is None and time.monotonic() < deadline:
            ns.drain()
        out, err = proc.communicate(timeout=max(1.0, deadline - time.monotonic()))
        ns.drain()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        ns.close()
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err), ns


def test_ready_watchdog_status_and_stopping_reach_the_service_manager(tmp_path: Path) -> None:
    done, ns = fly_notified(tmp_path, "--duration", "20", "--scenario", "level")
    assert done.returncode == 0, done.stderr[-2000:]
    ready = ns.with_key("READY")
    assert len(ready) == 1 and ready[0][1]["READY"] == "1"
    assert ready[0][1]["STATUS"].startswith("flying: ")  # every thread periodic by then
    pings = [t for t, m in ns.with_key("WATCHDOG") if "STOPPING" not in m]
    # 20 s of flight at 5x: 4 s of host time, a ping every 0.5 s (half of WATCHDOG_USEC)
    assert len(pings) >= 6
    gaps = [b - a for a, b in zip(pings, pings[1:], strict=False)]
    assert max(gaps) < 1.0  # never as long as the watchdog timeout
    stopping = ns.with_key("STOPPING")
    assert len(stopping) == 1 and "duration" in stopping[0][1]["STATUS"]
    assert int(stopping[0][1]["EXTEND_TIMEOUT_USEC"]) >= 30_000_000
    assert stopping[0][0] > ready[0][0]
    statuses = [m["STATUS"] for _, m in ns.with_key("STATUS")]
    assert all("\n" not in s and len(s) <= 400 for s in statuses)
    summary = json.loads(done.stdout)
    assert summary["escalated"] is None


def test_a_failed_flight_thread_escalates_to_the_service_manager(tmp_path: Path) -> None:
    done, ns = fly_notified(tmp_path, "--duration", "60", "--scenario", "level",
                            "--thread-fault", "control:crash-loop:10")
    assert done.returncode == EXIT_ESCALATED, done.stderr[-2000:]
    assert "control failed and escalated" in done.stderr
    summary = json.loads(done.stdout)
    assert summary["escalated"] == "control"
    assert summary["stop_reason"] == "escalated: control failed"
    kinds = [(e["kind"], e["thread"]) for e in summary["events"]]
    assert kinds.index(("failed", "control")) < kinds.index(("escalated", "control"))
    # it stopped at the failure, not at the end of the flight (60 s at 5x = 12 s of host time)
    assert summary["host_seconds"] < 8.0
    last = ns.with_key("STOPPING")[0][1]["STATUS"]
    assert "stopping (escalated: control failed)" in last and "failed: control" in last


def test_without_a_service_manager_a_failed_thread_is_left_down(tmp_path: Path) -> None:
    """MGR_ESCALATE 1 (the default) escalates only when something will restart the process;
    MGR_ESCALATE 0 never does, even under a service manager."""
    (tmp_path / "params.parm").write_text("MGR_ESCALATE 0\n")
    done, _ns = fly_notified(tmp_path, "--duration", "20", "--scenario", "level",
                             "--thread-fault", "control:crash-loop:5")
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads(done.stdout)
    threads = {t["name"]: t for t in summary["threads"]}
    assert threads["control"]["failed"] and summary["escalated"] is None
    assert summary["stop_reason"] == "duration"


def test_the_notifier_is_silent_without_a_socket_and_reads_the_watchdog_period() -> None:
    assert not supervised_by_service_manager({"INVOCATION_ID": "abc"})  # any unit's child
    assert supervised_by_service_manager({"NOTIFY_SOCKET": "/run/x"})
    quiet = Notifier({})
    assert not quiet.enabled and quiet.watchdog_interval_s is None
    quiet.ready("x")
    quiet.watchdog()  # nothing to send to: no error
    n = Notifier({"NOTIFY_SOCKET": "@abstract", "WATCHDOG_USEC": "4000000",
                  "WATCHDOG_PID": str(os.getpid())})
    assert n.enabled and n.watchdog_interval_s == 2.0
    other = Notifier({"NOTIFY_SOCKET": "/run/x", "WATCHDOG_USEC": "4000000", "WATCHDOG_PID": "1"})
    assert other.watchdog_interval_s is None  # the watchdog is another process's


def test_an_abstract_socket_and_a_vanished_socket(tmp_path: Path) -> None:
    name = f"companion-test-{os.getpid()}"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(b"\0" + name.encode())
    server.settimeout(2.0)
    try:
        n = Notifier({"NOTIFY_SOCKET": "@" + name})
        n.ready("flying: 5/5 threads ok")
        assert server.recv(4096) == b"READY=1\nSTATUS=flying: 5/5 threads ok\n"
        n.status("same\nline  twice")
        n.status("same line twice")  # unchanged once folded: not sent again
        n.status("other")
        assert server.recv(4096) == b"STATUS=same line twice\n"
        assert server.recv(4096) == b"STATUS=other\n"
        n.close()
    finally:
        server.close()
    gone = Notifier({"NOTIFY_SOCKET": str(tmp_path / "nobody-listens")})
    gone.watchdog()  # ENOENT/ECONNREFUSED: logged once, never raised
    gone.close()
