"""`companion sim --campaign SPEC --jobs J`: real lockstep flights in parallel processes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from companion.logs.dataset import query
from companion.sim.campaign import CampaignError, load_campaign

SPEC = """
duration_s = 10
scenario = "level"
[grid]
seed = [1, 2]
[[flight]]
seed = 7
params = { CTL_ROLL_KP = 0.8 }
[[flight]]
seed = 8
vanish = ["imu:not-a-time:1"]
"""


def campaign(tmp: Path, spec: str, *extra: str) -> subprocess.CompletedProcess[str]:
    path = tmp / "spec.toml"
    path.write_text(spec, encoding="utf-8")
    return subprocess.run([sys.executable, "-m", "companion", "sim", "--campaign", str(path),
                           "--campaign-dir", str(tmp / "out"), *extra],
                          capture_output=True, text=True, timeout=300)


def test_a_campaign_flies_every_flight_and_feeds_the_dataset(tmp_path: Path) -> None:
    proc = campaign(tmp_path, SPEC, "--jobs", "2", "--json")
    assert proc.returncode == 1, proc.stderr  # one flight of four is refused by its own sim
    result = json.loads(proc.stdout)
    assert (result["flights"], result["ok"], result["failed"]) == (4, 3, 1)
    runs = {r["index"]: r for r in result["runs"]}
    assert runs[4]["exit_code"] == 2 and "--vanish" in runs[4]["error"]
    for i in (1, 2, 3):
        assert runs[i]["exit_code"] == 0 and runs[i]["stop_reason"] == "duration", runs[i]
        assert Path(runs[i]["flight_dir"], "summary.json").is_file()
        assert "--lockstep" in runs[i]["command"]
    run3 = json.loads(Path(runs[3]["flight_dir"], "run.json").read_text())
    assert run3["parameters"]["CTL_ROLL_KP"] == pytest.approx(0.8)
    assert run3["simulation"]["seed"] == 7
    # the flown flights are in the Parquet dataset, queryable by their settings
    assert result["dataset"]["flights"] == 3
    columns, rows = query(tmp_path / "out" / "dataset",
                          "SELECT seed, stop_reason FROM flights ORDER BY seed")
    assert [tuple(r) for r in rows] == [(1, "duration"), (2, "duration"), (7, "duration")]
    saved = json.loads((tmp_path / "out" / "campaign.json").read_text())
    assert saved["runs"] == result["runs"]


@pytest.mark.parametrize(("spec", "message"), [
    ("seed = 'x'\n[grid]\nseed = [1]\n", "seed = 'x': expected int"),
    ("[grid]\nseed = []\n", "[grid] seed: expected a non-empty list"),
    ("[grid]\nspeed_of_light = [1]\n", "unknown key 'speed_of_light'"),
    ("[[flight]]\nparams = { NOPE = 1 }\n", "NOPE: unknown parameter"),
    ("[[flight]]\nparams = { CTL_ROLL_KP = 1e9 }\n", "CTL_ROLL_KP"),
    ("[[flight]]\nwind = [1, 2]\n", "expected [N, E, D]"),
    ("duration_s = 10\n", "no flights"),
    ("[grid\n", "spec.toml"),
])
def test_a_bad_specification_is_refused_before_anything_flies(
        tmp_path: Path, spec: str, message: str) -> None:
    path = tmp_path / "spec.toml"
    path.write_text(spec, encoding="utf-8")
    with pytest.raises(CampaignError, match=None) as err:
        load_campaign(path)
    assert message in str(err.value) and str(path) in str(err.value)
    proc = campaign(tmp_path, spec)
    assert proc.returncode == 2 and message in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "out").exists()
