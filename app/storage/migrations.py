"""Schema migrations: an ordered list of steps, each applied once and recorded in ``schema_versions``.

A writable open (``Database``) runs ``upgrade``: in one write transaction (SQLite's ``BEGIN IMMEDIATE``, or
PostgreSQL's transaction under the store's write lock, so hosts starting together migrate once), every step
after the database's recorded version is applied and recorded. A failing step rolls the whole upgrade back:
the database stays at its version, and the next start tries again. A database recorded at a version this
code does not know (made by a newer version) is refused rather than written with the wrong assumptions.

Step 1 is the schema as it was before migrations existed (every ``CREATE ... IF NOT EXISTS``): on a data
dir or database made then, it changes nothing and records version 1; on a new one, it makes the tables.
A later step is one ``Step`` appended to ``STEPS`` (``tests/storage/test_store_migrations.py`` shows one adding a
column), written in SQLite's spelling (the PostgreSQL connection translates types and placeholders).

Why our own steps rather than Alembic: the store speaks SQL through sqlite3 and psycopg directly, with no
SQLAlchemy engine or metadata to autogenerate from; Alembic would add SQLAlchemy and a second connection
stack (its own transaction handling beside ``BEGIN IMMEDIATE`` and the advisory write lock) to run what
is here a loop over a tuple and a one-table record.
"""

from __future__ import annotations

import sqlite3
import time
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import Any, Protocol

from app.errors import ServiceError
from app.storage.backend import StorageBackend


class Migratable(Protocol):
    """What a migration needs of ``app.storage.database.Database`` (which runs ``upgrade`` when it opens;
    a protocol, so the two modules do not import each other)."""

    backend: StorageBackend
    db: Any

    def transaction(self) -> AbstractContextManager[Any]: ...


@dataclass(frozen=True)
class Step:
    """One change of the schema: ``sql`` (statements separated by ``;``) applied once, as ``version``."""

    version: int
    name: str
    sql: str


class SchemaTooNew(ServiceError):
    """The database was migrated by a newer version than this one: writing it could break its invariants."""

    code = "not_ready"


VERSIONS_SCHEMA = """
CREATE TABLE IF NOT EXISTS schema_versions (
    version INTEGER PRIMARY KEY,
    name TEXT NOT NULL,
    applied_at TEXT NOT NULL
);
"""

#: The schema before migrations (commit 00671a8 and earlier): never edited, later changes are new steps.
BASELINE = """
CREATE TABLE IF NOT EXISTS refs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    sha256 TEXT NOT NULL UNIQUE,
    lat REAL NOT NULL,
    lon REAL NOT NULL,
    heading REAL,
    captured_at TEXT,
    label TEXT,
    source TEXT,
    image_ext TEXT,
    created_at TEXT NOT NULL,
    float_code BLOB,
    binary_code BLOB,
    status TEXT NOT NULL DEFAULT 'indexed',  -- pending (accepted, not encoded yet), indexed, failed
    error TEXT
);
CREATE INDEX IF NOT EXISTS refs_lat_lon ON refs(lat, lon);
CREATE INDEX IF NOT EXISTS refs_status ON refs(status);
CREATE INDEX IF NOT EXISTS refs_lon ON refs(lon);

CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);

CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    created_at TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS job_items (
    job_id TEXT NOT NULL REFERENCES jobs(id),
    position INTEGER NOT NULL,
    ref_id INTEGER NOT NULL,
    duplicate INTEGER NOT NULL DEFAULT 0,
    PRIMARY KEY (job_id, position)
);

-- The index's change log: one row per reference added to or deleted from the index.
CREATE TABLE IF NOT EXISTS changes (
    version INTEGER PRIMARY KEY AUTOINCREMENT,
    ref_id INTEGER NOT NULL,
    op TEXT NOT NULL CHECK (op IN ('add', 'delete', 'move'))
);

-- Claims: pending rows a bulk run encodes itself; a worker skips them until the lease ends.
CREATE TABLE IF NOT EXISTS claims (
    ref_id INTEGER PRIMARY KEY,
    owner TEXT NOT NULL,
    expires REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS claims_owner ON claims(owner);

-- Encoding attempts of pending rows, counted (and committed) before each attempt starts.
CREATE TABLE IF NOT EXISTS encode_attempts (
    ref_id INTEGER PRIMARY KEY,
    attempts INTEGER NOT NULL
);

-- A re-fit's codes until its switch, and the switched codes until they are copied into refs.
CREATE TABLE IF NOT EXISTS next_codes (
    ref_id INTEGER PRIMARY KEY,
    float_code BLOB,
    binary_code BLOB,
    error TEXT
);
CREATE TABLE IF NOT EXISTS switched_codes (
    ref_id INTEGER PRIMARY KEY,
    float_code BLOB,
    binary_code BLOB,
    error TEXT
);

-- Image files to remove, queued in the transaction that deletes the row naming them.
CREATE TABLE IF NOT EXISTS removals (
    name TEXT PRIMARY KEY,
    queued_at REAL NOT NULL
);
"""

