"""One machine-readable result per benchmark run: what docs/benchmarks.md is rendered from.

A benchmark makes a `Result` when it starts (the load average is read then), records each
figure and table as it prints it, and calls `write()` at the end, which adds the load after,
the wall time, the commit and the machine and writes `bench/results/<date>-<name>.json`.
`bench/render.py` turns the newest result of each benchmark into the page's generated blocks
and marks it stale when the code it measured (`paths_measured`) changed after its commit.

Why one helper: the page can only say which commit and load a figure belongs to if every
benchmark records them the same way; tables are printed from the same rows that are stored,
so what a run prints is what the page will show.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import platform
import re
import shlex
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TextIO

ROOT = Path(__file__).resolve().parents[1]
RESULTS_DIR = ROOT / "bench" / "results"
SCHEMA = 1
"""Bumped when the layout of the file changes; the renderer reads this one."""

Cell = str | int | float | None


def _git(*args: str) -> str | None:
    """A git command's output in the repository, or None without git or history."""
    try:
        done = subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True,
                              timeout=20, check=True)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip()


def machine() -> dict[str, Any]:
    """What the figures were measured on: a figure only compares with one from the same kind
    of machine."""
    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8").splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpus": os.cpu_count(), "cpu": model, "kernel": platform.release(),
            "python": platform.python_version()}


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


class Result:
    """The figures of one run of one benchmark.

    `name` is the benchmark's block on the page (`<!-- bench:NAME -->`); `paths_measured` are
    the repository paths whose code the figures depend on (the benchmark script is added), so
    that a later change to them marks the figures stale.
    """

    def __init__(self, name: str, paths_measured: list[str], *, quick: bool = False,
                 argv: list[str] | None = None) -> None:
        self.name = name
        script = Path(sys.argv[0]).resolve()
        # the benchmark's own script is part of what it measures (not a runner such as
        # pytest's, which may live in a virtualenv inside the checkout)
        own = ([str(script.relative_to(ROOT))]
               if script.is_relative_to(ROOT / "bench") else [])
        self.paths_measured = sorted(set(paths_measured) | set(own))
        self.quick = quick
        args = sys.argv[1:] if argv is None else argv
        self.command = shlex.join(["python", *(own or sys.argv[:1]), *args])
        self.started = datetime.now(UTC)
        self._t0 = time.monotonic()
        self.load_before = _load()
        # the code measured is what was checked out when the run began
        self.commit = _git("rev-parse", "HEAD") or "unknown"
        dirty = _git("status", "--porcelain", "--", *self.paths_measured)
        self.uncommitted = sorted(line[3:] for line in (dirty or "").splitlines())
        self.figures: dict[str, dict[str, Any]] = {}
        self.tables: list[dict[str, Any]] = []
        self.notes: list[str] = []
        self.data: dict[str, Any] = {}
        """Everything else the benchmark measured (per-run detail the page does not show)."""

    def figure(self, key: str, value: float | int | str, unit: str = "",
               label: str = "") -> float | int | str:
        """Records one figure (returned, so it can be used inline)."""
        if isinstance(value, float):
            value = round(value, 6)
        self.figures[key] = {"value": value, "unit": unit, "label": label or key}
        return value

    def table(self, title: str, columns: list[str], rows: list[list[Cell]],
              note: str = "") -> None:
        """Records a table and prints it as markdown, the way the page will render it."""
        self.tables.append({"title": title, "columns": list(columns),
                            "rows": [list(r) for r in rows], "note": note})
        print(f"\n### {title}\n" if title else "")
        print(markdown_table(columns, rows))
        if note:
            print(f"\n{note}")
        sys.stdout.flush()

    def note(self, text: str) -> None:
        """A sentence the page shows under the tables (e.g. what a run left out)."""
        self.notes.append(text)
        print(f"\n{text}", flush=True)

    @contextlib.contextmanager
    def capture(self) -> Iterator[None]:
        """Records the markdown a benchmark prints (headings, tables, the text around them)
        while still printing it: for benchmarks that format their own tables."""
        tee = _Tee(sys.stdout)
        sys.stdout = tee
        try:
            yield
        finally:
            sys.stdout = tee.out
            printed, found = split_json_lines(tee.buf.getvalue())
            if found:
                self.data["printed_json"] = found
            tables = parse_markdown(printed)
            # a benchmark that prints plain text is kept as printed (the page shows it as such)
            self.tables += tables or ([{"title": "", "text": printed.strip("\n")}]
                                      if printed.strip() else [])

    def as_dict(self) -> dict[str, Any]:
        return {
            "schema": SCHEMA, "name": self.name, "command": self.command, "commit": self.commit,
            "uncommitted_changes": self.uncommitted,
            "date": self.started.strftime("%Y-%m-%dT%H:%M:%SZ"), "quick": self.quick,
            "machine": machine(), "load_before": self.load_before, "load_after": _load(),
            "wall_s": round(time.monotonic() - self._t0, 1),
            "paths_measured": self.paths_measured, "figures": self.figures,
            "tables": self.tables, "notes": self.notes, "data": self.data,
        }

    def write(self, directory: Path | None = None) -> Path | None:
        """Writes the result; a `--quick` run's figures are not comparable, so it is written
        only when a directory is given (BENCH_RESULTS_DIR or the argument)."""
        env = os.environ.get("BENCH_RESULTS_DIR")
        if directory is None and env:
            directory = Path(env)
        if directory is None:
            if self.quick:
                print("(quick run: no result written)", file=sys.stderr)
                return None
            directory = RESULTS_DIR
        data = self.as_dict()
        directory.mkdir(parents=True, exist_ok=True)
        path = directory / f"{self.started:%Y-%m-%d}-{self.name}.json"
        path.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
        print(f"\n(result: {path}; load {data['load_before'][0]:.2f} before, "
              f"{data['load_after'][0]:.2f} after, {data['wall_s']:.0f} s)", file=sys.stderr)
        return path


