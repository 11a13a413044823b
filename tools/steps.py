"""Run one set-up step with one line of output when nobody watches a terminal.

    python3 tools/steps.py NAME [--live] -- COMMAND [ARGS...]

Why: on a terminal a person likes progress bars; in a log (CI, `make run > log`, a container) they are a
thousand lines of noise. Off a terminal the command's output goes to out/logs/NAME.log and this prints one
line with the step's time, or the log's tail when it fails. ``--live``, for a long step whose output is a
few plain lines (the fit's steps, its rate and ETA): those lines are shown too, indented, as they come,
so a first `make run` is not minutes of silence. Standard library only: it runs before the virtual
environment exists.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path


def main(argv: list[str]) -> int:
    live = len(argv) > 1 and argv[1] == "--live"
    if live:
        argv = argv[:1] + argv[2:]
    if len(argv) < 3 or argv[1] != "--":
        print(__doc__, file=sys.stderr)
        return 2
    name, cmd = argv[0], argv[2:]
    t0 = time.monotonic()
    if sys.stdout.isatty():
        print(f"==> {name}", flush=True)
        rc = subprocess.call(cmd)
    else:
        log = Path("out/logs") / f"{name}.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        with log.open("w") as f:
            rc = _shown(cmd, f) if live else subprocess.call(cmd, stdout=f, stderr=subprocess.STDOUT)
        if rc != 0:
            print(f"==> {name} FAILED after {time.monotonic() - t0:.0f} s (exit {rc}); the end of {log}:", flush=True)
            print("".join(log.read_text(errors="replace").splitlines(True)[-30:]), flush=True)
            return rc
    print(f"==> {name}: done in {time.monotonic() - t0:.0f} s", flush=True)
    return rc


def _shown(cmd: list[str], log) -> int:
    """Run ``cmd`` with its output written to ``log`` and echoed, indented, line by line."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, errors="replace")
    assert proc.stdout is not None
    for line in proc.stdout:
        log.write(line)
        log.flush()
        print(f"    {line.rstrip()}", flush=True)
    return proc.wait()


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
