"""The estimation bench runs end to end on a tiny configuration and writes sane figures."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench" / "estimation_bench.py"


def test_bench_smoke(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = importlib.util.spec_from_file_location("estimation_bench", BENCH)
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    out = tmp_path / "figures.json"
    assert bench.main(["--quick", "--trials", "1", "--duration-s", "30", "--json", str(out)]) == 0
    figures = json.loads(out.read_text())
    att, esk = figures["attitude"], figures["eskf"]
    assert 0.0 < att["inclination_rmse_deg_mean"] < 2.0
    assert att["step_us_median"] > 0.0
    assert 0.0 < esk["inclination_rmse_deg"] < 2.0
    assert 0.0 < esk["position_rmse_m"] < 2.0
    assert esk["faults"] == 0
    assert math.isfinite(esk["predict_us_median"])
    assert "ESKF" in capsys.readouterr().out
