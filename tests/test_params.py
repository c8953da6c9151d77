"""Parameter registry: validation, notification, persistence and parameter files."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from companion.core.params import (
    ParamError,
    ParamRegistry,
    ParamSpec,
    ParamType,
    float_param,
    int_param,
    parse_param_file,
)


def registry() -> ParamRegistry:
    reg = ParamRegistry()
    reg.declare_all([
        int_param("IMU_WDG_MS", 500, 10, 60_000, "ms", "watchdog"),
        float_param("EST_GYRO_NSD", 0.01, 0.0, 1.0, "rad/s", "gyro noise"),
        int_param("SYS_VERSION", 3, 0, 100, "", "version", read_only=True),
    ])
    return reg


def test_names_and_metadata_are_checked() -> None:
    with pytest.raises(ValueError, match="GROUP_NAME"):
        int_param("lowercase_name", 1, 0, 2)
    with pytest.raises(ValueError, match="at most 16"):
        int_param("ABCDEFGHIJ_KLMNOPQ", 1, 0, 2)
    with pytest.raises(ValueError, match="outside"):
        ParamSpec("A_B", ParamType.INT32, 5, 0, 2)
    reg = registry()
    with pytest.raises(ValueError, match="twice"):
        reg.declare(int_param("IMU_WDG_MS", 400, 10, 60_000))


def test_set_validates_and_explains_refusals() -> None:
    reg = registry()
    assert reg.set("IMU_WDG_MS", 250) == 250
    assert reg.set("IMU_WDG_MS", 300.0) == 300
    with pytest.raises(ParamError, match=r"out of range: 5 not in \[10, 60000\] ms"):
        reg.set("IMU_WDG_MS", 5)
    with pytest.raises(ParamError, match="not an integer"):
        reg.set("IMU_WDG_MS", 12.5)
    with pytest.raises(ParamError, match="read-only"):
        reg.set("SYS_VERSION", 4)
    with pytest.raises(ParamError, match="unknown parameter"):
        reg.set("NOPE_X", 1)
    with pytest.raises(ParamError, match="not finite"):
        reg.set("EST_GYRO_NSD", float("nan"))
    assert reg.get("IMU_WDG_MS") == 300
    # float32 precision is what the parameter really has
    assert reg.set("EST_GYRO_NSD", 0.1) == pytest.approx(0.1, rel=1e-7)
    assert reg.get("EST_GYRO_NSD") != 0.1


def test_listeners_hear_changes_only() -> None:
    reg = registry()
    heard: list[tuple[str, float]] = []
    unsubscribe = reg.subscribe(lambda n, v: heard.append((n, v)))
    reg.set("IMU_WDG_MS", 250)
    reg.set("IMU_WDG_MS", 250)
    unsubscribe()
    reg.set("IMU_WDG_MS", 260)
    assert heard == [("IMU_WDG_MS", 250)]


def test_persistence_across_restart(tmp_path: Path) -> None:
    path = tmp_path / "params.parm"
    reg = registry()
    assert reg.attach_file(path) == []
    reg.set("IMU_WDG_MS", 750)
    reg.set("EST_GYRO_NSD", 0.25)
    assert reg.dirty and reg.flush() and not reg.dirty
    again = registry()
    assert again.attach_file(path) == []
    assert again.get("IMU_WDG_MS") == 750
    assert again.get("EST_GYRO_NSD") == pytest.approx(0.25)


def test_damaged_file_reports_lines_and_keeps_defaults(tmp_path: Path) -> None:
    path = tmp_path / "params.parm"
    path.write_bytes(
        b"# comment\n"
        b"IMU_WDG_MS 900\n"
        b"EST_GYRO_NSD banana\n"
        b"NOPE_PARAM 3\n"
        b"IMU_WDG_MS\n"
        b"\xff\xfe garbage\n"
        b"EST_GYRO_NSD 7\n"
    )
    reg = registry()
    issues = reg.attach_file(path)
    assert [i.line for i in issues] == [3, 4, 5, 6, 7]
    assert "not a number" in issues[0].reason
    assert "unknown parameter" in issues[1].reason
    assert "expected 'NAME VALUE'" in issues[2].reason
    assert "not UTF-8" in issues[3].reason
    assert "out of range" in issues[4].reason
    assert str(path) in str(issues[0]) and ":3:" in str(issues[0])
    assert reg.get("IMU_WDG_MS") == 900  # the good line still applies
    assert reg.get("EST_GYRO_NSD") == pytest.approx(0.01)


def test_qgc_and_mavproxy_formats_round_trip(tmp_path: Path) -> None:
    reg = registry()
    reg.set("IMU_WDG_MS", 123)
    reg.set("EST_GYRO_NSD", 0.5)
    for fmt, suffix in (("params", ".params"), ("parm", ".parm")):
        out = tmp_path / f"export{suffix}"
        reg.save(out, fmt=fmt, sysid=7, compid=1)
        text = out.read_text()
        if fmt == "params":
            assert "7\t1\tIMU_WDG_MS\t123\t6" in text
            assert "7\t1\tEST_GYRO_NSD\t0.5\t9" in text
        other = registry()
        assert other.load(out) == []
        assert other.get("IMU_WDG_MS") == 123 and other.get("EST_GYRO_NSD") == 0.5
    rows = [(n, v) for _, n, _, v, p in parse_param_file(tmp_path / "export.params") if p is None]
    assert ("IMU_WDG_MS", 123.0) in rows


def test_sigkill_during_writes_never_leaves_a_torn_file(tmp_path: Path) -> None:
    path = tmp_path / "params.parm"
    script = textwrap.dedent(f"""
        import sys
        from pathlib import Path
        from companion.core.params import ParamRegistry, int_param
        reg = ParamRegistry()
        reg.declare_all([int_param(f"T_P{{i:03d}}", 0, 0, 10**9) for i in range(300)])
        reg.attach_file(Path({str(path)!r}))
        n = 0
        while True:
            n += 1
            for i in range(300):
                reg.set(f"T_P{{i:03d}}", n)
            reg.flush()
            if n == 3:
                print("ready", flush=True)
    """)
    for _ in range(3):
        proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE)
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == b"ready"
        time.sleep(0.05 + 0.03 * _)  # kill at some arbitrary moment in the write loop
        proc.send_signal(signal.SIGKILL)
        proc.wait(5)
        proc.stdout.close()
        rows = list(parse_param_file(path))
        assert len(rows) == 300 and all(p is None for *_, p in rows)
        values = {v for _, _, _, v, _ in rows}
        assert len(values) == 1, "a file mixing two generations was left behind"
    leftovers = [p for p in tmp_path.iterdir() if p.name != "params.parm"]
    # a kill between mkstemp and rename may leave one temp file, never a damaged params.parm
    assert all(p.name.endswith(".tmp") for p in leftovers)
