"""Index generations (a re-fit re-encodes every reference, then switches in one transaction).

The codes of the generation being built wait in ``next_codes``, one row per reference, until the switch.
Meta keys: ``generation`` (the number in use, 0 before any re-fit), ``pipeline`` (the fitted pipeline in use:
``models:<config>`` or ``pipelines/<config>-g<N>`` under the data dir) and ``reindex_target`` (JSON: the
generation being built, while a re-index runs). After the switch the filled table is renamed
``switched_codes`` (O(1), in the switch transaction) and its codes win over those in ``refs`` until they are
copied there in small transactions: the switch itself never holds the write lock for a time that grows with
the collection.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.errors import StaleReindex
from app.storage.database import Part, blob
from app.storage.errors import storage_guard

#: A fresh ``next_codes`` after the switch renamed the filled one (the same table as the baseline's).
NEXT_CODES = """
CREATE TABLE next_codes (
    ref_id INTEGER PRIMARY KEY,
    float_code BLOB,
    binary_code BLOB,
    error TEXT
)
"""
#: A reference's codes of the generation in use: its row in ``switched_codes`` when there is one.
CODES = (
    "CASE WHEN s.ref_id IS NULL THEN r.float_code ELSE s.float_code END, "
    "CASE WHEN s.ref_id IS NULL THEN r.binary_code ELSE s.binary_code END"
)


#: References per chunk of a bulk code read: 64 MB of 256-float codes, a few ms of work each.
CODE_CHUNK = 65536


@dataclass(frozen=True)
class CodeChunk:
    """Consecutive indexed references (by id) and their codes, one row each (None: the configuration has no
    codes of that kind)."""

    ids: np.ndarray  # int64
    float_codes: np.ndarray | None  # (n, dim) float32
    binary_codes: np.ndarray | None  # (n, bytes) uint8
    positions: np.ndarray  # (n, 2) float64 latitude, longitude (an index that holds positions stores them)


@dataclass(frozen=True)
class CodeStream:
    """One consistent read of every code (``Generations.code_stream``): ``chunks`` is read once."""

    generation: int
    version: int
    chunks: Iterator[CodeChunk]


def _codes(column: Sequence[bytes | None], dtype, n: int) -> np.ndarray | None:
    """One chunk's column of codes as an (n, d) array over one joined buffer (no array per row)."""
    if n == 0 or column[0] is None:
        return None
    return np.frombuffer(b"".join(column), dtype).reshape(n, -1)


def _chunk(rows: Sequence[tuple]) -> CodeChunk:
    n = len(rows)
    ids = np.fromiter((r[0] for r in rows), np.int64, n)
    positions = np.fromiter((v for r in rows for v in (r[3], r[4])), np.float64, 2 * n).reshape(n, 2)
    return CodeChunk(
        ids, _codes([r[1] for r in rows], np.float32, n), _codes([r[2] for r in rows], np.uint8, n), positions
    )


@dataclass(frozen=True)
class ReindexTarget:
    """The generation being built: what ``next_codes`` belongs to (recorded as meta ``reindex_target``)."""

    generation: int
    pipeline: str  # the fitted pipeline's folder, relative to the data dir
    config: str
    fingerprint: str

    def to_json(self) -> str:
        """The meta value (the same text for the same target: a re-run compares it to continue)."""
        d = {"generation": self.generation, "pipeline": self.pipeline, "config": self.config, "fp": self.fingerprint}
        return json.dumps(d, sort_keys=True)

    @classmethod
    def from_json(cls, value: str) -> ReindexTarget:
        d = json.loads(value)
        return cls(int(d["generation"]), d["pipeline"], d["config"], d["fp"])


