"""A lockstep flight's logs depend on its seed and configuration only: not on whether its
parameter file exists yet (the first flight in a fresh directory writes it, later ones read it
back as float32), nor on what else runs on the machine."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ARGS = ["sim", "--lockstep", "--duration", "20", "--seed", "7", "--scenario", "mixed",
        "--no-legacy", "--mavlink", "none"]


def fly(cwd: Path) -> subprocess.Popen[bytes]:
    """`companion sim` in `cwd`, with its parameter file and flights there (as a user runs it)."""
    cwd.mkdir(parents=True, exist_ok=True)
    return subprocess.Popen([sys.executable, "-m", "companion", *ARGS, "--log-dir", "flights"],
                            cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])})


def logs(cwd: Path) -> dict[str, bytes]:
    (flight,) = sorted((cwd / "flights").iterdir())[-1:]
    return {p.name: p.read_bytes() for p in sorted(flight.glob("*.bin"))}


def finish(proc: subprocess.Popen[bytes]) -> None:
    _, err = proc.communicate(timeout=240)
    assert proc.returncode == 0, err.decode(errors="replace")[-2000:]


def test_a_flight_in_a_fresh_directory_flies_as_one_after_it_and_one_on_a_busy_machine(
        tmp_path: Path) -> None:
    fresh = tmp_path / "fresh"
    finish(fly(fresh))
    assert (fresh / "params.parm").is_file()  # the first flight wrote it
    first = logs(fresh)
    assert {"estimator.bin", "imu.bin", "gps.bin", "control.bin", "truth.bin"} <= set(first)
    for p in (fresh / "flights").iterdir():  # the second flight reads the file back
        for f in p.iterdir():
            f.unlink()
        p.rmdir()
    finish(fly(fresh))
    second = logs(fresh)
    for name in first:
        assert first[name] == second[name], f"{name}: the second flight differs from the first"
    # two more at once, beside a process that keeps a core busy
    burner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        procs = [fly(tmp_path / "busy-a"), fly(tmp_path / "busy-b")]
        for proc in procs:
            finish(proc)
    finally:
        burner.kill()
        burner.wait()
    for other in ("busy-a", "busy-b"):
        theirs = logs(tmp_path / other)
        for name in first:
            assert first[name] == theirs[name], f"{name} differs in a flight on a busy machine"


@pytest.mark.parametrize("text", ["0.015", "0.1", "1e-7"])
def test_a_float_parameter_has_one_value_whatever_its_source(tmp_path: Path, text: str) -> None:
    """Its declared default, the value a file gives back, and what a ground station sets are
    the same float32."""
    from companion.core.params import ParamRegistry, float_param

    spec = float_param("TST_VALUE", float(text), 0.0, 1.0)
    reg = ParamRegistry()
    reg.declare(spec)
    default = reg.get("TST_VALUE")
    path = tmp_path / "p.parm"
    reg.attach_file(path)
    reg.set("TST_VALUE", float(text))
    reg.flush()
    again = ParamRegistry()
    again.declare(spec)
    again.attach_file(path)
    assert default == again.get("TST_VALUE") == reg.get("TST_VALUE") == spec.default
