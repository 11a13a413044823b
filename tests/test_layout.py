"""The layout's rules, checked on the source: engine/ imports nothing else of app/, app/ has no
import cycle (imports inside functions count too: they hide a cycle, they do not remove it), and each layer
uses the one below through its public names only (the faces call the service, the API never imports the
storage, no module takes another's private name)."""

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


#: The service's parts that only the use cases and the write path hold: a face asks the service instead.
SERVICE_PARTS = {"store", "collection", "pipeline"}
#: The names the faces give the service (``GeolocService``): a variable, a parameter, ``app.state.service``,
#: the routes' ``core``.
SERVICE_NAMES = {"service", "core"}


def service_parts_reached(root: Path = APP) -> list[str]:
    """``file:line`` of every ``<service>.store``, ``.collection`` or ``.pipeline`` outside app/usecases/
    and app/ingestion/ (``service.store.close()``, ``app.state.service.collection``...)."""
    found = []
    for path in sorted(root.rglob("*.py")):
        if path.is_relative_to(root / "usecases") or path.is_relative_to(root / "ingestion"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.Attribute) and node.attr in SERVICE_PARTS):
                continue
            owner = node.value
            name = owner.attr if isinstance(owner, ast.Attribute) else getattr(owner, "id", "")
            if name in SERVICE_NAMES:
                found.append(f"{path.relative_to(root.parent)}:{node.lineno} {name}.{node.attr}")
    return found


def test_the_faces_call_the_service_and_never_reach_through_it():
    """The HTTP routes, the CLI, the library and the jobs call the service's methods: what the store, the
    collection or the pipeline must do for them is one method of the service, not a path through it."""
    found = service_parts_reached()
    assert found == [], "reached through the service at:\n" + "\n".join(found)


def _all_imports(path: Path) -> list[tuple[int, str, list[str]]]:
    """(line, module, names) of every absolute import of ``path`` at any depth (``import a.b``: names [])."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.lineno, node.module, [a.name for a in node.names]))
    return out


def imports_of(root: Path, under: str, prefix: str) -> list[str]:
    """``file:line module`` of every import of ``prefix`` (a module or package) made by a module under
    ``root/under``."""
    found = []
    for path in sorted((root / under).rglob("*.py")):
        for line, module, _ in _all_imports(path):
            if module == prefix or module.startswith(prefix + "."):
                found.append(f"{path.relative_to(root.parent)}:{line} {module}")
    return found


def test_the_api_imports_no_storage_module():
    """The HTTP layer parses, calls the service or the library and shapes: the storage is theirs to use."""
    assert imports_of(APP, "api", "app.storage") == []


def registry_imports_of_the_index_kinds(root: Path = APP) -> list[str]:
    """``file:line name`` of everything app/engine/index/ imports from app.engine.configs but the type of a
    configuration (``PipelineConfig``): the named configurations, their lookup, their registration."""
    found = []
    for path in sorted((root / "engine" / "index").rglob("*.py")):
        for line, module, names in _all_imports(path):
            if module == "app.engine.configs":
                found += [f"{path.relative_to(root.parent)}:{line} {n}" for n in names if n != "PipelineConfig"]
                found += [f"{path.relative_to(root.parent)}:{line} {module}"] if not names else []
    return found


def test_the_index_kinds_do_not_know_the_named_configurations():
    """An index is told what it needs (its configuration, which named configurations serve a mode) by
    whoever builds it: the registry of named configurations sits above the index kinds."""
    assert registry_imports_of_the_index_kinds() == []


def private_names_imported(root: Path = APP) -> list[str]:
    """``file:line module.name`` of every ``_name`` (not a dunder) one module of app/ takes from another:
    ``from app.x import _name`` or ``x._name`` on an imported app module."""
    modules = {".".join(p.relative_to(root.parent).with_suffix("").parts) for p in root.rglob("*.py")}
    modules |= {m.removesuffix(".__init__") for m in modules}
    found = []
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text())
        bound: dict[str, str] = {}
        for line, module, names in _all_imports(path):
            if not module.startswith("app"):
                continue
            for name in names:
                if name.startswith("_") and not name.startswith("__"):
                    found.append(f"{path.relative_to(root.parent)}:{line} {module}.{name}")
                elif f"{module}.{name}" in modules:
                    bound[name] = f"{module}.{name}"
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id in bound
                and node.attr.startswith("_")
                and not node.attr.startswith("__")
            ):
                found.append(f"{path.relative_to(root.parent)}:{node.lineno} {bound[node.value.id]}.{node.attr}")
    return found


def test_no_private_name_is_used_across_modules():
    """A ``_name`` is its module's own: another module that needs it needs a public name for it."""
    assert private_names_imported() == []


def indexes_built_in_storage(root: Path = APP) -> list[str]:
    """``file:line`` of every index the storage builds itself (``ReferenceIndex(...)``, ``build_index(...)``,
    ``pipeline.new_index()``); a factory it is handed (a bare ``new_index()``) is not its own."""
    found = []
    for path in sorted((root / "storage").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.Call):
                continue
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
            if name in {"ReferenceIndex", "build_index"} or (isinstance(f, ast.Attribute) and name == "new_index"):
                found.append(f"{path.relative_to(root.parent)}:{node.lineno} {name}(")
    return found


def test_the_storage_builds_no_index():
    """Snapshots read and write the files of an index they are given or handed a factory for: which kinds an
    index is made of is the engine's and the collection's business, not the storage's."""
    assert indexes_built_in_storage() == []


def lower_layers_reaching_up(root: Path = APP) -> list[str]:
    """``file:line module`` of imports that reach a layer above: Settings (read by every face) importing a
    use case, the library and the jobs importing the evaluation package (they share ``app.manifests``)."""
    found = [
        f"app/settings.py:{line} {module}"
        for line, module, _ in _all_imports(root / "settings.py")
        if module == "app.usecases" or module.startswith("app.usecases.")
    ]
    return found + imports_of(root, "library", "app.evaluation") + imports_of(root, "jobs", "app.evaluation")


def test_settings_the_library_and_the_jobs_import_nothing_above_them():
    assert lower_layers_reaching_up() == []
