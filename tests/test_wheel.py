"""The wheel works away from the repository.

`pip wheel` builds the project from a copy of its packaged sources, the wheel is installed into a
new virtual environment, and the installed `companion` flies a SITL flight and converts its log
with its working directory outside the repository and a clean environment (no PYTHONPATH).

The dependencies are not installed again (that would need the network and minutes): the new
environment reaches the test environment's site-packages through a path line in a `.pth` file.
Python adds such a line to sys.path but does not process the `.pth` files inside the directory it
names, so the repository's editable-install hook (a `.pth` there) is not loaded: the test checks
that `companion` is not importable before the wheel is installed, and is imported from the new
environment after.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import sysconfig
import tomllib
import zipfile
from importlib import metadata
from pathlib import Path

from conftest import free_udp_port
from packaging.requirements import Requirement

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("companion", "gcs_bridge", "horizon", "legacy_protocol")
SOURCES = ("pyproject.toml", "README.md", "LICENSE", *PACKAGES)
FLIGHT_S = 10
BUILD_TIMEOUT_S = 120.0
VENV_TIMEOUT_S = 60.0
RUN_TIMEOUT_S = 60.0
SIM_TIMEOUT_S = 90.0


def _run(cmd: list[str], *, cwd: Path, env: dict[str, str] | None = None,
         timeout: float = RUN_TIMEOUT_S, hint: str = "") -> subprocess.CompletedProcess[str]:
    done = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout, stdin=subprocess.DEVNULL)
    assert done.returncode == 0, (
        f"{' '.join(cmd)} exited with {done.returncode}{hint}\n"
        f"stdout:\n{done.stdout[-3000:]}\nstderr:\n{done.stderr[-3000:]}")
    return done


def _backend_installed() -> bool:
    """Whether this environment has the build backend pyproject.toml asks for (then the build
    needs no network: --no-build-isolation)."""
    requires = tomllib.loads((REPO / "pyproject.toml").read_text())["build-system"]["requires"]
    for text in requires:
        req = Requirement(text)
        if req.name == "wheel":
            continue  # setuptools >= 70.1 builds wheels itself; "wheel" is only for older ones
        try:
            have = metadata.version(req.name)
        except metadata.PackageNotFoundError:
            return False
        if not req.specifier.contains(have, prereleases=True):
            return False
    return True


def _build_wheel(tmp: Path) -> Path:
    """Build from a copy of the packaged sources: no build/ or egg-info left in the repository,
    no stale build/lib files in the wheel."""
    src = tmp / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in SOURCES:
        path = REPO / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=ignore)
        else:
            shutil.copy2(path, src / name)
    # Offline when the backend is here; otherwise pip fetches it from the package index (a venv
    # made by `python3.11 -m venv` has setuptools 65, older than the >=77 that PEP 639's
    # `license = "MIT"` needs).
    offline = _backend_installed()
    isolation = ["--no-build-isolation"] if offline else ["--retries", "1", "--timeout", "15"]
    hint = "" if offline else (
        " (this environment lacks the build backend that pyproject.toml's [build-system] names,"
        " so pip had to fetch it from the package index; with it installed, e.g."
        " `pip install 'setuptools>=77'`, the build needs no network)")
    dist = tmp / "dist"
    _run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--quiet",
          "--disable-pip-version-check", *isolation, "-w", str(dist)],
         cwd=tmp, timeout=BUILD_TIMEOUT_S, hint=hint)
    (wheel,) = dist.glob("uav_companion-*.whl")
    return wheel


def _check_contents(wheel: Path) -> None:
    """Every module of the four packages is in the wheel (companion/drivers, for one, has no
    __init__.py and is found only as a namespace package), and the entry point is declared."""
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
        entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
        assert "companion = companion.cli:main" in zf.read(entry_points).decode()
    missing = [str(p.relative_to(REPO)) for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")
               if "__pycache__" not in p.parts and str(p.relative_to(REPO)) not in names]
    assert not missing, f"modules missing from the wheel: {missing}"
    assert not [n for n in names if n.startswith(("tests/", "bench/", "docs/"))]


def _make_venv(tmp: Path) -> tuple[Path, dict[str, str]]:
    venv = tmp / "venv"
    _run([sys.executable, "-m", "venv", str(venv)], cwd=tmp, timeout=VENV_TIMEOUT_S)
    py = venv / "bin" / "python"
    site = _run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                cwd=tmp).stdout.strip()
    ours = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (Path(site) / "uav_companion_test_deps.pth").write_text("".join(f"{p}\n" for p in ours))
    env = {"PATH": f"{venv / 'bin'}{os.pathsep}{os.defpath}", "HOME": str(tmp),
           "LANG": "C.UTF-8", "TMPDIR": str(tmp)}
    return venv, env


def test_wheel_installs_and_flies_away_from_the_repository(tmp_path: Path) -> None:
    wheel = _build_wheel(tmp_path)
    _check_contents(wheel)
    venv, env = _make_venv(tmp_path)
    py, companion = str(venv / "bin" / "python"), str(venv / "bin" / "companion")
    work = tmp_path / "work"
    work.mkdir()

    probe = ("import importlib.util as u; "
             "print(*(u.find_spec(n) is not None for n in ('companion', 'numpy', 'jsbsim')))")
    assert _run([py, "-c", probe], cwd=work, env=env).stdout.split() == ["False", "True", "True"], \
        "the new environment must see the dependencies but not the repository"

    _run([py, "-m", "pip", "install", "--no-deps", "--no-index", "--quiet",
          "--disable-pip-version-check", str(wheel)], cwd=work, env=env)
    where = _run([py, "-c", "import json, companion, gcs_bridge, horizon, legacy_protocol as l; "
                  "print(json.dumps([m.__file__ for m in (companion, gcs_bridge, horizon, l)]))"],
                 cwd=work, env=env)
    for path in json.loads(where.stdout):
        assert Path(path).resolve().is_relative_to(venv.resolve()), path
        assert not Path(path).resolve().is_relative_to(REPO), path

    version = _run([companion, "--version"], cwd=work, env=env)
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert version.stdout.strip() == f"companion {project['version']}"

    # Loopback only: MAVLink to a socket of this test, the legacy protocol bound to 127.0.0.1.
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
        gcs.bind(("127.0.0.1", 0))
        gcs.setblocking(False)
        sim = _run([companion, "sim", "--duration", str(FLIGHT_S), "--fast", "--json",
                    "--scenario", "turns", "--log-dir", str(work / "flights"),
                    "--params-file", str(work / "params.parm"),
                    "--mavlink", f"udpout:127.0.0.1:{gcs.getsockname()[1]}",
                    "--set", "legacy.bind=127.0.0.1",
                    "--legacy-listen", str(free_udp_port()),
                    "--legacy-dest", f"127.0.0.1:{free_udp_port()}"],
                   cwd=work, env=env, timeout=SIM_TIMEOUT_S)
        frames = []
        while True:
            try:
                frames.append(gcs.recv(65536))
            except BlockingIOError:
                break
    summary = json.loads(sim.stdout)
    assert summary["stop_reason"] == "duration", summary["stop_reason"]
    assert summary["simulator"]["sim_time_s"] > FLIGHT_S * 0.8, summary["simulator"]
    threads = {t["name"]: t for t in summary["threads"]}
    assert set(threads) >= {"imu", "gps", "servo", "estimator", "control"}
    assert all(t["cycles"] > 0 and not t["failed"] for t in threads.values()), threads
    assert frames and all(f[0] == 0xFD for f in frames), "no MAVLink 2 frames from the bridge"

    flight = Path(summary["flight_dir"])
    assert flight.parent.resolve() == (work / "flights").resolve()
    converted = _run([companion, "logs", "convert", str(flight / "imu.bin")], cwd=work, env=env)
    csvs = [Path(p) for p in converted.stdout.split()]
    assert csvs and all(p.parent == flight and p.name.startswith("imu_fmt") for p in csvs)
    rows = [ln for ln in csvs[0].read_text().splitlines() if ln and not ln.startswith("%")]
    assert len(rows) > 100, f"{csvs[0]}: {len(rows)} rows"
