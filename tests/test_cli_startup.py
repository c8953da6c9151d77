"""Commands start fast: none imports numpy, OpenCV or pymavlink unless it uses them.

Every `companion` command builds the whole parser (each sub-command's provider is imported, so
a broken installation stops at start); those providers keep their heavy imports inside the
commands. Checked in a fresh interpreter, as a user runs the command.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from conftest import data_file

HEAVY = ("numpy", "cv2", "pymavlink", "matplotlib", "scipy", "jsbsim", "rerun", "pandas",
         "pyarrow", "duckdb")
PROBE = """
import json, sys, runpy
sys.argv = ["companion", *json.loads(sys.argv[1])]
try:
    runpy.run_module("companion", run_name="__main__")
except SystemExit:
    pass
sys.stderr.write("\\nMODULES " + json.dumps(sorted(m for m in sys.modules)) + "\\n")
"""


def imported_by(*argv: str) -> set[str]:
    out = subprocess.run([sys.executable, "-c", PROBE, json.dumps(list(argv))],
                         capture_output=True, text=True, timeout=120,
                         cwd=Path(__file__).resolve().parents[1])
    line = next(ln for ln in out.stderr.splitlines() if ln.startswith("MODULES "))
    return {m.split(".")[0] for m in json.loads(line.removeprefix("MODULES "))}


def test_help_imports_no_heavy_library() -> None:
    loaded = imported_by("--help")
    assert "companion" in loaded
    assert not loaded & set(HEAVY), sorted(loaded & set(HEAVY))


def test_logs_info_imports_only_what_reading_a_log_needs() -> None:
    loaded = imported_by("logs", "info", str(data_file("vectors", "log-example.bin")))
    assert "numpy" in loaded  # the reader's arrays
    assert not loaded & {"cv2", "pymavlink", "matplotlib", "scipy", "jsbsim", "rerun",
                         "pandas", "duckdb"}, sorted(loaded & set(HEAVY))