def fmt(cell: Cell) -> str:
    """A cell as the page shows it: floats keep the digits the benchmark rounded them to."""
    if cell is None:
        return "-"
    if isinstance(cell, float):
        return f"{cell:,}" if abs(cell) >= 1000 else f"{cell:g}"
    if isinstance(cell, int) and not isinstance(cell, bool):
        return f"{cell:,}"
    return str(cell)


def markdown_table(columns: list[str], rows: list[list[Cell]]) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(fmt(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def split_row(row: str) -> list[Cell]:
    """The cells of a markdown table row a benchmark formatted itself (`| a | b |`)."""
    return [c.strip() for c in row.strip().strip("|").split(" | ")]


class _Tee(io.TextIOBase):
    def __init__(self, out: TextIO) -> None:
        self.out = out
        self.buf = io.StringIO()

    def write(self, text: str) -> int:
        self.buf.write(text)
        return self.out.write(text)

    def flush(self) -> None:
        self.out.flush()


def parse_markdown(text: str) -> list[dict[str, Any]]:
    """Tables of printed markdown: each with the heading above it (title), the text between
    heading and table (intro) and the text after it up to the next heading or table (note)."""
    tables: list[dict[str, Any]] = []
    title = ""
    intro: list[str] = []
    rows: list[list[Cell]] = []
    after: list[str] | None = None

    def close() -> None:
        nonlocal title, intro, rows, after
        if rows:
            tables.append({"title": title, "intro": "\n".join(intro).strip(),
                           "columns": rows[0], "rows": rows[1:], "note": ""})
            title, intro, rows = "", [], []
            after = []

    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("|"):
            if after is not None and not rows:
                tables[-1]["note"] = "\n".join(after).strip()
                after = None
            if not re.fullmatch(r"\|(\s*:?-+:?\s*\|)+", stripped):
                rows.append(split_row(stripped))
            continue
        close()
        if stripped.startswith("#"):
            if after is not None:
                tables[-1]["note"] = "\n".join(after).strip()
                after = None
            title, intro = stripped.lstrip("#").strip(), []
        elif after is not None:
            after.append(line)
        else:
            intro.append(line)
    close()
    if after is not None and tables:
        tables[-1]["note"] = "\n".join(after).strip()
    return tables


def run_captured(name: str, paths_measured: list[str], main: Callable[[], int | None]) -> int:
    """Runs a benchmark's `main` that prints its own markdown, records what it prints and
    writes the result when it succeeds (a failed run leaves the last good result in place).

    `--result NAME` on the command line (taken out before `main` parses it) names the result
    and so its block on the page: a run with other settings (another receiver, longer
    flights, public logs the repository does not hold) gets a block of its own instead of
    replacing the benchmark's default run."""
    argv = sys.argv[1:]
    if "--result" in argv[:-1]:
        at = argv.index("--result")
        name = argv[at + 1]
        del sys.argv[at + 1:at + 3]
    res = Result(name, paths_measured, quick="--quick" in sys.argv[1:],
                 argv=argv)
    with res.capture():
        code = main() or 0
    if code == 0:
        res.write()
    return code


def split_json_lines(text: str) -> tuple[str, list[Any]]:
    """(the text without the lines that are whole JSON documents, those documents): a
    benchmark that prints its figures as JSON for machines keeps them as data, not as prose."""
    kept: list[str] = []
    found: list[Any] = []
    for line in text.splitlines():
        if line.lstrip()[:1] in ("[", "{"):
            try:
                found.append(json.loads(line))
                continue
            except json.JSONDecodeError:
                pass
        kept.append(line)
    return "\n".join(kept), found
