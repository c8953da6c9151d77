"""docs/benchmarks.md is what the committed results render, and the renderer says when a result
no longer measures today's code.

The page's figures live in generated blocks rendered from bench/results/*.json by
bench/render.py (`make docs`); these tests compare the committed page with a fresh render and
check the renderer on small real git repositories: current, stale after a commit to the measured
code, unknown without git history, a block with no result, a result with no block, a raw output
with no result and a broken result file.
"""

from __future__ import annotations

import importlib
import json
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGE = REPO / "docs" / "benchmarks.md"
GIT = shutil.which("git")


def _load(name: str) -> ModuleType:
    """bench/NAME.py (bench/ is scripts, not an installed package: found from the repo root)."""
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    return importlib.import_module(f"bench.{name}")


render_mod = _load("render")
result_mod = _load("result")


def _has_history(root: Path) -> bool:
    if GIT is None:
        return False
    done = subprocess.run([GIT, "-C", str(root), "rev-parse", "--verify", "--quiet", "HEAD"],
                          capture_output=True, text=True, timeout=30, check=False)
    return done.returncode == 0


def test_page_is_what_the_results_render() -> None:
    if not _has_history(REPO):
        pytest.skip("the page's stale/current marks are rendered from git history; none here")
    current = PAGE.read_text(encoding="utf-8")
    wanted = render_mod.render(current, REPO, PAGE.parent)
    assert current == wanted, (
        "docs/benchmarks.md differs from what bench/results renders:\n"
        + render_mod.diff(current, wanted, "docs/benchmarks.md")
        + f"\nregenerate with: {render_mod.REGENERATE} (or make docs)")


def test_page_has_a_block_for_every_benchmark_run_all_runs() -> None:
    """Every benchmark `make bench` runs has its figures on the page, so none is measured and
    never shown (and none shown without being measured)."""
    names = {m["name"] for m in render_mod.BLOCK.finditer(PAGE.read_text(encoding="utf-8"))}
    run_all = _load("run_all")
    missing = sorted(n for n, _ in run_all.BENCHMARKS if n not in names)
    assert not missing, f"docs/benchmarks.md has no <!-- bench:NAME --> block for {missing}"


# ---------------------------------------------------------------- the renderer on a small repo
def _git(root: Path, *args: str) -> str:
    assert GIT is not None
    return subprocess.run([GIT, "-C", str(root), *args], capture_output=True, text=True,
                          timeout=30, check=True).stdout.strip()


def _repo(tmp_path: Path) -> Path:
    """A repository with measured code, one result of benchmark `demo` at its first commit and
    a page with blocks for `demo`, a benchmark without a result and a legacy section."""
    root = tmp_path / "repo"
    (root / "pkg").mkdir(parents=True)
    (root / "docs").mkdir()
    (root / "bench" / "results").mkdir(parents=True)
    (root / "pkg" / "code.py").write_text("x = 1\n")
    (root / "other.txt").write_text("not measured\n")
    _git(root, "init", "-q")
    _git(root, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "--allow-empty",
         "-m", "empty")
    _git(root, "add", "-A")
    _git(root, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "code")
    commit = _git(root, "rev-parse", "HEAD")
    result = {"schema": 1, "name": "demo", "command": "python bench/demo_bench.py",
              "commit": commit, "uncommitted_changes": [], "date": "2026-12-01T10:00:00Z",
              "machine": {"cpus": 2}, "load_before": [0.5, 0.4, 0.3],
              "load_after": [0.7, 0.5, 0.3], "wall_s": 12.0, "paths_measured": ["pkg"],
              "figures": {"rate": {"value": 42.5, "unit": "MB/s", "label": "rate"}},
              "tables": [{"title": "Demo", "intro": "", "columns": ["what", "value"],
                          "rows": [["rate", "42.5 MB/s"]], "note": "a note"}], "notes": []}
    (root / "bench" / "results" / "2026-12-01-demo.json").write_text(json.dumps(result))
    (root / "bench" / "results" / "2026-12-01-orphan.json").write_text(
        json.dumps({**result, "name": "orphan"}))
    (root / "bench" / "results" / "2026-11-01-old.md").write_text("| a | 1 |\n")
    (root / "docs" / "benchmarks.md").write_text(
        "# Page\n\n<!-- bench:index -->\n<!-- /bench -->\n\nprose\n\n"
        "<!-- bench:demo -->\nold figures\n<!-- /bench -->\n\n"
        "<!-- bench:nothing -->\n<!-- /bench -->\n\n"
        "<!-- bench:legacy legacy=bench/results/2026-11-01-old.md -->\n<!-- /bench -->\n")
    return root


