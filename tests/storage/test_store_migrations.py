"""Schema migrations (``app.storage.migrations``) on both backends: a new database is made by the baseline
and recorded at version 1; a later step (here: a column added, what per-reference data will need) is
applied once, in the open's one transaction, and recorded; a step that fails leaves the database at its
version; a database migrated by a newer version is refused. (A data dir and a PostgreSQL database made by
main before migrations existed: tests/api/test_store_upgrade.py.)"""

from __future__ import annotations

import numpy as np
import pytest

from app.errors import StorageUnavailable
from app.storage.database import Database
from app.storage.migrations import STEPS, SchemaTooNew, Step, schema_version, statements
from app.storage.postgres import PostgresBackend
from app.storage.sqlite import SqliteBackend
from app.storage.store import NewReference, ReferenceStore

#: What a later change of the schema looks like: one step appended to ``STEPS``.
ADD_COLUMN = Step(
    len(STEPS) + 1, "refs.local_features", "ALTER TABLE refs ADD COLUMN local_features BLOB;"
    "CREATE INDEX IF NOT EXISTS refs_has_local ON refs(id) WHERE local_features IS NOT NULL;",
)  # fmt: skip


@pytest.fixture(params=["sqlite", "postgres"])
def backend(request, tmp_path):
    if request.param == "sqlite":
        return SqliteBackend(tmp_path)
    return PostgresBackend(request.getfixturevalue("postgres_server").create_database(), tmp_path)


def _recorded(database: Database) -> list[tuple[int, str]]:
    return [tuple(r) for r in database.db.execute("SELECT version, name FROM schema_versions ORDER BY version")]


def _columns(database: Database) -> list[str]:
    return [d[0] for d in database.db.execute("SELECT * FROM refs LIMIT 0").description]


def test_a_new_database_is_made_by_the_baseline_and_recorded(backend):
    store = ReferenceStore(backend.data_dir, backend=backend)
    try:
        assert _recorded(store.database) == [(1, "baseline")] and schema_version(store.database) == len(STEPS)
        store.add_many([NewReference(b"x" * 64, "jpg", 40.0, -75.0, float_code=np.ones(4, np.float32))])
        assert store.count() == 1 and store.version == 1
    finally:
        store.close()
    again = ReferenceStore(backend.data_dir, backend=backend)  # a second open applies nothing again
    try:
        assert _recorded(again.database) == [(1, "baseline")] and again.count() == 1
    finally:
        again.close()


def test_a_later_step_is_applied_once_and_recorded(backend):
    ReferenceStore(backend.data_dir, backend=backend).close()
    steps = (*STEPS, ADD_COLUMN)
    first = Database(backend, steps=steps)
    try:
        assert _recorded(first)[-1] == (ADD_COLUMN.version, "refs.local_features")
        assert "local_features" in _columns(first)
    finally:
        first.close()
    second = Database(backend, steps=steps)  # applied once: a second ALTER would fail on the column
    try:
        assert [v for v, _ in _recorded(second)] == [1, ADD_COLUMN.version]
    finally:
        second.close()
    with pytest.raises(SchemaTooNew, match=f"schema version {ADD_COLUMN.version}"):
        Database(backend)  # the previous version's code refuses a database it does not know


def test_a_failing_step_leaves_the_database_at_its_version(backend):
    ReferenceStore(backend.data_dir, backend=backend).close()
    broken = Step(len(STEPS) + 1, "broken", "ALTER TABLE refs ADD COLUMN half TEXT; ALTER TABLE nowhere ADD x TEXT;")
    with pytest.raises(Exception) as e:
        Database(backend, steps=(*STEPS, broken))
    assert not isinstance(e.value, StorageUnavailable) or "nowhere" in str(e.value)
    database = Database(backend)
    try:
        assert [v for v, _ in _recorded(database)] == [1] and "half" not in _columns(database)
    finally:
        database.close()


def test_steps_must_be_numbered_in_order(tmp_path):
    with pytest.raises(ValueError, match="numbered"):
        Database(SqliteBackend(tmp_path), steps=(*STEPS, Step(len(STEPS) + 2, "gap", "SELECT 1")))


def test_a_script_splits_into_its_statements_without_comments():
    script = "-- a comment\nCREATE TABLE a (x TEXT, -- why\n y TEXT);\n\nCREATE INDEX i ON a(x);"
    assert statements(script) == ["CREATE TABLE a (x TEXT, -- why\n y TEXT)", "CREATE INDEX i ON a(x)"]