#: Every step, in order (versions 1, 2, ...).
STEPS: tuple[Step, ...] = (Step(1, "baseline", BASELINE),)


def statements(script: str) -> list[str]:
    """The statements of ``script``, one by one (a driver's ``executescript`` would commit the open
    transaction first), without the comment lines between them; a ``;`` inside a quoted string stays."""
    text = "\n".join(line for line in script.splitlines() if not line.strip().startswith("--"))
    out: list[str] = []
    buf = ""
    for piece in text.split(";"):
        buf += piece + ";"
        if sqlite3.complete_statement(buf):
            if buf.strip(" \n;"):
                out.append(buf.strip().rstrip(";").strip())
            buf = ""
    return out


def schema_version(database: Migratable) -> int:
    """The database's recorded version (0: none recorded, or no table yet)."""
    if not _has_versions(database):
        return 0
    return int(database.db.execute("SELECT COALESCE(MAX(version), 0) FROM schema_versions").fetchone()[0])


def _has_versions(database: Migratable) -> bool:
    try:
        database.db.execute("SELECT 1 FROM schema_versions LIMIT 1").fetchall()
    except Exception:  # no such table (either backend's error): a database from before migrations
        return False
    return True


def upgrade(database: Migratable, steps: tuple[Step, ...] = STEPS) -> list[int]:
    """Apply every step after the recorded version, in one write transaction; returns the versions
    applied (none when the database is current)."""
    _check_order(steps)
    with database.transaction() as db:
        for sql in statements(VERSIONS_SCHEMA):
            db.execute(sql)
        current = int(db.execute("SELECT COALESCE(MAX(version), 0) FROM schema_versions").fetchone()[0])
        refuse_too_new(database, current, steps)
        applied: list[int] = []
        for step in steps:
            if step.version <= current:
                continue
            for sql in statements(step.sql):
                db.execute(sql)
            db.execute(
                "INSERT INTO schema_versions(version, name, applied_at) VALUES(?, ?, ?)",
                (step.version, step.name, time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())),
            )
            applied.append(step.version)
    return applied


def refuse_too_new(database: Migratable, current: int, steps: tuple[Step, ...] = STEPS) -> None:
    """``SchemaTooNew`` when ``current`` (the database's recorded version) is past the last step this code
    knows. One rule for the writable open, which refuses to start, and for ``geoloc check``, which opens
    read-only (no upgrade runs) and would otherwise call such a database sound."""
    latest = steps[-1].version if steps else 0
    if current > latest:
        raise SchemaTooNew(
            f"{database.backend.describe()} is at schema version {current}, made by a newer version of geoloc "
            f"(this one knows up to {latest}): run that version, or restore a backup made by this one"
        )


def _check_order(steps: tuple[Step, ...]) -> None:
    """Versions 1, 2, ... with no gap or repeat: a step added out of order would be skipped silently."""
    versions = [s.version for s in steps]
    if versions != list(range(1, len(steps) + 1)):
        raise ValueError(f"migration steps must be numbered 1, 2, ... in order, not {versions}")