def _render(root: Path) -> str:
    page = root / "docs" / "benchmarks.md"
    return str(render_mod.render(page.read_text(), root, page.parent))


needs_git = pytest.mark.skipif(GIT is None, reason="git is not installed")


@needs_git
def test_a_result_renders_with_command_commit_load_and_table(tmp_path: Path) -> None:
    root = _repo(tmp_path)
    page = _render(root)
    commit = _git(root, "rev-parse", "HEAD")
    assert "old figures" not in page
    assert f"`python bench/demo_bench.py` at commit `{commit[:10]}`, 2026-12-01" in page
    assert "load 0.50 before, 0.70 after" in page
    assert "| rate | 42.5 MB/s |" in page and "a note" in page
    assert "Status: current" in page
    assert "prose" in page  # hand-written text outside the blocks is kept


@needs_git
def test_a_commit_to_the_measured_code_marks_the_result_stale(tmp_path: Path) -> None:
    root = _repo(tmp_path)
    (root / "other.txt").write_text("changed, but not measured\n")
    _git(root, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qam", "other")
    assert "Status: current" in _render(root)
    (root / "pkg" / "code.py").write_text("x = 2\n")
    # stale already before the commit (the page is rendered, then committed with the code),
    # and the same line after it
    before = _render(root)
    _git(root, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qam", "measured code")
    page = _render(root)
    assert "Status: **stale**: the measured code (pkg) changed after `" in page
    assert page == before
    assert "| demo |" in page and "| stale |" in page  # the index says so too


@needs_git
def test_a_commit_not_in_the_history_is_unknown_not_an_error(tmp_path: Path) -> None:
    root = _repo(tmp_path)
    path = root / "bench" / "results" / "2026-12-01-demo.json"
    data = json.loads(path.read_text())
    path.write_text(json.dumps({**data, "commit": "0123456789abcdef0123456789abcdef01234567"}))
    assert "staleness unknown: commit `0123456789ab` is not in this history" in _render(root)


@needs_git
def test_without_git_history_staleness_is_unknown(tmp_path: Path) -> None:
    root = _repo(tmp_path)
    shutil.rmtree(root / ".git")
    page = _render(root)
    assert "Status: staleness unknown: no git history here." in page
    assert "| rate | 42.5 MB/s |" in page


@needs_git
def test_blocks_without_results_and_results_without_blocks(tmp_path: Path) -> None:
    page = _render(_repo(tmp_path))
    assert "No result yet (no `bench/results/<date>-nothing.json`)." in page
    assert "**Unbacked**: no machine-readable result of `legacy`" in page
    assert "Other results (no block on this page): [2026-12-01-orphan.json]" in page
    assert "Unbacked: no machine-readable result (raw text of older runs" in page
    assert "[2026-11-01-old.md](../bench/results/2026-11-01-old.md)" in page


@needs_git
def test_the_newest_result_wins_and_quick_results_never_count(tmp_path: Path) -> None:
    root = _repo(tmp_path)
    results = root / "bench" / "results"
    data = json.loads((results / "2026-12-01-demo.json").read_text())
    newer = {**data, "date": "2026-12-02T10:00:00Z", "tables": [
        {"title": "", "columns": ["what", "value"], "rows": [["rate", "50 MB/s"]]}]}
    (results / "2026-12-02-demo.json").write_text(json.dumps(newer))
    quick = {**newer, "date": "2026-12-03T10:00:00Z", "quick": True, "tables": [
        {"title": "", "columns": ["what", "value"], "rows": [["rate", "99 MB/s"]]}]}
    (results / "2026-12-03-demo.json").write_text(json.dumps(quick))
    page = _render(root)
    assert "| rate | 50 MB/s |" in page and "42.5 MB/s" not in page and "99 MB/s" not in page


@needs_git
def test_check_reports_a_diff_and_the_command_then_render_fixes_it(tmp_path: Path) -> None:
    root = _repo(tmp_path)
    page = root / "docs" / "benchmarks.md"
    cmd = [sys.executable, str(REPO / "bench" / "render.py"), str(page), "--root", str(root)]
    check = subprocess.run([*cmd, "--check"], capture_output=True, text=True, timeout=60)
    assert check.returncode == 1
    assert "-old figures" in check.stderr and "regenerate: python bench/render.py" in check.stderr
    subprocess.run(cmd, check=True, timeout=60)
    again = subprocess.run([*cmd, "--check"], capture_output=True, text=True, timeout=60)
    assert again.returncode == 0, again.stderr


@needs_git
def test_a_broken_result_file_is_one_line_naming_it(tmp_path: Path) -> None:
    root = _repo(tmp_path)
    bad = root / "bench" / "results" / "2026-12-01-broken.json"
    bad.write_text('{"name": "demo", ')
    page = root / "docs" / "benchmarks.md"
    done = subprocess.run([sys.executable, str(REPO / "bench" / "render.py"), str(page),
                           "--root", str(root)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "2026-12-01-broken.json: not a readable JSON result" in lines[0]
    assert "Traceback" not in done.stderr


# ----------------------------------------------------------------------- the result writer
def test_a_result_records_what_the_benchmark_printed(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    res = result_mod.Result("demo", ["companion/logs"], argv=["--records", "10"])
    with res.capture():
        print("## Reader\n\nsome words\n\n| reader | MB/s |\n|---|---|\n| ours | 1,128 |\n\nafter")
        print('[{"k": 1, "held": true}]')  # figures printed as JSON for machines: data
    res.figure("read_mb_s", 1128.0, "MB/s")
    path = res.write(tmp_path)
    assert path is not None and path.name.endswith("-demo.json")
    data = json.loads(path.read_text())
    assert data["command"].endswith("--records 10") and data["name"] == "demo"
    assert len(data["load_before"]) == 3 and len(data["load_after"]) == 3
    assert data["machine"]["cpus"] and data["paths_measured"][0] == "companion/logs"
    assert data["figures"]["read_mb_s"] == {"value": 1128.0, "unit": "MB/s", "label": "read_mb_s"}
    assert data["tables"] == [{"title": "Reader", "intro": "some words", "columns":
                               ["reader", "MB/s"], "rows": [["ours", "1,128"]], "note": "after"}]
    assert data["data"] == {"printed_json": [[{"k": 1, "held": True}]]}
    assert "| ours | 1,128 |" in capsys.readouterr().out  # still printed


def test_plain_text_output_is_kept_as_printed(tmp_path: Path) -> None:
    res = result_mod.Result("demo", [])
    with res.capture():
        print("attitude\n  inclination RMSE      0.506 deg")
    path = res.write(tmp_path)
    assert path is not None
    table = json.loads(path.read_text())["tables"]
    assert table == [{"title": "", "text": "attitude\n  inclination RMSE      0.506 deg"}]
    page = render_mod.render_block("demo", {}, {"demo": render_mod.Stored(path, "demo", {
        "schema": 1, "tables": table})}, tmp_path, tmp_path)
    assert "```text\nattitude\n  inclination RMSE      0.506 deg\n```" in page


def test_a_quick_run_writes_no_result_unless_asked(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("BENCH_RESULTS_DIR", raising=False)
    assert result_mod.Result("demo", [], quick=True).write() is None
    monkeypatch.setenv("BENCH_RESULTS_DIR", str(tmp_path))
    path = result_mod.Result("demo", [], quick=True).write()
    assert path is not None and json.loads(path.read_text())["quick"] is True
