"""Render the figures of docs/benchmarks.md from the committed results in bench/results/.

    python bench/render.py docs/benchmarks.md          # rewrite the generated blocks (`make docs`)
    python bench/render.py docs/benchmarks.md --check  # exit 1 and print a diff if out of date

The page is hand-written prose with generated blocks between `<!-- bench:NAME -->` and
`<!-- /bench -->`. Each block is rendered from the newest result of benchmark NAME
(`bench/results/<date>-NAME.json`, written through bench/result.py): the command, the commit it
was measured on, the date and load, whether the measured code changed since (stale), then its
tables. A block whose benchmark has no result says so; `<!-- bench:NAME legacy=PATH -->` names
the raw text output an older run left, and the block marks the section's figures unbacked.
`<!-- bench:index -->` lists every block's state, the results with no block and the raw outputs
with no machine-readable result.

Why generated: figures copied by hand drifted from the runs behind them and outlived the code
they measured; here a figure cannot be on the page without its result, and a test
(tests/test_docs_benchmarks.py) fails when the page is not what the results render.
"""

from __future__ import annotations

import argparse
import difflib
import json
import os
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.result import markdown_table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
BLOCK = re.compile(r"<!-- bench:(?P<name>[\w.-]+)(?P<attrs>[^>]*?) -->\n(?P<body>.*?)<!-- /bench -->",
                   re.DOTALL)
DATED = re.compile(r"^(\d{4}-\d{2}-\d{2})-(.+)$")
REGENERATE = "python bench/render.py docs/benchmarks.md"


class RenderError(Exception):
    """A result file or the page cannot be read: one line naming the file and what is wrong."""


@dataclass
class Stored:
    """One result file as the renderer sees it."""

    path: Path
    name: str
    data: dict[str, Any] = field(default_factory=dict)

    @property
    def structured(self) -> bool:
        """Written through bench/result.py (has tables and paths), not an older free-form JSON."""
        return "schema" in self.data


# ------------------------------------------------------------------------------- results
def load_results(results_dir: Path) -> tuple[dict[str, Stored], list[Stored], list[Path]]:
    """(newest result per benchmark name, every JSON result, raw outputs with no JSON).

    The newest is the latest `date` (then file name); a `--quick` result never counts."""
    newest: dict[str, Stored] = {}
    every: list[Stored] = []
    raw: list[Path] = []
    if not results_dir.is_dir():
        return newest, every, raw
    for path in sorted(results_dir.iterdir()):
        if path.suffix != ".json":
            if path.is_file() and path.suffix in (".md", ".txt"):
                raw.append(path)
            continue
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise RenderError(f"{path}: not a readable JSON result ({exc})") from None
        if not isinstance(data, dict):
            raise RenderError(f"{path}: a result must be a JSON object, found "
                              f"{type(data).__name__}")
        m = DATED.match(path.stem)
        name = str(data.get("name") or (m.group(2) if m else path.stem))
        stored = Stored(path, name, data)
        every.append(stored)
        if data.get("quick"):
            continue
        old = newest.get(name)
        if old is None or (_date(stored), path.name) > (_date(old), old.path.name):
            newest[name] = stored
    stems = {s.path.stem for s in every}
    return newest, every, [p for p in raw if p.stem not in stems]


def _date(s: Stored) -> str:
    m = DATED.match(s.path.stem)
    return str(s.data.get("date") or (m.group(1) if m else ""))


