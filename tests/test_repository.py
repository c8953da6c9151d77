"""The repository stands alone: no tracked file names a path outside it (see .ci/check-paths)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from conftest import DATA, HORIZON_DEV, VECTORS

REPO = Path(__file__).resolve().parents[1]
CHECK = REPO / ".ci" / "check-paths"


def _check(repo: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(CHECK), str(repo)], capture_output=True,
                          text=True, timeout=60)


def test_no_tracked_file_names_a_path_outside_the_repository() -> None:
    result = _check(REPO)
    assert result.returncode == 0, result.stderr


def _git(repo: Path, *args: str) -> None:
    subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True, timeout=60)


def test_the_check_finds_machine_paths_and_sibling_directories(tmp_path: Path) -> None:
    repo = tmp_path / "r"
    repo.mkdir()
    _git(repo, "init", "-q")
    home = "/" + "home/alice/data.csv"  # split so this file does not trip the check itself
    sibling = "../" + "sha" + "red/specs/log.md"
    (repo / "a.py").write_text(f'PATH = "{home}"\nok = "/dev/ttyUSB0"\n')
    (repo / "b.md").write_text(f"see [the spec]({sibling})\n")
    (repo / "c.bin").write_bytes(b"\0" + home.encode())  # binary files are not text
    _git(repo, "add", ".")
    result = _check(repo)
    assert result.returncode == 1
    lines = result.stderr.splitlines()
    assert any(line.startswith("a.py:1: absolute path of a machine") for line in lines)
    assert any(line.startswith("b.md:1: path to a sibling directory") for line in lines)
    assert not any(line.startswith(("a.py:2", "c.bin")) for line in lines)


def test_only_ci_and_the_makefile_may_name_the_peer_tools(tmp_path: Path) -> None:
    """`.ci/run` and the Makefile may point at the peer programs beside the checkout (a real
    autopilot's SITL); any other file may not, and those two may name nothing else outside."""
    repo = tmp_path / "r"
    (repo / ".ci").mkdir(parents=True)
    _git(repo, "init", "-q")
    tools = "../" + "sha" + "red/tools/ardupilot/arduplane"  # split: see above
    specs = "../" + "sha" + "red/specs/x.md"
    home = "/" + "home/alice/tools/arduplane"
    (repo / ".ci" / "run").write_text(f'sitl="$here/{tools}"\nspec="{specs}"\n')
    (repo / "Makefile").write_text(f"ARDUPILOT_SITL ?= $(wildcard {tools})\nX := {home}\n")
    (repo / "README.md").write_text(f"run `{tools}`\n")
    (repo / "tests").mkdir()
    (repo / "tests" / "Makefile").write_text(f"S := {tools}\n")  # only the root Makefile
    _git(repo, "add", ".")
    result = _check(repo)
    assert result.returncode == 1
    lines = result.stderr.splitlines()
    assert not any(line.startswith((".ci/run:1:", "Makefile:1:")) for line in lines)
    assert any(line.startswith(".ci/run:2: path to a sibling directory") for line in lines)
    assert any(line.startswith("Makefile:2: absolute path of a machine") for line in lines)
    assert any(line.startswith("README.md:1: path to a sibling directory") for line in lines)
    assert any(line.startswith("tests/Makefile:1: path to a sibling directory") for line in lines)


def test_the_data_the_tests_read_is_in_the_repository() -> None:
    tracked = subprocess.run(["git", "-C", str(REPO), "ls-files", "tests/data"],
                             capture_output=True, text=True, check=True, timeout=60).stdout.split()
    assert "tests/data/README.md" in tracked
    assert "tests/data/horizon-dev/LICENSE" in tracked
    vectors = {p.name for p in VECTORS.iterdir()}
    assert {"devices.json", "imu-cycle.bin", "legacy-udp.json", "log-example.bin"} <= vectors
    images = [p for p in tracked if p.startswith("tests/data/horizon-dev/images/")]
    assert len(images) == 108
    assert (HORIZON_DEV / "gt.csv").is_file() and DATA.is_dir()
