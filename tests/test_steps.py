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


def test_a_live_step_shows_its_lines_as_they_come(tmp_path):
    """`make fit` off a terminal (a first `make run` once printed nothing for minutes): each line the
    command prints is shown indented, and is in the log too."""
    chatty = [sys.executable, "-c", "for i in range(3): print(f'fit: extract: {i}/3 img, 1.0 img/s', flush=True)"]
    ok = _step(tmp_path, "fit-x", "--live", "--", *chatty)
    assert ok.returncode == 0, ok.stderr
    lines = ok.stdout.splitlines()
    assert lines[:3] == [f"    fit: extract: {i}/3 img, 1.0 img/s" for i in range(3)]
    assert lines[3].startswith("==> fit-x: done in ")
    assert (tmp_path / "out" / "logs" / "fit-x.log").read_text().count("fit: extract") == 3


def test_make_names_the_fit_log_after_the_configuration_and_takes_a_port(tmp_path):
    """`make fit CONFIG=hybrid-bin` writes out/logs/fit-hybrid-bin.log (it overwrote fit.log), live; `make
    run PORT=8123` serves on that port (the README says so)."""
    fit = subprocess.run(["make", "-n", "-B", "fit", "CONFIG=hybrid-bin"], capture_output=True, text=True, cwd=REPO)
    assert "tools/steps.py fit-hybrid-bin --live -- " in fit.stdout, fit.stdout + fit.stderr
    run = subprocess.run(["make", "-n", "-B", "run", "PORT=8123"], capture_output=True, text=True, cwd=REPO)
    assert "serve --host 127.0.0.1 --port 8123" in run.stdout, run.stdout + run.stderr
    assert "make run PORT=" in (REPO / "README.md").read_text()
