"""Campaigns on a real two-node Ray cluster (head + a second node, both on 127.0.0.1), run in a
private network namespace whose only interface is loopback: no test traffic leaves the machine.

One cluster serves every test (tests/ray_cluster_driver.py flies the scenarios and reports);
`make test-cluster` runs them (a minute and a half: apart from `make test`; .ci/run runs both).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

pytestmark = [pytest.mark.cluster, pytest.mark.timeout(600)]

DRIVER = Path(__file__).with_name("ray_cluster_driver.py")


def _namespace_problem() -> str | None:
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "needs unshare and ip (util-linux, iproute2)"
    probe = subprocess.run(["unshare", "-n", "sh", "-c", "ip link set lo up"],
                           capture_output=True, text=True, timeout=30)
    return None if probe.returncode == 0 else f"cannot make a network namespace: {probe.stderr}"


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    pytest.importorskip("ray", reason="the cluster extra: pip install 'uav-companion[cluster]'")
    problem = _namespace_problem()
    if problem:
        pytest.skip(problem)
    work = tmp_path_factory.mktemp("cluster")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(Path(__file__).parents[1]), os.environ.get("PYTHONPATH", "")]),
        "RAY_USAGE_STATS_ENABLED": "0"}
    proc = subprocess.run(
        ["unshare", "-n", "sh", "-c", 'ip link set lo up && exec "$0" "$1" "$2"',
         sys.executable, str(DRIVER), str(work)],
        capture_output=True, text=True, timeout=540, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result: dict[str, Any] = json.loads(proc.stdout)
    return result


def _runs(step: dict[str, Any]) -> dict[int, dict[str, Any]]:
    assert step["rc"] == 0, step["stderr"]
    return {r["index"]: r for r in json.loads(step["stdout"])["runs"]}


def test_a_campaign_flies_on_both_nodes(report: dict[str, Any]) -> None:
    runs = _runs(report["plain"])
    assert len(runs) == 6 and all(r["exit_code"] == 0 for r in runs.values())
    assert {r["node"] for r in runs.values()} == set(report["nodes"].values())
    assert all(r["tries"] == 1 and "--lockstep" in r["command"] for r in runs.values())


def test_the_flights_of_a_lost_node_fly_again_elsewhere(report: dict[str, Any]) -> None:
    runs = _runs(report["lost"])
    assert all(r["exit_code"] == 0 for r in runs.values()), runs
    again = [r for r in runs.values() if r["tries"] > 1]
    assert again and all(r["node"] == report["nodes"]["head"] for r in again)
    assert report["lost"]["orphans"] == []


def test_an_interrupted_campaign_resumes_to_the_same_flights(report: dict[str, Any]) -> None:
    stopped = report["interrupted"]
    assert stopped["rc"] == 130 and "run the same command again" in stopped["stderr"]
    assert stopped["orphans"] == []  # SIGINT stopped every flight under way, on both nodes
    assert 1 <= len(stopped["markers"]) < 6
    resumed = json.loads(report["resumed"]["stdout"])
    assert resumed["ok"] == 6 and resumed["flown_now"] == 6 - len(stopped["markers"])
    assert report["resumed"]["hashes"] == report["plain"]["hashes"]
    assert len(report["plain"]["hashes"]) == 6 and all(report["plain"]["hashes"].values())


def test_a_search_on_the_cluster_finds_the_known_best_trim(report: dict[str, Any]) -> None:
    # with perfect sensors and no level calibration the best roll trim is 0: any other value
    # tilts the estimate by that much
    assert report["search"]["rc"] == 0, report["search"]["stderr"]
    found = json.loads(report["search"]["stdout"])
    assert found["trials"] == 8 and found["failed"] == 0
    assert abs(found["best_params"]["EST_TRIM_ROLL"]) < 0.02  # rad, of a range of +-0.1
    assert Path(found["best_parm"]).read_text().splitlines()[1].startswith("EST_TRIM_ROLL ")
