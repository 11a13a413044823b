"""Write docs/configuration.md from ``app.settings.Settings``: every ``GEOLOC_*`` setting, its default and
its meaning, so the page cannot drift from the code that reads the environment.

    python -m tools.config_docs            # rewrites docs/configuration.md
    python -m tools.config_docs --check    # exits 1 when the page differs from what Settings says

Why generated: a hand-kept list of settings went stale each time a setting was added; the descriptions live
beside the fields (``Field(description=...)``), and this renders them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pydantic_core import PydanticUndefined

from app.settings import REPO_ROOT, Settings

DOC = REPO_ROOT / "docs" / "configuration.md"

#: Defaults computed on the machine that runs the service, said in words rather than as this machine's value.
COMPUTED = {
    "locate_concurrency": "one per usable CPU",
    "build_cache": "`$XDG_CACHE_HOME/geoloc/wheels`, else `~/.cache/geoloc/wheels`",
}

INTRO = """# Configuration

Every setting of the service, read from the environment with the prefix `GEOLOC_` (`GEOLOC_DATA_DIR`,
`GEOLOC_CONFIG`, ...) once at start-up (`app/settings.py`, `Settings`; the storage's settings are
`StorageSettings`, `app/storage/settings.py`). `.env.example` lists them for docker compose, which reads a
`.env` file; outside Docker, export them in the shell (the service itself does not read `.env`). The command
line's `--data-dir`, `--models-dir` and `--config` override the first three.

This page is generated: `python -m tools.config_docs` writes it from the fields' defaults and descriptions,
and `python -m tools.config_docs --check` (run by tests/test_docs.py) fails when it differs from them.
Guides to these settings in context: [operations.md](operations.md) (data dir, snapshots, PostgreSQL,
security), [api.md](api.md) (limits).

| variable | default | meaning |
|---|---|---|
"""


def _default(name: str, field) -> str:
    if name in COMPUTED:
        return COMPUTED[name]
    value = field.default
    if value is PydanticUndefined or value is None:
        return "unset"
    if isinstance(value, Path):
        try:
            return f"`{value.relative_to(REPO_ROOT)}/` in the checkout"
        except ValueError:
            return f"`../{value.relative_to(REPO_ROOT.parent)}/` beside the checkout"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, int) and value >= 10_000 and value % (1024 * 1024) == 0:
        return f"`{value}` ({value // (1024 * 1024)} MiB)"
    return f"`{value}`"


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")


def render() -> str:
    """The page, one row per field of Settings (the storage's fields first, as the class inherits them)."""
    rows = []
    for name, field in Settings.model_fields.items():
        if not field.description:
            raise SystemExit(f"Settings.{name} has no description: add Field(description=...) in app/settings.py")
        rows.append(f"| `GEOLOC_{name.upper()}` | {_cell(_default(name, field))} | {_cell(field.description)} |")
    return INTRO + "\n".join(rows) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="exit 1 if docs/configuration.md is not what it renders")
    ap.add_argument("--out", type=Path, default=DOC)
    args = ap.parse_args(argv)
    text = render()
    if args.check:
        current = args.out.read_text() if args.out.exists() else ""
        if current != text:
            print(f"{args.out} differs from app/settings.py: run python -m tools.config_docs", file=sys.stderr)
            return 1
        print(f"{args.out} matches Settings")
        return 0
    args.out.write_text(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
