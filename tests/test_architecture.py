"""The layers of docs/architecture.md hold in the source: every import points down, none circles.

Imports are read from the source with `ast` (function-level imports included: a lazy import is
still a dependency), so the check needs nothing installed and fails on the line that breaks it.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("companion", "gcs_bridge", "legacy_protocol", "horizon")

# Lowest first. A module may import its own layer or any layer below it, never one above.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("core", ("companion.core", "companion")),
    ("logs", ("companion.logs",)),
    ("watchdog", ("companion.watchdog",)),
    ("flight", ("companion.drivers", "companion.estimation", "companion.control")),
    ("bridges", ("gcs_bridge", "legacy_protocol")),
    ("app", ("companion.vehicle", "companion.runtime", "companion.service", "companion.docgen",
             "companion.cli_common")),
    # the replay tools and the calibration command beside the drivers and the estimator read
    # the vehicle's table (device names, the estimator's prefix): tools, not flight code
    ("tools", ("companion.sim", "companion.evaluation", "companion.report", "companion.liveview",
               "companion.deploy", "companion.drivers.replay", "companion.drivers.cli",
               "companion.estimation.replay", "companion.estimation.calibration_cli")),
    ("cli", ("companion.cli", "companion.__main__")),
]
STANDALONE = "horizon"  # a library of its own: it imports nothing of the other packages


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in (REPO / pkg).rglob("*.py"):
            parts = list(path.relative_to(REPO).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


def _imports(modules: dict[str, Path]) -> dict[str, set[tuple[str, int]]]:
    """Module -> {(imported project module, line)}."""

    def resolve(name: str) -> str | None:
        parts = name.split(".")
        for i in range(len(parts), 0, -1):
            if ".".join(parts[:i]) in modules:
                return ".".join(parts[:i])
        return None

    out: dict[str, set[tuple[str, int]]] = {}
    for mod, path in modules.items():
        found: set[tuple[str, int]] = set()
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    pkg = mod.split(".")[: len(mod.split(".")) - node.level + int(is_pkg)]
                    base = ".".join(pkg + ([node.module] if node.module else []))
                names = [f"{base}.{a.name}" for a in node.names] + [base]
            for name in names:
                target = resolve(name)
                if target is not None and target != mod:
                    found.add((target, node.lineno))
        out[mod] = found
    return out


def layer_of(mod: str) -> int:
    best, best_len = -1, -1
    for index, (_name, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            if (mod == prefix or mod.startswith(prefix + ".")) and len(prefix) > best_len:
                best, best_len = index, len(prefix)
    return best


def test_every_module_has_a_layer() -> None:
    modules = _modules()
    unplaced = [m for m in modules if not m.startswith(STANDALONE) and layer_of(m) < 0]
    assert not unplaced, f"modules outside every layer of docs/architecture.md: {unplaced}"


def test_imports_point_down_the_layers() -> None:
    modules = _modules()
    wrong = []
    for mod, targets in _imports(modules).items():
        for target, line in sorted(targets):
            if mod.startswith(STANDALONE):
                if not target.startswith(STANDALONE):
                    wrong.append(f"{modules[mod].relative_to(REPO)}:{line}: the standalone "
                                 f"{STANDALONE} package imports {target}")
                continue
            if target.startswith(STANDALONE):
                continue  # any layer may use the library
            if layer_of(target) > layer_of(mod):
                wrong.append(f"{modules[mod].relative_to(REPO)}:{line}: {mod} "
                             f"({LAYERS[layer_of(mod)][0]}) imports {target} "
                             f"({LAYERS[layer_of(target)][0]}), a layer above it")
    assert not wrong, "\n".join(wrong)


def _package(mod: str) -> str:
    parts = mod.split(".")
    return ".".join(parts[:2]) if parts[0] == "companion" and len(parts) > 1 else parts[0]


def test_no_package_imports_circle() -> None:
    graph: dict[str, set[str]] = defaultdict(set)
    for mod, targets in _imports(_modules()).items():
        for target, _line in targets:
            a, b = _package(mod), _package(target)
            if a != b and b != "companion":  # the root package only holds the version
                graph[a].add(b)
    cycles = []
    state: dict[str, int] = {}

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append(" -> ".join(path[path.index(nxt):] + [nxt]))
            elif nxt not in state:
                visit(nxt, [*path, nxt])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    assert not cycles, f"package import cycles: {cycles}"


def test_the_check_sees_a_wrong_import() -> None:
    assert layer_of("companion.core.params") < layer_of("companion.watchdog.manager")
    assert layer_of("companion.runtime") > layer_of("gcs_bridge.link")
    assert layer_of("companion.sim.runner") > layer_of("companion.runtime")


def test_no_module_imports_circle() -> None:
    """No two modules reach each other through imports, type-only ones included: a cycle hides
    which of the two owns the fact they share (break a type-only one with a Protocol in the
    lower module)."""
    modules = _modules()
    graph = {mod: {t for t, _line in targets if not _is_package_of(t, mod)}
             for mod, targets in _imports(modules).items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []
    counter = [0]

    def strongconnect(v: str) -> None:  # Tarjan's algorithm, iterative enough for ~300 modules
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                strongconnect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strongconnect(v)
    assert not cycles, "modules that import each other (directly or around a loop): " + \
        "; ".join(" <-> ".join(c) for c in cycles)


def _is_package_of(target: str, mod: str) -> bool:
    """`from pkg.sub import x` also names `pkg` (its __init__): a package's own __init__ that
    re-exports its modules is not a cycle with them."""
    return mod.startswith(target + ".")


PRODUCT_MAX_LINES = 600


def test_no_module_of_the_product_is_over_600_lines() -> None:
    """Small modules with one job: a module that grows past 600 lines has more than one and is
    split by job (bench/ and tests/ are not the product)."""
    long = [f"{path.relative_to(REPO)} ({path.read_text(encoding='utf-8').count(chr(10))} lines)"
            for path in _modules().values()
            if path.read_text(encoding="utf-8").count("\n") > PRODUCT_MAX_LINES]
    assert not long, f"modules over {PRODUCT_MAX_LINES} lines: {long}"