# ----------------------------------------------------------------------------- staleness
def _git(root: Path, *args: str) -> str | None:
    try:
        done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True,
                              timeout=30, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def staleness(root: Path, commit: str, paths: list[str]) -> str:
    """The block's status line: current, stale (the measured code changed since the commit),
    or unknown (no git history, or a commit this history does not hold)."""
    if not paths:
        return "staleness unknown: the result does not name the code it measured"
    if _git(root, "rev-parse", "--verify", "--quiet", "HEAD") is None:
        return "staleness unknown: no git history here"
    if not re.fullmatch(r"[0-9a-f]{7,40}", commit) or _git(
            root, "cat-file", "-e", f"{commit}^{{commit}}") is None:
        return f"staleness unknown: commit `{commit[:12]}` is not in this history"
    log = _git(root, "log", "--format=%h", f"{commit}..HEAD", "--", *paths)
    if log is None:
        return "staleness unknown: git log failed"
    # Only whether, not how many or which: the page is rendered before the commit that
    # changes the code, so the line must read the same before and after that commit (changes
    # not yet committed count).
    uncommitted = _git(root, "diff", "--name-only", "HEAD", "--", *paths)
    if log.split() or uncommitted:
        return (f"**stale**: the measured code ({', '.join(paths)}) changed after "
                f"`{commit[:10]}`")
    return f"current: no commit since changed the measured code ({', '.join(paths)})"


# ----------------------------------------------------------------------------- rendering
def _load_text(data: dict[str, Any]) -> str:
    before = data.get("load_before") or data.get("load_average_before") or (
        data.get("machine") or {}).get("load_before")
    after = data.get("load_after") or data.get("load_average_after") or (
        data.get("machine") or {}).get("load_after")
    if not before or not after:
        return "load not recorded"
    return f"load {before[0]:.2f} before, {after[0]:.2f} after"


def _cores(data: dict[str, Any]) -> str:
    m = data.get("machine") or {}
    n = m.get("cpus") or m.get("cpu_count") or m.get("nproc") or data.get("cpus")
    return f"{n} cores, " if n else ""


def _paths(stored: Stored, attrs: dict[str, str]) -> list[str]:
    """The measured code: from the result, or for an older result that does not name it, from
    the block's `paths=a,b` attribute."""
    named = stored.data.get("paths_measured") or attrs.get("paths", "").split(",")
    return [str(p) for p in named if p]


def header(stored: Stored, attrs: dict[str, str], root: Path, page_dir: Path) -> list[str]:
    d = stored.data
    commit = str(d.get("commit") or "unknown")
    link = os.path.relpath(stored.path, page_dir)
    wall = f", {d['wall_s']:.0f} s" if isinstance(d.get("wall_s"), (int, float)) else ""
    lines = [f"*`{d.get('command', '(command not recorded)')}` at commit `{commit[:10]}`, "
             f"{str(d.get('date', '?'))[:10]} ({_cores(d)}{_load_text(d)}{wall}); "
             f"raw result [{stored.path.name}]({link}).*", ""]
    status = staleness(root, commit, _paths(stored, attrs))
    lines.append(f"Status: {status}.")
    dirty = d.get("uncommitted_changes") or []
    if dirty:
        lines.append(f"**Unbacked**: measured with uncommitted changes to {', '.join(dirty)}.")
    return lines


def render_block(name: str, attrs: dict[str, str], newest: dict[str, Stored], root: Path,
                 page_dir: Path) -> str:
    stored = newest.get(name)
    legacy = attrs.get("legacy")
    if stored is None:
        if legacy:
            return (f"**Unbacked**: no machine-readable result of `{name}`; the figures in this "
                    f"section come from the raw output [{Path(legacy).name}]"
                    f"({os.path.relpath(root / legacy, page_dir)}), measured on older code. "
                    f"Re-run the command in the heading to replace them.\n")
        return f"No result yet (no `bench/results/<date>-{name}.json`).\n"
    lines = header(stored, attrs, root, page_dir)
    if not stored.structured:
        lines += ["", "This result predates bench/result.py: its figures are in the raw file, "
                  "not rendered here."]
    for t in stored.data.get("tables", []):
        lines.append("")
        if "text" in t:  # printed as plain text, shown as printed
            lines += ["```text", str(t["text"]), "```"]
            continue
        if t.get("title"):
            lines += [f"**{t['title']}**", ""]
        if t.get("intro"):
            lines += [_squeeze(t["intro"]), ""]
        lines.append(markdown_table(t["columns"], t["rows"]))
        if t.get("note"):
            lines += ["", _squeeze(t["note"])]
    for note in stored.data.get("notes", []):
        lines += ["", _squeeze(note)]
    return "\n".join(lines) + "\n"


