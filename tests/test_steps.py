"""Set-up steps print one line each off a terminal, and the log's tail when they fail."""

import subprocess
import sys

from tests.conftest import REPO


def _step(tmp_path, *cmd):
    return subprocess.run(
        [sys.executable, str(REPO / "tools" / "steps.py"), *cmd], capture_output=True, text=True, cwd=tmp_path
    )


def test_one_line_per_step_and_the_log_on_failure(tmp_path):
    noisy = [sys.executable, "-c", "import sys\nfor i in range(500): print('progress', i)"]
    ok = _step(tmp_path, "fit", "--", *noisy)
    assert ok.returncode == 0 and ok.stdout.strip().splitlines() == [ok.stdout.strip()]
    assert ok.stdout.startswith("==> fit: done in ") and "progress" not in ok.stdout
    assert (tmp_path / "out" / "logs" / "fit.log").read_text().count("progress") == 500
    failing = [sys.executable, "-c", "print('the cause'); raise SystemExit(3)"]
    bad = _step(tmp_path, "model", "--", *failing)
    assert bad.returncode == 3 and "FAILED" in bad.stdout and "the cause" in bad.stdout
