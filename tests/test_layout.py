"""The layout's rules, checked on the source: engine/ imports nothing else of app/, and app/ has no
import cycle (imports inside functions count too: they hide a cycle, they do not remove it)."""

from __future__ import annotations

import ast
from pathlib import Path

APP = Path(__file__).resolve().parents[1] / "app"


def _module_name(path: Path) -> str:
    parts = path.relative_to(APP.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """Every app module ``path`` imports, at any depth of the file (``from app.x import y`` gives app.x
    and, when app.x.y is a module, app.x.y)."""
    modules = {_module_name(p) for p in APP.rglob("*.py")}
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("app")}
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("app") and node.level == 0:
            out.add(node.module)
            out |= {f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in modules}
    return {m for m in out if m in modules}


def import_graph() -> dict[str, set[str]]:
    return {_module_name(p): _imports(p) - {_module_name(p)} for p in APP.rglob("*.py")}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of module imports (package __init__ files that only re-export are nodes like any other)."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph.get(m, ())):
            if n.startswith(m + ".") or m.startswith(n + "."):  # a package and its own modules
                continue
            if state.get(n) == 1:
                return stack[stack.index(n) :] + [n]
            if n not in state:
                found = visit(n)
                if found:
                    return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state:
            found = visit(m)
            if found:
                return found
    return None


def test_the_engine_imports_nothing_else_of_the_app():
    graph = import_graph()
    leaks = {m: sorted(n for n in deps if not n.startswith("app.engine")) for m, deps in graph.items()}
    leaks = {m: d for m, d in leaks.items() if m.startswith("app.engine") and d}
    assert leaks == {}


def test_the_app_has_no_import_cycle():
    assert find_cycle(import_graph()) is None


def test_the_cycle_finder_finds_one():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_the_docs_name_files_that_exist():
    """README, METHOD, RESULTS and BENCHMARKS point readers at modules by path: a move must update them."""
    import re

    repo = APP.parent
    named = set()
    for doc in [repo / "README.md", *sorted((repo / "docs").glob("*.md"))]:
        named |= {(doc.name, m) for m in re.findall(r"\b((?:app|tools|bench|tests)/[\w/]+\.py)\b", doc.read_text())}
    missing = sorted((doc, path) for doc, path in named if not (repo / path).exists())
    assert missing == []


SQL_CALLS = {"execute", "executescript", "executemany"}


def sql_outside_storage() -> list[str]:
    """Modules of app/ outside app/storage/ that import sqlite3 or run SQL (``x.execute(...)``,
    ``executescript``, ``executemany``): SQL lives in storage/ only, behind methods that return typed values."""
    storage = APP / "storage"
    found = []
    for path in sorted(APP.rglob("*.py")):
        if path.is_relative_to(storage):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            where = f"{path.relative_to(APP.parent)}:{getattr(node, 'lineno', 0)}"
            if isinstance(node, ast.Import) and any(a.name.split(".")[0] == "sqlite3" for a in node.names):
                found.append(f"{where} imports sqlite3")
            elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "sqlite3":
                found.append(f"{where} imports from sqlite3")
            elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in SQL_CALLS:
                found.append(f"{where} calls .{node.func.attr}(")
    return found


def test_sql_lives_in_storage_only():
    assert sql_outside_storage() == []


ISSUE_NUMBER = r"(?i)\bissues? #?[0-9]"


def lines_citing_issue_numbers() -> list[str]:
    """``file:line`` of every line of app/ (vendored third-party code aside) that names an issue by number:
    the code says why, and the history of a change lives in the tracker and the commits."""
    import re

    vendor = APP / "web" / "static" / "vendor"
    found = []
    for path in sorted(APP.rglob("*.py")):
        if path.is_relative_to(vendor):
            continue
        for number, line in enumerate(path.read_text().splitlines(), start=1):
            if re.search(ISSUE_NUMBER, line):
                found.append(f"{path.relative_to(APP.parent)}:{number}")
    return found


def test_the_code_never_cites_issue_numbers():
    """Comments and docstrings say why, not which issue asked for it (docs/results.md and docs/benchmarks.md
    hold the measured figures and name their commands)."""
    found = lines_citing_issue_numbers()
    assert found == [], "issue numbers cited at:\n" + "\n".join(found)


#: The queue's consumer side (``app.storage.queue``, forwarded by ``ReferenceStore``): claiming pending rows,
#: their attempts, releasing and completing them.
QUEUE_CALLS = {"pending", "claim", "release", "start_attempts", "end_attempts", "complete"}


def queue_calls_outside_ingestion() -> list[str]:
    """``file:line`` of calls ``<x>.store.<call>(`` or ``store.<call>(`` of the queue's consumer side made
    outside app/ingestion/ and app/storage/."""
    found = []
    for path in sorted(APP.rglob("*.py")):
        if path.is_relative_to(APP / "ingestion") or path.is_relative_to(APP / "storage"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
                continue
            owner = node.func.value
            name = owner.attr if isinstance(owner, ast.Attribute) else getattr(owner, "id", "")
            if node.func.attr in QUEUE_CALLS and name == "store":
                found.append(f"{path.relative_to(APP.parent)}:{node.lineno} store.{node.func.attr}(")
    return found


def test_the_queue_is_consumed_by_the_ingestion_package_only():
    """The write path is one package: every claim, release and completion of queued rows is made there."""
    assert queue_calls_outside_ingestion() == []