class Generations(Part):
    """The ``next_codes`` and ``switched_codes`` tables and the generation's meta keys."""

    def head(self) -> tuple[int, int]:
        """(index version, generation) in one read: what every process compares before each search."""
        with self.database.lock:
            row = self.database.db.execute(
                "SELECT (SELECT COALESCE(MAX(version), 0) FROM changes), "
                "(SELECT value FROM meta WHERE key='generation')"
            ).fetchone()
        return int(row[0]), int(row[1] or 0)

    def generation_state(self) -> tuple[int, str | None, str | None]:
        """(generation, pipeline, config) read together, so a process never pairs one generation's number
        with another's pipeline."""
        with self.database.lock:
            rows = dict(
                self.database.db.execute(
                    "SELECT key, value FROM meta WHERE key IN ('generation', 'pipeline', 'config')"
                ).fetchall()
            )
        return int(rows.get("generation") or 0), rows.get("pipeline"), rows.get("config")

    def record_first_pipeline(self, target: ReindexTarget) -> bool:
        """Make ``target`` (a pipeline fitted in the data dir at its first start, generation 0) the one this
        data dir uses, in one transaction, only while none is recorded and no reference is stored: a data dir
        already bound to a pipeline is never re-bound. Returns whether it was recorded."""
        with self.database.transaction() as db:
            if db.execute("SELECT 1 FROM meta WHERE key='pipeline'").fetchone():
                return False
            if db.execute("SELECT 1 FROM refs LIMIT 1").fetchone():
                return False
            _bind_pipeline(db, target)
        return True

    @contextmanager
    def code_stream(self, chunk: int = CODE_CHUNK) -> Iterator[CodeStream]:
        """Every indexed reference's codes of the generation in use, with the generation and the index version
        they make up, read in one consistent snapshot and handed out ``chunk`` references at a time (a cold
        start, a new generation): what the reader holds is one chunk, never a Python object per reference.
        The read runs on a connection of its own, so the process's other threads keep the store's connection
        (and its lock) while the index is built from the chunks."""
        with storage_guard("reading the codes"):
            db = self.database.backend.connect(read_only=True)
        try:
            db.execute("BEGIN")
            gen = db.execute("SELECT value FROM meta WHERE key='generation'").fetchone()
            version = int(db.execute("SELECT COALESCE(MAX(version), 0) FROM changes").fetchone()[0])
            rows = self.database.backend.stream_rows(
                db,
                f"SELECT r.id, {CODES}, r.lat, r.lon FROM refs r LEFT JOIN switched_codes s ON s.ref_id = r.id "
                "WHERE r.status='indexed' ORDER BY r.id",
                chunk,
            )
            yield CodeStream(int(gen[0]) if gen else 0, version, (_chunk(r) for r in rows))
        finally:
            with contextlib.suppress(Exception):  # a broken connection ends its transaction by closing
                db.execute("COMMIT")
            db.close()

    def all_codes(self) -> tuple[int, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(version, ids, float codes, binary codes) of every indexed reference in single arrays: for tools and
        tests on small collections; a process building its index reads ``code_stream``."""
        with self.code_stream() as stream:
            chunks = list(stream.chunks)
        if not chunks:
            return stream.version, np.zeros(0, np.int64), None, None
        ids = np.concatenate([c.ids for c in chunks])
        f = None if chunks[0].float_codes is None else np.concatenate([c.float_codes for c in chunks])
        b = None if chunks[0].binary_codes is None else np.concatenate([c.binary_codes for c in chunks])
        return stream.version, ids, f, b

    def reindex_target(self) -> ReindexTarget | None:
        value = self.database.get_meta("reindex_target")
        return ReindexTarget.from_json(value) if value else None

    def start_reindex(self, target: ReindexTarget) -> int:
        """Make ``target`` the generation being built. The same target again continues (its codes so far are
        kept); another one starts over. Returns how many references already have their new codes."""
        value = target.to_json()
        while self.migrate_switched():  # the previous switch's codes first (an interrupted refit)
            pass
        with self.database.transaction() as db:
            row = db.execute("SELECT value FROM meta WHERE key='reindex_target'").fetchone()
            if row is None or row[0] != value:
                db.execute("DELETE FROM next_codes")
                db.execute(
                    "INSERT INTO meta(key, value) VALUES('reindex_target', ?) "
                    "ON CONFLICT(key) DO UPDATE SET value=excluded.value",
                    (value,),
                )
            return int(db.execute("SELECT COUNT(*) FROM next_codes").fetchone()[0])

    def abandon_reindex(self) -> None:
        with self.database.transaction() as db:
            db.execute("DELETE FROM next_codes")
            db.execute("DELETE FROM meta WHERE key='reindex_target'")

    def reindex_todo(self, limit: int, after: int = 0) -> list[tuple[int, Path]]:
        """Indexed references after ``after`` (by id) that have no code of the new generation yet."""
        rows = self.database.db.execute(
            "SELECT r.id, r.sha256, r.image_ext FROM refs r LEFT JOIN next_codes n ON n.ref_id = r.id "
            "WHERE r.status='indexed' AND r.id > ? AND n.ref_id IS NULL ORDER BY r.id LIMIT ?",
            (after, limit),
        ).fetchall()
        return [(r[0], self.database.image_path_for(r[1], r[2])) for r in rows]

    def put_next_codes(
        self, target: ReindexTarget, results: Sequence[tuple[int, np.ndarray | None, np.ndarray | None, str | None]]
    ) -> int:
        """Record a batch of the new generation's codes (or why a reference could not be encoded) in one
        transaction. Refused (``StaleReindex``) when another re-index has taken over the data dir."""
        value = target.to_json()
        with self.database.transaction() as db:
            row = db.execute("SELECT value FROM meta WHERE key='reindex_target'").fetchone()
            if row is None or row[0] != value:
                raise StaleReindex("another re-index took over this data dir (or it was switched already)")
            db.executemany(
                "INSERT INTO next_codes(ref_id, float_code, binary_code, error) VALUES(?,?,?,?) ON CONFLICT(ref_id) "
                "DO UPDATE SET float_code=excluded.float_code, binary_code=excluded.binary_code, error=excluded.error",
                [(i, blob(f, np.float32), blob(b, np.uint8), e) for i, f, b, e in results],
            )
        return len(results)

    def reindex_missing(self) -> int:
        """Indexed references still without a code of the new generation."""
        return int(
            self.database.db.execute(
                "SELECT COUNT(*) FROM refs r LEFT JOIN next_codes n ON n.ref_id = r.id "
                "WHERE r.status='indexed' AND n.ref_id IS NULL"
            ).fetchone()[0]
        )

    def switch_generation(self, target: ReindexTarget) -> int | None:
        """Switch to ``target`` in one write transaction: re-check that every indexed reference has its new
        code (uploads indexed meanwhile may not: then nothing changes and None is returned), mark failed the
        references the new pipeline could not encode, rename ``next_codes`` to ``switched_codes`` (whose
        codes every reader takes over those in ``refs``: constant time, whatever the collection's size) and
        record the target's pipeline, generation, fingerprint and configuration. ``migrate_switched`` then
        copies the codes into ``refs`` in short transactions. Returns the new generation."""
        value = target.to_json()
        with self.database.transaction() as db:
            row = db.execute("SELECT value FROM meta WHERE key='reindex_target'").fetchone()
            if row is None or row[0] != value:
                raise StaleReindex("another re-index took over this data dir (or it was switched already)")
            missing = db.execute(
                "SELECT COUNT(*) FROM refs r LEFT JOIN next_codes n ON n.ref_id = r.id "
                "WHERE r.status='indexed' AND n.ref_id IS NULL"
            ).fetchone()[0]
            if missing:
                return None
            if db.execute("SELECT 1 FROM switched_codes LIMIT 1").fetchone():
                raise StaleReindex("the previous switch's codes are still being copied: run `geoloc refit` again")
            db.execute(
                "UPDATE refs SET status='failed', error='re-index: ' || n.error, float_code=NULL, binary_code=NULL "
                "FROM (SELECT ref_id, error FROM next_codes WHERE error IS NOT NULL) n "
                "WHERE refs.id = n.ref_id AND refs.status='indexed'"
            )
            db.execute("DROP TABLE switched_codes")
            db.execute("ALTER TABLE next_codes RENAME TO switched_codes")
            db.execute(NEXT_CODES.strip())
            _bind_pipeline(db, target)
            db.execute("DELETE FROM meta WHERE key='reindex_target'")
            self.database.backend.notify(db)
        return int(target.generation)

    def migrate_switched(self, batch: int = 5000) -> int:
        """Copy up to ``batch`` of the last switch's codes into ``refs`` in one short transaction (readers see
        the same codes before and after); returns how many rows it handled (0: nothing left)."""
        with self.database.transaction() as db:
            rows = db.execute(
                "SELECT ref_id, float_code, binary_code FROM switched_codes ORDER BY ref_id LIMIT ?", (batch,)
            ).fetchall()
            if not rows:
                return 0
            db.executemany(
                "UPDATE refs SET float_code=?, binary_code=? WHERE id=? AND status='indexed'",
                [(f, b, i) for i, f, b in rows],
            )
            db.execute("DELETE FROM switched_codes WHERE ref_id <= ?", (rows[-1][0],))
        return len(rows)


def _bind_pipeline(db, target: ReindexTarget) -> None:
    """Record ``target`` as the data dir's pipeline (inside the caller's transaction): the four meta keys a
    loader reads to know which fitted pipeline the stored codes were made with."""
    meta = {
        "generation": str(int(target.generation)),
        "pipeline": str(target.pipeline),
        "fingerprint": target.fingerprint,
        "config": target.config,
    }
    db.executemany(
        "INSERT INTO meta(key, value) VALUES(?, ?) ON CONFLICT(key) DO UPDATE SET value=excluded.value",
        list(meta.items()),
    )
