"""The `companion` command line: parameters, configuration errors, docs generation."""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.cli import main
from companion.core.config import ConfigError, apply_override, load_config
from companion.docgen import reference
from companion.vehicle import load_vehicle_config

ROOT = Path(__file__).resolve().parents[1]


def test_parameter_docs_are_current() -> None:
    text = (ROOT / "docs" / "parameters.md").read_text(encoding="utf-8")
    assert text == reference(), "docs/parameters.md is stale: run `make docs`"
    assert "`AP_IMU_HZ`" in text  # every row's parameters, the autopilot link's too


def test_params_set_get_export_import(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pfile = tmp_path / "p.parm"
    assert main(["params", "--file", str(pfile), "set", "IMU_WDG_MS", "321"]) == 0
    assert main(["params", "--file", str(pfile), "get", "IMU_WDG_MS"]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == "321"
    assert main(["params", "--file", str(pfile), "set", "IMU_WDG_MS", "1"]) == 2
    assert "out of range" in capsys.readouterr().err
    out = tmp_path / "all.params"
    assert main(["params", "--file", str(pfile), "export", str(out)]) == 0
    text = out.read_text()
    assert "\tIMU_WDG_MS\t321\t6" in text and "MGR_WDG_GRAN_MS" in text
    other = tmp_path / "q.parm"
    assert main(["params", "--file", str(other), "import", str(out)]) == 0
    assert "IMU_WDG_MS       321" in other.read_text()
    assert main(["params", "--file", str(pfile), "show"]) == 0
    shown = capsys.readouterr().out
    assert "IMU_WDG_MS" in shown and "*" in shown


def test_damaged_param_file_is_reported_by_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pfile = tmp_path / "p.parm"
    pfile.write_text("IMU_WDG_MS 400\nGARBAGE LINE HERE\n")
    assert main(["params", "--file", str(pfile), "get", "IMU_WDG_MS"]) == 0
    captured = capsys.readouterr()
    assert captured.out.strip() == "400"
    assert f"{pfile}:2:" in captured.err


def test_config_file_and_overrides(tmp_path: Path) -> None:
    cfg_file = tmp_path / "a.toml"
    cfg_file.write_text('[vehicle]\nid = 7\n[devices.imu]\nport = "/dev/ttyUSB3"\n')
    cfg = load_vehicle_config(cfg_file)
    assert cfg.vehicle.id == 7 and cfg.devices["imu"].port == "/dev/ttyUSB3"
    assert cfg.devices["imu"].baud == 115200 and cfg.devices["servo"].port == "/dev/ttyS2"
    apply_override(cfg, "devices.gps.baud=57600")
    apply_override(cfg, "mavlink.endpoints=udpout:127.0.0.1:14551,tcpin:127.0.0.1:5760")
    assert cfg.devices["gps"].baud == 57600
    assert cfg.mavlink.endpoints == ["udpout:127.0.0.1:14551", "tcpin:127.0.0.1:5760"]
    with pytest.raises(ConfigError, match="unknown setting 'devices.imu.speed'"):
        apply_override(cfg, "devices.imu.speed=9600")
    with pytest.raises(ConfigError, match="must be int"):
        apply_override(cfg, "vehicle.id=seven")
    with pytest.raises(ConfigError, match=r"unknown setting 'devices.baro' "
                                          r"\(known: imu, gps, servo, autopilot\)"):
        apply_override(cfg, "devices.baro.port=/dev/ttyS9")
    baro = tmp_path / "baro.toml"
    baro.write_text('[devices.baro]\nport = "/dev/ttyS9"\n')
    with pytest.raises(ConfigError, match=r"baro.toml: unknown device 'devices.baro' "
                                          r"\(known: imu, gps, servo, autopilot\)"):
        load_vehicle_config(baro)
    bad = tmp_path / "bad.toml"
    bad.write_text("[vehicle]\nidd = 3\n")
    with pytest.raises(ConfigError, match=r"bad.toml: unknown setting 'vehicle.idd'"):
        load_config(bad)
    broken = tmp_path / "broken.toml"
    broken.write_text("[vehicle\n")
    with pytest.raises(ConfigError, match="broken.toml"):
        load_config(broken)


def test_cli_reports_config_errors_without_traceback(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[logs]\nenabled = 3\n")
    assert main(["run", "--config", str(bad), "--duration", "1"]) == 2
    assert "configuration error" in capsys.readouterr().err
