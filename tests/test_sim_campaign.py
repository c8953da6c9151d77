"""`companion sim --campaign SPEC --jobs J`: real lockstep flights in parallel processes."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
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


RESUME_SPEC = """
duration_s = 20
scenario = "level"
[[flight]]
seed = 1
duration_s = 4
[[flight]]
seed = 2
[[flight]]
seed = 3
"""


def _hashes(out: Path) -> dict[str, dict[str, str]]:
    import hashlib

    return {d.name: {f.name: hashlib.sha256(f.read_bytes()).hexdigest()
                     for f in sorted(d.glob("*.bin"))}
            for d in sorted((out / "flights").iterdir()) if not d.name.startswith(".")}


def _flight_processes(out: Path) -> list[str]:
    found = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            cmd = Path("/proc", pid, "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if f"{out}/" in cmd and "--log-dir" in cmd:
            found.append(cmd)
    return found


def _rows(out: Path) -> dict[str, list[tuple[object, ...]]]:
    from companion.logs.dataset import stream_names

    ds = out / "dataset"
    tables = {"flights": "SELECT flight, seed, stop_reason FROM flights ORDER BY flight"}
    tables |= {s: f"SELECT * FROM {s} ORDER BY ALL" for s in stream_names(ds)}
    return {name: [tuple(r) for r in query(ds, sql)[1]] for name, sql in tables.items()}


def test_a_campaign_killed_with_sigkill_resumes_to_the_same_dataset(tmp_path: Path) -> None:
    spec = tmp_path / "spec.toml"
    spec.write_text(RESUME_SPEC, encoding="utf-8")

    def command(out: Path) -> list[str]:
        return [sys.executable, "-m", "companion", "sim", "--campaign", str(spec),
                "--campaign-dir", str(out), "--jobs", "1", "--json"]

    whole = tmp_path / "whole"
    assert subprocess.run(command(whole), capture_output=True, timeout=300).returncode == 0
    killed = tmp_path / "killed"
    proc = subprocess.Popen(command(killed), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    assert proc.stderr is not None
    for line in proc.stderr:  # bounded: the flights end, and with them the output
        if line.startswith("[1/3]"):
            break
    deadline = time.monotonic() + 30
    while not _flight_processes(killed) and time.monotonic() < deadline:
        time.sleep(0.05)  # the second flight (seconds long) is starting
    assert _flight_processes(killed), "the second flight never started"
    proc.kill()  # SIGKILL: no handler runs, campaign.json is not written
    proc.wait(timeout=30)
    deadline = time.monotonic() + 1.0
    while _flight_processes(killed) and time.monotonic() < deadline:
        time.sleep(0.05)  # the flight under way dies with its driver (PR_SET_PDEATHSIG)
    assert _flight_processes(killed) == []
    markers = sorted(p.name for p in (killed / "runs").glob("*.json"))
    assert 1 <= len(markers) < 3 and not (killed / "campaign.json").exists()

    again = subprocess.run(command(killed), capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    result = json.loads(again.stdout)
    assert (result["ok"], result["flown_now"]) == (3, 3 - len(markers))
    assert _hashes(killed) == _hashes(whole) and len(_hashes(whole)) == 3
    assert _rows(killed) == _rows(whole)
    # and a third run has nothing left to fly
    third = json.loads(subprocess.run(command(killed), capture_output=True, text=True,
                                      timeout=300).stdout)
    assert third["flown_now"] == 0 and third["ok"] == 3


def test_a_failed_flight_is_flown_again_only_when_asked(tmp_path: Path) -> None:
    spec = "duration_s = 5\n[[flight]]\nvanish = ['imu:not-a-time:1']\n"
    first = campaign(tmp_path, spec, "--json")
    assert first.returncode == 1 and json.loads(first.stdout)["flown_now"] == 1
    again = campaign(tmp_path, spec, "--json")
    assert again.returncode == 1 and json.loads(again.stdout)["flown_now"] == 0
    assert "--vanish" in json.loads(again.stdout)["runs"][0]["error"]
    retried = campaign(tmp_path, spec, "--json", "--retry-failed")
    assert retried.returncode == 1 and json.loads(retried.stdout)["flown_now"] == 1


def test_another_specification_in_the_same_directory_is_refused(tmp_path: Path) -> None:
    spec = "duration_s = 5\n[[flight]]\nvanish = ['imu:not-a-time:1']\n"
    assert campaign(tmp_path, spec).returncode == 1
    other = campaign(tmp_path, spec.replace("imu:", "gps:"))
    assert other.returncode == 2 and "holds another campaign" in other.stderr
    assert len(other.stderr.strip().splitlines()) == 1


def test_an_unreachable_cluster_is_one_line_and_nothing_flies(tmp_path: Path) -> None:
    pytest.importorskip("ray")
    with socket.socket() as s:  # a loopback port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    proc = campaign(tmp_path, SPEC, "--executor", "ray", "--ray-address", f"127.0.0.1:{port}")
    assert proc.returncode == 2 and time.monotonic() - t0 < 60
    assert proc.stderr.strip().splitlines() == [
        f"companion sim: --ray-address 127.0.0.1:{port}: no Ray cluster answers there "
        "(Connection refused)"]
    assert not (tmp_path / "out").exists()


def test_ray_missing_is_one_line_saying_what_to_install(tmp_path: Path) -> None:
    path = tmp_path / "spec.toml"
    path.write_text(SPEC, encoding="utf-8")
    # this interpreter without Ray: an import of it fails as it would where it is not installed
    code = ("import sys; sys.modules['ray'] = None; from companion.cli import main; "
            f"sys.exit(main(['sim', '--campaign', {str(path)!r}, '--executor', 'ray']))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "companion sim: --executor ray needs Ray: pip install 'uav-companion[cluster]'"]


SEARCH = """
duration_s = 5
scenario = "level"
no_noise = true
no_level_cal = true
params = { EST_TRIM_BIAS = 0 }
[search]
metric = "roll_rmse_deg"
trials = 10
seed = 2
[search.params]
EST_TRIM_ROLL = [-0.1, 0.1]
"""


def test_a_search_finds_the_known_best_trim_and_writes_a_parm_file(tmp_path: Path) -> None:
    pytest.importorskip("optuna")
    proc = campaign(tmp_path, SEARCH, "--search", "--jobs", "2", "--json")
    assert proc.returncode == 0, proc.stderr
    found = json.loads(proc.stdout)
    # perfect sensors, no level calibration: any roll trim but 0 tilts the estimate by itself
    assert found["trials"] == 10 and abs(found["best_params"]["EST_TRIM_ROLL"]) < 0.02
    from companion.core.params import parse_param_file

    # read by the project's own reader, as --params-file reads it: one line, no problem
    [(_, name, _, value, problem)] = list(parse_param_file(Path(found["best_parm"])))
    assert (name, problem) == ("EST_TRIM_ROLL", None)
    assert value == pytest.approx(found["best_params"]["EST_TRIM_ROLL"], abs=1e-6)
    import pandas as pd

    history = pd.read_parquet(tmp_path / "out" / "dataset" / "search" / "trials.parquet")
    assert len(history) == 10 and history["value"].min() == pytest.approx(found["best_value"])
    # the same command again resumes the study: nothing left to fly
    again = json.loads(campaign(tmp_path, SEARCH, "--search", "--json").stdout)
    assert again["trials"] == 10 and again["best_value"] == found["best_value"]


@pytest.mark.parametrize(("table", "message"), [
    ("", "--search needs a [search] table"),
    ("[search]\nmetric = 'roll_rmse_deg'\ntrials = 2\n[search.params]\nNOPE_X = [0, 1]\n",
     "NOPE_X: unknown parameter"),
    ("[search]\nmetric = 'roll_rmse_deg'\ntrials = 2\n[search.params]\nCTL_ROLL_KP = [1, 1]\n",
     "empty range"),
    ("[search]\nmetric = 'roll_rmse_deg'\ntrials = 2\n[search.params]\nCTL_ROLL_KP = [1, 99]\n",
     "CTL_ROLL_KP"),
    ("[search]\nmetric = 'happiness'\ntrials = 2\n[search.params]\nCTL_ROLL_KP = [1, 2]\n",
     "unknown metric 'happiness'"),
    ("[search]\nmetric = 'roll_rmse_deg'\ntrials = 0\n[search.params]\nCTL_ROLL_KP = [1, 2]\n",
     "trials = 0"),
])
def test_a_bad_search_is_refused_before_anything_flies(
        tmp_path: Path, table: str, message: str) -> None:
    proc = campaign(tmp_path, "duration_s = 5\n" + table, "--search")
    assert proc.returncode == 2 and message in proc.stderr and "spec.toml" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


def test_a_full_output_disk_records_each_flight_failed_and_ends_in_one_line(
        tmp_path: Path) -> None:
    spec = tmp_path / "spec.toml"
    spec.write_text("duration_s = 5\nscenario = 'level'\n[grid]\nseed = [1, 2]\n",
                    encoding="utf-8")
    disk = tmp_path / "disk"
    disk.mkdir()
    # a 150 kB file system of its own (a private mount namespace): the state fits, a flight not
    script = ('mount -t tmpfs -o size=150k tmpfs "$0" && exec "$1" -m companion sim --campaign '
              '"$2" --campaign-dir "$0/out" --jobs 1')
    probe = subprocess.run(["unshare", "-m", "true"], capture_output=True, timeout=30)
    if probe.returncode != 0:
        pytest.skip("needs a private mount namespace (unshare -m) for a small file system")
    proc = subprocess.run(["unshare", "-m", "sh", "-c", script, str(disk), sys.executable,
                           str(spec)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert lines[-1].startswith(f"companion sim: --campaign-dir {disk}/out: ")
    assert "No space left on device" in lines[-1]
    failed = [line for line in lines if "FAILED (output" in line]
    assert len(failed) == 2 and all("No space left on device" in line for line in failed)


def _sigint_default() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _sigint_ignored() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.parametrize(("sig", "inherited"), [
    (signal.SIGINT, _sigint_default),
    # `companion sim --campaign ... &` in a script or a CI step: the shell starts it with
    # SIGINT ignored, and Python keeps that unless the command takes the signal over
    (signal.SIGINT, _sigint_ignored),
    (signal.SIGTERM, _sigint_default),
], ids=["SIGINT", "SIGINT-ignored-at-start", "SIGTERM"])
def test_ctrl_c_stops_the_flights_under_way_and_says_how_to_go_on(
        tmp_path: Path, sig: signal.Signals, inherited: Callable[[], None]) -> None:
    spec = tmp_path / "spec.toml"
    spec.write_text(RESUME_SPEC, encoding="utf-8")
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "companion", "sim", "--campaign", str(spec),
                             "--campaign-dir", str(out), "--jobs", "1"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=inherited)
    assert proc.stderr is not None
    for line in proc.stderr:
        if line.startswith("[1/3]"):
            break
    deadline = time.monotonic() + 30
    while not _flight_processes(out) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert _flight_processes(out), "the second flight never started"
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + sig, err
    assert err.strip().splitlines()[-1] == (
        f"companion sim: campaign interrupted; run the same command again to fly the rest "
        f"({out})")
    assert _flight_processes(out) == []
    saved = json.loads((out / "campaign.json").read_text())
    assert saved["interrupted"] and saved["ok"] == 1
    assert sorted(p.name for p in (out / "runs").glob("*.json")) == ["0001.json"]
