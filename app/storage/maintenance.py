"""What ``geoloc check`` and ``geoloc backup``/``restore`` read from the database, and the consistent copy
of it (SQLite's backup API copies a state of a database that other processes keep writing, which a plain
file copy of a WAL database does not)."""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from pathlib import Path

from app.storage.database import DB_NAME, Database
from app.storage.generations import CODES


@dataclass(frozen=True)
class StoredRow:
    """A reference as a check sees it: its image file's name, status and codes of the generation in use."""

    id: int
    image: str  # the file name under images/
    status: str
    float_code: bytes | None
    binary_code: bytes | None


class Maintenance(Database):
    def holds_tables(self) -> bool:
        """False for a main file whose content is still in a ``-wal`` file that is not there."""
        if self.engine == "postgres":
            return self.db.execute("SELECT to_regclass('refs') IS NOT NULL").fetchone()[0]
        return self.db.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name='refs'").fetchone() is not None

    def stored_rows(self) -> list[StoredRow]:
        """Every row (any status), with its codes of the generation in use."""
        rows = self.db.execute(
            f"SELECT r.id, r.sha256, r.image_ext, r.status, {CODES} FROM refs r "
            "LEFT JOIN switched_codes s ON s.ref_id = r.id"
        ).fetchall()
        return [StoredRow(i, f"{sha}.{ext}", status, f, b) for i, sha, ext, status, f, b in rows]


def copy_database(source_dir: Path, dest_dir: Path) -> None:
    """Copy ``source_dir``'s database into ``dest_dir`` (a consistent state, while others keep writing)."""
    src = sqlite3.connect(source_dir / DB_NAME)
    dst = sqlite3.connect(dest_dir / DB_NAME)
    try:
        src.backup(dst)
    finally:
        src.close()
        dst.close()


def image_names(data_dir: Path) -> list[str]:
    """The image file name of every row of ``data_dir``'s database (one per reference)."""
    con = sqlite3.connect(data_dir / DB_NAME)
    try:
        return [f"{sha}.{ext}" for sha, ext in con.execute("SELECT sha256, image_ext FROM refs").fetchall()]
    finally:
        con.close()
