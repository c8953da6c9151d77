"""A two-node Ray cluster on loopback and campaigns flown on it; run by tests/test_sim_cluster.py
inside a private network namespace (`unshare -n`, only `lo` up), so nothing leaves the machine.

Prints one JSON object: per scenario what the campaign command said and left behind. The
scenarios share one cluster (starting one takes seconds): a plain six-flight campaign, the same
with the second node killed under a flight, the same interrupted with SIGINT and resumed, and a
parameter search.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

SPEC = """
duration_s = 6
scenario = "level"
[grid]
seed = [1, 2, 3, 4, 5, 6]
"""

SEARCH = """
duration_s = 6
scenario = "level"
no_noise = true
no_level_cal = true
params = { EST_TRIM_BIAS = 0 }
[search]
metric = "roll_rmse_deg"
trials = 8
seed = 3
[search.params]
EST_TRIM_ROLL = [-0.1, 0.1]
"""

WAIT_S = 240.0


def campaign(spec: Path, out: Path, address: str, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "companion", "sim", "--campaign", str(spec),
                             "--campaign-dir", str(out), "--executor", "ray", "--ray-address",
                             address, "--json", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def hashes(out: Path) -> dict[str, dict[str, str]]:
    """Per flight, the SHA-256 of every log it wrote."""
    return {d.name: {f.name: hashlib.sha256(f.read_bytes()).hexdigest()
                     for f in sorted(d.glob("*.bin"))}
            for d in sorted((out / "flights").iterdir()) if d.is_dir() and not d.name.startswith(".")}


def flights_running(out: Path) -> list[str]:
    """Flight processes whose command line names the campaign directory (orphans, at the end)."""
    found = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            cmd = Path("/proc", pid, "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if str(out) in cmd and "--log-dir" in cmd:
            found.append(f"{pid}: {cmd[:120]}")
    return found


def until_line(proc: subprocess.Popen[str], want: Any) -> list[str]:
    """The command's stderr lines up to the first for which `want(line)` holds."""
    assert proc.stderr is not None
    seen = []
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            break
        seen.append(line.rstrip())
        if want(line):
            return seen
    raise SystemExit(f"no such line: {seen[-5:]}")


def finish(proc: subprocess.Popen[str]) -> dict[str, Any]:
    out, err = proc.communicate(timeout=WAIT_S)
    return {"rc": proc.returncode, "stdout": out, "stderr": err[-3000:]}


def main() -> None:
    from ray.cluster_utils import Cluster

    work = Path(sys.argv[1])
    spec = work / "spec.toml"
    spec.write_text(SPEC, encoding="utf-8")
    report: dict[str, Any] = {}
    t0 = time.monotonic()
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    second = cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    report["cluster_s"] = round(time.monotonic() - t0, 1)
    report["nodes"] = {"head": cluster.head_node.node_id, "second": second.node_id}
    try:
        # 1: six flights on two nodes
        plain = work / "plain"
        report["plain"] = finish(campaign(spec, plain, cluster.address))
        report["plain"]["hashes"] = hashes(plain)

        # 2: SIGINT after the first flight is done, then the same command again
        resumed = work / "resumed"
        proc = campaign(spec, resumed, cluster.address)
        until_line(proc, lambda line: "[1/6]" in line)
        proc.send_signal(signal.SIGINT)
        report["interrupted"] = finish(proc)
        report["interrupted"]["orphans"] = flights_running(resumed)
        report["interrupted"]["markers"] = sorted(p.name for p in (resumed / "runs").glob("*.json"))
        report["resumed"] = finish(campaign(spec, resumed, cluster.address))
        report["resumed"]["hashes"] = hashes(resumed)

        # 3: the second node killed while it flies a flight: flights of 120 simulated s (some
        # 5 s of wall time in lockstep), as a 6 s flight could end between the line that
        # says it started and the kill on a quiet machine (seen: no flight was lost)
        lost = work / "lost"
        long_spec = work / "long.toml"
        long_spec.write_text(SPEC.replace("duration_s = 6", "duration_s = 120"),
                             encoding="utf-8")
        proc = campaign(long_spec, lost, cluster.address)
        until_line(proc, lambda line: f"started on node {second.node_id}" in line)
        cluster.remove_node(second, allow_graceful=False)
        report["lost"] = finish(proc)
        report["lost"]["orphans"] = flights_running(lost)

        # 4: a parameter search through the (now one-node) cluster
        search = work / "search.toml"
        search.write_text(SEARCH, encoding="utf-8")
        report["search"] = finish(campaign(search, work / "search", cluster.address, "--search"))
        report["total_s"] = round(time.monotonic() - t0, 1)
    finally:
        cluster.shutdown()
    print(json.dumps(report))


if __name__ == "__main__":
    main()