def _squeeze(text: str) -> str:
    """Printed text as page paragraphs: runs of blank lines become one."""
    return re.sub(r"\n\s*\n+", "\n\n", text.strip())


def render_index(blocks: list[tuple[str, dict[str, str]]], newest: dict[str, Stored],
                 every: list[Stored], raw: list[Path], root: Path, page_dir: Path) -> str:
    lines = ["| block | newest result | commit | date | state |", "|---|---|---|---|---|"]
    for name, attrs in blocks:
        s = newest.get(name)
        if s is None:
            state = "unbacked: no machine-readable result" if attrs.get("legacy") else \
                "no result yet"
            lines.append(f"| {name} | - | - | - | {state} |")
            continue
        commit = str(s.data.get("commit") or "unknown")
        state = staleness(root, commit, _paths(s, attrs))
        state = state.split(":")[0].replace("**", "")
        if s.data.get("uncommitted_changes"):
            state += ", uncommitted changes"
        lines.append(f"| {name} | [{s.path.name}]({os.path.relpath(s.path, page_dir)}) | "
                     f"`{commit[:10]}` | {str(s.data.get('date', '?'))[:10]} | {state} |")
    named = {n for n, _ in blocks}
    others = sorted(s.path.name for s in every if s.name not in named)
    if others:
        lines += ["", "Other results (no block on this page): " + ", ".join(
            f"[{n}]({os.path.relpath(root / 'bench' / 'results' / n, page_dir)})"
            for n in others) + "."]
    if raw:
        lines += ["", "Unbacked: no machine-readable result (raw text of older runs, on older "
                  "code): " + ", ".join(f"[{p.name}]({os.path.relpath(p, page_dir)})"
                                        for p in raw) + "."]
    return "\n".join(lines) + "\n"


def _attrs(text: str) -> dict[str, str]:
    return dict(kv.split("=", 1) for kv in text.split() if "=" in kv)


def render(page: str, root: Path = ROOT, page_dir: Path | None = None) -> str:
    """The page with every generated block re-rendered from `root`/bench/results."""
    page_dir = page_dir or root / "docs"
    newest, every, raw = load_results(root / "bench" / "results")
    blocks = [(m["name"], _attrs(m["attrs"])) for m in BLOCK.finditer(page)
              if m["name"] != "index"]

    def one(m: re.Match[str]) -> str:
        name, attrs = m["name"], _attrs(m["attrs"])
        if name == "index":
            body = render_index(blocks, newest, every, raw, root, page_dir)
        else:
            body = render_block(name, attrs, newest, root, page_dir)
        return f"<!-- bench:{name}{m['attrs']} -->\n{body}<!-- /bench -->"

    return BLOCK.sub(one, page)


def diff(current: str, wanted: str, path: str) -> str:
    return "".join(difflib.unified_diff(current.splitlines(True), wanted.splitlines(True),
                                        f"{path} (committed)", f"{path} (rendered)"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("page", type=Path)
    ap.add_argument("--check", action="store_true", help="only compare; exit 1 if out of date")
    ap.add_argument("--root", type=Path, default=ROOT,
                    help="the repository whose bench/results to render (default: this one)")
    args = ap.parse_args(argv)
    try:
        current = args.page.read_text(encoding="utf-8")
        wanted = render(current, args.root.resolve(), args.page.resolve().parent)
    except (OSError, RenderError) as exc:
        print(f"render: {exc}", file=sys.stderr)
        return 2
    if args.check:
        if current != wanted:
            print(diff(current, wanted, str(args.page)) + f"\nregenerate: {REGENERATE}",
                  file=sys.stderr)
            return 1
        return 0
    if current != wanted:
        args.page.write_text(wanted, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
