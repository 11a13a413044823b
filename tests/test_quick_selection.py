"""`make test-quick` keeps the engine and API tests and leaves out the crash, fuzz, browser, library-scan
and container tests; `make test` leaves out the container test only (`make test-container` runs it)."""

import re
import subprocess
import sys

from tests.conftest import REPO


def _collected(marker_expr: str | None) -> set[str]:
    args = [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider"]
    out = subprocess.run(
        [*args, *(["-m", marker_expr] if marker_expr else [])], cwd=REPO, capture_output=True, text=True, timeout=300
    ).stdout
    return {line.split("::")[0] for line in out.splitlines() if "::" in line}


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
