"""The house's shape: no import circles, and only the modules every layer uses directly in mapd/.

The layers themselves are checked by ``lint-imports`` (contracts in pyproject.toml, run by ``make lint``).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import grimp

ROOT = Path(__file__).resolve().parents[1]

#: Modules directly in mapd/: what every layer uses, the command line, and the small shared helpers.
TOP_LEVEL = {
    "__init__", "__main__", "cli", "errors", "config", "plugins", "grid", "envelope",
    "files", "data", "keys", "tables", "identity", "poses",
    "wallclock",  # the daemon (a new state's versions) and the uwb link (TDMA turns) both ask it
}  # fmt: skip


def _cycles(graph: grimp.ImportGraph) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0
    for start in sorted(graph.modules):
        if start in index:
            continue
        work = [(start, iter(sorted(graph.find_modules_directly_imported_by(start))))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.find_modules_directly_imported_by(child)))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    m = stack.pop()
                    on_stack.discard(m)
                    component.append(m)
                    if m == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def _graph() -> grimp.ImportGraph:
    return grimp.build_graph("mapd", "transports", exclude_type_checking_imports=True, cache_dir=None)


def test_no_import_circles() -> None:
    assert _cycles(_graph()) == []


def test_the_cycle_finder_finds_a_cycle() -> None:
    graph = grimp.ImportGraph()
    for a, b in [("p.a", "p.b"), ("p.b", "p.c"), ("p.c", "p.a"), ("p.c", "p.d")]:
        graph.add_import(importer=a, imported=b)
    assert _cycles(graph) == [["p.a", "p.b", "p.c"]]


def test_mapd_top_level_holds_only_what_every_layer_uses() -> None:
    modules = {p.stem for p in (ROOT / "mapd").glob("*.py")}
    assert modules <= TOP_LEVEL, f"modules to move into a subpackage: {sorted(modules - TOP_LEVEL)}"


def test_every_package_has_an_init_and_transports_is_importable_at_the_top() -> None:
    for pkg in [*(ROOT / "mapd").rglob("__init__.py"), *(ROOT / "transports").rglob("__init__.py")]:
        assert pkg.read_text().startswith('"""'), f"{pkg} has no docstring saying what the package holds"
    assert importlib.util.find_spec("transports.base") is not None


def test_the_license_is_an_spdx_expression_with_its_text_beside_it() -> None:
    # The table form (license = {text = ...}) is deprecated and stops building with setuptools in 2027.
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert isinstance(project["license"], str), "license must be an SPDX expression (PEP 639)"
    assert project["license"] == "Apache-2.0"
    text = (ROOT / "LICENSE").read_text()
    assert "Apache License" in text and "Version 2.0, January 2004" in text
    assert project["license-files"] == ["LICENSE"]
