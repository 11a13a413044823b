"""`make test-quick` keeps the engine and API tests and leaves out the crash, fuzz and browser tests."""

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


def test_quick_selection_leaves_out_crash_fuzz_and_browser_only():
    quick_expr = re.search(r"^QUICK := (.+)$", (REPO / "Makefile").read_text(), re.M).group(1)
    everything, quick = _collected(None), _collected(quick_expr)
    left_out = {"tests/service/test_crash.py", "tests/service/test_fuzz.py", "tests/service/test_browser.py"}
    assert left_out <= everything
    assert everything - quick == left_out
    assert {"tests/engine/test_vlad.py", "tests/service/test_e2e.py", "tests/service/test_errors.py"} <= quick
