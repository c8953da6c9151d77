"""Campaign executors: the local process pool against Ray, one Ray node against two, and what a
parameter search adds per trial.

    python bench/campaign_bench.py                 # 20 flights of 10 simulated s, 2 at a time
    python bench/campaign_bench.py --flights 6 --duration 5      # a quick look

1. The same campaign (lockstep, scenario level, seeds 1..N) through the local pool
   (`--executor local --jobs 2`) and through a local Ray (`--executor ray --jobs 2`, ray.init
   on loopback): wall time, throughput, the ratio Ray / pool (target >= 0.9) and Ray's overhead
   per flight ((wall Ray - wall pool) x slots / flights). Ray's start-up is reported apart.
2. The same campaign on a Ray cluster of one node (1 CPU) and of two nodes (1 CPU each), both
   on this machine and on 127.0.0.1 (ray.cluster_utils.Cluster): throughput of each.
3. A search of K trials against a campaign of the same K flights, both through the pool: the
   search's overhead per trial (Optuna's ask/tell, its SQLite study, the metric).

Each campaign goes to a new directory; the numbers are campaign.json's wall time (the flights,
their markers and the dataset), measured in this process. Writes bench/results/<date>-campaign.
json (bench/result.py: the command, the commit, the machine and every figure), rendered on
docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from companion.sim.campaign import run_campaign  # noqa: E402
from companion.sim.campaign_spec import load_campaign  # noqa: E402
from companion.sim.executors import LocalExecutor, RayExecutor  # noqa: E402


def spec_file(tmp: Path, flights: int, duration_s: float) -> Path:
    path = tmp / "bench.toml"
    seeds = ", ".join(str(i) for i in range(1, flights + 1))
    path.write_text(f'duration_s = {duration_s}\nscenario = "level"\n[grid]\nseed = [{seeds}]\n',
                    encoding="utf-8")
    return path


def fly(spec: Path, out: Path, executor: Any) -> dict[str, Any]:
    t0 = time.monotonic()
    result = run_campaign(load_campaign(spec), str(out), executor, dataset=True)
    wall_s = time.monotonic() - t0
    if result["failed"]:
        raise SystemExit(f"{out}: {result['failed']} flights failed: "
                         f"{[r['error'] for r in result['runs'] if r['exit_code'] != 0][:2]}")
    n = result["flights"]
    return {"flights": n, "wall_s": round(wall_s, 2), "flights_per_s": round(n / wall_s, 3),
            "nodes": sorted({str(r["node"])[:8] for r in result["runs"]})}


def part1(tmp: Path, spec: Path, slots: int) -> dict[str, Any]:
    """Pool, Ray, Ray, pool, pool, Ray: the machine is shared with other work whose load comes
    and goes, so each executor flies three times, spread over the part, and the means of its
    runs are compared."""
    runs: dict[str, list[dict[str, Any]]] = {"pool": [], "ray": []}
    start_s: list[float] = []
    for i, name in enumerate(("pool", "ray", "ray", "pool", "pool", "ray")):
        if name == "pool":
            runs["pool"].append(fly(spec, tmp / f"pool{i}", LocalExecutor(slots)))
            continue
        t0 = time.monotonic()
        ray_ex = RayExecutor(None, slots)
        start_s.append(time.monotonic() - t0)
        try:
            runs["ray"].append(fly(spec, tmp / f"ray{i}", ray_ex))
        finally:
            ray_ex.close()
    n = runs["pool"][0]["flights"]
    wall = {k: sum(r["wall_s"] for r in v) / len(v) for k, v in runs.items()}
    return {"runs": runs, "pool_wall_s": round(wall["pool"], 2),
            "ray_wall_s": round(wall["ray"], 2),
            "pool_flights_per_s": round(n / wall["pool"], 3),
            "ray_flights_per_s": round(n / wall["ray"], 3),
            "ray_start_s": round(sum(start_s) / len(start_s), 2),
            "throughput_ratio_ray_over_pool": round(wall["pool"] / wall["ray"], 3),
            "ray_overhead_per_flight_s": round((wall["ray"] - wall["pool"]) * slots / n, 3)}


def part2(tmp: Path, spec: Path) -> dict[str, Any]:
    """In a network namespace of its own (`unshare -n`, only loopback up), where Ray finds
    nothing but 127.0.0.1: the nodes and the driver all on this machine, no traffic off it."""
    script = 'ip link set lo up && exec "$0" "$1" --nodes-part "$2" "$3"'
    proc = subprocess.run(["unshare", "-n", "sh", "-c", script, sys.executable, __file__,
                           str(spec), str(tmp)], capture_output=True, text=True, timeout=1800)
    if proc.returncode != 0:
        raise SystemExit(f"part 2: {proc.stderr[-2000:]}")
    out: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    out["two_over_one"] = round(out["2_node"]["flights_per_s"] / out["1_node"]["flights_per_s"], 3)
    return out


def nodes_part(spec: Path, tmp: Path) -> None:
    from ray.cluster_utils import Cluster

    out: dict[str, Any] = {}
    for nodes in (1, 2):
        cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
        for _ in range(nodes - 1):
            cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        try:
            executor = RayExecutor(cluster.address, None)
            try:
                out[f"{nodes}_node"] = fly(spec, tmp / f"nodes{nodes}", executor)
            finally:
                executor.close()
        finally:
            cluster.shutdown()
    print(json.dumps(out))


def part3(tmp: Path, trials: int, duration_s: float, slots: int) -> dict[str, Any]:
    from companion.sim.search import load_search, run_search

    search_spec = tmp / "search.toml"
    search_spec.write_text(
        f'duration_s = {duration_s}\nscenario = "level"\nno_noise = true\nno_level_cal = true\n'
        "params = { EST_TRIM_BIAS = 0 }\n[search]\nmetric = \"roll_rmse_deg\"\n"
        f"trials = {trials}\nseed = 1\n[search.params]\nEST_TRIM_ROLL = [-0.1, 0.1]\n",
        encoding="utf-8")
    plain_spec = tmp / "plain.toml"
    plain_spec.write_text(
        f'duration_s = {duration_s}\nscenario = "level"\nno_noise = true\nno_level_cal = true\n'
        "params = { EST_TRIM_BIAS = 0, EST_TRIM_ROLL = 0.05 }\n[grid]\nseed = "
        f"[{', '.join(['0'] * trials)}]\n", encoding="utf-8")
    plain = fly(plain_spec, tmp / "plain", LocalExecutor(slots))
    t0 = time.monotonic()
    found = run_search(load_search(search_spec), str(tmp / "search"), LocalExecutor(slots))
    search_wall_s = time.monotonic() - t0
    return {"trials": trials, "campaign_wall_s": plain["wall_s"],
            "search_wall_s": round(search_wall_s, 2),
            "overhead_per_trial_s": round((search_wall_s - plain["wall_s"]) / trials, 3),
            "best": {"value": found["best_value"], "params": found["best_params"]}}


def markdown(result: dict[str, Any]) -> str:
    p1, p2, p3 = result["part1"], result["part2"], result["part3"]
    n, d = result["flights"], result["duration_s"]
    lines = [
        f"## Pool against Ray: {n} lockstep flights of {d:g} simulated s, {result['slots']} "
        "at a time", "",
        "| executor | runs (wall s) | mean wall s | flights / s |", "|---|---|---|---|",
        f"| local pool | {', '.join(str(r['wall_s']) for r in p1['runs']['pool'])} | "
        f"{p1['pool_wall_s']} | {p1['pool_flights_per_s']} |",
        f"| local Ray | {', '.join(str(r['wall_s']) for r in p1['runs']['ray'])} | "
        f"{p1['ray_wall_s']} | {p1['ray_flights_per_s']} |", "",
        "Order: pool, Ray, Ray, pool, pool, Ray (so that a change in the machine's load falls on "
        "both; load average "
        f"{result['load_before']} before, {result['load_after']} after).", "",
        f"Ray / pool throughput: **{p1['throughput_ratio_ray_over_pool']}x** (target >= 0.9); "
        f"Ray overhead per flight {p1['ray_overhead_per_flight_s']} s; Ray's start-up "
        f"{p1['ray_start_s']} s (once per campaign, not in the wall times).", "",
        "## One Ray node against two (1 CPU each, both on this machine, 127.0.0.1)", "",
        "| cluster | wall s | flights / s |", "|---|---|---|",
        f"| 1 node | {p2['1_node']['wall_s']} | {p2['1_node']['flights_per_s']} |",
        f"| 2 nodes | {p2['2_node']['wall_s']} | {p2['2_node']['flights_per_s']} |", "",
        f"Two nodes / one: {p2['two_over_one']}x.", "",
        f"## Search overhead ({p3['trials']} trials against {p3['trials']} plain flights, pool)",
        "",
        "| what | wall s | overhead per trial s |", "|---|---|---|",
        f"| {p3['trials']} plain flights (a campaign) | {p3['campaign_wall_s']} | |",
        f"| a search of {p3['trials']} trials (Optuna's ask/tell, its SQLite study, the metric) "
        f"| {p3['search_wall_s']} | **{p3['overhead_per_trial_s']}** |", "",
        f"Best trial: {p3['best']}.", ""]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", type=int, default=20)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--slots", type=int, default=2)
    ap.add_argument("--trials", type=int, default=8)
    ap.add_argument("--nodes-part", nargs=2, type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.nodes_part:
        nodes_part(*args.nodes_part)
        return 0
    import os

    result: dict[str, Any] = {
        "cpus": os.cpu_count(), "flights": args.flights, "duration_s": args.duration,
        "slots": args.slots, "load_before": [round(x, 2) for x in os.getloadavg()]}
    with tempfile.TemporaryDirectory(prefix="campaign-bench-") as tmp_name:
        tmp = Path(tmp_name)
        spec = spec_file(tmp, args.flights, args.duration)
        result["part1"] = part1(tmp, spec, args.slots)
        result["part2"] = part2(tmp, spec)
        result["part3"] = part3(tmp, args.trials, args.duration, args.slots)
    result["load_after"] = [round(x, 2) for x in os.getloadavg()]
    print(markdown(result))
    # every figure as data too (bench/result.py keeps a whole-JSON line as data, not prose)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    from bench.result import run_captured

    if "--nodes-part" in sys.argv:  # the inner half of part 2, inside its network namespace
        sys.exit(main())
    sys.exit(run_captured("campaign", ["companion/sim", "bench/campaign_bench.py"], main))
