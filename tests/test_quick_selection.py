"""`make test-quick` keeps the engine and API tests and leaves out the crash, fuzz, browser, library-scan
and container tests; `make test` leaves out the container test only (`make test-container` runs it)."""

import functools
import json
import re
import subprocess
import sys

from _pytest.mark.expression import Expression

from tests.conftest import REPO

_LIST_ITEMS = """
import json, sys, pytest
class Listing:
    def pytest_collection_finish(self, session):
        items = [[i.nodeid, sorted({m.name for m in i.iter_markers()})] for i in session.items]
        print("ITEMS " + json.dumps(items))
sys.exit(pytest.main(["--collect-only", "-q", "-p", "no:cacheprovider"], plugins=[Listing()]))
"""


@functools.cache
def _every_test() -> tuple[tuple[str, frozenset[str]], ...]:
    """Each collected test's node id and marker names, from one collection of the whole suite."""
    out = subprocess.run([sys.executable, "-c", _LIST_ITEMS], cwd=REPO, capture_output=True, text=True, timeout=300)
    line = next((x for x in out.stdout.splitlines() if x.startswith("ITEMS ")), None)
    assert line is not None, out.stdout[-2000:] + out.stderr[-2000:]
    return tuple((nodeid, frozenset(marks)) for nodeid, marks in json.loads(line[len("ITEMS ") :]))


def _collected(marker_expr: str | None) -> set[str]:
    """The test files ``pytest -m MARKER_EXPR`` runs, selected by pytest's own marker expressions."""
    expr = Expression.compile(marker_expr) if marker_expr else None
    return {
        nodeid.split("::")[0]
        for nodeid, marks in _every_test()
        if expr is None or expr.evaluate(lambda name, /, _marks=marks, **_: name in _marks)
    }


def _make_var(name: str) -> str:
    return re.search(rf"^{name} := (.+)$", (REPO / "Makefile").read_text(), re.M).group(1)


def test_make_test_leaves_out_the_container_test_only():
    everything, full = _collected(None), _collected(_make_var("NOT_IN_TEST"))
    assert everything - full == {"tests/test_container_build.py"}
    assert '-m "$(NOT_IN_TEST)"' in (REPO / "Makefile").read_text()


def test_quick_selection_leaves_out_crash_fuzz_browser_library_and_container_only():
    everything, quick = _collected(None), _collected(_make_var("QUICK"))
    left_out = {
        "tests/api/test_crash.py",
        "tests/api/test_fuzz.py",
        "tests/api/test_browser.py",
        "tests/library/test_library_browser.py",
        "tests/library/test_readme_library.py",
        "tests/library/test_manifest_library.py",
        "tests/library/test_library_files.py",
        "tests/test_container_build.py",
    }
    assert left_out <= everything
    assert everything - quick == left_out
    assert {"tests/engine/test_vlad.py", "tests/api/test_e2e.py", "tests/api/test_errors.py"} <= quick
